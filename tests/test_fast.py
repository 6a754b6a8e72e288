import jax
import jax.numpy as jnp
import numpy as np
import pytest

from envs import base
from envs.fast import FastEnv, FastOracle, FastTask, random_windows

ENV = FastEnv()
TASK = FastTask(obstacles=jnp.array([[3.0, 0.0, 0.8]] + [[0.0, -5.0, 0.01]] * 3), start=jnp.zeros(3))


def test_reset_and_step_shapes():
    state = ENV.reset(jax.random.key(0), TASK)
    assert state.obs.images.shape == (4, 16, 32, 1) and state.obs.images.dtype == jnp.uint8
    assert state.obs.vector.shape == (4, 5)
    assert not np.any(np.asarray(state.obs.images[:3]))  # frames before the start are zeros
    state = jax.jit(ENV.step)(state, jnp.array([0.0, 1.0]))
    assert set(state.signals) == {"collision", "speed", "heading"}
    assert float(state.signals["speed"]) > 0


def test_obstacle_is_visible_in_the_image():
    image = np.asarray(ENV.reset(jax.random.key(0), TASK).obs.images[-1, :, :, 0])
    centre, edge = image[:, 14:18].mean(), image[:, :3].mean()
    assert centre != edge


def test_collision_stops_the_car_and_ends_the_episode():
    state = ENV.reset(jax.random.key(0), TASK)
    step = jax.jit(ENV.step)
    for _ in range(20):
        state = step(state, jnp.array([0.0, 3.0]))
    assert bool(state.done) and float(state.signals["speed"]) == 0.0
    assert float(state.info["pose"][0]) < 3.0 - 0.8  # it did not pass through


def test_nan_and_out_of_box_actions_are_sanitised():
    state = ENV.reset(jax.random.key(0), TASK)
    nan_state = ENV.step(state, jnp.array([jnp.nan, 1.0]))
    assert bool(nan_state.info["action_invalid"])
    assert np.all(np.isfinite(np.asarray(nan_state.obs.vector)))
    big = ENV.step(state, jnp.array([1000.0, 100.0]))
    clipped = ENV.step(state, jnp.array([45.0, 3.0]))
    np.testing.assert_allclose(big.info["pose"], clipped.info["pose"])


def test_wrong_action_shape_and_task_shape_are_clear_errors():
    state = ENV.reset(jax.random.key(0), TASK)
    with pytest.raises(ValueError, match="action has shape"):
        ENV.step(state, jnp.zeros(3))
    bad = FastTask(obstacles=jnp.zeros((2, 3)), start=jnp.zeros(3))
    with pytest.raises(ValueError, match=r"task.*obstacles.*\(4, 3\)"):
        ENV.reset(jax.random.key(0), bad)


def test_train_and_eval_tasks_differ():
    a = ENV.sample_task(jax.random.key(0), "train")
    b = ENV.sample_task(jax.random.key(0), "eval")
    c = ENV.sample_task(jax.random.key(0), "val")
    assert not np.allclose(a.obstacles, b.obstacles)
    assert not np.allclose(a.obstacles, c.obstacles) and not np.allclose(b.obstacles, c.obstacles)
    with pytest.raises(ValueError, match="split"):
        ENV.sample_task(jax.random.key(0), "test")


def test_wrappers_vmap_episode_length_and_auto_reset():
    env = base.VmapWrapper(base.AutoResetWrapper(base.EpisodeWrapper(ENV, episode_length=3)))
    tasks = env.sample_task(jax.random.split(jax.random.key(0), 2))
    state = env.reset(jax.random.split(jax.random.key(1), 2), tasks)
    step = jax.jit(env.step)
    dones = []
    for _ in range(5):
        state = step(state, jnp.tile(jnp.array([0.0, 0.5]), (2, 1)))
        dones.append(np.asarray(state.done))
    assert dones[2].all()  # the time limit ends episodes at step 3
    assert not dones[3].any()  # ... and the next step starts fresh ones
    np.testing.assert_array_equal(state.info["steps"], [1, 1])


def test_oracle_matches_the_env():
    state = ENV.reset(jax.random.key(0), TASK)
    actions = jnp.tile(jnp.array([10.0, 1.5]), (6, 1))
    oracle = FastOracle(ENV)
    preds = oracle.rollout(TASK, oracle.encode(TASK, state.obs), actions)
    for a in actions:
        state = ENV.step(state, a)
    np.testing.assert_allclose(preds["speed"][-1], state.signals["speed"], rtol=1e-5)
    np.testing.assert_allclose(jnp.arctan2(preds["heading"][-1, 1], preds["heading"][-1, 0]), state.signals["heading"], atol=1e-5)


def test_random_windows_mask_after_a_crash():
    batch = random_windows(ENV, jax.random.key(0), TASK, 64, 8)
    coll = np.asarray(batch.signals["collision"])
    valid = np.asarray(batch.valid)
    for c, v in zip(coll, valid):
        if c.max() > 0.5:
            first = int(np.argmax(c > 0.5))
            assert v[: first + 1].all() and not v[first + 1:].any()
