"""Every registered scene behind the env API: jit + vmap, shapes, no NaN, crashes end episodes,
auto-reset, per-robot layouts under one compiled step, and bad input.

Compiling an MJX step takes about a minute on a 2-core CPU, so each scene compiles exactly two functions
(a batched reset and a batched auto-reset step) and every check of that scene reuses them.
"""
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from envs import base
from envs.car import CarState

B = 2  # robots: 0 is put in front of an obstacle, 1 drives from its start


def _front_of_first_box(state: base.EnvState, speed: float, half_length: float) -> CarState:
    """Robot 0's car 0.3 m before the -x face of its scene's first box, driving into it."""
    box = state.physics.scene.boxes[0]
    yaw = box[4]
    d = jnp.stack([jnp.cos(yaw), jnp.sin(yaw)])
    xy = box[:2] - (box[2] + half_length + 0.3) * d  # the chassis reaches half_length ahead of its centre
    return CarState(qpos=jnp.concatenate([xy, yaw[None]]), qvel=jnp.concatenate([speed * d, jnp.zeros(1)]))


@pytest.fixture(scope="module", params=envs.SCENES)
def scene_run(request):
    """Run one scene for a few steps and record everything the tests check."""
    name = request.param
    env = envs.make(name)
    wrapped = base.VmapWrapper(base.AutoResetWrapper(env))
    traces = []

    def counted_step(state, action):
        traces.append(1)  # runs only while tracing
        return wrapped.step(state, action)

    step = jax.jit(counted_step)
    reset = jax.jit(wrapped.reset)
    keys = jax.random.split(jax.random.key(0), B)
    tasks = wrapped.sample_task(jax.random.split(jax.random.key(1), B))
    state0 = reset(keys, tasks)

    spec = env.spec
    fixed = env.config.fixed_speed
    speed = float(fixed) if fixed is not None else float(spec.plan_high[1])
    car0 = _front_of_first_box(jax.tree.map(lambda x: x[0], state0), speed, env.config.car.half_length)
    cars = jax.tree.map(lambda a, b: a.at[0].set(b), state0.physics.car, car0)
    state = state0.replace(physics=state0.physics.replace(car=cars))

    drive = np.zeros((B, spec.action_dim), np.float32)
    if spec.action_dim == 2:
        drive[:, 1] = speed
    history = [state]
    for i in range(10):
        action = drive.copy()
        if i == 1:
            action[1, 0] = np.nan  # a NaN action must not poison the state
        state = step(state, jnp.asarray(action))
        history.append(state)
    # A new batch of tasks (new layouts) through the same compiled step.
    other = reset(keys, wrapped.sample_task(jax.random.split(jax.random.key(2), B)))
    after_other = step(other, jnp.asarray(drive))
    return dict(name=name, env=env, wrapped=wrapped, tasks=tasks, state0=state0, history=history,
                traces=len(traces), other=other, after_other=after_other)


def _finite(state: base.EnvState) -> bool:
    """No NaN anywhere, and no inf outside the scene (whose open sky has ceiling_height = +inf)."""
    def ok(tree, check):
        return all(bool(jnp.all(check(x))) for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating))

    rest = (state.physics.car, state.obs, state.signals, state.metrics, state.info, state.task, state.reward)
    return ok(state, lambda x: ~jnp.isnan(x)) and ok(rest, jnp.isfinite)


def test_shapes_and_no_nan(scene_run):
    env, spec = scene_run["env"], scene_run["env"].spec
    for state in scene_run["history"]:
        assert state.obs.images.shape == (B, spec.history) + spec.image_shape
        assert state.obs.images.dtype == jnp.uint8
        assert state.obs.vector.shape == (B, spec.history, spec.vector_dim)
        assert tuple(sorted(state.signals)) == tuple(sorted(spec.signal_names))
        assert all(v.shape == (B,) for v in state.signals.values())
        assert state.info["pose"].shape == (B, 3) and state.done.shape == (B,)
        assert "goal_heading" in state.info
        assert _finite(state)
    assert not bool(jnp.any(scene_run["history"][-1].info["physics_overflow"]))
    assert env.check_task(jax.tree.map(lambda x: x[0], scene_run["tasks"])) is None


def test_signals_match_the_state(scene_run):
    for state in scene_run["history"][1:]:
        pose = state.info["pose"]
        np.testing.assert_allclose(state.signals["heading"], pose[:, 2], atol=1e-6)
        assert np.all(np.abs(np.asarray(pose[:, 2])) <= math.pi + 1e-6)
        vel = state.physics.car.qvel
        forward = vel[:, 0] * jnp.cos(pose[:, 2]) + vel[:, 1] * jnp.sin(pose[:, 2])
        np.testing.assert_allclose(state.signals["speed"], forward, atol=1e-5)
        # The newest vector frame is (collision, heading, speed) of the same instant.
        newest = state.obs.vector[:, -1]
        np.testing.assert_allclose(newest[:, 0], state.signals["collision"])
        np.testing.assert_allclose(newest[:, 1], state.signals["heading"])
        np.testing.assert_allclose(newest[:, 2], state.signals["speed"])


def test_collision_ends_the_episode_and_auto_reset_restarts(scene_run):
    history, state0 = scene_run["history"], scene_run["state0"]
    done = np.array([bool(s.done[0]) for s in history])
    assert done.any(), "driving into the first box must crash"
    k = int(np.argmax(done))
    crash = history[k]
    assert float(crash.signals["collision"][0]) == 1.0
    assert float(crash.metrics["crash"][0]) == 1.0
    # The terminal state is returned as is; the next step starts the same task afresh.
    fresh = history[k + 1]
    assert not bool(fresh.done[0])
    np.testing.assert_allclose(fresh.info["pose"][0], state0.info["pose"][0], atol=1e-6)
    assert int(jnp.sum(fresh.obs.images[0, :-1])) == 0  # history padding restarts
    # The other robot was not reset by robot 0's crash.
    assert not bool(jnp.allclose(history[k + 1].info["pose"][1], state0.info["pose"][1]))


def test_nan_action_is_flagged_and_harmless(scene_run):
    after = scene_run["history"][2]
    assert bool(after.info["action_invalid"][1]) and not bool(after.info["action_invalid"][0])
    assert _finite(after)


def test_two_seeds_two_layouts_one_compiled_step(scene_run):
    scenes = scene_run["state0"].physics.scene
    differ = [not np.allclose(np.asarray(getattr(scenes, f)[0]), np.asarray(getattr(scenes, f)[1]))
              for f in ("circles", "boxes")]
    assert any(differ)
    other = scene_run["other"].physics.scene
    assert not np.allclose(np.asarray(other.boxes), np.asarray(scenes.boxes)) or not np.allclose(
        np.asarray(other.circles), np.asarray(scenes.circles))
    assert scene_run["traces"] == 1
    assert _finite(scene_run["after_other"])


def test_train_and_eval_tasks_differ(scene_run):
    env = scene_run["env"]
    key = jax.random.key(5)
    train, eval_, val = (env.sample_task(key, split) for split in ("train", "eval", "val"))
    for one, other in ((train, eval_), (train, val), (eval_, val)):
        assert any(not np.allclose(np.asarray(a), np.asarray(b)) for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(other)))
    with pytest.raises(ValueError, match="split"):
        env.sample_task(key, "test")


# ------------------------------------------------------------------------------------------ bad input


def test_unknown_names_and_fields():
    with pytest.raises(ValueError, match="forest, city, indoor"):
        envs.make("jungle")
    with pytest.raises(ValueError, match="arena_half"):
        envs.make("forest", arena_size=30.0)
    with pytest.raises(ValueError, match="history must be >= 1"):
        envs.make("forest", history=0)
    longer = envs.make("forest", history=8)  # the observation's memory is a config field (trace only)
    state = jax.eval_shape(longer.reset, jax.random.key(0), longer.sample_task(jax.random.key(0)))
    assert state.obs.images.shape == (8,) + longer.spec.image_shape and state.obs.vector.shape == (8, 3)


@pytest.mark.parametrize("name", envs.SCENES)
def test_wrong_action_shape_and_task_shape(name):
    env = envs.make(name)
    task = env.sample_task(jax.random.key(0))
    state = jax.eval_shape(env.reset, jax.random.key(0), task)  # trace only, no compilation
    with pytest.raises(ValueError, match="action has shape"):
        jax.eval_shape(env.step, state, jnp.zeros(env.spec.action_dim + 1))
    field = jax.tree_util.tree_flatten_with_path(task)[0][0][0][0].name
    bad = task.replace(**{field: jnp.zeros((3, 3), jnp.float32)})
    with pytest.raises(ValueError, match=field):
        env.check_task(bad)
    with pytest.raises(ValueError, match=field):
        jax.eval_shape(env.reset, jax.random.key(0), bad)


def test_out_of_box_actions_are_clipped():
    env = envs.make("forest")
    action, invalid = base.sanitize_action(jnp.asarray([1000.0, -99.0]), env.spec)
    np.testing.assert_allclose(action, [env.spec.action_high[0], env.spec.action_low[1]])
    assert not bool(invalid)


@pytest.mark.parametrize("name", envs.SCENES)
def test_saved_mjcf_assets_open_in_mujoco(name):
    """envs/assets/<name>.xml (written by ``python -m envs.show NAME --mjcf``) is a valid family member."""
    import os

    import mujoco

    path = os.path.join(os.path.dirname(envs.__file__), "assets", f"{name}.xml")
    model = mujoco.MjModel.from_xml_path(path)
    env = envs.make(name)
    scene = jax.eval_shape(lambda k: env.layout(env.sample_task(k)), jax.random.key(0))
    ceiling = int(name == "indoor")
    assert model.ngeom == 1 + scene.circles.shape[0] + scene.boxes.shape[0] + ceiling + 1  # ground ... chassis


def test_windowed_projection_follows_a_car_cutting_a_corner():
    """A route of long segments (the halls' 25 m sides): a car turning early, off the centreline, keeps
    advancing along the route; the window only keeps the tracker from jumping ahead."""
    from envs.scenes.common import project_on_path

    route = jnp.asarray([[0.0, 10.0], [0.0, 0.0], [25.0, 0.0]])  # 10 m south, then 25 m east
    # Down the first side 1 m right of the centreline, a quarter circle of radius 2 m cutting the
    # corner, then east 1 m left of the centreline: 0.125 m per control step.
    arc = np.linspace(0.0, np.pi / 2, 26)[1:]
    cars = np.concatenate([np.stack([np.full(57, -1.0), np.linspace(10.0, 3.0, 57)], -1),
                           np.stack([1.0 - 2.0 * np.cos(arc), 3.0 - 2.0 * np.sin(arc)], -1),
                           np.stack([np.linspace(1.0, 20.0, 153), np.full(153, 1.0)], -1)])
    s_prev, track = 0.0, []
    for xy in cars:
        s, _ = project_on_path(route, jnp.asarray(xy, jnp.float32), s_prev - 1.0, s_prev + 2.0)
        s_prev = max(float(s), s_prev)
        track.append(s_prev)
    assert track[-1] == pytest.approx(10.0 + 20.0, abs=1e-4)  # at x = 20 on the second side
    assert np.all(np.diff(track) <= 2.0)  # never jumps beyond the window
    # Without a window: the nearest point of the whole route; a window picks the nearest point inside it.
    s, d = project_on_path(route, jnp.asarray([5.0, 0.5]))
    assert float(s) == pytest.approx(15.0) and float(d) == pytest.approx(0.5)
    s, d = project_on_path(route, jnp.asarray([5.0, 0.5]), 0.0, 12.0)
    assert float(s) == pytest.approx(12.0) and float(d) == pytest.approx(np.hypot(3.0, 0.5), rel=1e-5)


def test_forest_goal_path_is_the_stretch_ahead_relative_to_the_car():
    """``info['goal_path']`` starts at the car's projection on the path and runs ``goal_path_length`` m on,
    in the car-at-origin frame the reward's path term dead-reckons in."""
    from envs.scenes.common import path_ahead, polyline_lengths

    route = jnp.asarray([[0.0, 0.0], [4.0, 0.0], [4.0, 20.0]])
    ahead = np.asarray(path_ahead(route, jnp.asarray(2.0), jnp.asarray([2.0, -1.0]), 6.0, 7))
    np.testing.assert_allclose(ahead[0], [0.0, 1.0], atol=1e-6)  # the projection, 1 m left of the car
    np.testing.assert_allclose(ahead[-1], [2.0, 5.0], atol=1e-6)  # 6 m on: round the corner, 4 m up
    assert float(polyline_lengths(jnp.asarray(ahead))[-1]) == pytest.approx(6.0, rel=1e-5)
    env = envs.make("forest")
    state = env.reset(jax.random.key(0), env.sample_task(jax.random.key(1), "eval"))
    path = np.asarray(state.info["goal_path"])
    assert path.shape == (env.config.goal_path_points, 2)
    np.testing.assert_allclose(path[0], [0.0, 0.0], atol=1e-5)  # episodes start on the path
    state = env.step(state, jnp.asarray([0.0, 2.0]))
    expected = path_ahead(state.task.path, state.info["path_s"], state.info["pose"][:2],
                          env.config.goal_path_length, env.config.goal_path_points)
    np.testing.assert_allclose(state.info["goal_path"], expected, atol=1e-6)
    with pytest.raises(ValueError, match="goal_path_points"):
        envs.make("forest", goal_path_points=1)


def test_sharpest_bend_is_the_tightest_circle_through_the_path():
    from envs.scenes.common import sharpest_bend

    t = jnp.linspace(0.0, 2 * jnp.pi, 64)
    assert float(sharpest_bend(jnp.stack([3.0 * jnp.cos(t), 3.0 * jnp.sin(t)], -1))) == pytest.approx(3.0, rel=1e-3)
    u = jnp.linspace(-9.5, 9.5, 64)
    amplitude, wavelength = 2.0, 10.0  # y = A sin(2 pi x / L) bends tightest at its crests: L^2 / (4 pi^2 A)
    sine = jnp.stack([u, amplitude * jnp.sin(2 * jnp.pi * u / wavelength)], -1)
    assert float(sharpest_bend(sine)) == pytest.approx(wavelength**2 / (4 * np.pi**2 * amplitude), rel=0.05)
    assert float(sharpest_bend(jnp.stack([u, 0.5 * u], -1))) > 1e3  # straight


def test_halls_car_is_rc_sized_and_can_turn_inside_a_hallway():
    """The halls use the paper's RC-car scale: at the planner's steering limit the car's turning circle,
    swept by its whole footprint, fits in half a hallway (the 2 m car's did not fit in 4 m corridors)."""
    cfg = envs.make("indoor").config
    car = cfg.car
    wheelbase = car.front_axle + car.rear_axle
    steer = math.radians(float(envs.make("indoor").spec.plan_high[0]))
    radius = wheelbase / math.tan(steer)
    assert 2 * car.half_length <= 0.6
    assert radius + car.radius <= cfg.corridor_width / 2


def test_forest_tasks_starting_anywhere_keep_the_task_and_spread_over_the_arena():
    env = envs.make("forest")
    keys = jax.random.split(jax.random.key(5), 128)
    anywhere = jax.vmap(env.sample_task_anywhere)(keys)
    usual = jax.vmap(env.sample_task)(keys)
    np.testing.assert_array_equal(anywhere.path, usual.path)  # the same layout seed and path ...
    np.testing.assert_array_equal(anywhere.seed, usual.seed)
    start = np.asarray(anywhere.start)  # ... but the start drawn over the whole arena, any yaw
    room = env.config.arena_half - 1.5
    assert np.all(np.abs(start[:, :2]) <= room + 1e-5)
    assert np.abs(start[:, :2]).max() > 0.9 * room  # some start near the walls (the circles' starts never are)
    assert np.ptp(start[:, 2]) > 5.0
    states = jax.jit(jax.vmap(env.reset))(keys, anywhere)
    assert not np.asarray(states.signals["collision"]).any()  # obstacles are cleared around every start
    with pytest.raises(ValueError, match="wall_margin"):
        env.sample_task_anywhere(keys[0], wall_margin=20.0)
