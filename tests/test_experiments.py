"""The three experiments end to end on their ``ci`` preset (slow: each collects, labels, trains and
evaluates for real), plus the pieces of the pipeline that are cheap to check."""
import dataclasses
import json
import os
import subprocess
import sys
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import capsjax
import envs
from capsjax import checkpoint
from envs.fast import FastEnv, FastTask, random_windows
from experiments import city, forest, indoor, pipeline, report


def test_mean_ci_brackets_the_mean_and_narrows_with_more_episodes():
    rng = np.random.default_rng(0)
    few = report.mean_ci(rng.random(8) < 0.5)
    many = report.mean_ci(rng.random(800) < 0.5)
    for stat in (few, many):
        assert stat["ci_low"] <= stat["mean"] <= stat["ci_high"]
    assert many["ci_high"] - many["ci_low"] < few["ci_high"] - few["ci_low"]
    assert report.mean_ci([1.0, 1.0, 1.0])["ci_low"] == 1.0  # no spread, no interval
    assert report.mean_ci([np.nan])["n"] == 0


def test_mean_ci_with_groups_resamples_the_groups_too():
    # Two trained models: one finishes every path, the other none.  Over 200 episodes the episode-only interval
    # is narrow; resampling the models as well reaches both extremes (both draws the same model).
    values = np.repeat([1.0, 0.0], 100)
    seeds = np.repeat([0, 1], 100)
    episodes_only = report.mean_ci(values)
    grouped = report.mean_ci(values, groups=seeds)
    assert grouped["mean"] == episodes_only["mean"] == 0.5
    assert episodes_only["ci_high"] - episodes_only["ci_low"] < 0.2
    assert grouped["ci_low"] == 0.0 and grouped["ci_high"] == 1.0
    assert grouped["groups"] == {"0": 1.0, "1": 0.0} and "groups" not in episodes_only
    # One group, or none, is the episode-only bootstrap itself (the same draws).
    assert report.mean_ci(values, groups=np.zeros(200)) == episodes_only
    # Every model alike: the groups add nothing and the interval stays inside the episodes' spread.
    alike = report.mean_ci(np.tile([1.0, 0.0, 1.0, 1.0], 50), groups=np.repeat([0, 1], 100))
    assert 0.6 < alike["ci_low"] < alike["mean"] == 0.75 < alike["ci_high"] < 0.9
    with pytest.raises(ValueError, match="field 'groups' has 3 labels for 200 values"):
        report.mean_ci(values, groups=[0, 1, 2])
    ratio = report.relative_change_ci(np.repeat([2.0, 1.0], 100), np.ones(200), groups=seeds)
    assert ratio["mean"] == pytest.approx(0.5) and ratio["ci_low"] == pytest.approx(0.0)
    assert ratio["ci_high"] == pytest.approx(1.0)


def test_relative_change_ci_resamples_pairs_together():
    base = np.array([4.0, 2.0, 6.0, 3.0, 5.0, 4.0])
    stat = report.relative_change_ci(1.3 * base, base)  # every pair +30 %, however unequal the pairs are
    assert stat["mean"] == pytest.approx(0.3)
    assert stat["ci_low"] == pytest.approx(0.3) and stat["ci_high"] == pytest.approx(0.3)
    noisy = report.relative_change_ci(base + np.array([1.0, -1.0, 2.0, -2.0, 0.5, 0.0]), base)
    assert noisy["ci_low"] < noisy["mean"] < noisy["ci_high"]
    with pytest.raises(ValueError, match="paired"):
        report.relative_change_ci([1.0, 2.0], [1.0])


def test_forest_success_on_drivable_paths_leaves_out_the_tight_bends():
    from envs.scenes.forest import ForestConfig

    t = np.linspace(0.0, 2 * np.pi, 64)
    circle = np.stack([3.0 * np.cos(t), 3.0 * np.sin(t)], -1)  # radius 3 m: the car (1.8 m) can follow it
    u = np.linspace(-9.5, 9.5, 64)
    tight = np.stack([u, 3.0 * np.sin(2 * np.pi * u / 8.0)], -1)  # crests of radius 0.54 m
    tasks = types.SimpleNamespace(path=jnp.asarray(np.stack([circle, tight, circle]), jnp.float32))
    env = types.SimpleNamespace(config=ForestConfig())
    out = forest.task_metrics(tasks, env, {"success_rate": np.array([1.0, 1.0, 0.0])})
    np.testing.assert_allclose(out["sharpest_bend_m"][[0, 2]], 3.0, rtol=1e-3)
    assert out["sharpest_bend_m"][1] < 0.7  # sampled every 0.3 m, the polyline's crest is a little wider
    assert out["success_drivable"][0] == 1.0 and np.isnan(out["success_drivable"][1]) and out["success_drivable"][2] == 0.0
    assert report.mean_ci(out["success_drivable"])["n"] == 2  # the tight path counts in neither direction


def test_write_json_is_strict(tmp_path):
    report.write_json(tmp_path / "m.json", {"a": np.array([1.0, np.nan]), "b": float("inf"), "c": (np.float32(2.5),)})
    assert json.loads((tmp_path / "m.json").read_text()) == {"a": [1.0, None], "b": None, "c": [2.5]}
    # A dataclass (an env override such as a camera) is written as its fields, not as its repr.
    from envs.camera import FOREST_CAMERA
    report.write_json(tmp_path / "c.json", {"camera": FOREST_CAMERA})
    stored = json.loads((tmp_path / "c.json").read_text())["camera"]
    assert stored["hfov_deg"] == 120.0 and stored["projection"] == "pinhole" and stored["light_dir"] == [0.35, 0.5, 0.8]


def test_separated_needs_clear_intervals():
    a = report.mean_ci([1.0] * 10)
    b = report.mean_ci([0.0] * 10)
    assert report.separated(a, b) and not report.separated(b, a)
    assert not report.separated(a, report.mean_ci([0.0, 1.0, 1.0, 1.0, 1.0] * 2))  # its interval reaches 1


def test_table_puts_the_paper_row_under_ours():
    metrics = {"caps": report.summarize({"success_rate": np.array([1.0, 0.0]), "path_distance_mean": np.array([1.0, 3.0])})}
    text = report.table(metrics, forest.EXPERIMENT.columns, forest.EXPERIMENT.paper, title="t")
    lines = [line for line in text.splitlines() if line.startswith("| caps")]
    assert lines[0].startswith("| caps (ours) | 50 %") and lines[1].startswith("| caps (paper) | 75 %")


def test_episode_mean_stops_at_the_end_of_each_episode():
    class Traj:
        signals = {"speed": np.array([[1.0, 2.0, 9.0], [1.0, 1.0, 1.0]])}
        done = np.array([[False, True, True], [False, False, False]])

    np.testing.assert_allclose(pipeline.episode_mean(Traj, "speed"), [1.5, 1.0])


def test_every_experiment_names_the_issue_metrics():
    wanted = {
        forest: {"success_rate", "path_distance_mean"},
        city: {"no_crash_rate", "reached_goal_rate", "speed_mean", "right_lane_rate"},
        indoor: {"route_fraction", "no_crash_rate", "turn_success_rate", "door_seen_mean"},
    }
    for module, metrics in wanted.items():
        exp = module.EXPERIMENT
        assert metrics <= {c[0] for c in exp.columns}
        assert {"caps", "gc_dql"} & {m.kind for m in exp.methods}
        assert any(m.novel for m in exp.methods), f"{exp.name} needs a reward beyond the paper (Q1)"
        assert {"ci", "small", "paper"} <= set(module.PRESETS)


@pytest.mark.slow
@pytest.mark.parametrize("module", [forest, city, indoor], ids=lambda m: m.__name__.split(".")[-1])
def test_ci_preset_runs_end_to_end_and_resumes(module, tmp_path):
    exp = module.EXPERIMENT
    methods = (next(m.name for m in exp.methods if m.kind == "caps"), next(m.name for m in exp.methods if m.kind != "caps"))
    cfg = pipeline.RunConfig(preset="ci", out=tmp_path / "run", data_dir=tmp_path / "data", methods=methods,
                             progress=False)
    out = module.main(cfg)
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    for method in methods:
        for metric, _, _ in exp.columns:
            stat = saved["metrics"][method][metric]
            assert set(stat) >= {"mean", "ci_low", "ci_high", "n"}
    for name in ("table.md", "trajectories.png", "config.json", "fpv.gif"):
        assert (tmp_path / "run" / name).stat().st_size > 0, name
    # A second run reuses the stored dataset and checkpoints instead of collecting and training again.
    steps = out["dataset"]["steps"]
    again = module.main(cfg)
    assert again["dataset"]["steps"] == steps
    assert again["timings_s"]["collect_s"] < out["timings_s"]["collect_s"]


def test_smoke_preset_keeps_what_is_run_and_shrinks_how_much(tmp_path, monkeypatch):
    paper, ci = indoor.PRESETS["paper"], pipeline.ci_preset()
    smoke = pipeline.smoke_preset(paper)
    for name in ("cem", "horizon", "conv", "obs_hidden", "image_pool", "batch_size", "mirror", "cem_return",
                 "cem_warm_start"):
        assert getattr(smoke, name) == getattr(paper, name), name
    for name in ("collect_steps", "train_steps", "baseline_steps", "eval_episodes", "eval_steps", "segmenter_steps"):
        assert getattr(smoke, name) == getattr(ci, name) < getattr(paper, name), name
    assert smoke.onpolicy_steps == 0  # no on-policy stage where the preset has none
    onpolicy = pipeline.smoke_preset(indoor.PRESETS["small_onpolicy"])
    assert 0 < onpolicy.onpolicy_steps < indoor.PRESETS["small_onpolicy"].onpolicy_steps
    assert onpolicy.onpolicy_reward == indoor.PRESETS["small_onpolicy"].onpolicy_reward
    monkeypatch.chdir(tmp_path)  # resolve_paths creates the folders
    run_dir, data_dir = pipeline.resolve_paths(forest.EXPERIMENT, pipeline.RunConfig(preset="paper", smoke=True))
    assert "paper_smoke" in run_dir.name and "paper_smoke" in data_dir.name  # never the real run's folders


@pytest.mark.slow
@pytest.mark.parametrize("module", [forest, city, indoor], ids=lambda m: m.__name__.split(".")[-1])
def test_paper_preset_runs_every_stage_at_smoke_size(module, tmp_path):
    """The paper preset's model, horizon and CEM (meant for a GPU) through every stage, at ci's sizes."""
    exp = module.EXPERIMENT
    methods = tuple(m.name for m in exp.methods)
    cfg = pipeline.RunConfig(preset="paper", smoke=True, out=tmp_path / "run", data_dir=tmp_path / "data",
                             methods=methods, progress=False)
    out = module.main(cfg)
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["preset"]["cem"] == list(module.PRESETS["paper"].cem)
    assert config["preset"]["horizon"] == module.PRESETS["paper"].horizon
    assert set(out["metrics"]) == set(methods)
    assert np.isfinite(out["holdout_loss"]["loss"])


def test_val_split_has_its_own_tasks_and_run_folder(tmp_path):
    env = envs.make("forest")
    preset = dataclasses.replace(forest.PRESETS["ci"], eval_episodes=3)
    eval_paths = np.asarray(pipeline.eval_tasks(env, preset, 0).path)
    val_paths = np.asarray(pipeline.eval_tasks(env, preset, 0, "val").path)
    assert eval_paths.shape == val_paths.shape and not np.allclose(eval_paths, val_paths)
    cfg = pipeline.RunConfig(preset="ci", split="val", data_dir=tmp_path / "data")
    cwd = os.getcwd()
    try:
        os.chdir(tmp_path)
        run_dir, _ = pipeline.resolve_paths(forest.EXPERIMENT, cfg)
    finally:
        os.chdir(cwd)
    assert run_dir.as_posix() == "results/forest/ci_val_seed0"  # never the eval run's folder


def test_every_method_plans_with_the_presets_return_mode():
    env = envs.make("forest")
    preset = dataclasses.replace(forest.PRESETS["ci"], cem_return="mean")
    assert pipeline.cem_config(preset, env, horizon=1).return_mode == "mean"
    with pytest.raises(ValueError, match="return_mode"):
        pipeline.cem_config(dataclasses.replace(preset, cem_return="median"), env, horizon=4)


def test_goals_from_env_passes_the_forest_path_and_leaves_other_specs_alone():
    class Model:
        cue_names, action_low, action_high = ("collision", "speed", "heading"), (-30.0, 0.5), (30.0, 3.0)

    spec = pipeline.method_spec(pipeline.Method("p", "caps", {"collision": 1.0, "path": 1.0}), Model())
    assert float(spec.step_seconds) == envs.base.CONTROL_DT
    forest_env, city_env = envs.make("forest"), envs.make("city")
    state = forest_env.reset(jax.random.key(0), forest_env.sample_task(jax.random.key(1), "val"))
    out = pipeline.goals_from_env(state, spec)
    np.testing.assert_allclose(out.goal_path, state.info["goal_path"])
    h = float(state.info["goal_heading"])
    np.testing.assert_allclose(out.goal_heading, [np.cos(h), np.sin(h)], atol=1e-6)
    city_state = city_env.reset(jax.random.key(0), city_env.sample_task(jax.random.key(1), "val"))
    assert "goal_path" not in city_state.info
    np.testing.assert_allclose(pipeline.goals_from_env(city_state, spec).goal_path, spec.goal_path)


def test_warm_start_reaches_the_caps_planner_only():
    # The one-step baselines' planner has no sequence to shift, so the preset's warm start is CAPs' alone.
    env = envs.make("forest")
    preset = forest.PRESETS["medium"]
    assert preset.cem_warm_start and not forest.PRESETS["small"].cem_warm_start
    assert pipeline.cem_config(preset, env, horizon=preset.horizon).warm_start
    assert not pipeline.cem_config(preset, env, horizon=1).warm_start


def test_lr_decay_spans_each_models_whole_training(monkeypatch, tmp_path):
    # The cosine must end where each model's training ends: CAPs after its on-policy continuation too,
    # the baselines after their own steps; without ``lr_decay`` the rate stays the paper's constant.
    seen = {}

    def fit_caps(model, cfg, *args, **kwargs):
        seen["caps"] = cfg
        return types.SimpleNamespace(step=0), {}

    def fit_baseline(agent, cfg, *args, **kwargs):
        seen["gc_dql"] = cfg
        return types.SimpleNamespace(step=0, params={}), {}

    monkeypatch.setattr(pipeline.training, "fit", fit_caps)
    monkeypatch.setattr(pipeline.baselines, "fit_offline", fit_baseline)
    env = envs.make("forest")
    sampler = types.SimpleNamespace(batches=lambda batch_size: None)
    run = pipeline.RunConfig(progress=False)
    for lr_decay, caps_steps, baseline_steps in ((True, 250 + 300, 100), (False, None, None)):
        preset = dataclasses.replace(forest.PRESETS["ci"], train_steps=250, onpolicy_steps=100, onpolicy_train_steps=300,
                                     baseline_steps=100, lr_decay=lr_decay)
        seen.clear()
        model = capsjax.CAPsModel(pipeline.model_config(forest.EXPERIMENT, preset, env))
        pipeline.train_caps(forest.EXPERIMENT, preset, model, sampler, tmp_path, run)
        pipeline.train_baseline(forest.EXPERIMENT, preset, "gc_dql", model.config, env, sampler, tmp_path, run)
        assert seen["caps"].lr_decay_steps == caps_steps
        assert seen["gc_dql"].lr_decay_steps == baseline_steps
        assert seen["caps"].learning_rate == seen["gc_dql"].learning_rate == preset.learning_rate


def test_command_line_help_explains_every_option():
    out = subprocess.run([sys.executable, "-m", "experiments.indoor", "--help"], capture_output=True, text=True,
                         check=True, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    for option in ("--preset", "--seed", "--split", "--out", "--data-dir", "--train-seed", "--methods", "--smoke"):
        assert option in out.stdout, option


def test_eval_cache_key_changes_with_params_env_and_split():
    exp, preset = forest.EXPERIMENT, forest.PRESETS["ci"]
    method = exp.methods[0]
    params = {"w": np.arange(6, dtype=np.float32).reshape(2, 3)}
    env = envs.make("forest")

    def key(**changes):
        args = dict(method=method, preset=preset, data_dir=Path("d"), split="eval", env=env, params=params)
        return pipeline.eval_cache_key(**dict(args, **changes))

    assert key() == key(params={"w": params["w"].copy()})  # the same bytes: reused
    retrained = {"w": params["w"] + 1e-6}
    assert key(params=retrained) != key()
    assert key(env=envs.make("forest", arena_half=env.config.arena_half + 1.0)) != key()
    assert key(split="val") != key()
    assert key(method=dataclasses.replace(method, goal_speed=3.0)) != key()


def test_collection_start_choice_is_checked_and_named_in_the_dataset():
    preset = forest.PRESETS["ci"]
    forest_env = envs.make("forest")
    assert pipeline.collect_task_sampler(preset, forest_env) is None
    anywhere = dataclasses.replace(preset, collect_start="anywhere")
    sampler = pipeline.collect_task_sampler(anywhere, forest_env)
    assert sampler is pipeline.collect_task_sampler(anywhere, forest_env)  # cached: one compiled rollout
    assert pipeline.collect_policy_name(anywhere) != pipeline.collect_policy_name(preset)
    with pytest.raises(ValueError, match="sample_task_anywhere"):
        pipeline.collect_task_sampler(anywhere, envs.make("city"))
    with pytest.raises(ValueError, match="collect_start"):
        pipeline.collect_task_sampler(dataclasses.replace(preset, collect_start="corner"), forest_env)


def test_onpolicy_reward_names_the_caps_method_that_drives_and_rejects_others(tmp_path):
    small = indoor.PRESETS["small"]
    assert pipeline.onpolicy_method(indoor.EXPERIMENT, small).name == "caps_collision"  # default: the first
    chosen = dataclasses.replace(small, onpolicy_reward="caps_heading")
    assert pipeline.onpolicy_method(indoor.EXPERIMENT, chosen).weights == indoor.RC_CAR
    for bad in ("dql", "caps_heading_typo"):  # a baseline drives no MPC; a typo names nothing
        with pytest.raises(ValueError, match=r"onpolicy_reward.*caps_collision, caps_heading"):
            pipeline.onpolicy_method(indoor.EXPERIMENT, dataclasses.replace(small, onpolicy_reward=bad))
    typo = dataclasses.replace(indoor.PRESETS["ci"], onpolicy_steps=100, onpolicy_reward="caps_heading_typo")
    cfg = pipeline.RunConfig(preset="ci", out=tmp_path / "run", data_dir=tmp_path / "data", progress=False)
    with pytest.raises(ValueError, match="onpolicy_reward"):  # before anything is collected or written
        pipeline.run(indoor.EXPERIMENT, {"ci": typo}, cfg)
    assert not (tmp_path / "data").exists() and not (tmp_path / "run").exists()


@pytest.mark.slow
def test_onpolicy_stage_collects_with_the_first_model_and_continues_training(tmp_path):
    preset = dataclasses.replace(forest.PRESETS["ci"], onpolicy_steps=400, onpolicy_train_steps=50,
                                 onpolicy_cem=(32, 16, 2, 4))
    presets = dict(forest.PRESETS, ci=preset)
    cfg = pipeline.RunConfig(preset="ci", out=tmp_path / "run", data_dir=tmp_path / "data", methods=("caps",),
                             progress=False)
    out = pipeline.run(forest.EXPERIMENT, presets, cfg)
    from capsjax import data

    ds_on = data.Dataset.open(str(tmp_path / "data" / "onpolicy.zarr"))
    assert ds_on.num_steps >= 400 and ds_on.policy["policy"] == "CAPs MPC with exploration noise"
    assert len(ds_on.policy["params_sha256"]) == 64  # names the first model it was collected with
    steps = sorted(int(p.name) for p in (tmp_path / "data" / "checkpoints" / "caps_onpolicy").iterdir() if p.name.isdigit())
    assert steps[-1] == preset.train_steps + preset.onpolicy_train_steps
    again = pipeline.run(forest.EXPERIMENT, presets, cfg)  # resumes: nothing collected or trained again
    assert again["timings_s"]["collect_onpolicy_s"] < out["timings_s"]["collect_onpolicy_s"]
    assert data.Dataset.open(str(tmp_path / "data" / "onpolicy.zarr")).num_steps == ds_on.num_steps


def _tiny_model_and_sampler():
    """A tiny CAPs model and a sampler of 32 random-action windows of the fast world, for training-stage tests."""
    env = FastEnv()
    task = FastTask(obstacles=jnp.array([[5.5, 5.5, 0.01]] * 4), start=jnp.zeros(3))
    model = capsjax.CAPsModel(capsjax.ModelConfig.from_env_spec(
        env.spec, conv=((4, 3, 2),), obs_hidden=(16, 16), action_hidden=(8, 8), head_hidden=4, horizon=4))
    windows = random_windows(env, jax.random.key(1), task, 32, model.horizon)

    class Sampler:
        def batches(self, batch_size):
            return lambda key: jax.tree.map(lambda x: x[jax.random.randint(key, (batch_size,), 0, 32)], windows)

    return model, Sampler()


def test_checkpoints_trained_on_other_windows_are_refused_not_resumed(tmp_path):
    """A preset that turns ``mirror`` on must not resume the unmirrored model of an older run."""
    model, sampler = _tiny_model_and_sampler()
    preset = dataclasses.replace(forest.PRESETS["ci"], mirror=False, train_steps=4, save_every=4, batch_size=8)
    cfg = pipeline.RunConfig(preset="ci", progress=False)
    first = pipeline.train_caps(forest.EXPERIMENT, preset, model, sampler, tmp_path, cfg)
    again = pipeline.train_caps(forest.EXPERIMENT, preset, model, sampler, tmp_path, cfg)  # resumed as it is
    assert int(again.step) == 4
    np.testing.assert_array_equal(ravel_pytree(again.params)[0], ravel_pytree(first.params)[0])
    mirrored = dataclasses.replace(preset, mirror=True)
    with pytest.raises(checkpoint.ConfigMismatchError, match=r"TrainingWindows\.mirror: saved false != requested true"
                                                              r".*another --data-dir"):
        pipeline.train_caps(forest.EXPERIMENT, mirrored, model, sampler, tmp_path, cfg)
    assert sorted(p.name for p in (tmp_path / "checkpoints" / "caps").iterdir() if p.name.isdigit()) == ["4"]


def test_models_trained_at_once_equal_those_trained_one_after_another(tmp_path):
    """``RunConfig.jobs`` changes the wall clock only: CAPs and a baseline trained in threads at once are
    bit for bit the models trained one after the other, and every stage's time is recorded."""
    from tests.test_baselines import ENV, TRUNK, fast_transitions  # one-step windows with what Q-learning needs

    model, env = capsjax.CAPsModel(dataclasses.replace(TRUNK, horizon=1)), ENV
    sampler = types.SimpleNamespace(batches=lambda batch_size: lambda key: fast_transitions(key, batch_size))
    preset = dataclasses.replace(forest.PRESETS["ci"], train_steps=6, baseline_steps=4, save_every=2, batch_size=8)
    cfg = pipeline.RunConfig(preset="ci", progress=False)
    trained = {}
    for workers in (1, 0):
        data_dir, timings = tmp_path / f"workers{workers}", {}
        jobs = {"caps": lambda d=data_dir: pipeline.train_caps(forest.EXPERIMENT, preset, model, sampler, d, cfg),
                "gc_dql": lambda d=data_dir: pipeline.train_baseline(forest.EXPERIMENT, preset, "gc_dql", model.config,
                                                                     env, sampler, d, cfg)}
        trained[workers] = pipeline.run_concurrently(jobs, workers, timings)
        assert set(timings) == {"train_caps_s", "train_gc_dql_s", "train_s"}
        assert int(trained[workers]["caps"].step) == 6
    one_by_one, at_once = trained[1], trained[0]
    np.testing.assert_array_equal(ravel_pytree(at_once["caps"].params)[0], ravel_pytree(one_by_one["caps"].params)[0])
    np.testing.assert_array_equal(ravel_pytree(at_once["gc_dql"][1])[0], ravel_pytree(one_by_one["gc_dql"][1])[0])


def test_a_failing_training_job_is_raised_after_the_others_finish():
    finished = []

    def slow():
        import time
        time.sleep(0.2)
        finished.append("slow")
        return 1

    def bad():
        raise pipeline.training.NonFiniteTrainingError("10 training steps in a row had a non-finite loss")

    with pytest.raises(pipeline.training.NonFiniteTrainingError, match="non-finite"):
        pipeline.run_concurrently({"slow": slow, "bad": bad}, 0, {})
    assert finished == ["slow"]  # its checkpoints are saved for the rerun
    assert pipeline.run_concurrently({}, 0, {}) == {}
    for workers in (-1, 1.5, True):
        with pytest.raises(ValueError, match="jobs must be an int >= 0"):
            pipeline.run_concurrently({"slow": slow}, workers, {})


@pytest.mark.slow
def test_methods_evaluated_at_once_equal_those_evaluated_one_after_another(tmp_path):
    """``RunConfig.jobs`` changes the evaluation's wall clock only: the CAPs rewards (after the first, which
    compiles their shared program) and the baselines evaluated in threads give every episode as one after
    another does, and each method's time is recorded."""
    methods = ("caps", "caps_2ms", "caps_path", "gc_dql")
    runs = {}
    for jobs in (1, 2):
        cfg = pipeline.RunConfig(preset="ci", out=tmp_path / f"jobs{jobs}", data_dir=tmp_path / "data",
                                 methods=methods, progress=False, jobs=jobs)
        runs[jobs] = forest.main(cfg)  # the second run reuses the first's dataset and models
        assert {f"eval_{m}_s" for m in methods} | {"eval_s"} <= set(runs[jobs]["timings_s"])
    np.testing.assert_equal(runs[2]["per_episode"], runs[1]["per_episode"])  # NaN (no drivable path) equals NaN
    np.testing.assert_equal(runs[2]["metrics"], runs[1]["metrics"])


def test_forest_large_is_medium_with_more_caps_steps():
    # The `large` numbers in docs/forest.md were measured by continuing `medium`'s CAPs run on `medium`'s dataset;
    # that is only the same thing while the two presets differ in nothing but the CAPs step count.
    medium, large = forest.PRESETS["medium"], forest.PRESETS["large"]
    assert large.train_steps == 2 * medium.train_steps
    assert dataclasses.replace(large, train_steps=medium.train_steps) == medium


def test_ensemble_members_train_apart_from_the_single_model(tmp_path):
    """Member 0 is ``ensemble=1``'s model, resumed as it is; member i has its own checkpoints and key."""
    model, sampler = _tiny_model_and_sampler()
    preset = dataclasses.replace(forest.PRESETS["ci"], train_steps=4, save_every=4, batch_size=8, ensemble=2)
    cfg = pipeline.RunConfig(preset="ci", progress=False)
    single = pipeline.train_caps(forest.EXPERIMENT, dataclasses.replace(preset, ensemble=1), model, sampler,
                                 tmp_path, cfg)
    first = pipeline.train_caps(forest.EXPERIMENT, preset, model, sampler, tmp_path, cfg)
    second = pipeline.train_caps(forest.EXPERIMENT, preset, model, sampler, tmp_path, cfg, name="caps_member1",
                                 member=1)
    np.testing.assert_array_equal(ravel_pytree(first.params)[0], ravel_pytree(single.params)[0])
    assert not np.allclose(ravel_pytree(second.params)[0], ravel_pytree(first.params)[0])
    assert {p.name for p in (tmp_path / "checkpoints").iterdir()} == {"caps", "caps_member1"}
    stacked = capsjax.Ensemble(model, 2).stack([first.params, second.params])
    assert jax.tree.leaves(stacked)[0].shape[0] == 2


def test_bad_ensemble_settings_stop_before_anything_is_written(tmp_path):
    cfg = pipeline.RunConfig(preset="ci", out=tmp_path / "run", data_dir=tmp_path / "data", progress=False)
    for bad, match in ((dict(ensemble=0), "Preset.ensemble must be an int >= 1"),
                       (dict(ensemble=2, onpolicy_steps=100), "onpolicy_steps"),
                       (dict(ensemble=2, ensemble_max_cues=("colision",)), "ensemble_max_cues must name cues"),
                       (dict(ensemble_max_cues=("collision",)), "needs ensemble > 1")):
        with pytest.raises(SystemExit, match=match):
            pipeline.run(forest.EXPERIMENT, {"ci": dataclasses.replace(forest.PRESETS["ci"], **bad)}, cfg)
    assert not (tmp_path / "data").exists() and not (tmp_path / "run").exists()


def test_eval_cache_key_keeps_stored_evaluations_of_single_models():
    # Evaluations stored before ``Preset.ensemble`` existed keep their key at its implicit value, 1.
    exp, preset = forest.EXPERIMENT, forest.PRESETS["ci"]
    args = dict(method=exp.methods[0], data_dir=Path("d"), split="eval", env=envs.make("forest"),
                params={"w": np.zeros(3, np.float32)})
    single = pipeline.eval_cache_key(preset=preset, **args)
    assert not {"ensemble", "ensemble_max_cues"} & set(json.loads(single)["preset"])
    assert pipeline.eval_cache_key(preset=dataclasses.replace(preset, ensemble=3), **args) != single


@pytest.mark.slow
def test_ci_preset_runs_with_a_caps_ensemble(tmp_path):
    preset = dataclasses.replace(forest.PRESETS["ci"], ensemble=2)
    cfg = pipeline.RunConfig(preset="ci", out=tmp_path / "run", data_dir=tmp_path / "data", methods=("caps",),
                             progress=False)
    out = pipeline.run(forest.EXPERIMENT, dict(forest.PRESETS, ci=preset), cfg)
    assert len(out["holdout_loss"]["members"]) == 2
    assert np.isfinite(out["metrics"]["caps"]["success_rate"]["mean"])
    assert (tmp_path / "data" / "checkpoints" / "caps_member1").is_dir()
    assert (tmp_path / "run" / "fpv.gif").stat().st_size > 0


def test_eval_env_changes_the_evaluation_env_only_and_refuses_what_a_model_cannot_take(tmp_path, monkeypatch):
    exp = forest.EXPERIMENT
    env = envs.make("forest", **dict(exp.env_overrides))
    assert pipeline.evaluation_env(exp, env, {}) is env
    for module in (forest, city, indoor):  # every experiment's own evaluation-only fields are valid ones
        own = module.EXPERIMENT
        base_env = envs.make(own.env_name, **dict(own.env_overrides))
        assert pipeline.evaluation_env(own, base_env, own.eval_env).spec == base_env.spec
    farther = pipeline.evaluation_env(exp, env, {"lookahead": 4.0, "goal_path_points": 16.0})
    assert farther.config.lookahead == 4.0 and farther.spec == env.spec
    assert type(farther.config.goal_path_points) is int  # the CLI gives floats; int fields get ints
    narrower = pipeline.evaluation_env(exp, env, {"plan_steer_deg": 20.0})  # the planner's box may change
    assert narrower.spec.plan_high[0] == 20.0 and narrower.spec.action_high == env.spec.action_high
    assert pipeline.cem_config(forest.PRESETS["ci"], narrower, 12).action_high[0] == 20.0
    for bad, match in (({"lookahed": 4.0}, r"unknown config field 'lookahed'.*lookahead"),
                       ({"camera": 1.0}, r"field 'camera': only number fields"),
                       ({"goal_path_points": 2.5}, r"field 'goal_path_points': expected an integer"),
                       ({"history": 8.0}, r"changes the env's spec field\(s\) \['history'\]"),
                       ({"goal_path_points": 1.0}, r"--eval-env: goal_path_points must be >= 2")):
        with pytest.raises(SystemExit, match=match):
            pipeline.evaluation_env(exp, env, bad)
    # From the command line; and a bad field stops the run before any folder is made.
    cfg = pipeline.tyro.cli(pipeline.RunConfig, args=["--eval-env", "lookahead", "4"])
    assert cfg.eval_env == {"lookahead": 4.0}
    bad = pipeline.RunConfig(preset="ci", out=tmp_path / "run", data_dir=tmp_path / "data", eval_env={"history": 8})
    with pytest.raises(SystemExit, match="history"):
        pipeline.run(exp, forest.PRESETS, bad)
    assert not (tmp_path / "data").exists() and not (tmp_path / "run").exists()
    monkeypatch.chdir(tmp_path)  # resolve_paths creates the folders
    run_dir, _ = pipeline.resolve_paths(exp, pipeline.RunConfig(split="val", eval_env={"lookahead": 4.0}))
    assert run_dir.as_posix() == "results/forest/small_val_seed0_lookahead4"  # never the unchanged env's folder


@pytest.mark.slow
def test_eval_env_run_reuses_the_dataset_and_model_and_evaluates_in_the_changed_env(tmp_path):
    base = pipeline.RunConfig(preset="ci", out=tmp_path / "run", data_dir=tmp_path / "data", methods=("caps",),
                              progress=False)
    first = forest.main(base)
    steps = sorted(p.name for p in (tmp_path / "data" / "checkpoints" / "caps").iterdir())
    farther = forest.main(dataclasses.replace(base, out=tmp_path / "farther", eval_env={"lookahead": 4.0}))
    with np.load(tmp_path / "run" / "eval" / "caps.npz") as f:
        assert json.loads(str(f["key"]))["env"]["lookahead"] == forest.EXPERIMENT.eval_env["lookahead"]
    assert farther["dataset"] == first["dataset"]  # the same dataset, not recollected
    assert farther["timings_s"]["collect_s"] < first["timings_s"]["collect_s"]
    assert sorted(p.name for p in (tmp_path / "data" / "checkpoints" / "caps").iterdir()) == steps  # nor retrained
    assert farther["holdout_loss"] == first["holdout_loss"]
    assert json.loads((tmp_path / "farther" / "config.json").read_text())["eval_env"] == {"lookahead": 4.0}
    # The run's fields go on top of the experiment's own (the forest's 8 m pursuit point).
    assert farther["eval_env"] == {"lookahead": 4.0} and first["eval_env"] == dict(forest.EXPERIMENT.eval_env)
    with np.load(tmp_path / "farther" / "eval" / "caps.npz") as f:
        assert json.loads(str(f["key"]))["env"]["lookahead"] == 4.0
    assert "lookahead = 4" in (tmp_path / "farther" / "table.md").read_text()
