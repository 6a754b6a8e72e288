"""experiments/pool.py: pooling evaluation seeds and paired differences, from stored run folders only."""
import json

import numpy as np
import pytest

from experiments import pool


def write_run(folder, *, seed, success, distance, preset="small", split="val", experiment="forest",
              baseline_success=None, env_overrides=None, settings=None, starts=None, train_seed=0, eval_env=None):
    folder.mkdir(parents=True)
    if starts is not None:  # the stored evaluation's poses: [E, T, 3], each episode from its start
        (folder / "eval").mkdir()
        pose = np.repeat(np.asarray(starts, np.float32)[:, None, :], 3, axis=1)
        np.savez(folder / "eval" / "caps.npz", key="k", pose=pose)
    per_episode = {"caps": {"success_rate": [float(x) for x in success],
                            "path_distance_mean": [float(x) for x in distance]}}
    if baseline_success is not None:
        per_episode["gc_dql"] = {"success_rate": list(baseline_success),
                                 "path_distance_mean": [1.0] * len(baseline_success)}
    metrics = {"experiment": experiment, "preset": preset, "seed": seed, "split": split, "train_seed": train_seed,
               "paper": {"caps": {"success_rate": 0.75}}, "per_episode": per_episode}
    (folder / "metrics.json").write_text(json.dumps(metrics))
    if env_overrides is not None or settings is not None:
        config = {"env_overrides": env_overrides or {}, "preset": settings}
        if eval_env is not None:  # runs stored before the option existed have no field
            config["eval_env"] = eval_env
        (folder / "config.json").write_text(json.dumps(config))
    return folder


def test_pool_concatenates_seeds_and_recomputes_intervals(tmp_path):
    a = write_run(tmp_path / "s0", seed=0, success=[1, 1, 0, 1], distance=[1, 2, 3, 4], baseline_success=[0] * 4)
    b = write_run(tmp_path / "s1", seed=1, success=[0, 1, 1, 1], distance=[2, 2, 2, 2], baseline_success=[0] * 4)
    out = tmp_path / "pooled"
    pooled = pool.main(pool.PoolConfig(runs=(b, a), out=out))  # order of the folders does not matter
    caps = pooled["metrics"]["caps"]["success_rate"]
    assert caps["n"] == 8 and caps["mean"] == pytest.approx(6 / 8)
    assert caps["ci_low"] < caps["mean"] < caps["ci_high"]
    assert pooled["per_episode"]["caps"]["path_distance_mean"] == [1, 2, 3, 4, 2, 2, 2, 2]  # seed 0 first
    assert pooled["seeds"] == [0, 1]
    # 6 of 8 against 0 of 8: CAPs beats the baseline beyond both intervals over the pooled episodes.
    assert pooled["comparison"] == {"caps": {"gc_dql": True}}
    stored = json.loads((out / "metrics.json").read_text())
    assert stored["metrics"]["caps"]["success_rate"]["mean"] == pytest.approx(0.75)
    table = (out / "table.md").read_text()
    assert "caps (ours) | 75 % [" in table and "seeds 0, 1 pooled (8 episodes" in table


def test_paired_difference_is_per_task(tmp_path):
    success_a = np.array([1, 1, 1, 0, 1, 1, 0, 1])
    success_b = np.array([1, 0, 1, 0, 1, 1, 0, 0])  # loses exactly two tasks, wins none
    runs = [write_run(tmp_path / f"a{s}", seed=s, success=success_a[4 * s:4 * s + 4], distance=[1.0] * 4)
            for s in (0, 1)]
    against = [write_run(tmp_path / f"b{s}", seed=s, success=success_b[4 * s:4 * s + 4], distance=[1.5] * 4,
                         preset="other") for s in (0, 1)]
    pooled = pool.main(pool.PoolConfig(runs=tuple(runs), against=tuple(against)))
    diff = pooled["paired_difference"]["caps"]
    assert diff["success_rate"]["mean"] == pytest.approx(2 / 8)
    assert diff["success_rate"]["ci_low"] >= 0.0  # never negative on any task, so no resample is either
    assert diff["path_distance_mean"]["mean"] == pytest.approx(-0.5)
    assert diff["path_distance_mean"]["ci_low"] == pytest.approx(-0.5) == diff["path_distance_mean"]["ci_high"]


@pytest.mark.parametrize("change, message", [
    (dict(split="eval"), "field 'split' differs"),
    (dict(preset="large"), "field 'preset' differs"),
    (dict(seed=0), "field 'seed' repeats"),
    (dict(env_overrides={"arena_half": 20.0}), "field 'env_overrides'"),
    (dict(eval_env={"lookahead": 4.0}), "field 'eval_env'"),
])
def test_pool_refuses_runs_of_different_settings(tmp_path, change, message):
    a = write_run(tmp_path / "a", seed=0, success=[1], distance=[1.0], env_overrides={})
    b = write_run(tmp_path / "b", **{**dict(seed=1, success=[0], distance=[1.0], env_overrides={}), **change})
    with pytest.raises(ValueError, match=message):
        pool.pool([pool.load_run(a), pool.load_run(b)])


def test_runs_stored_before_eval_env_pool_with_runs_evaluated_in_the_same_env(tmp_path):
    older = write_run(tmp_path / "a", seed=0, success=[1], distance=[1.0], env_overrides={})
    newer = write_run(tmp_path / "b", seed=1, success=[0], distance=[1.0], env_overrides={}, eval_env={})
    assert pool.pool([pool.load_run(older), pool.load_run(newer)])["seeds"] == [0, 1]


def test_pool_compares_preset_settings_not_names(tmp_path):
    a = write_run(tmp_path / "a", seed=0, success=[1], distance=[1.0], preset="small", settings={"cem": [1024, 32]})
    # The same settings evaluated under a scratch name, stored before the field 'mirror' existed: they pool.
    b = write_run(tmp_path / "b", seed=1, success=[0], distance=[1.0], preset="scratch",
                  settings={"cem": [1024, 32], "mirror": True})
    assert pool.pool([pool.load_run(a), pool.load_run(b)])["metrics"]["caps"]["success_rate"]["n"] == 2
    c = write_run(tmp_path / "c", seed=2, success=[0], distance=[1.0], preset="small", settings={"cem": [1024, 64]})
    with pytest.raises(ValueError, match=r"field 'preset' settings \['cem'\] differ"):
        pool.pool([pool.load_run(a), pool.load_run(c)])


def test_paired_difference_needs_the_same_tasks(tmp_path):
    a = write_run(tmp_path / "a", seed=0, success=[1, 1], distance=[1.0, 1.0])
    other_seed = write_run(tmp_path / "b", seed=1, success=[1, 0], distance=[1.0, 1.0])
    fewer = write_run(tmp_path / "c", seed=0, success=[1], distance=[1.0])
    with pytest.raises(ValueError, match="fields 'train_seed' and 'seed' must match"):
        pool.paired_differences([pool.load_run(a)], [pool.load_run(other_seed)])
    with pytest.raises(ValueError, match="expected the same episodes"):
        pool.paired_differences([pool.load_run(a)], [pool.load_run(fewer)])


def test_paired_variants_may_differ_in_env_settings_but_not_in_tasks(tmp_path):
    starts = [[1.0, 2.0, 0.0], [-3.0, 4.0, 1.0]]
    a = write_run(tmp_path / "a", seed=0, success=[1, 1], distance=[1.0, 1.0], env_overrides={}, starts=starts)
    # Another observation history on the same tasks: its first recorded poses differ by less than one step.
    nearby = np.asarray(starts) + [0.3, -0.2, 0.1]
    b = write_run(tmp_path / "b", seed=0, success=[0, 1], distance=[1.0, 1.0], env_overrides={"history": 8},
                  starts=nearby)
    diff = pool.paired_differences([pool.load_run(a)], [pool.load_run(b)])
    assert diff["caps"]["success_rate"]["mean"] == pytest.approx(0.5)
    elsewhere = write_run(tmp_path / "c", seed=0, success=[0, 1], distance=[1.0, 1.0],
                          env_overrides={"arena_half": 20.0}, starts=np.asarray(starts) * 3)
    with pytest.raises(ValueError, match="do not start where"):
        pool.paired_differences([pool.load_run(a)], [pool.load_run(elsewhere)])
    # Without stored poses the env overrides must agree, as for pooling.
    no_poses = write_run(tmp_path / "d", seed=0, success=[0, 1], distance=[1.0, 1.0], env_overrides={"history": 8})
    with pytest.raises(ValueError, match="field 'env_overrides'"):
        pool.paired_differences([pool.load_run(a)], [pool.load_run(no_poses)])


def test_runs_of_several_training_seeds_pool_with_the_training_runs_resampled(tmp_path):
    # Two training seeds, each evaluated on seeds 0 and 1 (the same tasks): model 0 wins every path, model 1
    # none.  Pooled, the interval must reach both ends, since a third retraining may be like either.
    runs = [write_run(tmp_path / f"t{t}s{s}", seed=s, train_seed=t, success=[1 - t] * 20, distance=[1.0 + t] * 20)
            for t in (0, 1) for s in (0, 1)]
    out = tmp_path / "pooled"
    pooled = pool.main(pool.PoolConfig(runs=tuple(runs), out=out))
    caps = pooled["metrics"]["caps"]["success_rate"]
    assert caps["n"] == 80 and caps["mean"] == 0.5 and (caps["ci_low"], caps["ci_high"]) == (0.0, 1.0)
    assert caps["groups"] == {"0": 1.0, "1": 0.0}
    assert pooled["seeds"] == [0, 1] and pooled["train_seeds"] == [0, 1]
    assert "training seeds 0, 1" in (out / "table.md").read_text()
    # The same evaluation of one training seed twice is refused; another training seed's is not a repeat.
    with pytest.raises(ValueError, match="field 'seed' repeats for one training seed"):
        pool.pool([pool.load_run(runs[0]), pool.load_run(runs[0])])
    # Paired against a variant, each training seed's model against the other variant's of that seed.
    against = [write_run(tmp_path / f"b_t{t}s{s}", seed=s, train_seed=t, success=[0] * 20, distance=[1.0] * 20,
                         preset="other") for t in (0, 1) for s in (0, 1)]
    pooled = pool.main(pool.PoolConfig(runs=tuple(runs), against=tuple(against), out=out))
    diff = pooled["paired_difference"]["caps"]["success_rate"]
    assert diff["mean"] == 0.5 and diff["groups"] == {"0": 1.0, "1": 0.0} and diff["ci_low"] == 0.0
    table = (out / "table.md").read_text()
    assert "| caps, training seed 0 | +100 pts |" in table and "| caps, training seed 1 | +0 pts |" in table
    with pytest.raises(ValueError, match="fields 'train_seed' and 'seed' must match"):
        pool.paired_differences([pool.load_run(r) for r in runs], [pool.load_run(r) for r in against[:2]])


def test_pair_compares_two_methods_on_the_same_episodes(tmp_path):
    runs = [write_run(tmp_path / f"s{s}", seed=s, success=[1, 1, 0, 1], distance=[2.0, 2.0, 4.0, 2.0],
                      baseline_success=[0, 1, 0, 0]) for s in (0, 1)]
    pooled = pool.main(pool.PoolConfig(runs=tuple(runs), pair=("caps", "gc_dql")))
    success = pooled["pair"]["metrics"]["success_rate"]
    assert success["difference"]["mean"] == pytest.approx(0.5)  # 6 of 8 against 2 of 8
    assert success["relative"]["mean"] == pytest.approx(2.0)  # three times the baseline's rate
    distance = pooled["pair"]["metrics"]["path_distance_mean"]["relative"]
    assert distance["mean"] == pytest.approx(2.5 / 1.0 - 1)
    with pytest.raises(ValueError, match="pair: method 'dql'"):
        pool.main(pool.PoolConfig(runs=tuple(runs), pair=("caps", "dql")))


def test_load_run_names_what_is_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="no metrics.json"):
        pool.load_run(tmp_path)
    (tmp_path / "metrics.json").write_text(json.dumps({"experiment": "forest", "seed": 0}))
    with pytest.raises(ValueError, match="per_episode"):
        pool.load_run(tmp_path)
