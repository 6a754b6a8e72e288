"""What the three MJX worlds share: the car-in-a-scene env, its config, and path geometry helpers.

A scene env (brax / mujoco_playground style: one env = an MJCF + a class) is a ``SceneEnv`` subclass that
says how a task becomes a layout (``layout``), how tasks are drawn (``sample_task``) and how progress
along the task is scored (``task_init`` / ``task_update``).  Everything else -- the MJX car, the camera,
the signals, the observation history, bad-input handling -- lives here once.

State.  ``EnvState.physics`` is a ``SceneState``: the car's joint state plus the episode's layout (a
``Scene``), generated from the task in ``reset`` and read by ``step`` and the camera, so every robot of a
batch can drive in its own layout under one compiled step.
"""
from __future__ import annotations

import abc
import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from envs import base
from envs.camera import CameraConfig, render
from envs.car import CarConfig, CarPhysics, CarState, forward_speed
from envs.scene import DOOR, LANE_LINE, ROAD, Scene


@struct.dataclass
class SceneState:
    """``EnvState.physics`` of the MJX worlds."""

    car: CarState
    scene: Scene


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """Settings every scene has.  Actions are in env units: steering in degrees (positive turns left)
    and, unless ``fixed_speed`` is set, a speed set-point in m/s.  Out-of-box actions are clipped to
    the env box (``[-steer_limit_deg, steer_limit_deg]``, ``[-speed_limit, speed_limit]``); the planner
    samples from the plan box inside it."""

    car: CarConfig = CarConfig()
    camera: CameraConfig = CameraConfig()
    steer_limit_deg: float = 45.0
    plan_steer_deg: float = 30.0
    speed_limit: float = 4.0  # m/s; also the speed range of the vector state's normalisation box
    plan_speed: tuple[float, float] = (0.5, 3.0)
    fixed_speed: float | None = None  # steering-only robot at this speed (A = 1)
    lookahead: float = 2.0  # m: the goal heading is the task's direction this far ahead of the car
    history: int = 4  # frames (camera and vector) the observation carries, oldest first: the paper's 4 (1 s)

    def __post_init__(self):
        if self.history < 1:
            raise ValueError(f"history must be >= 1 frame, got {self.history}")
        if not 0 < self.plan_steer_deg <= self.steer_limit_deg:
            raise ValueError(f"need 0 < plan_steer_deg <= steer_limit_deg, got {self.plan_steer_deg}, "
                             f"{self.steer_limit_deg}")
        if self.fixed_speed is None and not -self.speed_limit <= self.plan_speed[0] <= self.plan_speed[1] <= self.speed_limit:
            raise ValueError(f"plan_speed {self.plan_speed} must be an ordered pair inside +-{self.speed_limit}")


class SceneEnv(base.Env, abc.ABC):
    """The car in a procedurally generated scene (see the module docstring)."""

    extra_signals: tuple[str, ...] = ()  # semantic signals beyond collision, speed, heading

    def __init__(self, config: SceneConfig):
        self.config = cfg = config
        # Slot counts of the family, from the layout's shapes (no layout is computed).
        shapes = jax.eval_shape(lambda k: self.layout(self.sample_task(k, "train")), jax.random.key(0))
        self.physics = CarPhysics(cfg.car, shapes.circles.shape[0], shapes.boxes.shape[0])
        v = cfg.speed_limit  # the speed part of the vector box (and of the action box when speed is an action)
        steer = ("steer_deg",), (-cfg.steer_limit_deg,), (cfg.steer_limit_deg,), (-cfg.plan_steer_deg,), (cfg.plan_steer_deg,)
        if cfg.fixed_speed is None:
            speed = ("speed",), (-v,), (v,), (cfg.plan_speed[0],), (cfg.plan_speed[1],)
            steer = tuple(a + b for a, b in zip(steer, speed))
        names, low, high, plan_low, plan_high = steer
        self.spec = base.EnvSpec(
            image_shape=cfg.camera.image_shape,
            vector_keys=("collision", "heading", "speed"),
            vector_low=(0.0, -math.pi, -v),
            vector_high=(1.0, math.pi, v),
            action_names=names,
            action_low=low,
            action_high=high,
            plan_low=plan_low,
            plan_high=plan_high,
            signal_names=("collision", "speed", "heading") + self.extra_signals,
            history=cfg.history,
        )

    # ---------------------------------------------------------------- what a scene defines

    @abc.abstractmethod
    def layout(self, task: Any) -> Scene:
        """The scene of a task (pure JAX, fixed slot counts)."""

    def start_pose(self, task: Any) -> jax.Array:
        """f32[3] pose (x, y, yaw) at reset: the task's ``start`` unless a scene derives it otherwise."""
        return jnp.asarray(task.start, jnp.float32)

    @abc.abstractmethod
    def task_init(self, task: Any, pose: jax.Array) -> tuple[dict, dict]:
        """``(info, metrics)`` entries at reset; ``info`` must hold ``goal_heading``."""

    @abc.abstractmethod
    def task_update(self, state: base.EnvState, pose: jax.Array, signals: dict) -> tuple[dict, dict, jax.Array]:
        """``(info, metrics, finished)`` after a step; ``state`` is the state before the step."""

    # ---------------------------------------------------------------- the env

    def sense(self, scene: Scene, car: CarState, collision: jax.Array):
        """Camera image, vector state and signals at this instant (image and vector from one instant)."""
        image, semantic, _ = render(scene, car.qpos, self.config.camera)
        speed = forward_speed(car)
        heading = base.wrap_angle(car.qpos[2])
        collision = collision.astype(jnp.float32)
        signals = {"collision": collision, "speed": speed, "heading": heading}
        signals.update(self.semantic_signals(semantic))
        return image, jnp.stack([collision, heading, speed]), signals

    def semantic_signals(self, semantic: jax.Array) -> dict:
        """The scene's semantic ground truth (lane, door) from the camera's class map."""
        out = {}
        if "lane_seen" in self.extra_signals:
            from capsjax import labellers  # the oracle labeller on the true class map

            seen, diff = labellers.lane_cues(semantic, road_id=ROAD, line_id=LANE_LINE)
            out.update(lane_seen=jnp.asarray(seen, jnp.float32), lane_diff=jnp.asarray(diff, jnp.float32))
        if "door_frac" in self.extra_signals:
            from capsjax import labellers

            out["door_frac"] = jnp.asarray(labellers.door_frac(semantic, door_id=DOOR), jnp.float32)
        return out

    def controls(self, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        steer = jnp.deg2rad(action[0])
        fixed = self.config.fixed_speed
        return steer, (action[1] if fixed is None else jnp.asarray(fixed, jnp.float32))

    def reset(self, key: jax.Array, task: Any) -> base.EnvState:
        self.check_task(task)
        del key  # the task fixes layout and start; auto-reset replays the same task
        scene = self.layout(task)
        car = self.physics.init(self.start_pose(task))
        image, vector, signals = self.sense(scene, car, jnp.zeros((), bool))
        info, metrics = self.task_init(task, car.qpos)
        info = dict(info, pose=car.qpos, action_invalid=jnp.zeros((), bool), physics_overflow=jnp.zeros((), bool))
        return base.EnvState(
            physics=SceneState(car=car, scene=scene),
            obs=base.initial_observation(self.spec, image, vector),
            signals=signals,
            reward=jnp.zeros((), jnp.float32),
            done=jnp.zeros((), bool),
            metrics=metrics,
            info=info,
            task=task,
        )

    def step(self, state: base.EnvState, action: jax.Array) -> base.EnvState:
        action, invalid = base.sanitize_action(action, self.spec)
        steer, setpoint = self.controls(action)
        scene = state.physics.scene
        car, collision, overflow = self.physics.step(state.physics.car, scene, steer, setpoint)
        image, vector, signals = self.sense(scene, car, collision)
        info, metrics, finished = self.task_update(state, car.qpos, signals)
        info = dict(info, pose=car.qpos, action_invalid=invalid, physics_overflow=overflow)
        return state.replace(
            physics=SceneState(car=car, scene=scene),
            obs=base.push_observation(state.obs, image, vector),
            signals=signals,
            done=state.done | collision | finished,
            metrics=metrics,
            info=info,
        )

    def split_key(self, key: jax.Array, split: str) -> jax.Array:
        """Disjoint random streams for the task splits (``base.split_key``)."""
        return base.split_key(key, split)


# ------------------------------------------------------------------------------------- path geometry


def polyline_lengths(path: jax.Array) -> jax.Array:
    """f32[P]: arc length at each vertex of a polyline f32[P, 2] (0 at the first)."""
    seg = jnp.linalg.norm(path[1:] - path[:-1], axis=-1)
    return jnp.concatenate([jnp.zeros((1,), path.dtype), jnp.cumsum(seg)])


def sharpest_bend(path: jax.Array) -> jax.Array:
    """f32: the smallest radius (m) of the circle through three consecutive vertices of a polyline f32[P, 2]
    (P >= 3); a straight polyline gives a huge radius.  How tightly a path asks the car to turn."""
    a, b, c = path[:-2], path[1:-1], path[2:]
    sides = (jnp.linalg.norm(b - a, axis=-1) * jnp.linalg.norm(c - b, axis=-1) * jnp.linalg.norm(a - c, axis=-1))
    twice_area = jnp.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    return jnp.min(sides / jnp.maximum(2.0 * twice_area, 1e-12))  # circumradius = abc / (4 * area)


def project_on_path(path: jax.Array, xy: jax.Array, s_min=-jnp.inf, s_max=jnp.inf):
    """Nearest point of the polyline to ``xy`` among arc lengths in [s_min, s_max].

    Returns ``(s, distance)``: the arc length of the nearest point and the distance to it.  The window
    lets a tracker follow a path that passes near itself (a closed circle) without jumping.
    """
    a, b = path[:-1], path[1:]
    ab = b - a
    seg_len2 = jnp.maximum(jnp.sum(ab**2, -1), 1e-12)
    seg_len = jnp.sqrt(seg_len2)
    s0 = polyline_lengths(path)
    # Each segment's part inside the window, as its parameter range: the nearest point is searched
    # there, not on the whole segment (a long segment whose nearest point lies beyond the window may
    # still hold the nearest in-window point: a car cutting a corner of a route of 25 m segments).
    t_lo = jnp.clip((s_min - s0[:-1]) / seg_len, 0.0, 1.0)
    t_hi = jnp.clip((s_max - s0[:-1]) / seg_len, 0.0, 1.0)
    t = jnp.clip(jnp.sum((xy - a) * ab, -1) / seg_len2, t_lo, t_hi)
    closest = a + t[:, None] * ab
    dist = jnp.linalg.norm(xy - closest, axis=-1)
    s = s0[:-1] + t * seg_len
    s_clamped = jnp.clip(s, s_min, s_max)
    # Segments wholly outside the window are penalised by how far outside they lie (never all excluded).
    score = dist + 1e3 * jnp.abs(s - s_clamped)
    i = jnp.argmin(score)
    return s[i], dist[i]


def path_point(path: jax.Array, s: jax.Array):
    """Position f32[2] and tangent heading f32[] of the polyline at arc length ``s`` (clamped)."""
    s0 = polyline_lengths(path)
    s = jnp.clip(s, 0.0, s0[-1])
    i = jnp.clip(jnp.searchsorted(s0, s, side="right") - 1, 0, path.shape[0] - 2)
    seg = path[i + 1] - path[i]
    length = jnp.maximum(s0[i + 1] - s0[i], 1e-12)
    point = path[i] + seg * ((s - s0[i]) / length)
    return point, jnp.arctan2(seg[1], seg[0])


def path_ahead(path: jax.Array, s: jax.Array, xy: jax.Array, length: float, num: int) -> jax.Array:
    """``num`` points f32[num, 2] of the polyline from arc length ``s`` to ``s + length`` (clamped at its
    end), relative to ``xy``: the stretch of path a planner's horizon can reach, in the frame of the
    positions it dead-reckons (world-aligned, the car at the origin)."""
    points, _ = jax.vmap(lambda si: path_point(path, si))(s + jnp.linspace(0.0, length, num))
    return points - xy


def running_mean(mean: jax.Array, value: jax.Array, count: jax.Array) -> jax.Array:
    """Mean of ``count`` values given the mean of the first ``count - 1``."""
    return mean + (value - mean) / jnp.maximum(count, 1).astype(jnp.float32)
