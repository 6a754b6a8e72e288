"""Data parallelism over local devices with ``jax.sharding`` (a ``Mesh`` and ``NamedSharding``s), nothing more.

The computation stays the same pure function on one device or many: arrays carry their sharding, jit
propagates it, and XLA inserts the collectives (the gradient all-reduce of a data-parallel step, for
example).  This module only builds the mesh and places pytrees on it:

* ``make_mesh(n)``: a 1-D mesh over the first ``n`` devices (all by default), axis ``'data'``;
* ``shard_batch`` / ``shard_robots``: the leading axis (windows of a batch, robots of a fleet) split
  over the mesh axis; ``replicate``: a full copy on every device (parameters, optimiser state);
* ``run_episodes``: closed-loop episodes (``mpc.run_episode``) vmapped over robots with the robot axis
  sharded over the mesh.

Multi-host runs are the same code: call ``jax.distributed.initialize()`` first on every host, then
``make_mesh()`` spans every device of every host (``jax.devices()`` is global) and ``shard_batch``
assembles each host's local slice of the batch into one global array.
"""
from __future__ import annotations

import functools

import jax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from capsjax import mpc

DATA_AXIS = "data"


def make_mesh(num_devices: int | None = None, axis: str = DATA_AXIS) -> Mesh:
    """A 1-D ``Mesh`` over the first ``num_devices`` devices (all of them when None)."""
    devices = jax.devices()
    if num_devices is None:
        num_devices = len(devices)
    if not isinstance(num_devices, int) or isinstance(num_devices, bool) or not 1 <= num_devices <= len(devices):
        raise ValueError(f"num_devices must be an int in [1, {len(devices)}] (the devices available), got {num_devices!r}")
    # Auto axes: shardings propagate through jit and XLA inserts the collectives (no explicit resharding).
    return jax.make_mesh((num_devices,), (axis,), axis_types=(jax.sharding.AxisType.Auto,),
                         devices=devices[:num_devices])


def leading_sharding(mesh: Mesh) -> NamedSharding:
    """Leading axis split over the mesh's (only) axis, the rest whole."""
    return NamedSharding(mesh, PartitionSpec(mesh.axis_names[0]))


def replicated_sharding(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


def _shard_leading(tree, mesh: Mesh, what: str):
    sharding = leading_sharding(mesh)
    size = mesh.devices.size

    def place(path, x):
        if getattr(x, "ndim", 0) == 0:
            raise ValueError(f"{what}{jax.tree_util.keystr(path)} is a scalar; every leaf needs a leading {what} axis")
        if x.shape[0] % size:
            raise ValueError(
                f"{what}{jax.tree_util.keystr(path)} has {x.shape[0]} entries on its leading axis, which must be "
                f"a multiple of the {size} devices of the mesh"
            )
        if jax.process_count() > 1:  # multi-host: every host holds its local slice of the global batch
            return jax.make_array_from_process_local_data(sharding, x)
        return jax.device_put(x, sharding)

    return jax.tree_util.tree_map_with_path(place, tree)


def shard_batch(batch, mesh: Mesh):
    """Put a batch (e.g. ``losses.Batch``) on the mesh, its leading (window) axis split over the devices."""
    return _shard_leading(batch, mesh, "batch")


def shard_robots(tree, mesh: Mesh):
    """Put per-robot data (tasks, keys, env states, specs) on the mesh, the robot axis split over devices."""
    return _shard_leading(tree, mesh, "robots")


def replicate(tree, mesh: Mesh):
    """A full copy of ``tree`` on every device of the mesh (parameters, optimiser state, shared specs)."""
    return jax.device_put(tree, replicated_sharding(mesh))


@functools.partial(jax.jit, static_argnames=("env", "policy", "num_steps", "update_spec", "spec_per_robot",
                                             "record_images"))
def _run_episodes(env, policy, params, spec, tasks, keys, *, num_steps, update_spec, spec_per_robot, record_images):
    one = functools.partial(mpc.run_episode, env, policy, num_steps=num_steps, update_spec=update_spec,
                            record_images=record_images)
    return jax.vmap(one, in_axes=(None, 0 if spec_per_robot else None, 0, 0))(params, spec, tasks, keys)


def run_episodes(env, policy: mpc.Policy, params, spec, tasks, keys, *, num_steps: int,
                 mesh: Mesh | None = None, update_spec=None, record_images: bool = False) -> mpc.Trajectory:
    """``mpc.run_episode`` for many robots, the robot axis sharded over ``mesh`` (all devices by default).

    ``tasks`` and ``keys`` have a leading robot axis; ``spec`` is either one ``RewardSpec`` shared by all
    robots or one per robot (weights ``f32[R, K]``).  The number of robots must be a multiple of the
    mesh size.  Returns the ``Trajectory`` with leading axes ``[R, T]``, sharded like the robots
    (``record_images``: with every robot's camera frames, as ``mpc.run_episode``).
    """
    mesh = mesh if mesh is not None else make_mesh()
    spec_per_robot = spec.weights.ndim == 2
    tasks, keys = shard_robots((tasks, keys), mesh)
    spec = shard_robots(spec, mesh) if spec_per_robot else replicate(spec, mesh)
    return _run_episodes(env, policy, replicate(params, mesh), spec, tasks, keys, num_steps=num_steps,
                         update_spec=update_spec, spec_per_robot=spec_per_robot, record_images=record_images)
