"""The env interface every capsjax world implements, and the brax-style wrappers around it.

Conventions shared by every env (the fast analytic world and the MJX scenes alike):

* One robot per call: ``reset(key, task) -> EnvState`` and ``step(state, action) -> EnvState`` are pure
  and jittable; batching over robots is ``VmapWrapper`` (``jax.vmap``), never a Python loop.
* Heading is the car's yaw in radians, math convention (0 faces +x, counter-clockwise positive),
  wrapped to (-pi, pi].  (The paper's Panda3D forest used 0 = +y; only the origin differs.)
* Actions are ``f32[A]`` in the env's own units (steering in degrees, speed set-point in m/s).  A step
  clips them to the env action box (documented, never an error under jit) and replaces non-finite
  entries by the centre of the box, flagging ``info['action_invalid']``, so a NaN never reaches physics.
  A wrong action *shape* is a trace-time ``ValueError``.
* The observation carries a history of ``spec.history`` frames, oldest first.  Frames from before the
  episode start are zeros (the paper's padding).  Image and vector of one frame come from the same
  instant.
* ``signals`` are the ground-truth per-step quantities from which cue labels are built (collision,
  speed, heading, and for scenes with semantics lane_seen, lane_diff, door_frac).  They describe the
  state *after* the step that produced it.
* ``task`` is data (a pytree of arrays of fixed shape per env), so one compiled step serves all tasks.
"""
from __future__ import annotations

import abc
import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

CONTROL_DT = 0.25  # seconds of physics per control step (the paper's 4 Hz)

# Task splits, each its own random stream.  'train' tasks are what data are collected on; 'eval' tasks are
# the reported test; 'val' tasks are of the eval kind (same paths, goals, driving direction) on a third
# stream, disjoint from both, for choosing rewards and settings without ever looking at 'eval'.
TASK_SPLITS = ("train", "eval", "val")


def split_key(key: jax.Array, split: str) -> jax.Array:
    """The random stream of one task split (train -> 0, eval -> 1, val -> 2: the first two as before)."""
    if split not in TASK_SPLITS:
        raise ValueError(f"split must be one of {TASK_SPLITS}, got {split!r}")
    return jax.random.fold_in(key, TASK_SPLITS.index(split))


@struct.dataclass
class Observation:
    """What the robot senses: ``images`` u8[L, h, w, c] and ``vector`` f32[L, D], oldest frame first."""

    images: jax.Array
    vector: jax.Array


@struct.dataclass
class EnvState:
    """The full state of one robot's episode (batch dimensions in front when vmapped)."""

    physics: Any  # the car and layout (envs.scenes.common.SceneState) or the analytic car (envs.fast)
    obs: Observation
    signals: dict  # name -> f32[] ground truth at this instant
    reward: jax.Array  # CAPs composes rewards from predictions; envs report 0 unless a task defines one
    done: jax.Array  # bool[]: this state is terminal (crash, task finished or time limit)
    metrics: dict  # name -> f32[] running episode metrics
    info: dict  # pose, step count, task progress, flags
    task: Any  # the task pytree this episode runs


@dataclasses.dataclass(frozen=True)
class EnvSpec:
    """Static description of an env's observation, action and signal spaces.

    ``vector_low/high`` give the box used to normalise the vector state ((x - mid) / half range).
    ``action_low/high`` are the env action space (used to normalise actions by the *full* range, as the
    paper does); ``plan_low/high`` the box the planner and exploration sample from (inside the former).
    """

    image_shape: tuple[int, int, int]  # (h, w, c)
    vector_keys: tuple[str, ...]
    vector_low: tuple[float, ...]
    vector_high: tuple[float, ...]
    action_names: tuple[str, ...]
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    plan_low: tuple[float, ...]
    plan_high: tuple[float, ...]
    signal_names: tuple[str, ...]
    history: int = 4

    def __post_init__(self):
        n = len(self.vector_keys)
        if len(self.vector_low) != n or len(self.vector_high) != n:
            raise ValueError(f"EnvSpec.vector_low/high must have {n} entries (one per vector key)")
        a = len(self.action_names)
        for name in ("action_low", "action_high", "plan_low", "plan_high"):
            if len(getattr(self, name)) != a:
                raise ValueError(f"EnvSpec.{name} must have {a} entries (one per action), got {getattr(self, name)}")
        if any(lo > hi for lo, hi in zip(self.plan_low, self.plan_high)):
            raise ValueError(f"EnvSpec.plan_low must be <= plan_high, got {self.plan_low} / {self.plan_high}")

    @property
    def action_dim(self) -> int:
        return len(self.action_names)

    @property
    def vector_dim(self) -> int:
        return len(self.vector_keys)


class Env(abc.ABC):
    """A single-robot world. Subclasses set ``self.spec`` and implement reset/step/sample_task."""

    spec: EnvSpec

    @abc.abstractmethod
    def reset(self, key: jax.Array, task: Any) -> EnvState:
        ...

    @abc.abstractmethod
    def step(self, state: EnvState, action: jax.Array) -> EnvState:
        ...

    @abc.abstractmethod
    def sample_task(self, key: jax.Array, split: str = "train") -> Any:
        """A task drawn from ``split`` (one of ``TASK_SPLITS``); splits draw from disjoint seeds/regions, and
        'val' draws the 'eval' kind of task (``split_key``)."""

    def check_task(self, task: Any) -> None:
        """Raise a ValueError naming the field when ``task`` does not match this env's task shapes."""
        expected = jax.eval_shape(lambda k: self.sample_task(k, "train"), jax.random.key(0))
        check_tree_shapes("task", task, expected)

    @property
    def unwrapped(self) -> "Env":
        return self


def check_tree_shapes(what: str, tree: Any, expected: Any) -> None:
    """Compare a pytree's structure and leaf shapes with ``expected``; raise a ValueError naming the field."""
    flat, treedef = jax.tree_util.tree_flatten_with_path(tree)
    flat_expected, treedef_expected = jax.tree_util.tree_flatten_with_path(expected)
    if treedef != treedef_expected:
        raise ValueError(f"{what} has structure {treedef}, expected {treedef_expected}")
    for (path, leaf), (_, ref) in zip(flat, flat_expected):
        if np.shape(leaf) != tuple(ref.shape):
            name = what + jax.tree_util.keystr(path)
            raise ValueError(f"{name} has shape {np.shape(leaf)}, expected {tuple(ref.shape)}")


def sanitize_action(action: jax.Array, spec: EnvSpec) -> tuple[jax.Array, jax.Array]:
    """Check the shape (trace time), replace non-finite entries by the box centre and clip to the box.

    Returns ``(action, invalid)`` where ``invalid`` is True when any entry was not finite.
    """
    action = jnp.asarray(action, jnp.float32)
    if action.shape != (spec.action_dim,):
        raise ValueError(
            f"action has shape {action.shape}, expected ({spec.action_dim},) for actions {spec.action_names}"
        )
    low = jnp.asarray(spec.action_low, jnp.float32)
    high = jnp.asarray(spec.action_high, jnp.float32)
    finite = jnp.isfinite(action)
    action = jnp.where(finite, action, 0.5 * (low + high))
    return jnp.clip(action, low, high), ~jnp.all(finite)


def initial_observation(spec: EnvSpec, image: jax.Array, vector: jax.Array) -> Observation:
    """History at reset: zero frames before the episode start, the current frame last."""
    images = jnp.zeros((spec.history,) + image.shape, jnp.uint8).at[-1].set(image)
    vectors = jnp.zeros((spec.history, vector.shape[-1]), jnp.float32).at[-1].set(vector)
    return Observation(images=images, vector=vectors)


def push_observation(obs: Observation, image: jax.Array, vector: jax.Array) -> Observation:
    """Drop the oldest frame and append the newest (static shapes, no Python lists)."""
    images = jnp.concatenate([obs.images[1:], image[None].astype(jnp.uint8)], axis=0)
    vectors = jnp.concatenate([obs.vector[1:], vector[None].astype(jnp.float32)], axis=0)
    return Observation(images=images, vector=vectors)


def wrap_angle(angle: jax.Array) -> jax.Array:
    """Wrap to (-pi, pi]."""
    return jnp.pi - jnp.mod(jnp.pi - angle, 2 * jnp.pi)


# --------------------------------------------------------------------------------------------- wrappers


class Wrapper(Env):
    """Delegates to an inner env; subclasses override what they change."""

    def __init__(self, env: Env):
        self.env = env
        self.spec = env.spec

    def reset(self, key, task):
        return self.env.reset(key, task)

    def step(self, state, action):
        return self.env.step(state, action)

    def sample_task(self, key, split="train"):
        return self.env.sample_task(key, split)

    def check_task(self, task):
        return self.env.check_task(task)

    @property
    def unwrapped(self) -> Env:
        return self.env.unwrapped

    def __getattr__(self, name):
        # Reached only for attributes the wrapper does not define: expose the inner env's (config, ...).
        if name == "env":
            raise AttributeError(name)
        return getattr(self.env, name)


class EpisodeWrapper(Wrapper):
    """Ends an episode after ``episode_length`` control steps (``info['truncated']`` marks the time limit)."""

    def __init__(self, env: Env, episode_length: int):
        super().__init__(env)
        if episode_length <= 0:
            raise ValueError(f"episode_length must be positive, got {episode_length}")
        self.episode_length = int(episode_length)

    def reset(self, key, task):
        state = self.env.reset(key, task)
        info = dict(state.info, steps=jnp.zeros((), jnp.int32), truncated=jnp.zeros((), bool))
        return state.replace(info=info)

    def step(self, state, action):
        steps = state.info["steps"] + 1
        state = self.env.step(state, action)
        truncated = (steps >= self.episode_length) & ~state.done
        info = dict(state.info, steps=steps, truncated=truncated)
        return state.replace(done=state.done | truncated, info=info)


class AutoResetWrapper(Wrapper):
    """After a terminal step the *next* step starts a fresh episode of the same task.

    The terminal state itself is returned unchanged (so its observation and signals can be recorded,
    the paper's "terminal observation included"); the following ``step`` resets with a key carried in
    ``info['reset_key']`` instead of executing the action.  Static shapes: both branches are computed
    and selected with ``jnp.where`` so the wrapper stays vmappable (under vmap a ``lax.cond`` would run
    both anyway).  It relies on the env contract that ``reset`` and ``step`` return identically
    structured states (``lax.scan`` needs that too).
    """

    def reset(self, key, task):
        key, reset_key = jax.random.split(key)
        state = self.env.reset(key, task)
        return state.replace(info=dict(state.info, reset_key=reset_key))

    def step(self, state, action):
        reset_key, next_key = jax.random.split(state.info["reset_key"])
        stepped = self.env.step(state, action)
        fresh = self.env.reset(reset_key, state.task)
        out = jax.tree.map(lambda a, b: jnp.where(_bcast(state.done, a), a, b), fresh, stepped)
        return out.replace(info=dict(out.info, reset_key=next_key))


def _bcast(flag, leaf):
    return jnp.reshape(flag, jnp.shape(flag) + (1,) * (jnp.ndim(leaf) - jnp.ndim(flag)))


class VmapWrapper(Wrapper):
    """Batches reset/step over robots with ``jax.vmap``: keys [B], tasks [B, ...], actions [B, A]."""

    def reset(self, key, task):
        return jax.vmap(self.env.reset)(key, task)

    def step(self, state, action):
        return jax.vmap(self.env.step)(state, action)

    def sample_task(self, key, split="train"):
        return jax.vmap(lambda k: self.env.sample_task(k, split))(key)
