"""``python -m experiments.forest``: train CAPs once, then drive unseen layouts under a composed reward.

INTERIM VERSION.  Until the MJX forest scene and the off-policy dataset pipeline land (issues 3, 4
and 6), this runs on the *fast analytic world* (``envs.fast``), not on the forest, and trains on
exactly labelled synthetic windows (random states, random action sequences), not on recorded
episodes.  What it does show end to end: one CAPs model trained once, then evaluated with the
paper's forest reward (500 * no-collision + heading cosine) on obstacle layouts drawn from the
evaluation seed stream, disjoint from the training layouts.  The task is to reach a goal location:
the goal heading is the direction from the car to the goal, recomputed every control step (as the
paper's CARLA goals).  Beside CAPs: a drive-straight policy and the exact-model oracle (the best any
predictor could do with this planner and reward).
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import tyro

import capsjax
from capsjax import mpc
from envs.fast import FastEnv, FastOracle, random_windows


@dataclasses.dataclass(frozen=True)
class Config:
    """Settings of the interim forest experiment (fast analytic world)."""

    preset: str = "small"
    """'ci' (about a minute), 'small' (the default, a few minutes on a 2-core CPU) or 'paper' (larger)."""
    seed: int = 0
    """Seed of the evaluation layouts and goals (training always uses the disjoint 'train' stream)."""
    out: Path = Path("results/forest")
    """Output folder; each run writes into a sub-folder named by the preset and seed."""
    train_tasks: int | None = None
    """Training layouts (default from the preset)."""
    windows_per_task: int | None = None
    """Labelled windows per training layout (default from the preset)."""
    train_steps: int | None = None
    """Gradient steps (default from the preset)."""
    eval_robots: int | None = None
    """Evaluation episodes, one robot each, in one vmap (default from the preset)."""
    eval_steps: int = 48
    """Control steps per evaluation episode (0.25 s each)."""


PRESETS = {
    "ci": dict(train_tasks=8, windows_per_task=64, train_steps=300, eval_robots=4, cem=(256, 128, 3, 16)),
    "small": dict(train_tasks=64, windows_per_task=128, train_steps=4000, eval_robots=12, cem=(1024, 256, 4, 32)),
    "paper": dict(train_tasks=256, windows_per_task=512, train_steps=30000, eval_robots=48, cem=(4096, 1024, 4, 128)),
}


def main(cfg: Config) -> dict:
    if cfg.preset not in PRESETS:
        raise SystemExit(f"--preset must be one of {sorted(PRESETS)}, got {cfg.preset!r}")
    preset = PRESETS[cfg.preset]
    settings = {k: getattr(cfg, k) if getattr(cfg, k) is not None else preset[k]
                for k in ("train_tasks", "windows_per_task", "train_steps", "eval_robots")}
    run_dir = cfg.out / f"{cfg.preset}_seed{cfg.seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    env = FastEnv()
    horizon = 12
    timings = {}

    # 1. Data: exactly labelled windows from the training layouts.
    t = time.time()
    train_tasks = jax.vmap(lambda k: env.sample_task(k, "train"))(jax.random.split(jax.random.key(10_000), settings["train_tasks"]))
    keys = jax.random.split(jax.random.key(1), settings["train_tasks"])
    data = jax.jit(jax.vmap(lambda k, task: random_windows(env, k, task, settings["windows_per_task"], horizon)))(keys, train_tasks)
    data = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), data)
    num_windows = int(data.actions.shape[0])
    timings["data_s"] = time.time() - t
    print(f"[forest] {num_windows} labelled windows from {settings['train_tasks']} layouts in {timings['data_s']:.1f}s")

    # 2. Train CAPs (paper architecture; collision and heading cues, as in the paper's forest).
    t = time.time()
    model = capsjax.CAPsModel(capsjax.ModelConfig.from_env_spec(
        env.spec, cues=(capsjax.cues.COLLISION, capsjax.cues.HEADING), horizon=horizon))
    train_cfg = capsjax.TrainConfig(learning_rate=1e-3, batch_size=32)
    state = capsjax.init_train_state(model, train_cfg, jax.random.key(2))

    def sample(key):
        return jax.tree.map(lambda x: x[jax.random.randint(key, (train_cfg.batch_size,), 0, num_windows)], data)

    chunk = min(500, settings["train_steps"])
    train = capsjax.make_train(model, train_cfg, sample, chunk)
    losses = []
    for done in range(0, settings["train_steps"], chunk):
        state, metrics = train(state)
        losses.append(float(metrics["loss"].mean()))
        print(f"[forest] step {done + chunk}: loss {losses[-1]:.4f}")
    timings["train_s"] = time.time() - t

    # 3. Evaluate on layouts and goal headings from the evaluation stream.
    t = time.time()
    init, samples, iterations, elites = preset["cem"]
    cem = capsjax.CEMConfig(env.spec.plan_low, env.spec.plan_high, horizon=horizon, init_samples=init,
                            samples=samples, iterations=iterations, elites=elites)
    n = settings["eval_robots"]
    eval_key = jax.random.key(1_000_000 + cfg.seed)
    eval_tasks = jax.vmap(lambda k: env.sample_task(k, "eval"))(jax.random.split(eval_key, n))
    goals = jax.vmap(lambda k, task: free_goal(env, k, task))(jax.random.split(jax.random.fold_in(eval_key, 1), n), eval_tasks)
    oracle = FastOracle(env)

    def evaluate(predictor, params_for):
        def one(task, goal, key):
            spec = capsjax.RewardSpec.from_terms(predictor, collision=500, heading_cos=1)
            toward = lambda state, spec: spec.with_goals(goal_heading=goal - state.info["pose"][:2])
            return mpc.run_episode(env, mpc.caps_policy(predictor, cem), params_for(task), spec, task, key,
                                   num_steps=cfg.eval_steps, update_spec=toward)

        return jax.jit(jax.vmap(one))(eval_tasks, goals, jax.random.split(jax.random.fold_in(eval_key, 2), n))

    results = {
        "caps": evaluate(model, lambda task: state.params),
        "oracle": evaluate(oracle, lambda task: task),
    }
    timings["eval_s"] = time.time() - t

    metrics = {name: summarize(traj, goals) for name, traj in results.items()}
    metrics["straight"] = summarize_straight(env, eval_tasks, goals, cfg.eval_steps)
    out = {"config": dataclasses.asdict(cfg) | {"resolved": settings, "cem": preset["cem"]},
           "env": "fast (interim: analytic world, not the MJX forest)", "metrics": metrics,
           "train_loss": losses, "timings_s": timings, "device": jax.devices()[0].device_kind}
    (run_dir / "metrics.json").write_text(json.dumps(out, indent=2, default=str))
    (run_dir / "table.md").write_text(table(metrics))
    plot(run_dir / "trajectories.png", eval_tasks, goals, results, env)
    print(table(metrics))
    print(f"[forest] wrote {run_dir}")
    return out


GOAL_RADIUS = 1.0  # metres: a goal counts as reached within this distance


def free_goal(env, key, task):
    """A goal point 1 m clear of every obstacle, 2.5 m from the start and 2.5 m inside the walls (the
    car's turning circle must fit around it); the first of 16 draws that qualifies."""
    span = env.config.arena_half - 2.5
    points = jax.random.uniform(key, (16, 2), minval=-span, maxval=span)
    clearance = jnp.min(jnp.linalg.norm(points[:, None] - task.obstacles[None, :, :2], axis=-1) - task.obstacles[None, :, 2], -1)
    ok = (clearance > 1.0) & (jnp.linalg.norm(points - task.start[:2], axis=-1) > 2.5)
    return points[jnp.argmax(ok)]


def summarize_poses(pose, collision, distance, goals) -> dict:
    """Reached = within GOAL_RADIUS of the goal before any crash; the episode ends there (as the
    paper's CARLA episodes), so later crashes do not count."""
    pose, collision, goals = np.asarray(pose), np.asarray(collision) > 0.5, np.asarray(goals)
    to_goal = np.linalg.norm(pose[:, :, :2] - goals[:, None], axis=-1)
    crashed_so_far = np.maximum.accumulate(collision, axis=1)
    at_goal = (to_goal < GOAL_RADIUS) & ~crashed_so_far
    reached = at_goal.any(1)
    ended = np.maximum.accumulate(at_goal, axis=1)
    crashed = np.any(collision & ~ended, axis=1)
    return {
        "reached_goal_rate": float(reached.mean()),
        "no_crash_rate": float(1 - crashed.mean()),
        "final_goal_distance_mean": float(to_goal[:, -1].mean()),
        "distance_mean": float(np.asarray(distance)[:, -1].mean()),
    }


def summarize(traj: mpc.Trajectory, goals) -> dict:
    return summarize_poses(traj.pose, traj.signals["collision"], traj.metrics["distance"], goals)


def summarize_straight(env, tasks, goals, steps) -> dict:
    """Drive straight at 1.5 m/s: the reference that shows the layouts are not trivially safe."""
    def one(task):
        state = env.reset(jax.random.key(0), task)

        def step(s, _):
            nxt = env.step(s, jnp.array([0.0, 1.5]))
            nxt = jax.tree.map(lambda a, b: jnp.where(s.done, a, b), s, nxt)
            return nxt, (nxt.signals["collision"], nxt.info["pose"], nxt.metrics["distance"])

        _, (coll, pose, dist) = jax.lax.scan(step, state, None, length=steps)
        return coll, pose, dist

    coll, pose, dist = jax.jit(jax.vmap(one))(tasks)
    return summarize_poses(pose, coll, dist, goals)


def table(metrics: dict) -> str:
    lines = ["| method | reached goal | no crash | final distance to goal (m) | driven (m) |", "|---|---|---|---|---|"]
    for name, m in metrics.items():
        lines.append(f"| {name} | {100 * m['reached_goal_rate']:.0f} % | {100 * m['no_crash_rate']:.0f} % | "
                     f"{m['final_goal_distance_mean']:.1f} | {m['distance_mean']:.1f} |")
    return "\n".join(lines) + "\n"


def plot(path, tasks, goals, results, env) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(4, tasks.obstacles.shape[0])
    fig, axes = plt.subplots(1, n, figsize=(4 * n, 4))
    half = env.config.arena_half
    for i, ax in enumerate(np.atleast_1d(axes)):
        for x, y, r in np.asarray(tasks.obstacles[i]):
            ax.add_patch(plt.Circle((x, y), r, color="forestgreen"))
        ax.plot(*np.asarray(goals[i]), marker="*", markersize=14, color="gold", markeredgecolor="k")
        for (name, traj), colour in zip(results.items(), ("tab:blue", "tab:orange")):
            pose = np.asarray(traj.pose[i])
            ax.plot(pose[:, 0], pose[:, 1], color=colour, label=name)
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_aspect("equal")
        ax.set_title(f"eval layout {i}")
    np.atleast_1d(axes)[0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


if __name__ == "__main__":
    main(tyro.cli(Config))
