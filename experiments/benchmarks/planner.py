"""``python -m experiments.bench planner``: CEM plan latency and FLOP efficiency at the paper's settings.

The headline figure is ``planner.flop_efficiency``: the achieved GFLOP/s of a paper-config plan (an
analytic count of the model's multiply-adds over all 7,168 candidate rollouts) divided by this
machine's dense float32 matmul GFLOP/s measured in the same run, so the figure is comparable across
machines and robust to a noisy neighbour.  Batched planning (many robots in one vmap) is reported as
per-robot efficiency relative to one robot.
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from capsjax import cues, planner
from capsjax.model import CAPsModel, ModelConfig, rollout_flops
from capsjax.reward import RewardSpec
from envs.base import Observation
from experiments.bench import emit

# The paper's CARLA CAPs model: 50x100 grayscale, 9 vector entries, (steer, motor), five cues.
PAPER_MODEL = ModelConfig(
    image_shape=(50, 100, 1),
    vector_keys=("coll", "coll_car", "coll_ped", "coll_oth", "heading", "speed", "accel_x", "accel_y", "accel_z"),
    vector_low=(0, 0, 0, 0, -np.pi, -30, -100, -100, -100),
    vector_high=(1, 1, 1, 1, np.pi, 30, 100, 100, 100),
    action_low=(-1.0, -1.0),
    action_high=(1.0, 1.0),
    cues=(cues.COLLISION, cues.SPEED, cues.HEADING, cues.LANE_SEEN, cues.LANE_DIFF),
)
PAPER_CEM = planner.CEMConfig.paper(action_low=(-1.0, 0.3), action_high=(1.0, 1.0))


def matmul_gflops(n: int = 2048, repeats: int = 5) -> float:
    """Dense float32 matmul rate of this device (the reference for the efficiency ratio): the best of
    ``repeats`` timings, since a reference should measure what the machine can do."""
    a = jax.random.normal(jax.random.key(0), (n, n), jnp.float32)
    b = jax.random.normal(jax.random.key(1), (n, n), jnp.float32)
    f = jax.jit(lambda a, b: a @ b)
    f(a, b).block_until_ready()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        f(a, b).block_until_ready()
        times.append(time.perf_counter() - t)
    return 2 * n**3 / min(times) / 1e9


def _inputs(model: CAPsModel, robots: int | None):
    cfg = model.config
    key = jax.random.key(0)
    images = jax.random.randint(key, (cfg.history,) + cfg.image_shape, 0, 256).astype(jnp.uint8)
    obs = Observation(images, jnp.zeros((cfg.history, len(cfg.vector_keys)), jnp.float32))
    spec = RewardSpec.from_terms(model, collision=50, speed=3, lane=5, steer=0.15, heading_angle=5,
                                 goal_speed=7.0, goal_heading=(1.0, 0.0))
    state = planner.init_plan_state(PAPER_CEM)
    if robots is None:
        return obs, spec, state
    stack = lambda x: jnp.broadcast_to(x, (robots,) + jnp.shape(x))
    return jax.tree.map(stack, obs), jax.tree.map(stack, spec), jax.tree.map(stack, state)


def time_plans(model, params, robots: int | None, num_plans: int, rounds: int, cfg=PAPER_CEM):
    """Compile seconds, per-call latencies (s) and the matmul reference (GFLOP/s) of each call's round.

    Plans and reference matmuls are interleaved in ``rounds`` so that a noisy neighbour affects both
    sides of the efficiency ratio alike.
    """
    obs, spec, state = _inputs(model, robots)
    if robots is None:
        fn = lambda k: planner.jit_plan(model, params, obs, spec, state, k, cfg=cfg)
        keys = jax.random.split(jax.random.key(1), num_plans + 1)
    else:
        fn = lambda k: planner.jit_plan_batch(model, params, obs, spec, state, k, cfg=cfg)
        keys = jax.random.split(jax.random.key(1), (num_plans + 1, robots))
    t = time.perf_counter()
    jax.block_until_ready(fn(keys[0]))
    compile_s = time.perf_counter() - t
    latencies, references = [], []
    per_round = max(1, num_plans // rounds)
    for i, k in enumerate(keys[1:]):
        if i % per_round == 0:
            reference = matmul_gflops()
        t = time.perf_counter()
        jax.block_until_ready(fn(k))
        latencies.append(time.perf_counter() - t)
        references.append(reference)
    return compile_s, np.asarray(latencies), np.asarray(references)


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench planner", description=__doc__)
    parser.add_argument("--plans", type=int, default=50, help="timed single-robot plans (>= 50 for the p90)")
    parser.add_argument("--batches", type=str, default="1,16,64", help="robot counts for batched planning")
    parser.add_argument("--batch-plans", type=int, default=5, help="timed calls per robot count")
    parser.add_argument("--gpu-robots", type=int, default=1024, help="robots for the GPU throughput figure")
    parser.add_argument("--gpu-candidate-chunk", type=int, default=0,
                        help="CEMConfig.candidate_chunk for the GPU figure (0 = auto: every candidate at once, "
                             "which needs at least 18 MiB of GPU memory per robot at the paper's settings)")
    args = parser.parse_args(argv)

    model = CAPsModel(PAPER_MODEL)
    params = model.init(jax.random.key(0))
    cem = PAPER_CEM
    candidates = cem.init_samples + (cem.iterations - 1) * cem.samples
    flops = candidates * rollout_flops(model.config, cem.horizon)
    context = dict(model="paper_carla", horizon=cem.horizon, candidates=candidates,
                   cem=f"{cem.init_samples}+{cem.iterations - 1}x{cem.samples}/elites{cem.elites}")

    compile_s, lat, refs = time_plans(model, params, None, args.plans, rounds=10)
    p50 = float(np.median(lat))
    emit("planner.matmul_gflops", float(np.median(refs)), "GFLOP/s", matmul_n=2048)
    emit("planner.compile_s", compile_s, "s", **context)
    emit("planner.plan_ms_p50", 1e3 * p50, "ms", plans=args.plans, **context)
    emit("planner.plan_ms_p90", 1e3 * float(np.percentile(lat, 90)), "ms", plans=args.plans, **context)
    emit("planner.candidates_per_s", candidates / p50, "1/s", **context)
    emit("planner.plan_gflops", flops / p50 / 1e9, "GFLOP/s", flops_per_plan=flops, **context)
    # Each plan against the reference of its own round, then the median: robust to load drifting.
    efficiency = float(np.median(flops / lat / 1e9 / refs))
    emit("planner.flop_efficiency", efficiency, "ratio", matmul_gflops=float(np.median(refs)), **context)

    per_robot_eff = {}
    for robots in [int(b) for b in args.batches.split(",") if b]:
        _, lat_b, refs_b = time_plans(model, params, robots, args.batch_plans, rounds=args.batch_plans)
        per_robot_eff[robots] = float(np.median(robots * flops / lat_b / 1e9 / refs_b))
        emit(f"planner.batch{robots}_plan_ms", 1e3 * float(np.median(lat_b)), "ms", robots=robots, **context)
        emit(f"planner.batch{robots}_flop_efficiency", per_robot_eff[robots], "ratio", robots=robots, **context)
    if 1 in per_robot_eff and 64 in per_robot_eff:
        emit("planner.batch64_relative_efficiency", per_robot_eff[64] / per_robot_eff[1], "ratio", **context)

    if jax.devices()[0].platform == "gpu":
        gpu_cem = dataclasses.replace(cem, candidate_chunk=args.gpu_candidate_chunk)
        try:
            _, lat_g, _ = time_plans(model, params, args.gpu_robots, args.batch_plans, rounds=1, cfg=gpu_cem)
        except jax.errors.JaxRuntimeError as err:
            if "RESOURCE_EXHAUSTED" not in str(err):
                raise
            # Measured on an H200 (141 GB): 4,096 robots with every candidate at once ask for one 72 GiB buffer.
            raise SystemExit(f"planner.gpu_plans_per_s: --gpu-robots {args.gpu_robots} do not fit in GPU memory with "
                             f"--gpu-candidate-chunk {args.gpu_candidate_chunk}; pass fewer robots or a smaller chunk "
                             f"(e.g. --gpu-candidate-chunk 1024)") from None
        emit("planner.gpu_plans_per_s", args.gpu_robots / float(np.median(lat_g)), "plans/s",
             robots=args.gpu_robots, candidate_chunk=args.gpu_candidate_chunk, **context)
