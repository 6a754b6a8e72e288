"""Pictures of a scene: ``python -m envs.show NAME [--seed S] [--split train|eval|val] [--out PATH] [--mjcf PATH]``.

Writes one PNG: a bird's-eye view of the layout (ground paint, obstacles by semantic class, the task:
forest path, city goal, halls route with its intersections and commands) with the trajectory of a
short demo drive, above a strip of first-person frames and their semantic class maps.  The demo driver
steers toward ``info['goal_heading']`` (a proportional controller, no collision avoidance), so it shows
the task and the camera, not a policy.  ``--mjcf PATH`` also writes the layout with the car at its
start as MJCF, for MuJoCo's own viewer (``python -m mujoco.viewer --mjcf PATH``); ``envs/assets/`` holds
one per scene family, written this way with seed 0.
"""
from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs import base
from envs.scene import CLASS_NAMES


def demo_rollout(env, task, steps: int):
    """Drive ``steps`` control steps toward the goal heading; returns (states stacked over time, first state)."""
    spec = env.spec

    def policy(state):
        error = base.wrap_angle(state.info["goal_heading"] - state.info["pose"][2])
        steer = jnp.clip(jnp.rad2deg(error) * 1.5, spec.plan_low[0], spec.plan_high[0])
        if spec.action_dim == 1:
            return steer[None]
        speed = 0.5 * (spec.plan_low[1] + spec.plan_high[1])
        return jnp.stack([steer, jnp.asarray(speed, jnp.float32)])

    def run(task):
        first = env.reset(jax.random.key(0), task)

        def body(state, _):
            nxt = env.step(state, policy(state))
            # Freeze after the episode ends so the picture shows where it ended.
            nxt = jax.tree.map(lambda a, b: jnp.where(state.done, a, b), state, nxt)
            return nxt, nxt

        _, states = jax.lax.scan(body, first, None, length=steps)
        return first, states

    return jax.jit(run)(task)


def class_colors() -> np.ndarray:
    """A fixed colour per semantic class for the class maps (u8[NUM_CLASSES, 3])."""
    table = {
        "sky": (135, 180, 235), "grass": (60, 140, 50), "road": (80, 80, 85), "lane_line": (250, 220, 40),
        "edge_line": (255, 255, 255), "sidewalk": (170, 165, 150), "tree": (110, 70, 30), "rock": (130, 130, 125),
        "wall": (200, 200, 190), "building": (160, 90, 80), "car": (40, 90, 220), "door": (230, 120, 20),
        "floor": (120, 115, 110), "ceiling": (235, 235, 225),
    }
    return np.asarray([table[n] for n in CLASS_NAMES], np.uint8)


def draw_scene(ax, scene, task, drives=None, first_pose=None, legend=True):
    """Bird's-eye view on a matplotlib axis: the layout, the task, and ``drives`` -- a dict of
    ``label -> poses f32[T, >=2]`` (or a list of such arrays) drawn as coloured lines -- with an arrow at
    ``first_pose`` (x, y, yaw)."""
    from matplotlib import patches as mpatches

    colors = class_colors() / 255.0
    sc = jax.tree.map(np.asarray, scene)
    b = sc.bounds
    pad = 3.0
    ax.add_patch(mpatches.Rectangle((b[0] - pad, b[1] - pad), b[2] - b[0] + 2 * pad, b[3] - b[1] + 2 * pad,
                                    color=sc.ground_color, zorder=0))
    for rect, color in zip(sc.patches, sc.patch_color):
        x0, y0, x1, y1 = rect
        if x1 > x0 and y1 > y0:
            ax.add_patch(mpatches.Rectangle((x0, y0), x1 - x0, y1 - y0, color=color, zorder=1, lw=0))
    for (x, y, r, _), cls in zip(sc.circles, sc.circle_class):
        if r > 0:
            ax.add_patch(mpatches.Circle((x, y), r, color=colors[cls], zorder=2))
    for (cx, cy, hx, hy, yaw, _), cls in zip(sc.boxes, sc.box_class):
        if hx > 0:
            c, s = np.cos(yaw), np.sin(yaw)
            corner = np.array([cx - c * hx + s * hy, cy - s * hx - c * hy])  # matplotlib rotates about it
            ax.add_patch(mpatches.Rectangle(corner, 2 * hx, 2 * hy, angle=np.degrees(yaw), color=colors[cls],
                                            zorder=3, lw=0))
    t = jax.tree.map(np.asarray, task)
    if hasattr(t, "path"):
        ax.plot(t.path[:, 0], t.path[:, 1], "--", color="magenta", lw=1.5, zorder=4, label="path")
    if hasattr(t, "goal"):
        ax.add_patch(mpatches.Circle(t.goal, 10.0, fill=False, color="magenta", lw=1.5, zorder=4))
        ax.plot(*t.goal, "*", color="magenta", ms=14, zorder=5, label="goal")
    if hasattr(t, "route"):
        ax.plot(t.route[:, 0], t.route[:, 1], "--", color="magenta", lw=1.5, zorder=4, label="route")
    if hasattr(t, "junction_s"):
        from envs.scenes.common import path_point

        for s, h in zip(t.junction_s, t.commands):
            p, _ = path_point(jnp.asarray(t.route), jnp.asarray(s))
            p = np.asarray(p)
            ax.plot(*p, "o", color="magenta", ms=6, zorder=5)
            ax.arrow(p[0], p[1], 2 * np.cos(h), 2 * np.sin(h), color="magenta", width=0.15, zorder=5)
    palette = ("red", "tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "black")
    for (label, poses), color in zip((drives or {}).items(), palette):
        for i, p in enumerate(poses if isinstance(poses, (list, tuple)) else [poses]):
            p = np.asarray(p)
            ax.plot(p[:, 0], p[:, 1], "-", color=color, lw=2, zorder=6, label=label if i == 0 else None)
    if first_pose is not None:
        x, y, yaw = np.asarray(first_pose)[:3]
        ax.arrow(x, y, 1.5 * np.cos(yaw), 1.5 * np.sin(yaw), color="red", width=0.3, zorder=7)
    ax.set_xlim(b[0] - pad, b[2] + pad)
    ax.set_ylim(b[1] - pad, b[3] + pad)
    ax.set_aspect("equal")
    if legend:
        ax.legend(loc="upper right", fontsize=7)


def show(name: str, *, seed: int = 0, split: str = "train", steps: int = 40, frames: int = 6, out: str | None = None,
         **overrides) -> str:
    """Write the picture of scene ``name`` and return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from envs.camera import render

    env = envs.make(name, **overrides)
    task = env.sample_task(jax.random.key(seed), split)
    first, states = demo_rollout(env, task, steps)
    poses = np.concatenate([np.asarray(first.info["pose"])[None], np.asarray(states.info["pose"])])
    scene = first.physics.scene
    cam = env.config.camera
    picks = np.linspace(0, len(poses) - 1, frames).round().astype(int)
    views = [jax.jit(render, static_argnums=2)(scene, jnp.asarray(poses[i]), cam) for i in picks]

    fig = plt.figure(figsize=(2.2 * frames, 2.2 * frames * 0.6 + 2.6 * 2))
    grid = fig.add_gridspec(3, frames, height_ratios=[frames * 0.6 * 2.2, 2.2 * cam.height / cam.width * 1.2,
                                                      2.2 * cam.height / cam.width * 1.2])
    ax = fig.add_subplot(grid[0, :])
    draw_scene(ax, scene, task, {"demo drive": poses}, poses[0])
    ax.set_title(f"{name} ({split}, seed {seed}): layout, task and a {steps}-step demo drive")
    table = class_colors()
    for k, (i, (image, semantic, _)) in enumerate(zip(picks, views)):
        image = np.asarray(image)
        a = fig.add_subplot(grid[1, k])
        a.imshow(image[..., 0] if image.shape[-1] == 1 else image, cmap="gray" if image.shape[-1] == 1 else None,
                 vmin=0, vmax=255)
        a.set_title(f"step {i}", fontsize=8)
        a.axis("off")
        a = fig.add_subplot(grid[2, k])
        a.imshow(table[np.asarray(semantic)])
        a.axis("off")
    fig.tight_layout()
    out = out or os.path.join("results", "show", f"{name}.png")
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def scene_mjcf(name: str, *, seed: int = 0, split: str = "train", **overrides) -> str:
    """The MJCF of scene ``name``'s layout for task ``seed`` with the car at its start pose."""
    from envs.car import full_mjcf

    env = envs.make(name, **overrides)
    task = env.sample_task(jax.random.key(seed), split)
    scene = jax.jit(env.layout)(task)
    return full_mjcf(env.config.car, jax.tree.map(np.asarray, scene), np.asarray(env.start_pose(task)),
                     name=f"{name}_{split}_{seed}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m envs.show", description=__doc__.splitlines()[0])
    parser.add_argument("name", help=f"one of {', '.join(envs.SCENES)}")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--split", choices=base.TASK_SPLITS, default="train")
    parser.add_argument("--steps", type=int, default=40, help="control steps of the demo drive")
    parser.add_argument("--frames", type=int, default=6, help="first-person frames in the strip")
    parser.add_argument("--out", default=None, help="PNG path (default results/show/NAME.png)")
    parser.add_argument("--mjcf", default=None, help="also write the layout as MJCF to this path")
    parser.add_argument("--no-picture", action="store_true", help="skip the PNG (with --mjcf)")
    args = parser.parse_args(argv)
    if args.name not in envs.SCENES:
        raise SystemExit(f"unknown scene {args.name!r}; valid scenes: {', '.join(envs.SCENES)}")
    if args.mjcf:
        os.makedirs(os.path.dirname(args.mjcf) or ".", exist_ok=True)
        with open(args.mjcf, "w") as f:
            f.write(scene_mjcf(args.name, seed=args.seed, split=args.split) + "\n")
        print(args.mjcf)
    if args.no_picture:
        return
    print(show(args.name, seed=args.seed, split=args.split, steps=args.steps, frames=args.frames, out=args.out))


if __name__ == "__main__":
    # A program, like the experiments: 512-bit vectors on an AVX-512 host before JAX starts (renders faster).
    from experiments import runtime

    runtime.use_wide_vectors()
    main()
