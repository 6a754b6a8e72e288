"""Closed-loop control: act, execute, observe, repeat, all in one scan -- for CAPs and the baselines alike.

A ``Policy`` is the one interface every method plugs into (CAPs MPC, the Q-learning baselines, a
scripted driver): ``act(params, obs, spec, policy_state, key) -> (action, policy_state, info)`` with
``info['value']`` the method's score of its choice (and, for predictive methods, ``info['preds']``).
``run_episode`` drives one robot for a fixed number of control steps under ``jax.lax.scan``; vmap it
over robots (each with its own task, reward spec and key).  Once an episode is done the state is
frozen, so fixed-length scans give exact episode metrics without host round trips.
"""
from __future__ import annotations

import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
from flax import struct

from capsjax import planner
from capsjax.reward import RewardSpec


@struct.dataclass
class Trajectory:
    """Per-step records of one closed-loop episode (leading axis = control steps)."""

    pose: jax.Array  # f32[T, 3]
    signals: dict  # name -> f32[T]
    done: jax.Array  # bool[T]: done after this step
    action: jax.Array  # f32[T, A]
    value: jax.Array  # f32[T]: the planner's predicted reward of the chosen sequence
    preds: dict  # the chosen sequence's predicted cues, name -> f32[T, H(, 2)]
    metrics: dict  # the env's running metrics after each step
    image: jax.Array | None = None  # u8[T, h, w, c]: the camera frame each decision saw (record_images)


class Policy(NamedTuple):
    """A controller: ``act(params, obs, spec, policy_state, key) -> (action, policy_state, info)``.

    Static (hashable) so a jitted loop compiles once per policy; everything that varies (params, reward
    weights and goals, keys) is an argument.
    """

    act: Callable
    init_state: Callable[[], Any]


def caps_policy(model, cfg: planner.CEMConfig) -> Policy:
    """CAPs: CEM over action sequences scored by the predicted cues under the reward ``spec``.
    ``model`` may be any predictor with ``encode``/``rollout`` (a ``CAPsModel`` or an exact oracle)."""
    return Policy(act=functools.partial(planner.plan, model, cfg=cfg),
                  init_state=functools.partial(planner.init_plan_state, cfg))


def run_episode(
    env,
    policy: Policy,
    params,
    spec: RewardSpec,
    task,
    key: jax.Array,
    *,
    num_steps: int,
    update_spec: Callable | None = None,
    record_images: bool = False,
) -> Trajectory:
    """One robot, ``num_steps`` control steps.  ``update_spec(state, spec) -> spec`` refreshes goals each
    step (e.g. the path tangent ahead, or the direction to a goal); it must only change array values.
    ``record_images`` keeps each step's camera frame (for first-person videos; memory grows with T)."""
    reset_key, key = jax.random.split(key)
    state = env.reset(reset_key, task)

    def step(carry, step_key):
        state, policy_state = carry
        step_spec = update_spec(state, spec) if update_spec is not None else spec
        action, new_policy_state, info = policy.act(params, state.obs, step_spec, policy_state, step_key)
        stepped = env.step(state, action)
        # Freeze finished episodes: same shapes, no host round trip.
        frozen = jax.tree.map(lambda a, b: jnp.where(state.done, a, b), state, stepped)
        record = Trajectory(
            pose=frozen.info["pose"], signals=frozen.signals, done=frozen.done, action=action,
            value=info["value"], preds=info.get("preds", {}), metrics=frozen.metrics,
            image=state.obs.images[-1] if record_images else None,
        )
        return (frozen, new_policy_state), record

    keys = jax.random.split(key, num_steps)
    _, trajectory = jax.lax.scan(step, (state, policy.init_state()), keys)
    return trajectory
