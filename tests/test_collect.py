"""capsjax.collect: policies with the paper's exploration schedule, and collection into a dataset (fast env)."""
from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import envs
from capsjax import collect, data, mpc
from envs import fast

ENV = envs.make("fast")
# One reset per step for 8 robots: finished robots often wait a step, which the tests below exercise.
KW = dict(num_robots=8, steps_per_chunk=16, episode_length=24, max_resets_per_step=1, progress=False)
POLICY = collect.random_policy(ENV.spec)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    path = str(tmp_path_factory.mktemp("collect") / "fast.zarr")
    return collect.collect(ENV, POLICY, None, None, path=path, num_steps=400, key=jax.random.key(0),
                           policy_name="uniform random", **KW)


def test_schedule_values_at_the_breakpoints():
    s = collect.PAPER_SCHEDULE
    sigma = lambda n: float(collect.piecewise_linear(s.sigma, n))
    eps = lambda n: float(collect.piecewise_linear(s.epsilon, n))
    assert s.uniform_steps == 4_000
    for n, want in ((0, 0.25), (40_000, 0.15), (80_000, 0.05), (240_000, 0.005), (10**7, 0.005)):
        assert sigma(n) == pytest.approx(want, rel=1e-5), n
    for n, want in ((0, 1.0), (1_000, 1.0), (40_500, 0.55), (80_000, 0.1), (160_000, 0.01), (10**7, 0.01)):
        assert eps(n) == pytest.approx(want, rel=1e-5), n


def test_exploration_noise_follows_the_schedule():
    spec = ENV.spec
    target = jnp.array([10.0, 1.0])
    constant = mpc.Policy(act=lambda p, o, r, s, k: (target, s, {"value": jnp.zeros(())}),
                          init_state=lambda: jnp.zeros(()))
    policy = collect.exploration_policy(constant, spec)

    @jax.jit
    def actions(env_steps, keys):
        state = policy.init_state().replace(env_steps=jnp.int32(env_steps), stride=jnp.int32(8))
        act = lambda k: policy.act(None, None, None, state, k)
        a, new_state, info = jax.vmap(act)(keys)
        return a, new_state.env_steps, info["epsilon"]

    keys = jax.random.split(jax.random.key(0), 4000)
    low, high = np.array(spec.plan_low), np.array(spec.plan_high)
    early, steps, _ = actions(100, keys)  # the first 4,000 env steps: uniform over the plan box
    assert np.all(steps == 108)  # the count advances by the fleet's stride
    assert np.all((early >= low) & (early <= high))
    assert np.std(np.asarray(early[:, 0])) == pytest.approx((high[0] - low[0]) / np.sqrt(12), rel=0.1)
    late, _, eps = actions(10**6, keys)  # sigma 0.005 of the env range, epsilon 0.01
    assert np.all(eps == pytest.approx(0.01))
    far = np.any(np.abs(np.asarray(late) - np.asarray(target)) > 5 * 0.005 * (np.array(spec.action_high) - spec.action_low), -1)
    assert 0.003 < far.mean() < 0.02
    near = np.asarray(late)[~far]
    np.testing.assert_allclose(np.std(near[:, 0]), 0.005 * 90.0, rtol=0.15)  # 0.005 x the 90 deg steer range


def test_episodes_are_stored_with_clean_time_indexing(dataset):
    ds = dataset
    assert ds.num_steps >= 400 and ds.env_name == "fast" and ds.policy == "uniform random"
    assert ds.env_config["num_obstacles"] == ENV.config.num_obstacles
    assert not ds.has_semantic
    _, lengths = ds.episode_bounds()
    assert np.all(lengths <= 25)  # 24 steps, plus the stored terminal observation
    tasks = ds.episode_tasks()
    render = jax.jit(jax.vmap(lambda key, pose: fast.render(ENV.config, pose, ENV.sample_task(
        jax.random.wrap_key_data(key), "train"))))
    crashes = 0
    for i in range(0, ds.num_episodes, 3):
        ep = ds.read_episode(i)
        n = lengths[i]
        np.testing.assert_array_equal(ep["done"], np.arange(n) == n - 1)  # done only on the terminal entry
        # Image and vector of one entry come from the same instant: the image re-rendered at the
        # recorded pose matches, and the vector holds the same pose and collision flag.
        poses = np.zeros((25, 3), np.float32)  # padded: one compiled renderer for every length
        poses[:n] = ep["pose"]
        np.testing.assert_array_equal(ep["image"], render(np.repeat(tasks[i][None], 25, 0), poses)[:n])
        np.testing.assert_allclose(ep["vector"][:, 3:5], ep["pose"][:, :2], atol=1e-6)
        np.testing.assert_allclose(ep["vector"][:, 1], ep["pose"][:, 2], atol=1e-6)
        np.testing.assert_array_equal(ep["vector"][:, 0], ep["signal/collision"])
        # Only the terminal entry may be a crash; an episode shorter than the limit ended in one.
        assert not ep["signal/collision"][:-1].any()
        if n < 25:
            assert ep["signal/collision"][-1] == 1
            crashes += 1
        # Actions of executed steps lie in the plan box; the pose moves between entries.
        assert np.all((ep["action"][:-1] >= ENV.spec.plan_low) & (ep["action"][:-1] <= ENV.spec.plan_high))
    assert crashes > 0


def test_collect_resumes_by_appending_and_refuses_another_env(dataset):
    before = dataset.read_episode(0)
    n0, e0 = dataset.num_steps, dataset.num_episodes
    ds = collect.collect(ENV, POLICY, None, None, path=dataset.path, num_steps=n0 + 150, key=jax.random.key(1),
                         policy_name="uniform random", **KW)
    assert ds.num_steps >= n0 + 150 and ds.num_episodes > e0
    np.testing.assert_array_equal(ds.read_episode(0)["image"], before["image"])
    assert ds.verify() == []
    other = envs.make("fast", num_obstacles=3)
    with pytest.raises(ValueError, match="env_config"):
        collect.collect(other, collect.random_policy(other.spec), None, None, path=dataset.path,
                        num_steps=10**6, key=jax.random.key(2), **KW)
    assert data.Dataset.open(dataset.path).num_steps == ds.num_steps
    sampler = data.make_sampler(ds, horizon=8)
    batch = jax.jit(data.WindowSampler.sample, static_argnums=2)(sampler, jax.random.key(0), 64)
    assert batch.obs.images.shape == (64, 4, 16, 32, 1)


def test_finished_robots_beyond_the_reset_slots_wait_and_are_not_stored(dataset):
    # The same compiled chunk as the fixture's collection (cached), run from a fresh fleet.
    env = collect._episode_env(ENV, KW["episode_length"])
    sampler = collect._default_sampler(ENV, "train")
    run = collect.make_chunk_fn(env, POLICY, sampler, KW["steps_per_chunk"], 1)
    keys = jax.random.split(jax.random.key(3), 8)
    fleet = collect.Fleet(collect._fleet_reset(env, sampler)(keys), jax.vmap(lambda _: POLICY.init_state())(jnp.arange(8)),
                          jax.vmap(jax.random.key_data)(keys), jnp.zeros(8, bool))
    chunks = []
    for i in range(6):
        fleet, records = run(fleet, None, None, jax.random.key(10 + i))
        chunks.append(records)
    valid = np.concatenate([np.asarray(c.valid) for c in chunks])
    done = np.concatenate([np.asarray(c.done) for c in chunks])
    pose = np.concatenate([np.asarray(c.pose) for c in chunks])
    assert (~valid).any()  # some robot waited
    assert np.all(done[~valid])  # only a finished robot waits ...
    prev = np.argmax(~valid, axis=0)
    for r in np.flatnonzero((~valid).any(0)):  # ... on its terminal state, repeated unchanged
        t = prev[r]
        np.testing.assert_array_equal(pose[t, r], pose[t - 1, r])
        assert done[t - 1, r]
    assert np.all(done.sum(0) - (~valid).sum(0) >= 1)  # every robot also finished episodes that were stored


@pytest.mark.slow
def test_forest_collection_stores_semantic_maps_of_the_labelled_frames(tmp_path):
    from envs.camera import render

    env = envs.make("forest")
    ds = collect.collect(env, collect.random_policy(env.spec), None, None, path=str(tmp_path / "f.zarr"),
                         num_steps=300, num_robots=4, key=jax.random.key(0), labelled_fraction=0.05,
                         steps_per_chunk=16, episode_length=40, progress=False)
    steps, images, semantic = ds.labelled_frames()
    assert 3 <= steps.size <= 40 and semantic.shape[1:] == env.spec.image_shape[:2]
    episode = ds.episode_of_step(steps[0])
    task = env.sample_task(jax.random.wrap_key_data(ds.episode_tasks()[episode]), "train")
    pose = ds.read_steps("pose", int(steps[0]), int(steps[0]) + 1)[0]
    image, sem, _ = render(env.layout(task), jnp.asarray(pose), env.config.camera)
    np.testing.assert_array_equal(semantic[0], sem)
    np.testing.assert_array_equal(images[0], image)  # the stored frame is the one at the stored pose
    # One frame per step is stored, so an env whose observation keeps a longer history reuses the dataset
    # (nothing recollected), and the sampler stacks that history from it.
    longer = envs.make("forest", history=8)
    again = collect.collect(longer, collect.random_policy(longer.spec), None, None, path=ds.path, num_steps=300,
                            num_robots=4, key=jax.random.key(0), labelled_fraction=0.05, steps_per_chunk=16,
                            episode_length=40, progress=False)
    assert again.num_steps == ds.num_steps
    sampler = data.make_sampler(again, horizon=4, history=longer.spec.history)
    batch = jax.jit(data.WindowSampler.sample, static_argnums=2)(sampler, jax.random.key(0), 8)
    assert batch.obs.images.shape == (8, 8) + env.spec.image_shape
    # Another camera stores other frames: refused, naming the field, and the stored dataset is untouched.
    wide = envs.make("forest", camera=dataclasses.replace(env.config.camera, projection="cylindrical", hfov_deg=200.0))
    with pytest.raises(ValueError, match="env_config.*projection"):
        collect.collect(wide, collect.random_policy(wide.spec), None, None, path=ds.path, num_steps=300,
                        num_robots=4, key=jax.random.key(0), progress=False)
    assert data.Dataset.open(ds.path).num_steps == ds.num_steps


def test_comparable_settings_leave_out_history_and_later_fields_at_their_old_values():
    old = {"history": 4, "camera": {"width": 64, "hfov_deg": 120.0}, "lookahead": 2.0}  # stored before the fields
    now = {"history": 8, "camera": {"width": 64, "hfov_deg": 120.0, "projection": "pinhole"}, "lookahead": 2.0}
    assert collect.comparable_settings(old) == collect.comparable_settings(now)
    assert "projection" in now["camera"]  # the input is not modified
    wide = {**now, "camera": {**now["camera"], "projection": "cylindrical"}}
    assert collect.comparable_settings(wide) != collect.comparable_settings(old)
    assert collect.comparable_settings({"history": 4}) == {}
    # A later top-level field (the forest's goal path) at its old value is left out; another value is kept.
    assert collect.comparable_settings({**now, "goal_path_points": 16}) == collect.comparable_settings(old)
    assert collect.comparable_settings({**now, "goal_path_points": 8})["goal_path_points"] == 8


COLLECTOR = textwrap.dedent("""
    import sys
    sys.path.insert(0, {root!r})
    import jax, envs
    from capsjax import collect
    env = envs.make("fast")
    collect.collect(env, collect.random_policy(env.spec), None, None, path={path!r}, num_steps=10**8,
                    num_robots=8, steps_per_chunk=16, episode_length=24, key=jax.random.key(5), progress=False)
""")


@pytest.mark.slow
def test_collection_killed_mid_write_resumes(tmp_path):
    path = str(tmp_path / "k.zarr")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.Popen([sys.executable, "-c", COLLECTOR.format(root=root, path=path)])
    try:
        deadline = time.time() + 300
        while time.time() < deadline:
            if os.path.exists(os.path.join(path, "commit.json")) and data.Dataset.open(path).num_steps > 2000:
                break
            time.sleep(0.1)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    ds = data.Dataset.open(path)
    assert ds.num_steps > 2000 and ds.verify() == []
    for i in range(ds.num_episodes):
        assert ds.read_episode(i)["done"][-1]
    n = ds.num_steps
    ds = collect.collect(ENV, collect.random_policy(ENV.spec), None, None, path=path, num_steps=n + 100,
                         key=jax.random.key(6), **KW)
    assert ds.num_steps >= n + 100 and ds.verify() == []


def test_held_random_actions_repeat_and_mean_hold_one_is_independent():
    spec = ENV.spec
    held, independent = collect.random_policy(spec, 4.0), collect.random_policy(spec)

    def drive(policy, steps=400):
        state, actions = policy.init_state(), []
        for key in jax.random.split(jax.random.key(3), steps):
            action, state, _ = policy.act(None, None, None, state, key)
            actions.append(np.asarray(action))
        return np.stack(actions)

    a_held, a_free = drive(held), drive(independent)
    low, high = np.asarray(spec.plan_low), np.asarray(spec.plan_high)
    for a in (a_held, a_free):
        assert np.all((a >= low) & (a <= high)) and np.all(np.isfinite(a))
    repeats = lambda a: np.mean(np.all(a[1:] == a[:-1], axis=-1))  # noqa: E731
    assert 0.6 < repeats(a_held) < 0.9  # a fresh draw with probability 1/4 per step
    assert repeats(a_free) == 0.0
    with pytest.raises(ValueError, match="mean_hold"):
        collect.random_policy(spec, 0.5)


def test_a_stored_dataset_is_not_reused_by_another_policy(dataset):
    with pytest.raises(ValueError, match="policy"):
        collect.collect(ENV, POLICY, None, None, path=dataset.path, num_steps=10, num_robots=4,
                        key=jax.random.key(0), policy_name="someone else's policy")


def test_update_spec_gives_each_robot_goals_from_its_own_state(tmp_path):
    # A policy that steers by its spec; the spec is refreshed per robot from the robot's heading, so every
    # stored action must equal the function of the heading recorded at the same entry.
    limit = float(ENV.spec.plan_high[0])

    def act(params, obs, spec, state, key):
        return jnp.stack([limit * jnp.tanh(spec), jnp.float32(ENV.spec.plan_high[1])]), state, {"value": spec}

    policy = mpc.Policy(act=act, init_state=lambda: jnp.zeros(()))
    update = lambda state, spec: spec + state.info["pose"][2]  # noqa: E731
    ds = collect.collect(ENV, policy, None, jnp.float32(0.5), path=str(tmp_path / "u.zarr"), num_steps=200,
                         key=jax.random.key(4), policy_name="steer by heading", update_spec=update, **KW)
    steer, yaw = [], []
    for i in range(ds.num_episodes):
        ep = ds.read_episode(i)
        steer.append(ep["action"][:-1, 0])  # the terminal entry's action is padding
        yaw.append(ep["pose"][:-1, 2])
    steer, yaw = np.concatenate(steer), np.concatenate(yaw)
    np.testing.assert_allclose(steer, limit * np.tanh(0.5 + yaw), rtol=1e-5, atol=1e-4)
    assert np.std(yaw) > 0.1  # the robots' headings (and so their goals) differ
