"""Closed-loop model-predictive control: plan, execute the first action, observe, repeat, all in one scan.

``run_episode`` drives one robot for a fixed number of control steps under ``jax.lax.scan``; vmap it
over robots (each with its own task, reward spec and key).  Once an episode is done the state is
frozen, so fixed-length scans give exact episode metrics without host round trips.
"""
from __future__ import annotations

from typing import Callable

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


def run_episode(
    env,
    model,
    params,
    spec: RewardSpec,
    task,
    key: jax.Array,
    *,
    cfg: planner.CEMConfig,
    num_steps: int,
    update_spec: Callable | None = None,
) -> Trajectory:
    """One robot, ``num_steps`` MPC steps.  ``update_spec(state, spec) -> spec`` refreshes goals each step
    (e.g. the path tangent ahead, or the direction to a goal); it must only change array values."""
    reset_key, key = jax.random.split(key)
    state = env.reset(reset_key, task)

    def step(carry, step_key):
        state, plan_state = carry
        step_spec = update_spec(state, spec) if update_spec is not None else spec
        action, new_plan_state, info = planner.plan(model, params, state.obs, step_spec, plan_state, step_key, cfg=cfg)
        stepped = env.step(state, action)
        # Freeze finished episodes: same shapes, no host round trip.
        frozen = jax.tree.map(lambda a, b: jnp.where(state.done, a, b), state, stepped)
        record = Trajectory(
            pose=frozen.info["pose"], signals=frozen.signals, done=frozen.done, action=action,
            value=info["value"], preds=info["preds"], metrics=frozen.metrics,
        )
        return (frozen, new_plan_state), record

    keys = jax.random.split(key, num_steps)
    _, trajectory = jax.lax.scan(step, (state, planner.init_plan_state(cfg)), keys)
    return trajectory
