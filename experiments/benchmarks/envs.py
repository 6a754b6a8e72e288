"""Env throughput: ``python -m experiments.bench envs [--scenes forest,city,indoor] [--batches 1,64,256] ...``

Per scene, JSON lines (``experiments.bench.emit``):

* ``envs.<scene>.steps_per_s_<B>``: control steps per second for B robots stepping together (``vmap``
  of ``env.step``: 0.25 s of MJX physics in substeps plus one camera frame and the signals), timed over
  ``--steps`` steps inside one ``lax.scan`` after compilation;
* ``envs.<scene>.render_frames_per_s``: ``envs.camera.render`` alone, ``--render-batch`` views at once;
* ``envs.<scene>.mjx_ray_frames_per_s``: the same views by ``mjx.ray`` per pixel (``--ray-batch`` views,
  the full scene's MJCF), and ``envs.<scene>.render_speedup_vs_mjx_ray``: the ratio of the two at the same
  batch (``--ray-batch``, by default the render batch), i.e. per pixel;
* ``envs.<scene>.compile_s``: wall time spent compiling the scene's functions.

Devices.  Every batch (robots, views) is split over the local devices with ``jax.sharding``
(``capsjax.sharding``), the way collection runs a fleet.  On a CPU the benchmark first splits the host
into ``--host-devices`` XLA devices (default: one per core, ``--xla_force_host_platform_device_count``,
set before JAX starts): XLA:CPU runs each of the renderer's fused loops on one thread, while ``mjx.ray``'s
large ops already spread over the cores, so one device per core is what lets *both* sides use the whole
machine -- the comparison is then machine against machine, not one core against two.  ``--host-devices 1``
gives the one-device figures of earlier READMEs.  A batch that does not divide evenly runs on the
largest device count that divides it (batch 1: one device); the lines record ``sharded_over``.

Compilation dominates the run time (MJX's step takes most of a minute to compile on a 2-core CPU): the
scene's functions are compiled in parallel threads first, and ``--batches`` / ``--scenes`` shrink the run.
A sample is one untimed call, then back-to-back calls for at least 0.3 s.  Rates are medians over
``--repeats`` samples.  The speedup samples the renderer and ``mjx.ray`` in turn, ``--rounds`` rounds,
and divides their fastest rounds: interference from other work on a shared machine only adds time (the
renderer's median moved by up to 30 % between runs), so the fastest round is the steadiest estimate of
each side's own cost; the line also carries the ratio of the medians and every round's ratio.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from capsjax import sharding
from envs.camera import mjx_ray_depth, render
from experiments.bench import emit
from experiments.runtime import use_host_devices


def _mesh_for(batch: int):
    """The largest mesh of local devices that splits ``batch`` evenly, and its device count."""
    count = max(d for d in range(1, jax.local_device_count() + 1) if batch % d == 0)
    return sharding.make_mesh(count), count


def _sample(fn, min_seconds: float) -> float:
    """Seconds per call of ``fn``: one untimed call (whatever ran before leaves caches and allocator
    cold), then back-to-back calls for at least ``min_seconds`` (one millisecond call is mostly timer
    and scheduler noise)."""
    jax.block_until_ready(fn())
    calls, start = 0, time.perf_counter()
    while True:
        jax.block_until_ready(fn())
        calls += 1
        if time.perf_counter() - start >= min_seconds:
            return (time.perf_counter() - start) / calls


def _median_time(fn, repeats: int, min_seconds: float = 0.3) -> float:
    """Median over ``repeats`` samples (``_sample``) of the seconds per call."""
    return float(np.median([_sample(fn, min_seconds) for _ in range(repeats)]))


def _interleaved_times(fns: dict, rounds: int, min_seconds: float = 0.3) -> dict:
    """``{name: [seconds per call, one per round]}``, the functions sampled in turn in every round, so
    a slow spell of a shared machine falls on all of them alike."""
    times = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            times[name].append(_sample(fn, min_seconds))
    return times


def bench_scene(name: str, batches: list[int], steps: int, repeats: int, render_batch: int, ray_batch: int,
                rounds: int = 5) -> None:
    env = envs.make(name)
    spec = env.spec
    low, high = np.asarray(spec.plan_low, np.float32), np.asarray(spec.plan_high, np.float32)
    context = dict(scene=name, substeps=env.config.car.substeps, image=list(spec.image_shape))

    def rollout(state, actions):
        def body(s, a):
            return jax.vmap(env.step)(s, a), None

        return jax.lax.scan(body, state, actions)[0]

    # Inputs per batch size: tasks from distinct seeds (distinct layouts), random plan-box actions.
    inputs, compiled, spread = {}, {}, {}
    for b in batches:
        keys = jax.random.split(jax.random.key(b), b)
        tasks = jax.vmap(lambda k: env.sample_task(k, "train"))(keys)
        state = jax.jit(jax.vmap(env.reset))(keys, tasks)
        u = np.random.default_rng(b).uniform(size=(steps, b, spec.action_dim)).astype(np.float32)
        mesh, spread[b] = _mesh_for(b)
        actions = jax.device_put(jnp.asarray(low + u * (high - low)),
                                 jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(None, sharding.DATA_AXIS)))
        inputs[b] = (sharding.shard_robots(state, mesh), actions)

    # The first robot's layout and start, on one device (the views are sharded below).
    first = jax.tree.map(jnp.asarray, jax.device_get(inputs[batches[0]][0]))
    scene = jax.tree.map(lambda x: x[0], first.physics.scene)
    all_poses = jax.vmap(lambda k: _free_pose(env, first, k))(jax.random.split(jax.random.key(7), render_batch))
    view_batches = sorted({render_batch, ray_batch})
    poses = {}
    for b in view_batches:
        mesh, spread[b] = _mesh_for(b)
        poses[b] = sharding.shard_robots(all_poses[:b], mesh)
    cam = env.config.camera
    render_fn = jax.jit(jax.vmap(lambda p: render(scene, p, cam)))

    import mujoco
    from mujoco import mjx

    from envs.car import full_mjcf

    mj_model = mujoco.MjModel.from_xml_string(full_mjcf(env.config.car, scene, name=name))
    model = mjx.put_model(mj_model, impl="jax")
    data = mjx.kinematics(model, mjx.make_data(model))
    ray_fn = jax.jit(jax.vmap(lambda p: mjx_ray_depth(model, data, p, cam)))

    jobs = {("steps", b): (jax.jit(rollout), inputs[b]) for b in batches}
    jobs[("render", render_batch)] = (render_fn, (poses[render_batch],))
    jobs[("render", ray_batch)] = (render_fn, (poses[ray_batch],))
    jobs[("ray", ray_batch)] = (ray_fn, (poses[ray_batch],))
    start = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        futures = {k: pool.submit(lambda f=f, a=a: f.lower(*a).compile()) for k, (f, a) in jobs.items()}
        compiled = {k: fut.result() for k, fut in futures.items()}
    emit(f"envs.{name}.compile_s", time.perf_counter() - start, "s", **context)

    for b in batches:
        fn, args = compiled[("steps", b)], inputs[b]
        seconds = _median_time(lambda: fn(*args), repeats)
        emit(f"envs.{name}.steps_per_s_{b}", b * steps / seconds, "steps/s", batch=b, steps=steps,
             sharded_over=spread[b], **context)
    frames = _median_time(lambda: compiled[("render", render_batch)](poses[render_batch]), repeats)
    emit(f"envs.{name}.render_frames_per_s", render_batch / frames, "frames/s", batch=render_batch,
         sharded_over=spread[render_batch], **context)
    times = _interleaved_times({"render": lambda: compiled[("render", ray_batch)](poses[ray_batch]),
                                "ray": lambda: compiled[("ray", ray_batch)](poses[ray_batch])}, rounds)
    render_t, ray_t = np.asarray(times["render"]), np.asarray(times["ray"])
    emit(f"envs.{name}.mjx_ray_frames_per_s", ray_batch / np.median(ray_t), "frames/s", batch=ray_batch,
         ngeom=mj_model.ngeom, sharded_over=spread[ray_batch], **context)
    # Interference from other work only ever adds time, so each side's fastest round is its best
    # estimate of its own cost (timeit's convention); the ratio of medians and the per-round ratios
    # ride along to show the spread.
    emit(f"envs.{name}.render_speedup_vs_mjx_ray", ray_t.min() / render_t.min(), "x", batch=ray_batch,
         sharded_over=spread[ray_batch], rounds=rounds, estimator="ratio of the fastest rounds",
         ratio_of_medians=float(np.median(ray_t) / np.median(render_t)),
         per_round=[round(float(r), 1) for r in ray_t / render_t], **context)


def _free_pose(env, state, key):
    """A camera pose near the first robot's start, turned by a random angle (a view of the scene)."""
    pose = state.info["pose"][0]
    return pose.at[2].add(jax.random.uniform(key, (), minval=-jnp.pi, maxval=jnp.pi))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench envs", description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(envs.SCENES))
    parser.add_argument("--batches", default="1,64,256", help="robot batch sizes")
    parser.add_argument("--steps", type=int, default=8, help="control steps per timed rollout")
    parser.add_argument("--repeats", type=int, default=3, help="samples per rate (median)")
    parser.add_argument("--rounds", type=int, default=5, help="interleaved rounds of the speedup")
    parser.add_argument("--render-batch", type=int, default=256)
    parser.add_argument("--ray-batch", type=int, default=None,
                        help="views for the mjx.ray comparison (default: --render-batch)")
    parser.add_argument("--host-devices", type=int, default=os.cpu_count() or 1,
                        help="XLA devices a CPU host is split into (default: one per core; see the module docstring)")
    args = parser.parse_args(argv)
    for option in ("host_devices", "repeats", "rounds", "steps", "render_batch"):
        if getattr(args, option) < 1:
            parser.error(f"--{option.replace('_', '-')} must be >= 1, got {getattr(args, option)}")
    ray_batch = args.render_batch if args.ray_batch is None else args.ray_batch
    if not 1 <= ray_batch <= args.render_batch:
        parser.error(f"--ray-batch must be in [1, --render-batch = {args.render_batch}], got {ray_batch}")
    use_host_devices(args.host_devices)
    batches = [int(b) for b in args.batches.split(",") if b]
    for name in args.scenes.split(","):
        bench_scene(name, batches, args.steps, args.repeats, args.render_batch, ray_batch, args.rounds)


if __name__ == "__main__":
    main()
