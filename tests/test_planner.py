import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from capsjax import planner
from capsjax.reward import RewardSpec
from envs.fast import FastEnv, FastOracle, FastTask

ENV = FastEnv()
ORACLE = FastOracle(ENV)
CFG = planner.CEMConfig(ENV.spec.plan_low, ENV.spec.plan_high, horizon=8, init_samples=256, samples=128,
                        iterations=3, elites=16)
ONE_OBSTACLE = FastTask(obstacles=jnp.array([[3.0, 0.0, 0.8]] + [[0.0, -5.0, 0.01]] * 3), start=jnp.array([0.0, 0.0, 0.0]))


def _drive(spec, steps, cfg=CFG, task=ONE_OBSTACLE, plan_fn=None, key=0):
    plan_fn = plan_fn or planner.jit_plan
    state = ENV.reset(jax.random.key(0), task)
    plan_state = planner.init_plan_state(cfg)
    step = jax.jit(ENV.step)
    key = jax.random.key(key)
    for _ in range(steps):
        key, sub = jax.random.split(key)
        action, plan_state, info = plan_fn(ORACLE, task, state.obs, spec, plan_state, sub, cfg=cfg)
        state = step(state, action)
        if bool(state.done):
            break
    return state


def test_straight_line_hits_the_obstacle():
    state = ENV.reset(jax.random.key(0), ONE_OBSTACLE)
    for _ in range(20):
        state = ENV.step(state, jnp.array([0.0, 2.0]))
    assert bool(state.done) and float(state.signals["collision"]) == 1.0


def test_planner_avoids_the_obstacle():
    spec = RewardSpec.from_terms(ORACLE, collision=100, speed=1, goal_speed=2.0)
    state = _drive(spec, 20)
    assert not bool(state.done)
    assert float(state.metrics["distance"]) > 5.0  # it kept driving, it did not just stop


def test_planner_reaches_a_goal_heading():
    spec = RewardSpec.from_terms(ORACLE, collision=100, heading_cos=1, goal_heading=(0.0, 1.0))
    state = _drive(spec, 12)
    assert not bool(state.done)
    assert abs(float(state.info["pose"][2]) - np.pi / 2) < 0.3


def test_switching_the_reward_changes_behaviour_without_recompiling():
    traces = []

    def counted(*args, **kwargs):
        traces.append(1)
        return planner.plan(*args, **kwargs)

    plan_fn = jax.jit(counted, static_argnums=(0,), static_argnames=("cfg",))
    open_task = FastTask(obstacles=jnp.array([[0.0, -5.0, 0.01]] * 4), start=jnp.array([0.0, 0.0, 0.0]))
    specs = [
        RewardSpec.from_terms(ORACLE, collision=100.0),  # Python floats
        RewardSpec.from_terms(ORACLE, collision=np.float32(100), heading_cos=np.float64(1), goal_heading=np.array([0.0, -1.0])),
        RewardSpec.from_terms(ORACLE, collision=jnp.asarray(100.0), heading_cos=jnp.asarray(1.0), goal_heading=jnp.array([0.0, 1.0])),
        RewardSpec.from_terms(ORACLE, collision=100, speed=2, goal_speed=np.float32(0.5)),
        RewardSpec.from_terms(ORACLE, collision=1, speed=1, heading_angle=3, goal_speed=2, goal_heading=(-1, 0)),
    ]
    finals = [_drive(s, 10, task=open_task, plan_fn=plan_fn) for s in specs]
    assert len(traces) == 1
    yaw_right, yaw_left = float(finals[1].info["pose"][2]), float(finals[2].info["pose"][2])
    assert yaw_right < -0.5 and yaw_left > 0.5  # the goal heading decides which way it turns
    slow, fast = float(finals[3].signals["speed"]), float(finals[4].signals["speed"])
    assert slow < 1.0 < fast


def test_capsjax_plan_is_compiled_once_for_many_weights():
    import capsjax

    obs = ENV.reset(jax.random.key(0), ONE_OBSTACLE).obs
    cfg = dataclasses.replace(CFG, horizon=4)
    before = capsjax.plan._cache_size()
    for w in (1.0, np.float32(2.0), jnp.asarray(3.0), 4, np.float64(5.0)):
        spec = RewardSpec.from_terms(ORACLE, collision=w, speed=w, goal_speed=w)
        capsjax.plan(ORACLE, ONE_OBSTACLE, obs, spec, planner.init_plan_state(cfg), jax.random.key(0), cfg=cfg)
    assert capsjax.plan._cache_size() == before + 1


class _NaNForLeftTurns(FastOracle):
    def rollout(self, params, carry, actions):
        preds = super().rollout(params, carry, actions)
        poison = jnp.where(actions[..., :1, 0] > 0, jnp.nan, 0.0)  # [..., 1]: whole sequence
        return {**preds, "collision": preds["collision"] + poison}


def test_candidates_with_nan_predictions_are_never_chosen():
    model = _NaNForLeftTurns(ENV)
    # Turning left would be preferred (goal heading north), but every left-turn prediction is NaN.
    spec = RewardSpec.from_terms(model, collision=1, heading_cos=10, goal_heading=(0.0, 1.0))
    obs = ENV.reset(jax.random.key(0), ONE_OBSTACLE).obs
    for optimizer in ("cem", "random"):
        cfg = dataclasses.replace(CFG, optimizer=optimizer)
        action, _, info = planner.plan(model, ONE_OBSTACLE, obs, spec, planner.init_plan_state(cfg), jax.random.key(1), cfg=cfg)
        assert float(action[0]) <= 0.0 and np.isfinite(float(info["value"]))


@pytest.mark.parametrize("options", [
    dict(covariance="diag"), dict(centred=False), dict(return_mode="mean"), dict(return_mode="local_mean"),
    dict(local_refit=True), dict(optimizer="random"),
    dict(warm_start=True), dict(iterations=1), dict(iterations=2),
])
def test_every_option_returns_an_action_in_the_box(options):
    cfg = dataclasses.replace(CFG, **options)
    spec = RewardSpec.from_terms(ORACLE, collision=100, speed=1, goal_speed=2)
    state = ENV.reset(jax.random.key(0), ONE_OBSTACLE)
    ps = planner.init_plan_state(cfg)
    for i in range(2):
        action, ps, info = planner.jit_plan(ORACLE, ONE_OBSTACLE, state.obs, spec, ps, jax.random.key(i), cfg=cfg)
        low, high = np.array(cfg.action_low), np.array(cfg.action_high)
        assert np.all(np.asarray(action) >= low - 1e-5) and np.all(np.asarray(action) <= high + 1e-5)
        assert info["actions"].shape == (cfg.horizon, 2) and info["preds"]["collision"].shape == (cfg.horizon,)
    assert bool(ps.has_previous)


def test_warm_start_keeps_a_good_plan():
    cfg = dataclasses.replace(CFG, warm_start=True, init_samples=32, iterations=1, optimizer="random")
    spec = RewardSpec.from_terms(ORACLE, collision=100, heading_cos=1, goal_heading=(0.0, 1.0))
    obs = ENV.reset(jax.random.key(0), ONE_OBSTACLE).obs
    good = jnp.tile(jnp.array([30.0, 1.0]), (cfg.horizon, 1))
    ps = planner.PlanState(previous=good, has_previous=jnp.ones((), bool))
    _, _, warm = planner.plan(ORACLE, ONE_OBSTACLE, obs, spec, ps, jax.random.key(0), cfg=cfg)
    _, _, cold = planner.plan(ORACLE, ONE_OBSTACLE, obs, spec, planner.init_plan_state(cfg), jax.random.key(0), cfg=cfg)
    assert float(warm["value"]) >= float(cold["value"])


def test_local_mean_stays_in_one_of_two_equally_good_modes():
    # Two equally good plans, steering -1 and +1 throughout (round an obstacle on either side), and a
    # straight plan, between them, that is the worst: the elite mean of a population holding both modes
    # is that straight plan, the mean of the elites near the best stays in the best's mode.
    cfg = planner.CEMConfig((-1.0,), (1.0,), horizon=4, init_samples=512, samples=512, iterations=1, elites=64)

    def score(seqs):  # f32[M, H, 1]: distance to the nearer mode
        x = seqs[..., 0]
        return -jnp.minimum(jnp.sum(jnp.square(x - 1.0), -1), jnp.sum(jnp.square(x + 1.0), -1))

    state = planner.init_plan_state(cfg)
    chosen = {mode: planner.cem_search(score, jax.random.key(3), state, cfg=dataclasses.replace(cfg, return_mode=mode))[0]
              for mode in ("mean", "local_mean")}
    assert abs(float(chosen["mean"].mean())) < 0.3  # between the modes
    local = np.asarray(chosen["local_mean"][:, 0])
    assert np.all(np.abs(local) > 0.5) and len(set(np.sign(local))) == 1  # inside one mode


def test_local_refit_follows_one_of_two_equally_good_modes():
    # The same two modes: refitting the Gaussian to all elites keeps sampling both (and the straight plan
    # between them), so after three iterations the elite mean is still often pulled towards the middle;
    # refitting to the elites near the best follows one mode, so the final elites, and their plain mean,
    # lie inside it.
    cfg = planner.CEMConfig((-1.0,), (1.0,), horizon=4, init_samples=512, samples=512, iterations=3, elites=64,
                            return_mode="mean")

    def score(seqs):
        x = seqs[..., 0]
        return -jnp.minimum(jnp.sum(jnp.square(x - 1.0), -1), jnp.sum(jnp.square(x + 1.0), -1))

    state = planner.init_plan_state(cfg)
    off_mode = {}  # mean distance of the chosen plan's steps from the nearer mode, over planner keys
    for local in (False, True):
        search = jax.jit(functools.partial(planner.cem_search, score, cfg=dataclasses.replace(cfg, local_refit=local)))
        plans = [np.asarray(search(jax.random.key(k), state)[0][:, 0]) for k in range(6)]
        off_mode[local] = np.mean([1.0 - np.abs(p) for p in plans])
        if local:
            assert all(len(set(np.sign(p))) == 1 for p in plans)  # every step of a plan in one mode
    assert off_mode[True] < 0.3 < off_mode[False] - 0.1, off_mode


def test_vmap_over_robots_with_their_own_rewards():
    n = 3
    tasks = jax.tree.map(lambda x: jnp.stack([x] * n), ONE_OBSTACLE)
    states = jax.vmap(ENV.reset)(jax.random.split(jax.random.key(0), n), tasks)
    headings = jnp.array([[0.0, 1.0], [0.0, -1.0], [1.0, 0.0]])
    specs = jax.vmap(lambda g: RewardSpec.from_terms(ORACLE, collision=100, heading_cos=1).with_goals(goal_heading=g))(headings)
    ps = jax.vmap(lambda _: planner.init_plan_state(CFG))(jnp.arange(n))
    plan_b = jax.jit(jax.vmap(lambda t, o, s, p, k: planner.plan(ORACLE, t, o, s, p, k, cfg=CFG)))
    actions, _, info = plan_b(tasks, states.obs, specs, ps, jax.random.split(jax.random.key(1), n))
    assert actions.shape == (n, 2)
    final = info["preds"]["heading"][:, -1]  # each robot's planned final heading follows its own goal
    assert float(final[0, 1]) > 0.3 and float(final[1, 1]) < -0.3 and float(final[2, 0]) > 0.9


@pytest.mark.parametrize("kwargs, field", [
    (dict(init_samples=0), "init_samples"), (dict(samples=-5), "samples"), (dict(elites=300), "elites"),
    (dict(horizon=0), "horizon"), (dict(action_low=(-1.0,)), "action_low"), (dict(covariance="lowrank"), "covariance"),
    (dict(return_mode="median"), "return_mode"), (dict(optimizer="mppi"), "optimizer"),
    (dict(action_low=(1.0, 1.0), action_high=(0.0, 2.0)), "action_low"),
])
def test_bad_configs_fail_before_compiling(kwargs, field):
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(CFG, **kwargs)


def test_action_box_must_match_the_model():
    cfg = planner.CEMConfig((-1.0,), (1.0,), horizon=4, init_samples=16, samples=16, elites=4)
    obs = ENV.reset(jax.random.key(0), ONE_OBSTACLE).obs
    spec = RewardSpec.from_terms(ORACLE, collision=1)
    with pytest.raises(ValueError, match="action_low has 1 entries"):
        planner.plan(ORACLE, ONE_OBSTACLE, obs, spec, planner.init_plan_state(cfg), jax.random.key(0), cfg=cfg)


def test_plan_batch_equals_planning_each_robot():
    n = 2
    tasks = jax.tree.map(lambda x: jnp.stack([x] * n), ONE_OBSTACLE)
    states = jax.vmap(ENV.reset)(jax.random.split(jax.random.key(0), n), tasks)
    spec = RewardSpec.from_terms(ORACLE, collision=100, heading_cos=1, goal_heading=(0.0, 1.0))
    specs = jax.tree.map(lambda x: jnp.stack([x] * n), spec)
    ps = jax.tree.map(lambda x: jnp.stack([x] * n), planner.init_plan_state(CFG))
    keys = jax.random.split(jax.random.key(3), n)
    actions, _, _ = planner.jit_plan_batch(ORACLE, ONE_OBSTACLE, states.obs, specs, ps, keys, cfg=CFG)
    for i in range(n):
        obs_i = jax.tree.map(lambda x: x[i], states.obs)
        single, _, _ = planner.jit_plan(ORACLE, ONE_OBSTACLE, obs_i, spec, planner.init_plan_state(CFG), keys[i], cfg=CFG)
        np.testing.assert_allclose(actions[i], single, rtol=1e-4, atol=1e-4)


def test_lists_for_the_action_box_give_a_hashable_config():
    cfg = planner.CEMConfig([-30, 0.5], np.array([30.0, 2.0]), horizon=4, init_samples=16, samples=16, elites=4)
    assert cfg.action_low == (-30.0, 0.5) and hash(cfg) == hash(dataclasses.replace(cfg))
