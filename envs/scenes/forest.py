"""The forest (caps-algorithm.md section 9.1): a walled arena with trees and rocks, and paths to follow.

Layout (from the task's seed, pure JAX): the paper's 25 x 25 m arena inside 1 m thick, 3 m tall walls,
obstacles on a 5 m grid without its four corner cells (21 in the paper's arena), each jittered by up to
``jitter`` m, a tree (trunk radius 0.6-1.0 m, tall) or a rock (radius 0.5-0.8 m, 0.5-1.0 m tall) at
random, which leaves free gaps of roughly 3-4 m.  Obstacles within ``start_clearance`` of the start
pose are removed (their slots become unused), so an episode never starts in a crash.  A larger
``arena_half`` grows the grid; the obstacle count is fixed per config, so every layout of one config
shares one compiled step.

Tasks: follow a path given as a polyline of ``path_points`` vertices.  'train' draws circles (the
paper's training path) centred near the middle of the arena; 'eval' draws sinusoids of random
amplitude and wavelength crossing the arena in one of four directions, from a disjoint seed stream;
'val' draws sinusoids too, in layouts of a third stream (for tuning without touching 'eval').
The paths ignore the obstacles (as in the paper): the car has to leave the path to get around a tree.
``info['goal_heading']`` points from the car to the path point ``lookahead`` m ahead of the car's
projection on it (a pursuit point: on the path this is about the tangent; off the path, after going
round a tree, it leads back to the path instead of running parallel to it).  ``info['goal_path']`` is
the next ``goal_path_length`` m of the path relative to the car, for the reward's ``path`` term.

Metrics: ``path_distance`` (now) and ``mean_path_distance`` (the paper's average distance from the
path, m), ``progress`` (fraction of the path's length covered, monotone), ``crash`` (0/1).  The episode
ends on a collision or when the path is complete.

Actions: steering in degrees (env box +-45, planning +-30) and a speed set-point in m/s (env box +-4 as
the paper's forest; planning [0.5, 3]: forward only, slow enough to turn around a tree).
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
from flax import struct

from envs.camera import FOREST_CAMERA, CameraConfig
from envs.scene import GRASS, ROCK, TREE, WALL, Scene, empty_scene
from envs.scenes import common


@dataclasses.dataclass(frozen=True)
class ForestConfig(common.SceneConfig):
    camera: CameraConfig = FOREST_CAMERA
    arena_half: float = 12.5  # the drivable arena is [-arena_half, arena_half]^2
    wall_thickness: float = 1.0
    wall_height: float = 3.0
    grid_spacing: float = 5.0
    jitter: float = 0.5
    tree_radius: tuple[float, float] = (0.6, 1.0)
    tree_height: tuple[float, float] = (5.0, 10.0)
    rock_radius: tuple[float, float] = (0.5, 0.8)
    rock_top: tuple[float, float] = (0.5, 1.0)
    rock_fraction: float = 0.5
    start_clearance: float = 2.5  # m from the start pose's centre kept free of obstacles
    path_points: int = 64
    circle_radius: tuple[float, float] = (5.0, 8.0)  # train paths
    sine_amplitude: tuple[float, float] = (1.0, 3.0)  # eval paths
    sine_wavelength: tuple[float, float] = (8.0, 16.0)
    path_margin: float = 3.0  # paths keep this far from the walls
    finish_tolerance: float = 0.5  # m before the path's end that counts as finished
    # info['goal_path']: the path from the car's projection this far ahead (m), as this many points; 10 m
    # is more than the fastest plan (3 m/s over 12 steps of 0.25 s) can reach.
    goal_path_length: float = 10.0
    goal_path_points: int = 16

    def __post_init__(self):
        super().__post_init__()
        if self.goal_path_points < 2 or not self.goal_path_length > 0:
            raise ValueError(f"goal_path_points must be >= 2 and goal_path_length > 0 m, got "
                             f"{self.goal_path_points} and {self.goal_path_length}")

    @property
    def grid(self) -> int:
        """Grid points per side: the paper's 5 for a 25 m arena."""
        return int(math.floor(2 * (self.arena_half - 2.5) / self.grid_spacing + 1e-6)) + 1

    @property
    def num_obstacles(self) -> int:
        return self.grid**2 - 4


@struct.dataclass
class ForestTask:
    seed: jax.Array  # u32[2]: raw key data of the layout
    path: jax.Array  # f32[P, 2]
    start: jax.Array  # f32[3]: x, y, yaw


class ForestEnv(common.SceneEnv):
    def __init__(self, config: ForestConfig = ForestConfig()):
        super().__init__(config)

    # ---------------------------------------------------------------- tasks

    def sample_task(self, key: jax.Array, split: str = "train") -> ForestTask:
        cfg = self.config
        key = self.split_key(key, split)
        k_seed, k_path = jax.random.split(key)
        path = (circle_path if split == "train" else sine_path)(cfg, k_path)
        _, heading = common.path_point(path, jnp.zeros(()))
        start = jnp.concatenate([path[0], heading[None]])
        return ForestTask(seed=jax.random.key_data(k_seed).astype(jnp.uint32), path=path, start=start)

    def sample_task_anywhere(self, key: jax.Array, split: str = "train", wall_margin: float = 1.5) -> ForestTask:
        """A task of ``split`` whose start pose is drawn uniformly over the arena (centre at least
        ``wall_margin`` m from the walls, any yaw) instead of at the path's start.  For data collection:
        episodes from the path starts never come near the walls, and the paper's forest resets put the
        car at the arena's corners, 1.5 m from two walls (caps-algorithm.md 9.1)."""
        task = self.sample_task(key, split)
        k_xy, k_yaw = jax.random.split(jax.random.fold_in(key, 7))
        room = self.config.arena_half - wall_margin
        if not room > 0:
            raise ValueError(f"wall_margin must be below arena_half={self.config.arena_half}, got {wall_margin}")
        xy = jax.random.uniform(k_xy, (2,), minval=-room, maxval=room)
        yaw = jax.random.uniform(k_yaw, (), minval=-jnp.pi, maxval=jnp.pi)
        return task.replace(start=jnp.concatenate([xy, yaw[None]]).astype(jnp.float32))

    def layout(self, task: ForestTask) -> Scene:
        return forest_layout(self.config, task.seed, task.start)

    # ---------------------------------------------------------------- progress

    def task_init(self, task: ForestTask, pose):
        s, dist = common.project_on_path(task.path, pose[:2], 0.0, 0.0)
        info = self._goal_info(task, s, pose)
        zero = jnp.zeros((), jnp.float32)
        metrics = {"path_distance": dist, "mean_path_distance": dist, "progress": zero, "crash": zero,
                   "steps": zero}
        return info, metrics

    def task_update(self, state, pose, signals):
        task, m = state.task, state.metrics
        s_prev = state.info["path_s"]
        # The car moves at most ~1 m per step: search the path just around the last projection so a
        # closed circle never jumps from its end back to its start.
        s, _ = common.project_on_path(task.path, pose[:2], s_prev - 2.0, s_prev + 4.0)
        s = jnp.maximum(s, s_prev)
        _, dist = common.project_on_path(task.path, pose[:2])
        length = common.polyline_lengths(task.path)[-1]
        steps = m["steps"] + 1
        metrics = {
            "path_distance": dist,
            "mean_path_distance": common.running_mean(m["mean_path_distance"], dist, steps + 1),
            "progress": s / length,
            "crash": jnp.maximum(m["crash"], signals["collision"]),
            "steps": steps,
        }
        return self._goal_info(task, s, pose), metrics, s >= length - self.config.finish_tolerance

    def _goal_info(self, task, s, pose):
        cfg = self.config
        return {"path_s": s, "goal_heading": self._goal_heading(task, s, pose),
                "goal_path": common.path_ahead(task.path, s, pose[:2], cfg.goal_path_length, cfg.goal_path_points)}

    def _goal_heading(self, task, s, pose):
        point, tangent = common.path_point(task.path, s + self.config.lookahead)
        d = point - pose[:2]
        # At the path's very end the pursuit point can coincide with the car: use the tangent there.
        return jnp.where(jnp.linalg.norm(d) > 0.5, jnp.arctan2(d[1], d[0]), tangent)


# -------------------------------------------------------------------------------------------- layout


def forest_layout(cfg: ForestConfig, seed: jax.Array, start: jax.Array) -> Scene:
    """The arena, its walls and ``cfg.num_obstacles`` trees/rocks from ``seed`` (u32[2] key data)."""
    key = jax.random.wrap_key_data(jnp.asarray(seed, jnp.uint32))
    k_jit, k_kind, k_rad, k_h, k_col = jax.random.split(key, 5)
    n, g = cfg.num_obstacles, cfg.grid
    coords = cfg.grid_spacing * (jnp.arange(g) - (g - 1) / 2)
    gx, gy = jnp.meshgrid(coords, coords, indexing="ij")
    corner = ((jnp.arange(g)[:, None] % (g - 1)) == 0) & ((jnp.arange(g)[None, :] % (g - 1)) == 0)
    keep = jnp.nonzero(~corner.reshape(-1), size=n)[0]
    xy = jnp.stack([gx.reshape(-1)[keep], gy.reshape(-1)[keep]], -1)
    xy = xy + jax.random.uniform(k_jit, (n, 2), minval=-cfg.jitter, maxval=cfg.jitter)

    rock = jax.random.uniform(k_kind, (n,)) < cfg.rock_fraction
    u_r, u_h = jax.random.uniform(k_rad, (n,)), jax.random.uniform(k_h, (n,))
    lerp = lambda lo_hi, u: lo_hi[0] + (lo_hi[1] - lo_hi[0]) * u  # noqa: E731
    radius = jnp.where(rock, lerp(cfg.rock_radius, u_r), lerp(cfg.tree_radius, u_r))
    # A capsule of radius r and height h reaches r above h (envs/scene.py): rocks are given by their top.
    height = jnp.where(rock, jnp.maximum(lerp(cfg.rock_top, u_h) - radius, 0.0), lerp(cfg.tree_height, u_h))
    clear = jnp.linalg.norm(xy - start[:2], axis=-1) - radius > cfg.start_clearance
    radius = jnp.where(clear, radius, 0.0)

    shade = jax.random.uniform(k_col, (n, 1), minval=0.8, maxval=1.2)
    color = jnp.where(rock[:, None], jnp.asarray([0.52, 0.5, 0.47]), jnp.asarray([0.4, 0.28, 0.17])) * shade

    scene = empty_scene(n, 4, 1)
    h, t = cfg.arena_half, cfg.wall_thickness
    length = h + t  # half-length: the walls overlap at the corners
    walls = jnp.asarray([
        [h + t / 2, 0.0, t / 2, length, 0.0, cfg.wall_height],
        [-h - t / 2, 0.0, t / 2, length, 0.0, cfg.wall_height],
        [0.0, h + t / 2, length, t / 2, 0.0, cfg.wall_height],
        [0.0, -h - t / 2, length, t / 2, 0.0, cfg.wall_height],
    ], jnp.float32)
    return scene.replace(
        circles=jnp.stack([xy[:, 0], xy[:, 1], radius, height], -1).astype(jnp.float32),
        circle_class=jnp.where(rock, ROCK, TREE).astype(jnp.int32),
        circle_color=jnp.clip(color, 0.0, 1.0).astype(jnp.float32),
        boxes=walls,
        box_class=jnp.full((4,), WALL, jnp.int32),
        box_color=jnp.tile(jnp.asarray([[0.62, 0.58, 0.52]], jnp.float32), (4, 1)),
        ground_class=jnp.asarray(GRASS, jnp.int32),
        ground_color=jnp.asarray([0.33, 0.45, 0.22], jnp.float32),
        bounds=jnp.asarray([-h, -h, h, h], jnp.float32),
    )


# --------------------------------------------------------------------------------------------- paths


def circle_path(cfg: ForestConfig, key: jax.Array) -> jax.Array:
    """A full counter- or clockwise lap of a circle, starting at a random angle (train)."""
    k_r, k_c, k_a, k_dir = jax.random.split(key, 4)
    radius = jax.random.uniform(k_r, (), minval=cfg.circle_radius[0], maxval=cfg.circle_radius[1])
    room = jnp.maximum(cfg.arena_half - cfg.path_margin - radius, 0.0)
    centre = jax.random.uniform(k_c, (2,), minval=-room, maxval=room)
    direction = jnp.where(jax.random.bernoulli(k_dir), 1.0, -1.0)
    angle = jax.random.uniform(k_a, (), maxval=2 * jnp.pi) + direction * jnp.linspace(0.0, 2 * jnp.pi, cfg.path_points)
    return (centre + radius * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)).astype(jnp.float32)


def sine_path(cfg: ForestConfig, key: jax.Array) -> jax.Array:
    """A sinusoid across the arena along one of the four axis directions (eval)."""
    k_a, k_w, k_ph, k_off, k_dir = jax.random.split(key, 5)
    amplitude = jax.random.uniform(k_a, (), minval=cfg.sine_amplitude[0], maxval=cfg.sine_amplitude[1])
    wavelength = jax.random.uniform(k_w, (), minval=cfg.sine_wavelength[0], maxval=cfg.sine_wavelength[1])
    phase = jax.random.uniform(k_ph, (), maxval=2 * jnp.pi)
    half = cfg.arena_half - cfg.path_margin
    offset = jax.random.uniform(k_off, (), minval=-(half - amplitude), maxval=half - amplitude)
    u = jnp.linspace(-half, half, cfg.path_points)
    v = offset + amplitude * jnp.sin(2 * jnp.pi * u / wavelength + phase)
    yaw = jax.random.randint(k_dir, (), 0, 4).astype(jnp.float32) * (jnp.pi / 2)
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.stack([c * u - s * v, s * u + c * v], -1).astype(jnp.float32)
