"""A tiny analytic world for fast tests of the planner and the trainer (no MuJoCo, no renderer).

A point car with bicycle kinematics drives on a plane inside a square arena with a few circular
obstacles.  It has the same interface as the MJX scenes (``envs.base.Env``): the same actions
(steering in degrees, speed set-point in m/s), the same signals (collision, speed, heading) and an
observation of a 4-frame image history plus a vector history.  The image is a cheap synthetic one:
one ray per column, obstacles drawn as bright bands whose height shrinks with distance.

Unlike the real scenes, the vector state also carries the car's (x, y): the fast world is a test bed,
and a known position lets tiny models learn the fixed obstacles in seconds.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from envs import base


@dataclasses.dataclass(frozen=True)
class FastConfig:
    arena_half: float = 6.0  # the arena spans [-arena_half, arena_half]^2
    num_obstacles: int = 4
    obstacle_radius: tuple[float, float] = (0.5, 1.0)
    car_radius: float = 0.5
    wheelbase: float = 1.0
    speed_gain: float = 1.25  # the paper's P gain of the speed controller
    max_accel: float = 2.0  # m/s^2 (the paper's car: 0.5; faster here so tests need fewer steps)
    substeps: int = 5
    image_height: int = 16
    image_width: int = 32
    hfov_deg: float = 120.0
    far: float = 15.0
    max_speed: float = 3.0
    steer_limit_deg: float = 45.0
    plan_steer_deg: float = 30.0
    plan_speed: tuple[float, float] = (0.5, 2.0)


@struct.dataclass
class FastTask:
    obstacles: jax.Array  # f32[N, 3]: x, y, radius
    start: jax.Array  # f32[3]: x, y, yaw


@struct.dataclass
class CarState:
    pose: jax.Array  # f32[3]: x, y, yaw
    speed: jax.Array  # f32[]


def car_step(cfg: FastConfig, car: CarState, action: jax.Array) -> CarState:
    """Advance one 0.25 s control step: bicycle kinematics and a saturated P speed controller."""
    dt = base.CONTROL_DT / cfg.substeps
    steer = jnp.deg2rad(action[0])
    setpoint = action[1]

    def substep(c, _):
        accel = jnp.clip(cfg.speed_gain * (setpoint - c.speed), -cfg.max_accel, cfg.max_accel)
        speed = c.speed + accel * dt
        x, y, yaw = c.pose
        yaw = base.wrap_angle(yaw + speed * jnp.tan(steer) / cfg.wheelbase * dt)
        pose = jnp.stack([x + speed * jnp.cos(yaw) * dt, y + speed * jnp.sin(yaw) * dt, yaw])
        return CarState(pose=pose, speed=speed), None

    car, _ = jax.lax.scan(substep, car, None, length=cfg.substeps)
    return car


def collides(cfg: FastConfig, pose: jax.Array, task: FastTask) -> jax.Array:
    """The car's disc overlaps an obstacle or leaves the arena."""
    dist = jnp.linalg.norm(task.obstacles[:, :2] - pose[:2], axis=-1) - task.obstacles[:, 2]
    hit_obstacle = jnp.any(dist < cfg.car_radius)
    hit_wall = jnp.any(jnp.abs(pose[:2]) > cfg.arena_half - cfg.car_radius)
    return hit_obstacle | hit_wall


def simulate(cfg: FastConfig, car: CarState, actions: jax.Array, task: FastTask) -> dict:
    """Exact future signals of an action sequence ``f32[H, A]`` (an analytic predictor for tests)."""

    def step(carry, action):
        car, crashed = carry
        moved = car_step(cfg, car, action)
        crashed = crashed | collides(cfg, moved.pose, task)
        return (moved, crashed), {"collision": crashed.astype(jnp.float32), "speed": moved.speed,
                                  "heading": moved.pose[2], "x": moved.pose[0], "y": moved.pose[1]}

    _, out = jax.lax.scan(step, (car, jnp.zeros((), bool)), actions)
    return out


def render(cfg: FastConfig, pose: jax.Array, task: FastTask) -> jax.Array:
    """u8[h, w, 1]: per column, the nearest obstacle or wall as a band whose height falls with distance."""
    angles = pose[2] + jnp.deg2rad(cfg.hfov_deg) * (0.5 - (jnp.arange(cfg.image_width) + 0.5) / cfg.image_width)
    dirs = jnp.stack([jnp.cos(angles), jnp.sin(angles)], -1)  # [W, 2]
    # Ray-circle: |p + t d - c|^2 = r^2, nearest positive root.
    rel = pose[None, :2] - task.obstacles[:, :2]  # [N, 2]
    b = dirs @ rel.T  # [W, N]
    c = jnp.sum(rel**2, -1) - task.obstacles[:, 2] ** 2
    disc = b**2 - c
    t = -b - jnp.sqrt(jnp.maximum(disc, 0.0))
    t_circle = jnp.min(jnp.where((disc > 0) & (t > 0), t, jnp.inf), axis=-1)
    # Ray-arena: the exit distance from the square.
    safe = jnp.where(jnp.abs(dirs) < 1e-6, 1e-6, dirs)
    t_wall = jnp.min((jnp.sign(safe) * cfg.arena_half - pose[None, :2]) / safe, axis=-1)
    depth = jnp.clip(jnp.minimum(t_circle, t_wall), 0.05, cfg.far)
    rows = jnp.arange(cfg.image_height) - (cfg.image_height - 1) / 2
    half_band = 0.5 * cfg.image_height / depth  # 1 m tall at 1 m fills the image
    wall = jnp.abs(rows)[:, None] <= half_band[None, :]
    shade = 255.0 * (1.0 - depth / cfg.far) * jnp.where(t_circle <= t_wall, 1.0, 0.6)
    background = jnp.where(rows[:, None] > 0, 60.0, 160.0)  # ground below the horizon, sky above
    image = jnp.where(wall, shade[None, :], background)
    return jnp.round(image).astype(jnp.uint8)[..., None]


class FastEnv(base.Env):
    """The fast analytic world behind the standard env interface."""

    def __init__(self, config: FastConfig = FastConfig()):
        self.config = cfg = config
        v = cfg.max_speed
        self.spec = base.EnvSpec(
            image_shape=(cfg.image_height, cfg.image_width, 1),
            vector_keys=("collision", "heading", "speed", "x", "y"),
            vector_low=(0.0, -jnp.pi, -v, -cfg.arena_half, -cfg.arena_half),
            vector_high=(1.0, jnp.pi, v, cfg.arena_half, cfg.arena_half),
            action_names=("steer_deg", "speed"),
            action_low=(-cfg.steer_limit_deg, -v),
            action_high=(cfg.steer_limit_deg, v),
            plan_low=(-cfg.plan_steer_deg, cfg.plan_speed[0]),
            plan_high=(cfg.plan_steer_deg, cfg.plan_speed[1]),
            signal_names=("collision", "speed", "heading"),
        )

    def sample_task(self, key, split="train"):
        """Random obstacles; each split's layouts come from its own key stream (``base.split_key``)."""
        cfg = self.config
        key = base.split_key(key, split)
        k_pos, k_rad, k_yaw = jax.random.split(key, 3)
        span = cfg.arena_half - 1.5
        pos = jax.random.uniform(k_pos, (cfg.num_obstacles, 2), minval=-span, maxval=span)
        # Keep the start area (a disc of 2 m around the origin) clear.
        norm = jnp.linalg.norm(pos, axis=-1, keepdims=True)
        pos = jnp.where(norm < 2.5, pos / jnp.maximum(norm, 1e-3) * 2.5, pos)
        radius = jax.random.uniform(k_rad, (cfg.num_obstacles, 1), minval=cfg.obstacle_radius[0], maxval=cfg.obstacle_radius[1])
        yaw = jax.random.uniform(k_yaw, (), minval=-jnp.pi, maxval=jnp.pi)
        return FastTask(obstacles=jnp.concatenate([pos, radius], -1), start=jnp.stack([0.0, 0.0, yaw]))

    def _observe(self, car: CarState, collided, task: FastTask):
        vector = jnp.stack([collided.astype(jnp.float32), car.pose[2], car.speed, car.pose[0], car.pose[1]])
        signals = {"collision": collided.astype(jnp.float32), "speed": car.speed, "heading": car.pose[2]}
        return render(self.config, car.pose, task), vector, signals

    def reset(self, key, task):
        self.check_task(task)
        car = CarState(pose=jnp.asarray(task.start, jnp.float32), speed=jnp.zeros((), jnp.float32))
        collided = collides(self.config, car.pose, task)
        image, vector, signals = self._observe(car, collided, task)
        return base.EnvState(
            physics=car,
            obs=base.initial_observation(self.spec, image, vector),
            signals=signals,
            reward=jnp.zeros((), jnp.float32),
            done=collided,
            metrics={"distance": jnp.zeros((), jnp.float32)},
            info={"pose": car.pose, "action_invalid": jnp.zeros((), bool)},
            task=task,
        )

    def step(self, state, action):
        action, invalid = base.sanitize_action(action, self.spec)
        moved = car_step(self.config, state.physics, action)
        collided = collides(self.config, moved.pose, state.task)
        # A crash stops the car where it hit (the bumper), it does not pass through.
        car = CarState(pose=jnp.where(collided, state.physics.pose, moved.pose), speed=jnp.where(collided, 0.0, moved.speed))
        image, vector, signals = self._observe(car, collided, state.task)
        travelled = jnp.linalg.norm(car.pose[:2] - state.physics.pose[:2])
        return state.replace(
            physics=car,
            obs=base.push_observation(state.obs, image, vector),
            signals=signals,
            done=state.done | collided,
            metrics={"distance": state.metrics["distance"] + travelled},
            info={"pose": car.pose, "action_invalid": invalid},
        )


def random_windows(env: FastEnv, key: jax.Array, task: FastTask, batch: int, horizon: int):
    """Exactly labelled training windows from random states and random action sequences.

    Returns ``capsjax.losses.Batch``: a current observation (a still history: the car has been at
    its pose for all frames), ``horizon`` uniform actions from the plan box and the true future
    signals; steps after a crash are invalid (the crash step itself is valid).
    """
    from capsjax.losses import Batch  # envs stay importable without the learning library

    cfg = env.config
    k_pose, k_speed, k_act = jax.random.split(key, 3)
    span = cfg.arena_half - cfg.car_radius - 0.2
    # Window starts never lie on a terminal state: draw twice as many poses, keep collision-free ones
    # first (static shapes: a stable sort on the collision flag instead of rejection sampling).
    xy = jax.random.uniform(k_pose, (2 * batch, 2), minval=-span, maxval=span)
    yaw = jax.random.uniform(jax.random.fold_in(k_pose, 1), (2 * batch,), minval=-jnp.pi, maxval=jnp.pi)
    pose = jnp.concatenate([xy, yaw[:, None]], -1)
    in_collision = jax.vmap(lambda p: collides(cfg, p, task))(pose)
    pose = pose[jnp.argsort(in_collision, stable=True)[:batch]]
    speed = jax.random.uniform(k_speed, (batch,), minval=0.0, maxval=cfg.plan_speed[1])
    low, high = jnp.asarray(env.spec.plan_low), jnp.asarray(env.spec.plan_high)
    actions = jax.random.uniform(k_act, (batch, horizon, env.spec.action_dim), minval=low, maxval=high)

    def one(pose, speed, acts):
        car = CarState(pose=pose, speed=speed)
        image, vector, _ = env._observe(car, jnp.zeros((), bool), task)
        obs = base.Observation(
            images=jnp.broadcast_to(image, (env.spec.history,) + image.shape),
            vector=jnp.broadcast_to(vector, (env.spec.history, vector.shape[0])),
        )
        future = simulate(cfg, car, acts, task)
        crashed_before = jnp.concatenate([jnp.zeros((1,), bool), future["collision"][:-1] > 0.5])
        return obs, future, ~crashed_before

    obs, future, valid = jax.vmap(one)(pose, speed, actions)
    signals = {name: future[name] for name in env.spec.signal_names}
    return Batch(obs=obs, actions=actions, signals=signals, valid=valid)


@dataclasses.dataclass(frozen=True)
class FastOracle:
    """An exact CAPs-style predictor of the fast world: the planner's model protocol without learning.

    ``params`` is the ``FastTask`` (the oracle knows the obstacles); ``encode`` reads the car's pose and
    speed from the newest vector frame; ``rollout`` simulates.  It isolates the planner and the reward
    composition from model error in tests, and bounds what a learned model could achieve.
    """

    env: FastEnv

    cue_names = ("collision", "speed", "heading")

    @property
    def action_low(self):
        return self.env.spec.action_low

    @property
    def action_high(self):
        return self.env.spec.action_high

    horizon = None  # any horizon

    def encode(self, params: FastTask, obs: base.Observation) -> CarState:
        v = obs.vector[-1]
        return CarState(pose=jnp.stack([v[3], v[4], v[1]]), speed=v[2])

    def rollout(self, params: FastTask, carry: CarState, actions: jax.Array) -> dict:
        """Like ``CAPsModel.rollout``: leading dims of ``actions`` are candidates."""
        sim = lambda a: simulate(self.env.config, carry, a, params)
        for _ in range(actions.ndim - 2):
            sim = jax.vmap(sim)
        out = sim(actions)
        heading = out["heading"]
        return {"collision": out["collision"], "speed": out["speed"],
                "heading": jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1)}
