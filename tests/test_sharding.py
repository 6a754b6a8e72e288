"""capsjax.sharding: 4 forced CPU devices give the same training step, episodes and checkpoints as 1.

The 4-device checks run in a subprocess (``XLA_FLAGS=--xla_force_host_platform_device_count=4`` must be
set before JAX starts): ``python tests/test_sharding.py check OUT.json`` writes what it measured and the
test asserts on it, so a failure shows the numbers.
"""
import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import capsjax
from capsjax import checkpoint, mpc, planner, sharding, training
from capsjax.reward import RewardSpec
from envs.fast import FastEnv, FastOracle, FastTask, random_windows

ENV = FastEnv()
TASK = FastTask(obstacles=jnp.array([[5.5, 5.5, 0.01]] * 4), start=jnp.zeros(3))
MODEL = capsjax.CAPsModel(capsjax.ModelConfig.from_env_spec(
    ENV.spec, conv=((4, 3, 2),), obs_hidden=(16, 16), action_hidden=(8, 8), head_hidden=4, horizon=4))
CFG = capsjax.TrainConfig(batch_size=8, learning_rate=1e-3)
CEM = planner.CEMConfig(ENV.spec.plan_low, ENV.spec.plan_high, horizon=4, init_samples=64, samples=32,
                        iterations=2, elites=8)
ROBOTS = 4


def test_single_device_helpers_and_errors():
    mesh = sharding.make_mesh()
    assert mesh.axis_names == ("data",) and mesh.devices.size == len(jax.devices())
    with pytest.raises(ValueError, match=r"num_devices must be an int in \[1, 1\].*got 2"):
        sharding.make_mesh(len(jax.devices()) + 1)
    with pytest.raises(ValueError, match=r"batch\['x'\] is a scalar"):
        sharding.shard_batch({"x": jnp.zeros(())}, mesh)
    placed = sharding.shard_batch({"x": jnp.arange(6.0)}, mesh)
    assert placed["x"].sharding.spec == jax.sharding.PartitionSpec("data")


def _flat(tree) -> dict:
    return {jax.tree_util.keystr(p): np.asarray(x) for p, x in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _max_diff(a, b) -> float:
    fa, fb = _flat(a), _flat(b)
    assert fa.keys() == fb.keys()
    return max(float(np.max(np.abs(fa[k].astype(np.float64) - fb[k]), initial=0.0)) for k in fa)


def _check(out_path: str, ckpt_dir: str) -> None:
    """Runs under 4 forced devices: measure 4-vs-1 differences and write them as JSON."""
    assert len(jax.devices()) == 4, jax.devices()
    results = {}
    data = jax.jit(random_windows, static_argnums=(0, 3, 4))(ENV, jax.random.key(1), TASK, 32, MODEL.horizon)

    def sample(key):
        idx = jax.random.randint(key, (CFG.batch_size,), 0, 32)
        return jax.tree.map(lambda x: x[idx], data)

    # One data-parallel training step vs the plain single-device step.
    state = training.init_train_state(MODEL, CFG, jax.random.key(2))
    mesh4 = sharding.make_mesh(4)
    train4 = training.make_train(MODEL, CFG, sample, 1, mesh=mesh4)
    # Compile once, call the executable.  The outer jit because on CPU ``make_train`` is a host loop of
    # jitted steps (``training.repeat_steps``); with one step its program is that step's.
    compiled4 = jax.jit(train4).lower(sharding.replicate(state, mesh4)).compile()
    results["all_reduce_in_hlo"] = "all-reduce" in compiled4.as_text()
    state4, m4 = compiled4(sharding.replicate(state, mesh4))
    with jax.default_device(jax.devices()[0]):
        state1, m1 = training.make_train(MODEL, CFG, sample, 1)(jax.device_put(state, jax.devices()[0]))
    results["train_devices"] = [len(state4.params["params"]["conv0"]["kernel"].sharding.device_set),
                                len(state1.params["params"]["conv0"]["kernel"].sharding.device_set)]
    results["loss"] = [float(m4["loss"][0]), float(m1["loss"][0])]
    results["param_max_diff"] = _max_diff(state4.params, state1.params)
    results["param_max_change"] = _max_diff(state1.params, state.params)

    # A checkpoint written from 4 devices restores onto 1 device, and one written from 1 onto 4.
    with checkpoint.Checkpointer(os.path.join(ckpt_dir, "from4"), config={"run": "from4"}) as manager:
        manager.save(1, state4)
        manager.wait()
        restored1, _ = manager.restore(jax.device_put(state, jax.devices()[0]))
    with checkpoint.Checkpointer(os.path.join(ckpt_dir, "from1"), config={"run": "from1"}) as manager:
        manager.save(1, state1)
        manager.wait()
        restored4, _ = manager.restore(sharding.replicate(state, mesh4))
    results["restore_4_to_1"] = [_max_diff(restored1.params, state4.params),
                                 len(restored1.params["params"]["conv0"]["kernel"].sharding.device_set)]
    results["restore_1_to_4"] = [_max_diff(restored4.params, state1.params),
                                 len(restored4.params["params"]["conv0"]["kernel"].sharding.device_set)]

    # Closed-loop episodes of 4 robots sharded over 4 devices vs all on 1 (exact oracle, CEM planner).
    oracle = FastOracle(ENV)
    policy = mpc.caps_policy(oracle, CEM)
    keys = jax.random.split(jax.random.key(3), ROBOTS)
    task = ENV.sample_task(jax.random.key(4), "eval")  # the oracle's params: one layout, robots differ by key
    tasks = jax.tree.map(lambda x: jnp.broadcast_to(x, (ROBOTS,) + x.shape), task)
    spec = RewardSpec.from_terms(oracle, collision=100, speed=1, goal_speed=1.5)
    runs = {n: sharding.run_episodes(ENV, policy, task, spec, tasks, keys, num_steps=6, mesh=sharding.make_mesh(n))
            for n in (4, 1)}
    results["episode_devices"] = [len(runs[n].pose.sharding.device_set) for n in (4, 1)]
    results["episode_pose_max_diff"] = _max_diff(runs[4].pose, runs[1].pose)
    results["episode_action_max_diff"] = _max_diff(runs[4].action, runs[1].action)
    results["episode_done_equal"] = bool(np.array_equal(runs[4].done, runs[1].done))
    results["episode_shape"] = list(runs[4].pose.shape)

    try:
        sharding.shard_robots({"task": jnp.zeros((6, 3))}, mesh4)
    except ValueError as e:
        results["indivisible_error"] = str(e)
    with open(out_path, "w") as f:
        json.dump(results, f)


def _run_four_devices(mode: str, out, tmp_path) -> subprocess.CompletedProcess:
    """This file's ``mode`` check in a subprocess with 4 forced CPU devices (the flag must precede JAX)."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu",
               PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, os.path.abspath(__file__), mode, str(out), str(tmp_path)], env=env,
                          capture_output=True, text=True, timeout=600, check=False)


@pytest.mark.slow  # ~70 s: a 4-device training step, closed-loop episodes and checkpoint restores
def test_four_devices_match_one(tmp_path):
    out = tmp_path / "results.json"
    proc = _run_four_devices("check", out, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    r = json.loads(out.read_text())
    print(r)
    # Training: the batch really was split (XLA inserted the gradient all-reduce), same loss and params.
    assert r["all_reduce_in_hlo"] and r["train_devices"] == [4, 1]
    np.testing.assert_allclose(r["loss"][0], r["loss"][1], rtol=1e-5)
    assert r["param_max_change"] > 1e-5  # the step moved the params ...
    assert r["param_max_diff"] < 1e-6  # ... the same way on 4 devices as on 1
    # Checkpoints restore exactly onto another device count.
    assert r["restore_4_to_1"] == [0.0, 1] and r["restore_1_to_4"] == [0.0, 4]
    # Closed-loop evaluation: the same episodes.
    assert r["episode_devices"] == [4, 1] and r["episode_shape"] == [ROBOTS, 6, 3]
    assert r["episode_done_equal"]
    assert r["episode_pose_max_diff"] < 1e-5 and r["episode_action_max_diff"] < 1e-4
    assert "multiple of the 4 devices" in r["indivisible_error"] and "robots['task']" in r["indivisible_error"]


def _check_collect(out_path: str, store_dir: str) -> None:
    """Runs under 4 forced devices: the same collection with the robots sharded over 4 devices and on 1."""
    from capsjax import collect

    assert len(jax.devices()) == 4, jax.devices()
    chunk_devices = []
    make_chunk_fn = collect.make_chunk_fn

    def recording_chunk_fn(*args, **kwargs):  # records over how many devices each chunk's fleet lies
        run = make_chunk_fn(*args, **kwargs)

        def traced_run(fleet, *rest):
            chunk_devices.append(len(fleet.waiting.sharding.device_set))
            return run(fleet, *rest)

        return traced_run

    collect.make_chunk_fn = recording_chunk_fn
    policy = collect.random_policy(ENV.spec)
    kw = dict(num_steps=300, key=jax.random.key(5), labelled_fraction=0.0, steps_per_chunk=32, episode_length=20,
              progress=False)
    stores, devices = {}, {}
    for n in (4, 1):
        chunk_devices.clear()
        path = os.path.join(store_dir, f"collect{n}.zarr")
        stores[n] = collect.collect(ENV, policy, None, None, path=path, num_robots=ROBOTS,
                                    mesh=sharding.make_mesh(4) if n == 4 else None, **kw)
        devices[n] = sorted(set(chunk_devices))
    a, b = stores[4], stores[1]
    results = {"chunk_devices": [devices[4], devices[1]], "num_steps": [a.num_steps, b.num_steps],
               "num_episodes": [a.num_episodes, b.num_episodes],
               "bounds_equal": all(np.array_equal(x, y) for x, y in zip(a.episode_bounds(), b.episode_bounds())),
               "tasks_equal": bool(np.array_equal(a.episode_tasks(), b.episode_tasks())),
               "fields": list(a.step_fields()), "field_max_diff": {}}
    for field in a.step_fields():
        x, y = a.read_steps(field, 0, a.num_steps), b.read_steps(field, 0, min(a.num_steps, b.num_steps))
        results["field_max_diff"][field] = (
            float(np.max(np.abs(x.astype(np.float64) - y), initial=0.0)) if x.shape == y.shape else None)
    bad_path = os.path.join(store_dir, "indivisible.zarr")
    try:
        collect.collect(ENV, policy, None, None, path=bad_path, num_robots=6, mesh=sharding.make_mesh(4), **kw)
    except ValueError as e:
        results["indivisible_error"] = str(e)
    results["indivisible_store_created"] = os.path.exists(bad_path)
    with open(out_path, "w") as f:
        json.dump(results, f)


def test_collection_on_four_devices_matches_one(tmp_path):
    out = tmp_path / "collect.json"
    proc = _run_four_devices("collect", out, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    r = json.loads(out.read_text())
    print(r)
    assert r["chunk_devices"] == [[4], [1]]  # the fleet really was split over the 4 devices, and not on 1
    assert r["num_steps"][0] == r["num_steps"][1] >= 300 and r["num_episodes"][0] == r["num_episodes"][1] > 4
    assert r["bounds_equal"] and r["tasks_equal"]
    assert set(r["fields"]) >= {"image", "vector", "action", "done", "pose"}
    for field, diff in r["field_max_diff"].items():
        assert diff is not None and diff < 1e-5, (field, diff)
    assert "num_robots=6" in r["indivisible_error"] and "4 devices" in r["indivisible_error"]
    assert not r["indivisible_store_created"]


if __name__ == "__main__":
    if sys.argv[1] == "check":
        _check(sys.argv[2], sys.argv[3])
    elif sys.argv[1] == "collect":
        _check_collect(sys.argv[2], sys.argv[3])
