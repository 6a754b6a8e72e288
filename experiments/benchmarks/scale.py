"""``python -m experiments.bench scale``: data-parallel training and sharded env stepping on 1 and N devices.

JSON lines (``experiments.bench.emit``):

* ``scale.train_samples_per_s_<n>dev``: training windows per second of the paper's CARLA CAPs model
  (``experiments.benchmarks.planner.PAPER_MODEL``, 50x100 grayscale, H = 12), batch ``--batch`` sharded
  over ``n`` devices with the state replicated (``capsjax.sharding``), ``--steps`` steps per jitted
  chunk, median of ``--repeats`` chunks after compilation;
* ``scale.env_steps_per_s_<n>dev``: fast-world control steps per second, ``--robots`` robots sharded
  over ``n`` devices, ``--env-steps`` steps in one ``lax.scan`` (collection's inner loop without the
  policy and the disk);
* ``scale.collect_steps_per_s_<n>dev``: committed steps per second of ``capsjax.collect.collect`` (random
  policy, fast world, ``--robots`` robots sharded over ``n`` devices with ``mesh=``, zarr store in a
  temporary directory, no labelled frames), ``--collect-steps`` steps per timed collection, median of
  ``--repeats`` collections into fresh stores after a first one that compiles;
* ``scale.train_ratio_<n>dev_vs_1dev`` / ``scale.env_ratio_<n>dev_vs_1dev`` / ``scale.collect_ratio_<n>dev_vs_1dev``:
  the same-run ratios;
* with a GPU present, the same figures on it with the suffix ``_gpu``.

CPU device counts are forced with ``XLA_FLAGS=--xla_force_host_platform_device_count=n``, which must be
set before JAX starts, so each count runs in its own subprocess (``--worker n``).  Forced CPU devices
share the machine's cores: expect no speed-up there; the ratio shows the cost of the collectives.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments.bench import emit


def _median_time(fn, arg, repeats: int) -> float:
    jax.block_until_ready(fn(arg))  # compile and warm up
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(arg))
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def _synthetic_windows(model, count: int):
    """A device-resident buffer of ``count`` random windows shaped for ``model`` (throughput only)."""
    from capsjax.losses import Batch
    from envs.base import Observation

    cfg = model.config
    k = jax.random.split(jax.random.key(0), 4)
    obs = Observation(
        images=jax.random.randint(k[0], (count, cfg.history) + cfg.image_shape, 0, 256).astype(jnp.uint8),
        vector=jax.random.uniform(k[1], (count, cfg.history, len(cfg.vector_keys))),
    )
    actions = jax.random.uniform(k[2], (count, cfg.horizon, cfg.action_dim), minval=-1.0, maxval=1.0)
    signals = {c.source: jax.random.uniform(jax.random.fold_in(k[3], i), (count, cfg.horizon))
               for i, c in enumerate(cfg.cues)}
    return Batch(obs=obs, actions=actions, signals=signals, valid=jnp.ones((count, cfg.horizon), bool))


def train_samples_per_s(mesh, batch: int, steps: int, repeats: int) -> float:
    from capsjax import CAPsModel, TrainConfig, init_train_state, sharding, training
    from experiments.benchmarks.planner import PAPER_MODEL

    model = CAPsModel(PAPER_MODEL)
    cfg = TrainConfig(batch_size=batch)
    buffer = _synthetic_windows(model, 4 * batch)

    def sample(key):
        idx = jax.random.randint(key, (batch,), 0, 4 * batch)
        return jax.tree.map(lambda x: x[idx], buffer)

    state = sharding.replicate(init_train_state(model, cfg, jax.random.key(1)), mesh)
    train = training.make_train(model, cfg, sample, steps, mesh=mesh)
    return batch * steps / _median_time(lambda s: train(s)[0].step, state, repeats)


def env_steps_per_s(mesh, robots: int, steps: int, repeats: int) -> float:
    from capsjax import sharding
    from envs.fast import FastEnv

    env = FastEnv()
    keys = jax.random.split(jax.random.key(2), robots)
    tasks = jax.vmap(env.sample_task)(keys)
    state = sharding.shard_robots(jax.jit(jax.vmap(env.reset))(keys, tasks), mesh)
    low, high = jnp.asarray(env.spec.plan_low), jnp.asarray(env.spec.plan_high)
    actions = jax.random.uniform(jax.random.key(3), (steps, robots, env.spec.action_dim), minval=low, maxval=high)
    actions = jax.device_put(actions, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(None, "data")))

    @jax.jit
    def rollout(state):
        return jax.lax.scan(lambda s, a: (jax.vmap(env.step)(s, a), None), state, actions)[0].done

    return robots * steps / _median_time(rollout, state, repeats)


def collect_steps_per_s(mesh, robots: int, steps: int, repeats: int) -> float:
    """End-to-end collection (rollout, host splitting, zarr writes) with the fleet sharded over ``mesh``."""
    from capsjax import collect
    from envs.fast import FastEnv

    env = FastEnv()
    policy = collect.random_policy(env.spec)
    times, committed = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeats + 1):  # the first one compiles the chunk and is not timed
            start = time.perf_counter()
            ds = collect.collect(env, policy, None, None, path=os.path.join(tmp, f"run{i}.zarr"), num_steps=steps,
                                 num_robots=robots, key=jax.random.key(i), labelled_fraction=0.0,
                                 episode_length=100, progress=False, mesh=mesh)
            if i:
                times.append(time.perf_counter() - start)
                committed.append(ds.num_steps)
    return float(np.median(np.asarray(committed) / np.asarray(times)))


def measure(suffix: str, args) -> dict:
    from capsjax import sharding

    mesh = sharding.make_mesh()
    n = mesh.devices.size
    context = dict(batch=args.batch, steps=args.steps, robots=args.robots, env_steps=args.env_steps,
                   collect_steps=args.collect_steps,
                   model="paper CARLA CAPs (50x100x1, H=12)", mesh_devices=n)
    out = {}
    out["train"] = emit(f"scale.train_samples_per_s_{suffix}", train_samples_per_s(mesh, args.batch, args.steps, args.repeats),
                        "samples/s", **context)["value"]
    out["env"] = emit(f"scale.env_steps_per_s_{suffix}", env_steps_per_s(mesh, args.robots, args.env_steps, args.repeats),
                      "steps/s", **context)["value"]
    out["collect"] = emit(f"scale.collect_steps_per_s_{suffix}",
                          collect_steps_per_s(mesh, args.robots, args.collect_steps, args.repeats),
                          "steps/s", **context)["value"]
    return out


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench scale")
    parser.add_argument("--devices", default="1,4", help="forced CPU device counts, comma-separated")
    parser.add_argument("--batch", type=int, default=32, help="training batch (a multiple of every device count)")
    parser.add_argument("--steps", type=int, default=10, help="training steps per timed chunk")
    parser.add_argument("--robots", type=int, default=64)
    parser.add_argument("--env-steps", type=int, default=100)
    parser.add_argument("--collect-steps", type=int, default=20_000, help="committed steps per timed collection")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--worker", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.worker:  # inside a subprocess with the forced device count
        measure(f"{args.worker}dev", args)
        return
    counts = [int(c) for c in args.devices.split(",")]
    results = {}
    for n in counts:
        env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS=f"--xla_force_host_platform_device_count={n}")
        cmd = [sys.executable, "-m", "experiments.bench", "scale", "--worker", str(n)] + argv
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
        if proc.returncode:
            raise SystemExit(f"scale worker with {n} devices failed:\n{proc.stderr[-4000:]}")
        results[n] = {}
        for line in proc.stdout.splitlines():
            if line.startswith("{"):
                print(line, flush=True)
                record = json.loads(line)
                results[n][record["metric"].split(".")[1].split("_")[0]] = record["value"]
    base = min(counts)
    for n in counts:
        if n != base:
            for what in ("train", "env", "collect"):
                emit(f"scale.{what}_ratio_{n}dev_vs_{base}dev", results[n][what] / results[base][what], "ratio",
                     note="forced CPU devices share the same cores: no speed-up is expected")
    if jax.default_backend() == "gpu":
        measure("gpu", args)
