"""Collection throughput: ``python -m experiments.bench collect [--scene forest] [--steps 100000] [--robots 256]``

JSON lines (``experiments.bench.emit``):

* ``collect.<scene>.steps_per_s``: committed dataset steps per second of ``capsjax.collect.collect``
  with the uniform random policy -- rollout, host splitting, semantic maps of the labelled fraction,
  compression and zarr writes included, compilation excluded (compiled before the clock starts);
* ``collect.<scene>.env_only_steps_per_s``: the reference from the same run, the same compiled chunk
  function (policy, env step, auto-reset) run back to back with nothing fetched or written;
* ``collect.<scene>.disk_overhead_ratio``: steps_per_s / env_only_steps_per_s (1.0 = disk writes fully hidden);
* ``collect.<scene>.minutes_for_800k``: the projected time of the paper's 800,000-step dataset;
* ``collect.<scene>.bytes_per_step``: bytes on disk per stored step (compressed), and ``compile_s``.

The dataset goes to ``--out`` (default: a temporary directory, removed afterwards).
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from capsjax import collect as collect_lib
from experiments.bench import emit


def _dir_bytes(path: str) -> int:
    return sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(path) for f in files)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench collect")
    parser.add_argument("--scene", default="forest", choices=envs.ALL_ENVS)
    parser.add_argument("--steps", type=int, default=100_000)
    parser.add_argument("--robots", type=int, default=256)
    parser.add_argument("--steps-per-chunk", type=int, default=32)
    parser.add_argument("--episode-length", type=int, default=200)
    parser.add_argument("--reference-chunks", type=int, default=4, help="chunks timed for the env-only reference")
    parser.add_argument("--out", default=None, help="dataset path (default: a temporary directory, removed)")
    args = parser.parse_args(argv)

    env = envs.make(args.scene)
    policy = collect_lib.random_policy(env.spec)
    context = dict(scene=args.scene, robots=args.robots, steps=args.steps, steps_per_chunk=args.steps_per_chunk,
                   episode_length=args.episode_length, policy="uniform random", image=list(env.spec.image_shape),
                   cpu_count=os.cpu_count(), load_avg_1m=os.getloadavg()[0])

    # Compile everything collect() uses (the same cached functions) before any clock starts.
    start = time.perf_counter()
    wrapped = collect_lib._episode_env(env, args.episode_length)
    sampler = collect_lib._default_sampler(env, "train")
    run = collect_lib.make_chunk_fn(wrapped, policy, sampler, args.steps_per_chunk, None)  # as collect() calls it
    keys = jax.random.split(jax.random.key(0), args.robots)
    state = collect_lib._fleet_reset(wrapped, sampler)(keys)
    fleet = collect_lib.Fleet(state=state, policy_state=jax.vmap(lambda _: policy.init_state())(jnp.arange(args.robots)),
                              task_key=jax.vmap(jax.random.key_data)(keys), waiting=jnp.zeros(args.robots, bool))
    fleet, records = run(fleet, None, None, jax.random.key(1))
    jax.block_until_ready(records)
    renderer = collect_lib._cached_renderer(env, sampler)
    if renderer is not None:
        h, w, _ = env.spec.image_shape
        collect_lib._render_padded(renderer, np.zeros((1, 2), np.uint32), np.zeros((1, 3), np.float32), (h, w))
    emit(f"collect.{args.scene}.compile_s", time.perf_counter() - start, "s", **context)

    # Reference: the compiled rollout alone, nothing leaves the device.
    start = time.perf_counter()
    for i in range(args.reference_chunks):
        fleet, records = run(fleet, None, None, jax.random.key(2 + i))
    jax.block_until_ready((fleet, records))
    env_only = args.reference_chunks * args.robots * args.steps_per_chunk / (time.perf_counter() - start)
    emit(f"collect.{args.scene}.env_only_steps_per_s", env_only, "steps/s", **context)

    out = args.out or os.path.join(tempfile.mkdtemp(prefix="capsjax-collect-"), "data.zarr")
    try:
        start = time.perf_counter()
        ds = collect_lib.collect(env, policy, None, None, path=out, num_steps=args.steps, num_robots=args.robots,
                                 key=jax.random.key(3), steps_per_chunk=args.steps_per_chunk,
                                 episode_length=args.episode_length, policy_name="uniform random", progress=False)
        elapsed = time.perf_counter() - start
        rate = ds.num_steps / elapsed
        context.update(committed_steps=ds.num_steps, episodes=ds.num_episodes, labelled_frames=ds.num_labelled,
                       seconds=elapsed, load_avg_1m_after=os.getloadavg()[0])
        emit(f"collect.{args.scene}.steps_per_s", rate, "steps/s", **context)
        emit(f"collect.{args.scene}.disk_overhead_ratio", rate / env_only, "ratio", **context)
        emit(f"collect.{args.scene}.minutes_for_800k", 800_000 / rate / 60, "min", **context)
        emit(f"collect.{args.scene}.bytes_per_step", _dir_bytes(out) / max(ds.num_steps, 1), "B", **context)
    finally:
        if args.out is None:
            shutil.rmtree(os.path.dirname(out), ignore_errors=True)
