import functools
import math
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import capsjax
from capsjax import baselines as bl
from capsjax import collect, mpc
from envs import base
from envs.fast import CarState, FastEnv, FastTask, simulate

ENV = FastEnv()
# An open arena: collisions are with its walls only (a known function of the vector state).
OPEN = FastTask(obstacles=jnp.array([[5.5, 5.5, 0.01]] * 4), start=jnp.zeros(3))
TRUNK = capsjax.ModelConfig.from_env_spec(ENV.spec, conv=((8, 4, 2), (8, 3, 2)), obs_hidden=(32, 32),
                                          action_hidden=(16, 32), head_hidden=8)
SIGNALS = types.SimpleNamespace(cue_names=bl.SIGNAL_CUES, action_low=ENV.spec.action_low,
                                action_high=ENV.spec.action_high)


def agent_of(cfg: bl.BaselineConfig) -> bl.BaselineAgent:
    return bl.BaselineAgent.create(TRUNK, cfg, ENV.spec.plan_low, ENV.spec.plan_high)


@functools.partial(jax.jit, static_argnums=(1,), static_argnames=("yaw",))
def fast_transitions(key, batch: int, task=OPEN, yaw=None, goal_spread: float = 1.0) -> capsjax.Batch:
    """Exact one-step transitions of the fast world from random states (still 4-frame histories), as a
    ``losses.Batch`` with done/next_obs/context; ``final_xy`` is a random point around the car (its
    hindsight goal heading is then a random direction)."""
    k_xy, k_yaw, k_speed, k_act, k_goal = jax.random.split(key, 5)
    span = ENV.config.arena_half - ENV.config.car_radius - 0.2
    xy = jax.random.uniform(k_xy, (batch, 2), minval=-span, maxval=span)
    yaws = jax.random.uniform(k_yaw, (batch,), minval=-jnp.pi, maxval=jnp.pi) if yaw is None else jnp.full((batch,), yaw)
    pose = jnp.concatenate([xy, yaws[:, None]], -1)
    speed = jax.random.uniform(k_speed, (batch,), minval=0.5, maxval=2.0)
    low, high = jnp.asarray(ENV.spec.plan_low), jnp.asarray(ENV.spec.plan_high)
    actions = jax.random.uniform(k_act, (batch, 1, 2), minval=low, maxval=high)

    def one(pose, speed, acts):
        car = CarState(pose=pose, speed=speed)
        image, vector, _ = ENV._observe(car, jnp.zeros((), bool), task)
        obs = base.Observation(images=jnp.broadcast_to(image, (4,) + image.shape), vector=jnp.broadcast_to(vector, (4, 5)))
        out = simulate(ENV.config, car, acts, task)
        moved = CarState(pose=jnp.stack([out["x"][0], out["y"][0], out["heading"][0]]), speed=out["speed"][0])
        image2, vector2, _ = ENV._observe(moved, out["collision"][0] > 0.5, task)
        return obs, base.push_observation(obs, image2, vector2), {k: out[k] for k in ("collision", "speed", "heading")}

    obs, next_obs, signals = jax.vmap(one)(pose, speed, actions)
    final_xy = xy + goal_spread * jax.random.normal(k_goal, (batch, 2))
    return capsjax.Batch(obs=obs, actions=actions, signals=signals, valid=jnp.ones((batch, 1), bool),
                         done=signals["collision"] > 0.5, next_obs=next_obs,
                         context={"pose": pose, "final_xy": final_xy})


# ------------------------------------------------------------------------------------------ config


def test_bad_config_is_refused_with_the_field_named():
    with pytest.raises(ValueError, match="kind"):
        bl.BaselineConfig(kind="dqn")
    with pytest.raises(ValueError, match="gamma"):
        bl.BaselineConfig(gamma=1.0)
    with pytest.raises(ValueError, match="target_every"):
        bl.BaselineConfig(target_every=0)
    with pytest.raises(ValueError, match="reward_terms"):
        bl.BaselineConfig(reward_terms=(("collision", 1.0),))
    with pytest.raises(ValueError, match="no_bootstrap"):
        bl.BaselineConfig(kind="gc_dql", no_bootstrap=("speed",))
    with pytest.raises(ValueError, match="reward_scaling must be a positive"):
        bl.BaselineConfig(reward_scaling=0.0)
    with pytest.raises(ValueError, match="reward_scaling must be 1.0 for gc_dql_sep"):
        bl.BaselineConfig(kind="gc_dql_sep", reward_scaling=0.5)
    with pytest.raises(ValueError, match="plan_low"):
        bl.BaselineAgent.create(TRUNK, bl.BaselineConfig(), (0.0,), (1.0,))
    with pytest.raises(ValueError, match="horizon"):
        bl.baseline_policy(agent_of(bl.BaselineConfig()), capsjax.CEMConfig(ENV.spec.plan_low, ENV.spec.plan_high, horizon=2))


def test_q_network_is_the_caps_trunk_with_goal_inputs_and_q_heads():
    for kind, heads in (("dql", ("q",)), ("gc_dql", ("q",)),
                        ("gc_dql_sep", ("collision", "heading_angle", "door"))):
        agent = agent_of(bl.BaselineConfig.halls(kind))
        cfg = agent.model.config
        assert cfg.horizon == 1 and agent.model.cue_names == heads
        assert (cfg.conv, cfg.obs_hidden, cfg.action_hidden, cfg.history) == (
            TRUNK.conv, TRUNK.obs_hidden, TRUNK.action_hidden, TRUNK.history)
        extra = bl.GOAL_KEYS if kind != "dql" else ()
        assert cfg.vector_keys == TRUNK.vector_keys + extra
    sep = agent_of(bl.BaselineConfig.halls("gc_dql_sep")).model.cues
    assert (sep[0].kind, sep[0].activation) == ("binary", "sigmoid") and sep[1].activation == "linear"


# ------------------------------------------------------------------------------------------ targets


def _transition(collision, speed, heading, done, goal_heading, action=(0.0, 1.0)):
    n = len(collision)
    return bl.Transition(obs=None, action=jnp.tile(jnp.asarray(action, jnp.float32), (n, 1)), next_obs=None,
                         signals={"collision": jnp.asarray(collision, jnp.float32), "speed": jnp.asarray(speed, jnp.float32),
                                  "heading": jnp.asarray(heading, jnp.float32)},
                         done=jnp.asarray(done), valid=jnp.ones((n,), bool),
                         goal_speed=jnp.full((n,), 2.0, jnp.float32), goal_heading=jnp.asarray(goal_heading, jnp.float32))


def test_rewards_and_td_targets_on_a_hand_computed_example():
    # Two transitions, goal speed 2 m/s: (a) no crash, v = 1, heading pi/2 against goal +x;
    # (b) crash, v = 3, heading 0 along goal +x.
    tr = _transition([0.0, 1.0], [1.0, 3.0], [math.pi / 2, 0.0], [False, True], [[1.0, 0.0], [1.0, 0.0]])
    cfg = bl.BaselineConfig("gc_dql", gamma=0.9, collision_reward=-100.0,
                            reward_terms=(("speed", 2.0), ("heading_angle", 4.0)), goal_speed=2.0)
    r = bl.head_rewards(agent_of(cfg), tr)["q"]
    # (a) 2 * (-|1 - 2| / 2) + 4 * (-(pi/2) / pi) = -1 - 2 = -3; (b) the crash: -100.
    np.testing.assert_allclose(r, [-3.0, -100.0], rtol=1e-5)
    # reward_scaling: the same reward in units of the crash penalty (the forest's and CARLA's variants).
    scaled = bl.head_rewards(agent_of(dataclasses_replace(cfg, reward_scaling=0.01)), tr)["q"]
    np.testing.assert_allclose(scaled, [-0.03, -1.0], rtol=1e-5)
    for factory, penalty in ((bl.BaselineConfig.forest, 500.0), (bl.BaselineConfig.carla, 1000.0)):
        assert factory("gc_dql").reward_scaling * penalty == factory("dql").reward_scaling * penalty == 1.0
        assert factory("gc_dql_sep").reward_scaling == 1.0
    y = bl.td_targets({"q": r}, {"q": jnp.array([10.0, 50.0])}, tr.done, cfg.gamma)["q"]
    np.testing.assert_allclose(y, [-3.0 + 0.9 * 10.0, -100.0], rtol=1e-5)  # no bootstrap past the crash

    sep = agent_of(dataclasses_replace(cfg, kind="gc_dql_sep"))
    rs = bl.head_rewards(sep, tr)
    np.testing.assert_allclose(rs["collision"], [0.0, 1.0])
    np.testing.assert_allclose(rs["speed"], [-0.5, -0.5], rtol=1e-5)
    np.testing.assert_allclose(rs["heading_angle"], [-0.5, 0.0], atol=1e-3)
    nxt = {"collision": jnp.array([0.2, 0.7]), "speed": jnp.array([-1.0, -1.0]), "heading_angle": jnp.array([-0.3, -0.3])}
    ys = bl.td_targets(rs, nxt, tr.done, 0.9, no_bootstrap=("speed",))
    np.testing.assert_allclose(ys["collision"], [0.9 * 0.2, 1.0], rtol=1e-5)
    np.testing.assert_allclose(ys["speed"], [-0.5, -0.5], rtol=1e-5)
    np.testing.assert_allclose(ys["heading_angle"], [-0.5 - 0.27, 0.0], atol=1e-3)


def dataclasses_replace(cfg, **kw):
    import dataclasses

    return dataclasses.replace(cfg, **kw)


def test_double_q_target_evaluates_the_online_argmax_with_the_target_net():
    # Stub Q-functions of the next observation's last vector entry and the action: the online net
    # prefers steering near +20 deg, the target net prefers -20 deg.  A double-Q target takes the
    # online argmax and the *target's* value there, far below the target's own maximum (0).
    agent = agent_of(bl.BaselineConfig("dql", gamma=0.5, collision_reward=-1.0, reward_terms=()))
    q_online = lambda obs, a: {"q": -jnp.abs(a[:, 0, 0] - 20.0) + 0.0 * obs.vector[-1, 0]}
    q_target = lambda obs, a: {"q": -jnp.abs(a[:, 0, 0] + 20.0) + obs.vector[-1, 0]}
    obs = base.Observation(images=jnp.zeros((2, 4, 1, 1, 1), jnp.uint8),
                           vector=jnp.array([[[0.0]] * 4, [[3.0]] * 4]))
    tr = _transition([0.0, 0.0], [1.0, 1.0], [0.0, 0.0], [False, True], [[0.0, 0.0]] * 2).replace(next_obs=obs)
    y = jax.jit(lambda tr, key: bl.compute_targets(agent, q_online, q_target, tr, key))(tr, jax.random.key(0))["q"]
    # a* within ~1 deg of +20 among 100 uniform samples in [-30, 30] (P(miss) < 1e-3): Q_target ~ -40.
    np.testing.assert_allclose(y, [0.5 * (-40.0 + 0.0), 0.0], atol=1.0)


# ------------------------------------------------------------------------------------------ training


GOAL_CFG = bl.BaselineConfig("gc_dql", gamma=0.5, target_every=3, collision_reward=-1.0,
                             reward_terms=(("heading_angle", 1.0),), goal_speed=1.0)
GOAL_AGENT = agent_of(GOAL_CFG)
GOAL_TRAIN_CFG = capsjax.TrainConfig(learning_rate=3e-3, batch_size=32)
GOAL_STEPS = 150


@pytest.fixture(scope="module")
def goal_training():
    """GC-DQL trained in 1-step chunks on transitions facing +x with random hindsight goals; the state
    after every step is kept (for the target-copy test)."""
    sample = lambda key: fast_transitions(key, GOAL_TRAIN_CFG.batch_size, yaw=0.0)
    train = bl.make_offline_train(GOAL_AGENT, GOAL_TRAIN_CFG, sample, 1)
    state = jax.jit(functools.partial(bl.init_state, GOAL_AGENT, GOAL_TRAIN_CFG))(jax.random.key(0))
    history = [state]
    for _ in range(GOAL_STEPS):
        state, metrics = train(state)
        if len(history) < 8:
            history.append(state)
    return state, history, metrics


def _same(a, b) -> bool:
    return all(bool(jnp.array_equal(x, y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_target_net_is_copied_exactly_every_target_every_steps(goal_training):
    _, history, _ = goal_training
    assert _same(history[0].target_params, history[0].params)
    for step in range(1, len(history)):
        state = history[step]
        assert int(state.step) == step
        assert not _same(state.params, history[step - 1].params)  # every step trains
        if step % GOAL_CFG.target_every == 0:
            assert _same(state.target_params, state.params), step
        else:
            assert _same(state.target_params, history[step - 1].target_params), step
            assert not _same(state.target_params, state.params), step


def test_goal_conditioned_q_responds_to_the_goal_heading(goal_training):
    # The reward is -angle(heading, goal) / pi: after brief training, Q for the goal the car faces
    # (+x) must exceed Q for the goal behind it (-x) for the same observation and actions (true gap
    # about 1.5 at gamma 0.5); an untrained net shows no such gap.
    state, _, metrics = goal_training
    assert np.isfinite(float(metrics["loss"][-1]))
    obs = jax.tree.map(lambda x: x[0], fast_transitions(jax.random.key(5), 1, yaw=0.0).obs)
    obs = obs.replace(vector=obs.vector.at[:, 3:].set(0.0))  # at the centre, facing +x
    actions = jax.random.uniform(jax.random.key(6), (64, 1, 2), minval=jnp.asarray(ENV.spec.plan_low),
                                 maxval=jnp.asarray(ENV.spec.plan_high))

    @jax.jit
    def mean_q(params, goal):
        carry = GOAL_AGENT.model.encode(params, GOAL_AGENT.with_goals(obs, 1.0, goal))
        return jnp.mean(GOAL_AGENT.q_values(params, carry, actions)["q"])

    gap = float(mean_q(state.params, jnp.array([1.0, 0.0])) - mean_q(state.params, jnp.array([-1.0, 0.0])))
    assert gap > 0.4, gap


def test_baseline_runs_through_the_shared_episode_loop_without_recompiling(goal_training):
    state, _, _ = goal_training
    cem = capsjax.CEMConfig(ENV.spec.plan_low, ENV.spec.plan_high, horizon=1, init_samples=64, samples=32, elites=8)
    policy = bl.baseline_policy(GOAL_AGENT, cem)
    traces = []

    @jax.jit
    def run(params, spec, key):
        traces.append(1)
        return mpc.run_episode(ENV, policy, params, spec, OPEN, key, num_steps=6)

    for goal in ((1.0, 0.0), (0.0, 1.0)):
        spec = capsjax.RewardSpec.from_terms(SIGNALS, collision=float(goal[1]), goal_speed=1.5, goal_heading=goal)
        traj = run(state.params, spec, jax.random.key(2))
        assert traj.action.shape == (6, 2) and bool(jnp.all(jnp.isfinite(traj.value)))
    assert len(traces) == 1


def test_sep_selection_combines_heads_with_the_task_weights():
    agent = agent_of(bl.BaselineConfig("gc_dql_sep", reward_terms=(("speed", 1.0), ("heading_angle", 1.0))))
    q = {"collision": jnp.array([0.1, 0.5]), "speed": jnp.array([-1.0, 0.0]), "heading_angle": jnp.array([0.0, -0.2])}
    spec = capsjax.RewardSpec.from_terms(SIGNALS, collision=100.0, speed=3.0, heading_angle=5.0)
    np.testing.assert_allclose(agent.selection_value(q, spec.weights),
                               [100 * 0.9 - 3.0, 100 * 0.5 - 1.0], rtol=1e-6)


def test_q_learning_batches_need_done_next_obs_and_hindsight_context():
    batch = fast_transitions(jax.random.key(0), 4)
    with pytest.raises(ValueError, match="next_obs"):
        bl.transitions_from_batch(GOAL_AGENT, batch.replace(next_obs=None))
    with pytest.raises(ValueError, match="final_xy"):
        bl.transitions_from_batch(GOAL_AGENT, batch.replace(context={"pose": batch.context["pose"]}))
    lane = agent_of(bl.BaselineConfig("gc_dql", reward_terms=(("lane", 1.0),)))
    with pytest.raises(ValueError, match="lane_seen"):
        bl.head_rewards(lane, bl.transitions_from_batch(lane, batch))
    heading = bl.hindsight_heading(jnp.array([[1.0, 1.0, 0.3]]), jnp.array([[1.0, 3.0]]))
    np.testing.assert_allclose(heading, [[0.0, 1.0]], atol=1e-6)


def test_checkpoint_round_trip_and_config_check(goal_training, tmp_path):
    state, _, _ = goal_training
    with bl.checkpointer(GOAL_AGENT, GOAL_TRAIN_CFG, tmp_path / "ckpt", async_save=False) as ckpt:
        ckpt.save(int(state.step), state, force=True)
    with bl.checkpointer(GOAL_AGENT, GOAL_TRAIN_CFG, tmp_path / "ckpt") as ckpt:
        restored, step = ckpt.restore(state)
    assert step == int(state.step) and _same(restored.params, state.params)
    assert _same(restored.target_params, state.target_params)
    other = agent_of(dataclasses_replace(GOAL_CFG, gamma=0.9))
    with bl.checkpointer(other, GOAL_TRAIN_CFG, tmp_path / "ckpt") as ckpt:
        with pytest.raises(capsjax.checkpoint.ConfigMismatchError, match="gamma"):
            ckpt.restore(state)
    # Metadata (how the training windows were drawn) is saved and checked like the configs.
    with bl.checkpointer(GOAL_AGENT, GOAL_TRAIN_CFG, tmp_path / "meta", metadata={"windows": {"mirror": True}},
                         async_save=False) as ckpt:
        ckpt.save(int(state.step), state, force=True)
    with bl.checkpointer(GOAL_AGENT, GOAL_TRAIN_CFG, tmp_path / "meta", metadata={"windows": {"mirror": False}}) as ckpt:
        with pytest.raises(capsjax.checkpoint.ConfigMismatchError, match=r"windows\.mirror: saved true != requested false"):
            ckpt.restore(state)


def test_fit_offline_resumes_up_to_num_steps_and_refuses_a_longer_run(tmp_path):
    # A shorter preset pointed at a longer run's directory must get its own step, never the longer run.
    sample = lambda key: fast_transitions(key, GOAL_TRAIN_CFG.batch_size, yaw=0.0)
    fit = functools.partial(bl.fit_offline, GOAL_AGENT, GOAL_TRAIN_CFG, sample, key=jax.random.key(0),
                            ckpt_dir=tmp_path / "ckpt", save_every=2, keep=2)
    longer, _ = fit(6)  # keeps steps 4 and 6
    shorter, _ = fit(4)
    assert int(shorter.step) == 4 and not _same(shorter.params, longer.params)
    with pytest.raises(ValueError, match=r"fit_offline: .* past num_steps=2 \(steps \[4, 6\]\)"):
        fit(2)
    again, _ = fit(6)
    assert int(again.step) == 6 and _same(again.params, longer.params)


# ------------------------------------------------------------------------------------------ slow


def _survival(policy, params, spec, tasks, steps=40):
    run = jax.jit(jax.vmap(lambda task, key: mpc.run_episode(ENV, policy, params, spec, task, key, num_steps=steps)))
    traj = run(tasks, jax.random.split(jax.random.key(9), tasks.start.shape[0]))
    return float(jnp.mean(traj.signals["collision"][:, -1] < 0.5))


@pytest.mark.slow
def test_dql_learns_collision_avoidance_offline():
    cfg = bl.BaselineConfig("dql", gamma=0.9, target_every=200, collision_reward=-10.0,
                            reward_terms=(("speed", 1.0),), goal_speed=2.0)
    agent = agent_of(cfg)
    train_cfg = capsjax.TrainConfig(learning_rate=1e-3, batch_size=64)
    sample = lambda key: fast_transitions(key, train_cfg.batch_size)
    state, metrics = bl.fit_offline(agent, train_cfg, sample, 3000, key=jax.random.key(0), save_every=1000)
    assert np.isfinite(float(metrics["loss"][-1]))
    tasks = jax.vmap(lambda k: OPEN.replace(start=jnp.stack([0.0, 0.0, jax.random.uniform(k, (), minval=-3.0, maxval=3.0)])))(
        jax.random.split(jax.random.key(3), 8))
    spec = capsjax.RewardSpec.from_terms(SIGNALS, goal_speed=2.0)
    dql = _survival(bl.baseline_policy(agent, bl.small_cem(ENV.spec.plan_low, ENV.spec.plan_high)), state.params, spec, tasks)
    straight = mpc.Policy(act=lambda p, o, s, ps, k: (jnp.array([0.0, 2.0]), ps, {"value": jnp.zeros(())}),
                          init_state=lambda: jnp.zeros(()))
    random = collect.random_policy(ENV.spec)
    base_straight = _survival(straight, None, spec, tasks)
    base_random = _survival(random, None, spec, tasks)
    assert dql >= 0.75 and dql > base_straight + 0.25 and dql > base_random + 0.25, (dql, base_straight, base_random)


@pytest.mark.slow
def test_online_dql_collects_and_trains_under_one_jit():
    cfg = bl.BaselineConfig("dql", gamma=0.9, target_every=8, collision_reward=-10.0, reward_terms=(("speed", 1.0),),
                            goal_speed=2.0)
    agent = agent_of(cfg)
    train_cfg = capsjax.TrainConfig(learning_rate=1e-3, batch_size=16)
    schedule = collect.ExplorationSchedule(uniform_steps=16, sigma=((0, 0.2),), epsilon=((0, 0.5), (40, 0.1)))
    trainer = bl.make_online_train(agent, train_cfg, ENV, num_robots=2, env_steps=24, episode_length=12,
                                   learning_starts=16, replay_capacity=256, grad_steps_per_env_step=1,
                                   schedule=schedule)
    state = trainer.init(jax.random.key(0))
    spec = capsjax.RewardSpec.from_terms(SIGNALS, goal_speed=2.0)
    state, metrics = trainer.train(state, spec)
    loss = np.asarray(metrics["loss"])
    assert int(state.env_steps) == 48 and int(state.learner.step) == (48 - 16) // 2 * 2 + 2
    assert np.all(np.isnan(loss[:7])) and np.all(np.isfinite(loss[7:]))
    assert int(state.replay.current_index) == 48
    # The target was last copied at env step 48 (a multiple of 8): it equals the online params.
    assert _same(state.learner.target_params, state.learner.params)
