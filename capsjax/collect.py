"""Off-policy data collection: many robots under one jit, finished episodes streamed to a zarr dataset.

A chunk of ``steps_per_chunk`` control steps for all robots runs as one ``lax.scan`` over steps of a
``vmap`` over robots, with the policy inside.  A finished episode's terminal observation is recorded
as its own entry (the paper's done handling, caps-algorithm.md section 8.1); the next step starts a
fresh episode on a freshly drawn task instead of executing the action, so the terminal entry's action
is padding.  The host splits each robot's stream into episodes at the done flags and a writer thread
appends complete episodes to the dataset while the device computes the next chunk (JAX's async
dispatch), so disk writes and compression overlap the rollout.

Time indexing is clean: entry t holds the image and vector of observation t (one instant), the action
executed at t, the signals of observation t and the pose at t.  The "hand-labelled" fraction of frames
(default 0.2 %, the paper's) get their ground-truth semantic maps rendered from the recorded pose and
the episode's task (scene envs only; the camera is exact, so re-rendering reproduces the frame).
"""
from __future__ import annotations

import functools
import os
import queue
import threading
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from jax.sharding import Mesh

from capsjax import mpc, sharding
from capsjax.data import SPLITS, Dataset, _jsonable

# ------------------------------------------------------------------------------------------ policies


class ExplorationSchedule(NamedTuple):
    """Exploration noise as piecewise-linear functions of env steps (constant after the last point)."""

    uniform_steps: int  # env steps of uniform random actions before the policy is used at all
    sigma: tuple[tuple[float, float], ...]  # (env steps, Gaussian sigma in normalised action units)
    epsilon: tuple[tuple[float, float], ...]  # (env steps, probability of a uniform action)


# caps-algorithm.md section 5.3.
PAPER_SCHEDULE = ExplorationSchedule(
    uniform_steps=4_000,
    sigma=((0, 0.25), (80_000, 0.05), (240_000, 0.005)),
    epsilon=((0, 1.0), (1_000, 1.0), (80_000, 0.1), (160_000, 0.01)),
)


def piecewise_linear(points: tuple[tuple[float, float], ...], x: jax.Array) -> jax.Array:
    """Linear between ``points`` (x ascending), the end values outside them."""
    xs = jnp.asarray([p[0] for p in points], jnp.float32)
    ys = jnp.asarray([p[1] for p in points], jnp.float32)
    return jnp.interp(jnp.asarray(x, jnp.float32), xs, ys)


def _uniform(key: jax.Array, spec) -> jax.Array:
    low = jnp.asarray(spec.plan_low, jnp.float32)
    high = jnp.asarray(spec.plan_high, jnp.float32)
    return jax.random.uniform(key, low.shape, minval=low, maxval=high)


@functools.lru_cache(maxsize=16)
def random_policy(spec, mean_hold: float = 1.0) -> mpc.Policy:
    """Uniform random actions from the env's plan box (``spec``: an ``envs.base.EnvSpec``), each held for
    a random number of steps with mean ``mean_hold`` (a fresh action is drawn with probability
    ``1 / mean_hold`` each step).  ``mean_hold=1`` draws every step independently.  Why hold: a planner
    scores sequences that keep turning or keep a speed for seconds, but independent draws average the
    steering to zero within a few steps, so the data hold few sustained turns for the model to learn
    from.  Cached per (spec, mean_hold), so collections with equal settings share one compiled rollout."""
    if not mean_hold >= 1.0:
        raise ValueError(f"random_policy: mean_hold must be >= 1 (steps each action is held), got {mean_hold}")
    resample_probability = 1.0 / float(mean_hold)

    def act(params, obs, reward_spec, held, key):
        del params, obs, reward_spec
        fresh = _uniform(key, spec)  # the same draw as without holding, so mean_hold=1 is unchanged
        draw = jnp.isnan(held[0]) | (jax.random.uniform(jax.random.fold_in(key, 1)) < resample_probability)
        action = jnp.where(draw, fresh, held)
        return action, action, {"value": jnp.zeros((), jnp.float32)}

    # The held action; NaN until the first draw.
    return mpc.Policy(act=act, init_state=lambda: jnp.full((len(spec.plan_low),), jnp.nan, jnp.float32))


@struct.dataclass
class ExplorationState:
    inner: Any  # the wrapped policy's state
    env_steps: jax.Array  # i32[]: env steps taken by the whole fleet so far (drives the schedule)
    stride: jax.Array  # i32[]: env steps per act (the number of robots stepping together)


def exploration_policy(policy: mpc.Policy, spec, *, schedule: ExplorationSchedule = PAPER_SCHEDULE) -> mpc.Policy:
    """The paper's data-collection exploration around ``policy`` (section 5.3).

    The first ``schedule.uniform_steps`` env steps are uniform from the plan box.  After that the
    policy's action gets Gaussian noise (normalised by the mid and full range of the env action box,
    sigma on ``schedule.sigma``), is clipped to the plan box, and with probability epsilon
    (``schedule.epsilon``) is replaced by a uniform action.  The env-step count lives in the policy
    state (traced), so the schedule advances without recompiling; ``collect`` sets it to the dataset's
    step count (resuming continues the schedule) and the stride to the number of robots.
    """
    low = jnp.asarray(spec.action_low, jnp.float32)
    high = jnp.asarray(spec.action_high, jnp.float32)
    plan_low = jnp.asarray(spec.plan_low, jnp.float32)
    plan_high = jnp.asarray(spec.plan_high, jnp.float32)
    mid, span = 0.5 * (low + high), high - low

    def act(params, obs, reward_spec, state: ExplorationState, key):
        k_policy, k_noise, k_eps, k_uniform = jax.random.split(key, 4)
        action, inner, info = policy.act(params, obs, reward_spec, state.inner, k_policy)
        n = state.env_steps
        sigma = piecewise_linear(schedule.sigma, n)
        eps = piecewise_linear(schedule.epsilon, n)
        noisy = (action - mid) / span + sigma * jax.random.normal(k_noise, action.shape)
        noisy = jnp.clip(noisy * span + mid, plan_low, plan_high)
        uniform = _uniform(k_uniform, spec)
        explore = (n < schedule.uniform_steps) | (jax.random.uniform(k_eps) < eps)
        action = jnp.where(explore, uniform, noisy)
        info = dict(info, sigma=sigma, epsilon=eps)
        return action, state.replace(inner=inner, env_steps=n + state.stride), info

    def init_state():
        return ExplorationState(inner=policy.init_state(), env_steps=jnp.zeros((), jnp.int32),
                                stride=jnp.ones((), jnp.int32))

    return mpc.Policy(act=act, init_state=init_state)


# ------------------------------------------------------------------------------------------ rollout


class Record(NamedTuple):
    """One step entry per robot (the dataset's per-step fields)."""

    image: jax.Array
    vector: jax.Array
    action: jax.Array
    done: jax.Array
    pose: jax.Array
    signals: dict
    task: jax.Array  # u32[2]: key data of the episode's task
    valid: jax.Array  # bool: False for a finished robot's repeated terminal entry while it waits to reset


@struct.dataclass
class Fleet:
    state: Any  # batched EnvState
    policy_state: Any
    task_key: jax.Array  # u32[R, 2]
    waiting: jax.Array  # bool[R]: finished last step but not reset yet (its next entry is a repeat)


@functools.lru_cache(maxsize=16)
def make_chunk_fn(env, policy: mpc.Policy, task_sampler: Callable, steps_per_chunk: int,
                  max_resets: int | None = None, update_spec: Callable | None = None) -> Callable:
    """``run(fleet, params, reward_spec, key) -> (fleet, Record[S, R])``: one jitted chunk of the fleet.

    ``update_spec(state, spec) -> spec`` (as in ``mpc.run_episode``) gives each robot its own goals every
    step from its state, e.g. the heading of its path; None: every robot acts on ``reward_spec`` as is.

    After a terminal entry a robot starts a fresh episode on a task drawn from its key.  Resetting
    costs a camera frame and a layout, so only up to ``max_resets`` robots (default an eighth of the
    fleet) are reset per step, chosen among the finished ones with static shapes; a finished robot
    beyond that waits on its terminal state for the next step, and its repeated entry is marked
    invalid (``Record.valid``) and never stored.  A batch-level ``lax.cond`` skips the resets
    entirely on steps where no robot finished."""

    def reset_one(key):
        task = task_sampler(key)
        return env.reset(jax.random.fold_in(key, 1), task)

    def step(carry, key):
        fleet, params, reward_spec = carry
        state = fleet.state
        robots = state.done.shape[0]
        slots = min(robots, max_resets or max(1, -(-robots // 8)))
        k_act, k_task = jax.random.split(key)
        if update_spec is None:
            specs, spec_axis = reward_spec, None
        else:
            specs, spec_axis = jax.vmap(update_spec, in_axes=(0, None))(state, reward_spec), 0
        actions, policy_state, _ = jax.vmap(policy.act, in_axes=(None, 0, spec_axis, 0, 0))(
            params, state.obs, specs, fleet.policy_state, jax.random.split(k_act, robots))
        record = Record(image=state.obs.images[:, -1], vector=state.obs.vector[:, -1], action=actions,
                        done=state.done, pose=state.info["pose"], signals=state.signals, task=fleet.task_key,
                        valid=~fleet.waiting)
        stepped = jax.vmap(env.step)(state, actions)

        def with_resets():
            # The finished robots first (stable argsort of the flags), then the first ``slots`` of them.
            order = jnp.argsort(~state.done, stable=True)[:slots]
            chosen = state.done[order]
            keys = jax.random.split(k_task, slots)
            fresh = jax.vmap(reset_one)(keys)
            waiting = state.done & ~jnp.zeros(robots, bool).at[order].set(chosen)

            def merge(f, st, old):
                keep = jnp.where(_bcast(waiting, st), old, st)  # waiting robots stay terminal
                return keep.at[order].set(jnp.where(_bcast(chosen, f), f, keep[order]))

            new_state = jax.tree.map(merge, fresh, stepped, state)
            key_data = jax.vmap(jax.random.key_data)(keys)
            task_key = fleet.task_key.at[order].set(jnp.where(chosen[:, None], key_data, fleet.task_key[order]))
            return new_state, task_key, waiting

        new_state, task_key, waiting = jax.lax.cond(
            jnp.any(state.done), with_resets, lambda: (stepped, fleet.task_key, jnp.zeros(robots, bool)))
        return (Fleet(new_state, policy_state, task_key, waiting), params, reward_spec), record

    @jax.jit
    def run(fleet, params, reward_spec, key):
        (fleet, _, _), records = jax.lax.scan(step, (fleet, params, reward_spec),
                                              jax.random.split(key, steps_per_chunk))
        return fleet, records

    return run


def _bcast(flag, leaf):
    return jnp.reshape(flag, flag.shape + (1,) * (leaf.ndim - flag.ndim))


def _semantic_renderer(env, task_sampler):
    """``render(task_key u32[b,2], pose f32[b,3]) -> semantic u8[b,h,w]`` for scene envs, else None."""
    scene_env = env.unwrapped
    if not (hasattr(scene_env, "layout") and hasattr(getattr(scene_env, "config", None), "camera")):
        return None
    from envs.camera import render  # lazy: capsjax does not import envs at module load

    def one(task_key, pose):
        scene = scene_env.layout(task_sampler(jax.random.wrap_key_data(task_key)))
        return render(scene, pose, scene_env.config.camera)[1]

    return jax.jit(jax.vmap(one))


# Cached per env object, so repeated or resumed collections with the same env reuse compiled code.
@functools.lru_cache(maxsize=16)
def _episode_env(env, episode_length):
    from envs.base import EpisodeWrapper

    return env if episode_length is None else EpisodeWrapper(env, episode_length)


@functools.lru_cache(maxsize=16)
def _default_sampler(env, split: str) -> Callable:
    return lambda key: env.sample_task(key, split)


@functools.lru_cache(maxsize=16)
def _fleet_reset(env, task_sampler: Callable) -> Callable:
    return jax.jit(jax.vmap(lambda k: env.reset(jax.random.fold_in(k, 1), task_sampler(k))))


@functools.lru_cache(maxsize=16)
def _cached_renderer(env, task_sampler: Callable):
    return _semantic_renderer(env, task_sampler)


class _Splitter:
    """Host side: cuts each robot's stream of step entries into complete episodes."""

    def __init__(self, robots: int):
        self.pending: list[list[dict]] = [[] for _ in range(robots)]

    def feed(self, records: dict) -> list[dict]:
        """``records``: field -> [S, R, ...] (with 'valid'); returns the episodes completed in this chunk."""
        valid = records.pop("valid")
        out = []
        for r in range(valid.shape[1]):
            rows = np.flatnonzero(valid[:, r])
            stream = {k: v[rows, r] for k, v in records.items()}
            ends = np.flatnonzero(stream["done"])
            begin = 0
            for e in ends:
                piece = {k: v[begin: e + 1] for k, v in stream.items()}
                parts = self.pending[r] + [piece]
                out.append({k: np.concatenate([p[k] for p in parts]) for k in piece})
                self.pending[r] = []
                begin = e + 1
            if begin < rows.size:
                self.pending[r].append({k: v[begin:] for k, v in stream.items()})
        return out


def _flatten(record: Record) -> dict:
    out = {"image": record.image, "vector": record.vector, "action": record.action, "done": record.done,
           "pose": record.pose, "task": record.task, "valid": record.valid}
    out.update({f"signal/{k}": v for k, v in record.signals.items()})
    return out


# Env config fields added after datasets and evaluations were stored, keyed by their path in the config, with
# the value every earlier config implicitly had: at that value they are left out of the comparison, so the
# stored work of older versions stays valid, and any other value tells the configs apart.
_ADDED_LATER = {("camera", "projection"): "pinhole",
                # the forest's goal path for the reward's path term (2026-12-06); info only, nothing stored
                ("goal_path_length",): 10.0, ("goal_path_points",): 16}


def comparable_settings(settings: dict) -> dict:
    """An env's spec or config as stored work is compared on: without its observation ``history`` (one frame is
    stored per step, so the history length does not change what is stored -- ``make_sampler`` draws any history
    -- and a dataset is reused across it), and without later-added fields at their old implicit values
    (``_ADDED_LATER``).  Datasets of older versions, whose env config lacked those fields, stay usable."""
    out = {k: v for k, v in settings.items() if k != "history"}
    for field_path, old in _ADDED_LATER.items():
        out = _without_default(out, field_path, old)
    return out


def _without_default(settings: dict, field_path: tuple, old) -> dict:
    """``settings`` without the field at ``field_path`` when it holds ``old`` (or is absent)."""
    head, *rest = field_path
    if not rest:
        return {k: v for k, v in settings.items() if not (k == head and v == old)}
    if not isinstance(settings.get(head), dict):
        return settings
    return dict(settings, **{head: _without_default(settings[head], tuple(rest), old)})


def collect(env_name_or_env, policy: mpc.Policy, params, spec, *, path, num_steps: int, num_robots: int,
            key: jax.Array, labelled_fraction: float = 0.002, steps_per_chunk: int = 64, split: str = "train",
            task_sampler: Callable | None = None, episode_length: int | None = 200,
            policy_name: str | dict = "custom", chunk_steps: int = 1024, max_resets_per_step: int | None = None,
            progress: bool = True, mesh: Mesh | None = None, update_spec: Callable | None = None) -> Dataset:
    """Roll out ``num_robots`` robots under ``policy`` until the dataset at ``path`` holds ``num_steps``
    committed steps; returns the dataset (reopened read-only).

    ``spec`` is what the policy's ``act`` receives (a ``RewardSpec`` for CAPs; ignored by random
    policies).  Tasks come from ``task_sampler(key)`` (default ``env.sample_task(key, split)``), a new
    one for every episode.  ``episode_length`` caps episodes (``EpisodeWrapper``; None: only crashes and
    task ends finish them).  An existing store at ``path`` is appended to (or, when it holds enough
    steps already, reused), never overwritten, after checking that it was recorded in the same env by
    a policy of the same ``policy_name``.  Episodes still running when the target is reached
    are dropped (only complete episodes are stored).  ``max_resets_per_step`` and ``update_spec`` (per-robot
    goals from each robot's state, for a goal-following policy): see ``make_chunk_fn``.

    ``mesh`` (e.g. ``sharding.make_mesh()``): the robots are split over its devices (the fleet's robot
    axis sharded, ``params`` and ``spec`` replicated), so the same jitted chunk runs data-parallel;
    ``num_robots`` must be a multiple of the mesh size.  None: everything on the default device.  The
    random streams do not depend on the placement, so the same key gives the same episodes either way.
    """
    import envs  # lazy: capsjax does not import envs at module load

    if isinstance(env_name_or_env, str):
        env_name, env = env_name_or_env, envs.make(env_name_or_env)
    else:
        env = env_name_or_env
        env_name = _registry_name(env.unwrapped)
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    if num_robots < 1 or steps_per_chunk < 1 or num_steps < 1:
        raise ValueError(f"num_robots, steps_per_chunk and num_steps must be >= 1, got {num_robots}, "
                         f"{steps_per_chunk}, {num_steps}")
    if not 0.0 <= labelled_fraction <= 1.0:
        raise ValueError(f"labelled_fraction must be in [0, 1], got {labelled_fraction}")
    if mesh is not None and num_robots % mesh.devices.size:
        raise ValueError(f"num_robots must be a multiple of the {mesh.devices.size} devices of the mesh, "
                         f"got num_robots={num_robots}")
    base_env = env
    env = _episode_env(base_env, episode_length)
    sampler = task_sampler or _default_sampler(base_env, split)
    env_config = _jsonable(getattr(base_env.unwrapped, "config", {}))
    render_semantic = _cached_renderer(base_env, sampler)

    if os.path.exists(path):
        ds = Dataset.open(path, "a")
        stored = comparable_settings
        for field, have, want in (("env_name", ds.env_name, env_name),
                                  ("spec", stored(_jsonable(ds.spec)), stored(_jsonable(env.spec))),
                                  ("env_config", stored(ds.env_config), stored(env_config)),
                                  ("policy", ds.policy, _jsonable(policy_name))):
            if have != want:
                raise ValueError(f"the dataset at {path!r} has {field} {have!r}; this collection has {want!r} "
                                 f"(a stored dataset is appended to or reused only with the same {field}; collect into another path)")
    else:
        ds = Dataset.create(path, env_name=env_name, env_config=env_config, spec=env.spec,
                            policy=_jsonable(policy_name), chunk_steps=chunk_steps,
                            has_semantic=render_semantic is not None)
    if ds.num_steps >= num_steps:
        return Dataset.open(path, "r")

    # Initial fleet: fresh tasks, policy state per robot (exploration schedules resume at the step count).
    key, k_init = jax.random.split(key)
    init_keys = jax.random.split(k_init, num_robots)
    state = _fleet_reset(env, sampler)(init_keys)
    policy_state = jax.vmap(lambda _: policy.init_state())(jnp.arange(num_robots))
    if isinstance(policy_state, ExplorationState):
        policy_state = policy_state.replace(
            env_steps=jnp.asarray(ds.num_steps + np.arange(num_robots), jnp.int32),
            stride=jnp.full((num_robots,), num_robots, jnp.int32))
    fleet = Fleet(state=state, policy_state=policy_state, task_key=jax.vmap(jax.random.key_data)(init_keys),
                  waiting=jnp.zeros(num_robots, bool))
    if mesh is not None:
        # jit follows the arguments' shardings: robot-sharded fleet in, robot-sharded fleet and records out.
        fleet = sharding.shard_robots(fleet, mesh)
        params, spec, key = sharding.replicate((params, spec, key), mesh)
    run = make_chunk_fn(env, policy, sampler, steps_per_chunk, max_resets_per_step, update_spec)
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).astype(np.uint64))
    split_code = SPLITS.index(split)
    h, w, _ = env.spec.image_shape

    # Writer thread: host splitting, semantic re-rendering and zarr appends overlap the next chunk.
    todo: queue.Queue = queue.Queue(maxsize=2)
    errors: list[BaseException] = []
    splitter = _Splitter(num_robots)
    bar = _progress(progress, num_steps, ds.num_steps)

    def write(records: dict) -> None:
        episodes = splitter.feed(records)
        room = num_steps - ds.num_steps
        kept, total = [], 0
        for ep in episodes:
            if total >= room:
                break
            kept.append(ep)
            total += len(ep["done"])
        if not kept:
            return
        lengths = np.array([len(ep["done"]) for ep in kept], np.int64)
        batch = {k: np.concatenate([ep[k] for ep in kept]) for k in kept[0] if k != "task"}
        batch["task"] = np.stack([ep["task"][0] for ep in kept])
        batch["split"] = np.full(len(kept), split_code, np.uint8)
        n = int(lengths.sum())
        if render_semantic is not None and labelled_fraction > 0:
            index = np.flatnonzero(rng.random(n) < labelled_fraction)
            task_of_step = np.repeat(batch["task"], lengths, axis=0)
            batch["labelled_index"] = index
            batch["semantic"] = _render_padded(render_semantic, task_of_step[index], batch["pose"][index], (h, w))
        ds.append_episodes(batch, lengths)
        bar.update(n)

    def writer() -> None:
        while True:
            item = todo.get()
            try:
                if item is None:
                    return
                if not errors:
                    write(item)
            except BaseException as err:  # noqa: BLE001 -- re-raised in the main thread
                errors.append(err)
            finally:
                todo.task_done()

    thread = threading.Thread(target=writer, daemon=True)
    thread.start()
    start_steps, per_chunk = ds.num_steps, num_robots * steps_per_chunk
    try:
        key, k_chunk = jax.random.split(key)
        fleet, records = run(fleet, params, spec, k_chunk)
        produced = per_chunk
        while True:
            # Dispatch the next chunk before fetching this one, so the device computes while the host
            # copies, splits, compresses and writes.  ``produced`` counts unfinished episodes too, so it
            # is an upper bound of what will be committed: stop the pipeline there ...
            nxt = None
            if start_steps + produced < num_steps:
                key, k_chunk = jax.random.split(key)
                nxt = run(fleet, params, spec, k_chunk)
                produced += per_chunk
            todo.put({k: np.asarray(v) for k, v in _flatten(records).items()})
            if nxt is None:
                # ... and go on one chunk at a time while episodes still running keep the count short.
                todo.join()
                if errors or ds.num_steps >= num_steps:
                    break
                key, k_chunk = jax.random.split(key)
                nxt = run(fleet, params, spec, k_chunk)
                produced += per_chunk
            fleet, records = nxt
            if errors:
                break
    finally:
        todo.put(None)
        thread.join()
        bar.close()
    if errors:
        raise errors[0]
    return Dataset.open(path, "r")


def _render_padded(render_fn, task_keys: np.ndarray, poses: np.ndarray, hw: tuple[int, int], bucket: int = 32):
    """Render in fixed batches of ``bucket`` (padded) so the renderer compiles once."""
    n = task_keys.shape[0]
    out = np.zeros((n,) + hw, np.uint8)
    for s in range(0, n, bucket):
        k = np.zeros((bucket, 2), np.uint32)
        p = np.zeros((bucket, 3), np.float32)
        b = min(bucket, n - s)
        k[:b], p[:b] = task_keys[s: s + b], poses[s: s + b]
        out[s: s + b] = np.asarray(render_fn(k, p))[:b]
    return out


def _registry_name(env) -> str:
    """The registry name of an env object (``ForestEnv`` -> 'forest'), else its class name."""
    import envs

    cls = type(env).__name__
    for name in envs.ALL_ENVS:
        if cls.lower() == f"{name}env":
            return name
    return cls


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress(enabled: bool, total: int, initial: int):
    if not enabled:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="step", desc="collect")
