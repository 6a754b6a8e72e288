"""Online mode: collect with the baseline's own CEM policy and train, in one jit (see the package docstring)."""
from __future__ import annotations

import types
from typing import Any, Callable, NamedTuple

import flashbax as fbx
import jax
import jax.numpy as jnp
from flax import struct

from capsjax import planner, training
from capsjax.baselines.agent import (BaselineAgent, BaselineState, Transition, baseline_policy, init_state,
                                     make_train_step, small_cem, sync_target)


@struct.dataclass
class OnlineState:
    learner: BaselineState
    env_state: Any  # batched over robots
    policy_state: Any  # the exploration policy's state, batched over robots
    episode_steps: jax.Array  # i32[R]
    replay: Any  # flashbax item buffer state of ``Transition`` items
    env_steps: jax.Array  # i32[]: transitions collected by the whole fleet
    key: jax.Array


class OnlineTrainer(NamedTuple):
    init: Callable  # init(key, learner=None) -> OnlineState
    train: Callable  # train(state, spec) -> (state, metrics[env_steps]) under one jit


def make_online_train(agent: BaselineAgent, train_cfg: training.TrainConfig, env, *, num_robots: int,
                      env_steps: int, episode_length: int, cem_cfg: planner.CEMConfig | None = None,
                      grad_steps_per_env_step: int = 4, learning_starts: int = 1000,
                      replay_capacity: int = 400_000, schedule=None, update_spec: Callable | None = None,
                      task_split: str = "train") -> OnlineTrainer:
    """Collect with the baseline's own CEM policy and the paper's exploration while training, in one jit.

    Each of ``env_steps`` loop iterations steps all ``num_robots`` robots (vmapped), stores their
    transitions in a device-resident flashbax item buffer and, once ``learning_starts`` transitions
    are stored, takes ``grad_steps_per_env_step * num_robots`` gradient steps (the paper's 4 per env
    step).  Exploration is ``collect.exploration_policy`` (section 5.3) counting fleet env steps; the
    target is copied every ``config.target_every`` env steps.  Episodes end on a crash (no bootstrap)
    or after ``episode_length`` steps (bootstrapped), then restart on a fresh ``task_split`` task.
    ``update_spec(env_state, spec) -> spec`` sets each robot's acting goals (stored with its transitions).
    """
    from capsjax import collect  # lazy: collect imports data (zarr), which the rest of this module never needs

    for name, v in (("num_robots", num_robots), ("env_steps", env_steps), ("episode_length", episode_length),
                    ("grad_steps_per_env_step", grad_steps_per_env_step), ("replay_capacity", replay_capacity)):
        if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
            raise ValueError(f"make_online_train: {name} must be a positive int, got {v!r}")
    if train_cfg.batch_size > replay_capacity:
        raise ValueError(f"replay_capacity ({replay_capacity}) must hold at least one batch ({train_cfg.batch_size})")
    cem_cfg = cem_cfg or small_cem(env.spec.plan_low, env.spec.plan_high)
    policy = collect.exploration_policy(baseline_policy(agent, cem_cfg), env.spec,
                                        schedule=schedule or collect.PAPER_SCHEDULE)
    # flashbax's item buffer: a ring buffer of single transitions with uniform sampling, all on device.
    buffer = fbx.make_item_buffer(max_length=replay_capacity, min_length=train_cfg.batch_size,
                                  sample_batch_size=train_cfg.batch_size, add_batches=True)
    step_fn = make_train_step(agent, train_cfg)
    grad_steps = grad_steps_per_env_step * num_robots
    reset_all = jax.vmap(env.reset)
    sample_tasks = jax.vmap(lambda k: env.sample_task(k, task_split))

    def spec_for(state, spec):
        return jax.vmap(lambda s: update_spec(s, spec))(state) if update_spec else jax.tree.map(
            lambda x: jnp.broadcast_to(x, (num_robots,) + x.shape), spec)

    def init(key, learner: BaselineState | None = None) -> OnlineState:
        k_learn, k_task, k_reset, key = jax.random.split(key, 4)
        learner = learner if learner is not None else init_state(agent, train_cfg, k_learn)
        env_state = reset_all(jax.random.split(k_reset, num_robots), sample_tasks(jax.random.split(k_task, num_robots)))
        pstate = jax.vmap(lambda _: policy.init_state())(jnp.arange(num_robots))
        pstate = pstate.replace(stride=jnp.full((num_robots,), num_robots, jnp.int32))
        example = jax.tree.map(lambda x: x[0], _transition(env_state, env_state, jnp.zeros((num_robots, cem_cfg.action_dim)),
                                                           spec_for_init(env_state)))
        return OnlineState(learner=learner, env_state=env_state, policy_state=pstate,
                           episode_steps=jnp.zeros((num_robots,), jnp.int32), replay=buffer.init(example),
                           env_steps=jnp.zeros((), jnp.int32), key=key)

    def spec_for_init(env_state):
        zeros = jnp.zeros((num_robots,), jnp.float32)
        return types.SimpleNamespace(goal_speed=zeros, goal_heading=jnp.zeros((num_robots, 2), jnp.float32))

    def _transition(before, after, action, spec):
        crash = after.signals["collision"] > 0.5
        return Transition(obs=before.obs, action=action, next_obs=after.obs, signals=after.signals, done=crash,
                          valid=~before.done, goal_speed=spec.goal_speed, goal_heading=spec.goal_heading)

    def loop(state: OnlineState, spec):
        key, k_act, k_task, k_reset, k_train = jax.random.split(state.key, 5)
        specs = spec_for(state.env_state, spec)
        action, pstate, info = jax.vmap(policy.act, in_axes=(None, 0, 0, 0, 0))(
            state.learner.params, state.env_state.obs, specs, state.policy_state, jax.random.split(k_act, num_robots))
        stepped = jax.vmap(env.step)(state.env_state, action)
        replay = buffer.add(state.replay, _transition(state.env_state, stepped, action, specs))
        episode_steps = state.episode_steps + 1
        finished = stepped.done | (episode_steps >= episode_length)
        fresh = reset_all(jax.random.split(k_reset, num_robots), sample_tasks(jax.random.split(k_task, num_robots)))
        pick = lambda f, s: jnp.where(finished.reshape(finished.shape + (1,) * (s.ndim - 1)), f, s)
        env_state = jax.tree.map(pick, fresh, stepped)
        count = state.env_steps + num_robots

        def learn(learner):
            def one(learner, k):
                k_sample, k_target = jax.random.split(k)
                batch = buffer.sample(replay, k_sample).experience
                return step_fn(learner, batch, k_target)

            learner, metrics = jax.lax.scan(one, learner, jax.random.split(k_train, grad_steps))
            return learner, metrics["loss"].mean()

        ready = (count >= learning_starts) & buffer.can_sample(replay)
        learner, loss = jax.lax.cond(ready, learn, lambda l: (l, jnp.full((), jnp.nan)), state.learner)
        learner = sync_target(learner, state.env_steps, count, agent.config.target_every)
        new = OnlineState(learner=learner, env_state=env_state, policy_state=pstate,
                          episode_steps=jnp.where(finished, 0, episode_steps), replay=replay, env_steps=count, key=key)
        metrics = {"loss": loss, "collisions": jnp.sum(stepped.signals["collision"] > 0.5),
                   "finished": jnp.sum(finished), "epsilon": info["epsilon"][0], "sigma": info["sigma"][0]}
        return new, metrics

    def train(state: OnlineState, spec):
        return jax.lax.scan(lambda s, _: loop(s, spec), state, None, length=env_steps)

    return OnlineTrainer(init=init, train=jax.jit(train))


