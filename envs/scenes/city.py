"""The city (the paper's CARLA town, reduced to what CAPs uses): a street grid, lanes, parked cars, goals.

Layout: ``blocks x blocks`` city blocks on a square grid of ``block_pitch`` m.  Two-way roads run along
every grid line (one ``lane_width`` lane per direction) with painted edge lines (EDGE_LINE) and a centre
line (LANE_LINE) that stop at the intersections; the unpainted ground is sidewalk.  Each block holds two
buildings (the block split at a random fraction along a random axis, random setbacks, heights and
colours), four long buildings close the world beyond the outer roads, and ``parked_cars`` parked cars
(class CAR) stand at the kerb of random road segments, narrowing that lane to about 1.6 m: the car can
squeeze past inside its lane or swerve.  All counts are fixed per config; parked cars that would stand
near the start pose are removed (unused slots).

Tasks: drive from a start pose (right lane of a road segment, facing along it) to a goal location (the
middle of another road segment, at least ``min_goal_distance`` away).  'train' goals are on the
even-numbered road segments, 'eval' and 'val' goals on the odd ones, and the splits use disjoint layout
seeds.  ``info['goal_heading']`` is the direction from the car to the goal.

Signals add ``lane_seen`` and ``lane_diff`` (the right lane's visibility and centre offset in the image,
from ``capsjax.labellers`` on the camera's true class map).  Metrics (the paper's CARLA table):
``reached_goal`` (within ``goal_radius`` = 10 m; ends the episode), ``crash``, ``mean_speed`` (m/s),
``right_lane_fraction`` (fraction of steps in the right lane, from the true pose; intersections count
as in lane).  Actions: steering in degrees (env box +-45, planning +-30) and a speed set-point (env box
+-10 m/s, planning [1, 10]; the task's target speed is ``target_speed`` = 7 m/s as in the paper).
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from envs.camera import CameraConfig
from envs.car import CarConfig
from envs.scene import BUILDING, CAR, EDGE_LINE, LANE_LINE, ROAD, SIDEWALK, Scene, empty_scene
from envs.scenes import common

# The paper's CARLA camera is 120 degrees wide, 1.4 m up, grayscale 100x50; looking slightly down makes
# the lane lines ahead fill more rows.
CITY_CAMERA = CameraConfig(width=100, height=50, grayscale=True, mount_height=1.4, mount_forward=0.5,
                           pitch_deg=math.degrees(math.atan2(1.4, 12.0)), far=120.0)


@dataclasses.dataclass(frozen=True)
class CityConfig(common.SceneConfig):
    camera: CameraConfig = CITY_CAMERA
    car: CarConfig = CarConfig(near_circles=0, near_boxes=3)
    speed_limit: float = 10.0
    plan_speed: tuple[float, float] = (1.0, 10.0)
    target_speed: float = 7.0
    lookahead: float = 0.0  # the goal heading points at the goal itself
    blocks: int = 3
    block_pitch: float = 30.0  # distance between neighbouring road centrelines
    lane_width: float = 3.5
    sidewalk: float = 2.0
    line_width: float = 0.15
    edge_inset: float = 0.3  # edge lines this far inside the road edge
    building_height: tuple[float, float] = (6.0, 20.0)
    parked_cars: int = 8
    parked_size: tuple[float, float, float] = (2.0, 0.9, 1.5)  # half length, half width, height
    goal_radius: float = 10.0
    min_goal_distance: float = 40.0
    start_clearance: float = 10.0  # no parked car this close to the start

    @property
    def road_centres(self) -> np.ndarray:
        """Coordinates of the road centrelines (the same along x and y)."""
        return (self.block_pitch * (np.arange(self.blocks + 1) - self.blocks / 2)).astype(np.float32)

    @property
    def segments(self) -> np.ndarray:
        """f32[S, 5] road segments between intersections: x0, y0, x1, y1 (centreline ends), axis (0=x, 1=y)."""
        c, w = self.road_centres, self.lane_width
        out = []
        for axis in (0, 1):
            for fixed in c:
                for lo, hi in zip(c[:-1], c[1:]):
                    a, b = lo + w, hi - w
                    out.append([a, fixed, b, fixed, axis] if axis == 0 else [fixed, a, fixed, b, axis])
        return np.asarray(out, np.float32)


@struct.dataclass
class CityTask:
    seed: jax.Array  # u32[2]: raw key data of the layout
    goal: jax.Array  # f32[2]
    start: jax.Array  # f32[3]


class CityEnv(common.SceneEnv):
    extra_signals = ("lane_seen", "lane_diff")

    def __init__(self, config: CityConfig = CityConfig()):
        super().__init__(config)

    # ---------------------------------------------------------------- tasks

    def sample_task(self, key: jax.Array, split: str = "train") -> CityTask:
        cfg = self.config
        key = self.split_key(key, split)
        k_seed, k_seg, k_dir, k_pos, k_goal = jax.random.split(key, 5)
        seg = jnp.asarray(cfg.segments)
        i = jax.random.randint(k_seg, (), 0, seg.shape[0])
        start = lane_pose(cfg, seg[i], jax.random.bernoulli(k_dir), jax.random.uniform(k_pos, (), minval=0.2, maxval=0.8))
        mids = 0.5 * (seg[:, :2] + seg[:, 2:4])
        parity = np.arange(seg.shape[0]) % 2 == (0 if split == "train" else 1)
        ok = jnp.asarray(parity) & (jnp.linalg.norm(mids - start[:2], axis=-1) >= cfg.min_goal_distance)
        goal = mids[jax.random.categorical(k_goal, jnp.where(ok, 0.0, -jnp.inf))]
        return CityTask(seed=jax.random.key_data(k_seed).astype(jnp.uint32), goal=goal, start=start)

    def layout(self, task: CityTask) -> Scene:
        return city_layout(self.config, task.seed, task.start)

    # ---------------------------------------------------------------- progress

    def task_init(self, task: CityTask, pose):
        zero = jnp.zeros((), jnp.float32)
        info = {"goal_heading": self._goal_heading(task, pose), "goal_distance": self._goal_distance(task, pose)}
        metrics = {"reached_goal": zero, "crash": zero, "mean_speed": zero,
                   "right_lane_fraction": in_right_lane(self.config, pose).astype(jnp.float32), "steps": zero}
        return info, metrics

    def task_update(self, state, pose, signals):
        task, m = state.task, state.metrics
        steps = m["steps"] + 1
        distance = self._goal_distance(task, pose)
        reached = distance < self.config.goal_radius
        metrics = {
            "reached_goal": jnp.maximum(m["reached_goal"], reached.astype(jnp.float32)),
            "crash": jnp.maximum(m["crash"], signals["collision"]),
            "mean_speed": common.running_mean(m["mean_speed"], signals["speed"], steps),
            "right_lane_fraction": common.running_mean(
                m["right_lane_fraction"], in_right_lane(self.config, pose).astype(jnp.float32), steps + 1),
            "steps": steps,
        }
        info = {"goal_heading": self._goal_heading(task, pose), "goal_distance": distance}
        return info, metrics, reached

    def _goal_heading(self, task, pose):
        d = task.goal - pose[:2]
        return jnp.arctan2(d[1], d[0])

    def _goal_distance(self, task, pose):
        return jnp.linalg.norm(task.goal - pose[:2])


def lane_pose(cfg: CityConfig, segment: jax.Array, reverse: jax.Array, frac: jax.Array) -> jax.Array:
    """f32[3]: the pose at fraction ``frac`` of a road segment, in the right lane of its direction."""
    a, b = segment[:2], segment[2:4]
    a, b = jnp.where(reverse, b, a), jnp.where(reverse, a, b)
    d = (b - a) / jnp.maximum(jnp.linalg.norm(b - a), 1e-6)
    right = jnp.stack([d[1], -d[0]])
    xy = a + frac * (b - a) + 0.5 * cfg.lane_width * right
    return jnp.concatenate([xy, jnp.arctan2(d[1], d[0])[None]]).astype(jnp.float32)


def in_right_lane(cfg: CityConfig, pose: jax.Array) -> jax.Array:
    """bool[]: the car's centre is in the right-hand lane of the road it drives along (true pose).

    On a road along x (y) the car drives along x (y) when its heading is closer to that axis; its
    centre must then lie between the centre line and the road edge on its right.  Inside an
    intersection any position counts as in lane; off the road never does.
    """
    c, w = jnp.asarray(cfg.road_centres), cfg.lane_width
    x, y, yaw = pose[0], pose[1], pose[2]
    near_x = jnp.min(jnp.abs(y - c))  # distance to the nearest road along x
    near_y = jnp.min(jnp.abs(x - c))
    on_x, on_y = near_x < w, near_y < w
    span = (c[0] - w <= jnp.minimum(x, y)) & (jnp.maximum(x, y) <= c[-1] + w)
    cy = c[jnp.argmin(jnp.abs(y - c))]
    cx = c[jnp.argmin(jnp.abs(x - c))]
    right_n = jnp.stack([jnp.sin(yaw), -jnp.cos(yaw)])  # unit vector to the car's right
    lateral_x = (y - cy) * right_n[1]  # offset to the right of the centreline of a road along x
    lateral_y = (x - cx) * right_n[0]
    along_x = jnp.abs(jnp.cos(yaw)) >= jnp.abs(jnp.sin(yaw))
    ok_x = on_x & (lateral_x > 0)
    ok_y = on_y & (lateral_y > 0)
    return span & ((on_x & on_y) | jnp.where(along_x, ok_x, ok_y))


# -------------------------------------------------------------------------------------------- layout


def city_paint(cfg: CityConfig):
    """The ground paint (fixed per config): roads, edge and centre lines, intersections painted last."""
    c, w, lw = cfg.road_centres, cfg.lane_width, cfg.line_width
    lo, hi = float(c[0] - w), float(c[-1] + w)
    road_color, line_color, edge_color = (0.3, 0.3, 0.32), (0.95, 0.85, 0.2), (0.95, 0.95, 0.95)
    rects, classes, colors = [], [], []

    def add(rect_along_x, fixed, cls, color, along_x):
        (a0, a1), (b0, b1) = rect_along_x, (fixed[0], fixed[1])
        rects.append([a0, b0, a1, b1] if along_x else [b0, a0, b1, a1])
        classes.append(cls)
        colors.append(color)

    for along_x in (True, False):
        for r in c:
            add((lo, hi), (r - w, r + w), ROAD, road_color, along_x)
            add((lo, hi), (r - lw / 2, r + lw / 2), LANE_LINE, line_color, along_x)
            for side in (-1, 1):
                e = r + side * (w - cfg.edge_inset)
                add((lo, hi), (e - lw / 2, e + lw / 2), EDGE_LINE, edge_color, along_x)
    for rx in c:  # intersections: plain road over the lines
        for ry in c:
            rects.append([rx - w, ry - w, rx + w, ry + w])
            classes.append(ROAD)
            colors.append(road_color)
    return np.asarray(rects, np.float32), np.asarray(classes, np.int32), np.asarray(colors, np.float32)


def city_layout(cfg: CityConfig, seed: jax.Array, start: jax.Array) -> Scene:
    """Roads, buildings and parked cars from ``seed`` (u32[2] key data)."""
    key = jax.random.wrap_key_data(jnp.asarray(seed, jnp.uint32))
    k_split, k_frac, k_set, k_h, k_col, k_pseg, k_pside, k_ppos = jax.random.split(key, 8)
    c, w, n = cfg.road_centres, cfg.lane_width, cfg.blocks
    inner = w + cfg.sidewalk  # from a road centreline to the building line

    # Two buildings per block: the block interior split along x or y at a random fraction.
    bx0 = np.repeat(c[:-1], n) + inner
    by0 = np.tile(c[:-1], n) + inner
    size = cfg.block_pitch - 2 * inner
    split_x = jax.random.bernoulli(k_split, 0.5, (n * n,))
    frac = jax.random.uniform(k_frac, (n * n,), minval=0.35, maxval=0.65)
    setback = jax.random.uniform(k_set, (n * n, 2, 2), minval=0.0, maxval=1.5)  # [block, building, (x, y)]
    cut = frac * size
    lengths = jnp.stack([cut, size - cut], -1)  # [block, 2] along the split axis
    offsets = jnp.stack([jnp.zeros_like(cut), cut], -1)
    half_along = jnp.maximum(0.5 * lengths - setback[..., 0], 1.0)
    half_across = jnp.maximum(0.5 * size - setback[..., 1], 1.0)
    centre_along = offsets + 0.5 * lengths
    cx = jnp.where(split_x[:, None], bx0[:, None] + centre_along, bx0[:, None] + 0.5 * size)
    cy = jnp.where(split_x[:, None], by0[:, None] + 0.5 * size, by0[:, None] + centre_along)
    hx = jnp.where(split_x[:, None], half_along, half_across)
    hy = jnp.where(split_x[:, None], half_across, half_along)
    height = jax.random.uniform(k_h, (n * n, 2), minval=cfg.building_height[0], maxval=cfg.building_height[1])
    buildings = jnp.stack([cx, cy, hx, hy, jnp.zeros_like(cx), height], -1).reshape(-1, 6)

    # The world's edge: four long buildings beyond the outer roads' sidewalks.
    edge, t = float(c[-1] + inner), 5.0
    border = jnp.asarray([
        [edge + t, 0.0, t, edge + 2 * t, 0.0, 12.0],
        [-edge - t, 0.0, t, edge + 2 * t, 0.0, 12.0],
        [0.0, edge + t, edge + 2 * t, t, 0.0, 12.0],
        [0.0, -edge - t, edge + 2 * t, t, 0.0, 12.0],
    ], jnp.float32)

    # Parked cars: at the kerb of random segments, on a random side, away from the intersections.
    seg = jnp.asarray(cfg.segments)
    k = cfg.parked_cars
    si = jax.random.randint(k_pseg, (k,), 0, seg.shape[0])
    reverse = jax.random.bernoulli(k_pside, 0.5, (k,))
    margin = (cfg.parked_size[0] + 2.0) / jnp.linalg.norm(seg[si, 2:4] - seg[si, :2], axis=-1)
    frac_p = jax.random.uniform(k_ppos, (k,), minval=margin, maxval=1.0 - margin)
    poses = jax.vmap(lambda s, r, f: lane_pose(cfg, s, r, f))(seg[si], reverse, frac_p)
    kerb = w - cfg.parked_size[1] - 0.1 - 0.5 * w  # from the lane centre toward the kerb
    right = jnp.stack([jnp.sin(poses[:, 2]), -jnp.cos(poses[:, 2])], -1)
    pxy = poses[:, :2] + kerb * right
    clear = jnp.linalg.norm(pxy - start[:2], axis=-1) > cfg.start_clearance
    ph = jnp.where(clear, cfg.parked_size[0], 0.0)
    parked = jnp.stack([pxy[:, 0], pxy[:, 1], ph, jnp.full((k,), cfg.parked_size[1]), poses[:, 2],
                        jnp.full((k,), cfg.parked_size[2])], -1)

    nb = buildings.shape[0]
    shade = jax.random.uniform(k_col, (nb, 3), minval=0.45, maxval=0.8)
    car_col = jax.random.uniform(jax.random.fold_in(k_col, 1), (k, 3), minval=0.1, maxval=0.9)
    rects, classes, colors = city_paint(cfg)
    scene = empty_scene(0, nb + 4 + k, rects.shape[0])
    return scene.replace(
        boxes=jnp.concatenate([buildings, border, parked]).astype(jnp.float32),
        box_class=jnp.asarray([BUILDING] * (nb + 4) + [CAR] * k, jnp.int32),
        box_color=jnp.concatenate([shade, jnp.full((4, 3), 0.55), car_col]).astype(jnp.float32),
        patches=jnp.asarray(rects),
        patch_class=jnp.asarray(classes),
        patch_color=jnp.asarray(colors),
        ground_class=jnp.asarray(SIDEWALK, jnp.int32),
        ground_color=jnp.asarray([0.62, 0.6, 0.57], jnp.float32),
        bounds=jnp.asarray([-edge, -edge, edge, edge], jnp.float32),
    )
