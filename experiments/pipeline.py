"""The pipeline every experiment runs: collect -> label -> train CAPs and the baselines -> evaluate -> report.

An experiment (``experiments/forest.py``, ``city.py``, ``indoor.py``) is data: an ``Experiment`` saying
which scene, cues, collection policy, rewards, metrics and paper numbers it uses, plus ``Preset`` sizes.
``run`` does the rest through one code path for every method (``capsjax.mpc.Policy``), and caches each
stage so an interrupted run resumes where it stopped:

* the dataset (``<data_dir>/dataset.zarr``) is appended to until it holds the preset's steps;
* the learned labeller is saved once and its labels written beside the episodes (``relabel``);
* CAPs and each baseline train from their latest orbax checkpoint to the preset's steps;
* each method's evaluation is saved (``<run>/eval/<method>.npz``, keyed by the method and preset) and reused.

Training never sees an evaluation task: training data come from the env's 'train' task stream (layouts,
paths, goals), evaluation tasks from its disjoint 'eval' stream seeded by ``--seed``.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import functools
import hashlib
import json
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
import tyro

import capsjax
import envs
from capsjax import baselines, checkpoint, collect, data, labellers, mpc, sharding, training
from capsjax.reward import RewardSpec
from experiments import report, runtime

METHOD_KINDS = ("caps",) + baselines.KINDS
HOLDOUT_FRACTION = 0.1
HOLDOUT_BATCH, HOLDOUT_BATCHES = 256, 16  # held-out loss over 4,096 windows


@dataclasses.dataclass(frozen=True)
class Preset:
    """Sizes of one run (the ``ci`` / ``small`` / ``paper`` presets of each experiment)."""

    collect_steps: int
    collect_robots: int
    episode_length: int
    train_steps: int
    baseline_steps: int
    eval_episodes: int
    eval_steps: int
    cem: tuple[int, int, int, int]  # init samples, samples, iterations (incl. the first), elites
    horizon: int = 12
    batch_size: int = 32
    learning_rate: float = 1e-4
    # Decay every model's learning rate to zero by a cosine over its whole training (CAPs: ``train_steps``
    # plus ``onpolicy_train_steps``; baselines: ``baseline_steps``; ``TrainConfig.lr_decay_steps``), instead
    # of the paper's constant rate.
    lr_decay: bool = False
    labelled_fraction: float = 0.002
    segmenter_steps: int = 1500
    conv: tuple = capsjax.model.PAPER_CONV
    obs_hidden: tuple = (256, 128)
    save_every: int = 1000
    image_pool: int = 1  # ModelConfig.image_pool: average-pool frames before the CNN (a CPU-budget knob)
    mirror: bool = False  # mirror half of the training windows left-right (data.make_sampler(mirror=True))
    cem_return: str = "best"  # CEMConfig.return_mode of every method's planner: the paper's 'best', 'mean' or 'local_mean'
    # CEMConfig.warm_start of the CAPs planner (horizon > 1; not the paper's): half of CEM's first samples
    # are drawn around the previous control step's plan shifted by one step, so a plan is refined over steps.
    cem_warm_start: bool = False
    cem_local_refit: bool = False  # CEMConfig.local_refit of every method's planner (not the paper's)
    collect_hold: float = 1.0  # collect.random_policy(mean_hold=...): mean steps each random action is held
    # Where collection episodes start: 'task' (the training task's own start, e.g. on its path) or
    # 'anywhere' (uniform over the arena, any yaw: the env's ``sample_task_anywhere``; forest only).
    collect_start: str = "task"
    # On-policy data (the paper's forest data were partly on-policy): after CAPs has trained on the random
    # data, it drives ``onpolicy_steps`` more steps on *training* tasks (MPC on the CAPs method named
    # ``onpolicy_reward``, or the experiment's first CAPs method when empty, a cheaper ``onpolicy_cem``, Gaussian noise ``onpolicy_noise[0]`` in normalised action units
    # and a uniform action with probability ``onpolicy_noise[1]``), stored as a second dataset; CAPs then
    # trains ``onpolicy_train_steps`` more steps and the baselines train from scratch, all on both datasets.
    onpolicy_steps: int = 0
    onpolicy_train_steps: int = 0
    onpolicy_cem: tuple[int, int, int, int] = (256, 64, 2, 16)
    onpolicy_noise: tuple[float, float] = (0.1, 0.1)
    onpolicy_reward: str = ""
    # CAPs as an ensemble of this many models (``capsjax.ensemble.Ensemble``, not the paper's): each trained
    # ``train_steps`` on the same data with its own initialisation and batch order, the planner scoring with
    # their mean prediction.  Member 0 is the single model of ``ensemble=1`` (``checkpoints/caps``); member i
    # trains in ``checkpoints/caps_member<i>``.
    ensemble: int = 1
    ensemble_max_cues: tuple[str, ...] = ()  # Ensemble.max_cues: cues planned on by the members' maximum


@dataclasses.dataclass(frozen=True)
class TrainingWindows:
    """How a run's training windows are drawn beyond what the dataset and the model config record, saved
    beside every CAPs and baseline checkpoint (``metadata`` of ``training.fit`` / ``fit_offline``): a
    checkpoint folder trained on other windows (say before a preset turned ``mirror`` on) is refused,
    never resumed as if it were this preset's model.  Checkpoints older than this section read as its
    defaults."""

    mirror: bool = False


def training_metadata(preset: Preset) -> dict:
    return {"TrainingWindows": TrainingWindows(mirror=preset.mirror)}


@contextlib.contextmanager
def _advice_on_mismatch(ckpt_dir: Path):
    """A refused checkpoint folder names what to do (nothing in it is deleted)."""
    try:
        yield
    except checkpoint.ConfigMismatchError as e:
        raise checkpoint.ConfigMismatchError(
            f"{e}. The checkpoints in {ckpt_dir} were trained with other settings: train into another "
            f"--data-dir, or move that folder away to retrain (it is left as it is)") from e


def ci_preset(**overrides) -> Preset:
    """The ``ci`` preset every experiment shares: tiny data, a tiny trunk and a few short episodes --
    enough to exercise every stage, not to learn the task."""
    settings = dict(collect_steps=3000, collect_robots=32, episode_length=100, train_steps=200, baseline_steps=100,
                    eval_episodes=4, eval_steps=40, cem=(128, 64, 2, 16), horizon=8, batch_size=16,
                    learning_rate=1e-3, labelled_fraction=0.02, segmenter_steps=100,
                    conv=((16, 5, 3), (16, 3, 2)), obs_hidden=(64, 64), save_every=100)
    return Preset(**dict(settings, **overrides))


# The fields of a preset that set how much is done (data, steps, episodes), as opposed to what is done
# (model, horizon, planner, training and collection settings).
_SIZE_FIELDS = ("collect_steps", "collect_robots", "episode_length", "train_steps", "baseline_steps", "eval_episodes",
                "eval_steps", "labelled_fraction", "segmenter_steps", "save_every")


def smoke_preset(preset: Preset) -> Preset:
    """``preset`` at the ``ci`` preset's sizes: its model, horizon, planner, training and collection
    settings unchanged, but ci's data, step and episode counts (an on-policy stage kept, at ci sizes), so
    every stage of a long run -- e.g. ``paper`` on a GPU -- is exercised in minutes before paying for it."""
    ci = ci_preset()
    sizes = {name: getattr(ci, name) for name in _SIZE_FIELDS}
    if preset.onpolicy_steps:
        sizes.update(onpolicy_steps=ci.collect_steps // 2, onpolicy_train_steps=ci.train_steps)
    return dataclasses.replace(preset, **sizes)


@dataclasses.dataclass(frozen=True)
class Method:
    """A controller evaluated on the eval tasks: a trained model (``kind``) driven by a reward.

    ``weights`` are ``RewardSpec`` term weights (the task reward; GC-DQL-sep combines its heads with
    them), ``goal_speed`` and ``lane_offset`` its goals, ``gated`` its gated terms; the goal heading is
    refreshed from the env every step.  ``novel`` marks a reward that appears nowhere in training or in
    the paper (the flexibility question Q1)."""

    name: str
    kind: str
    weights: Mapping[str, float]
    goal_speed: float = 0.0
    lane_offset: float = 0.0
    gated: tuple[str, ...] = ()
    novel: bool = False
    description: str = ""


@dataclasses.dataclass(frozen=True)
class Experiment:
    name: str
    env_name: str
    env_overrides: Mapping[str, object]
    cues: tuple  # capsjax.cues.Cue of the CAPs model
    learned_cues: tuple[str, ...]  # cues labelled by the learned segmenter ('lane_seen', 'door_frac', ...)
    baseline_config: Callable[[str], baselines.BaselineConfig]  # kind -> config
    methods: tuple[Method, ...]
    episode_metrics: Callable  # (trajectory with [E, T] leaves, env) -> {metric: f32[E]}
    columns: tuple[tuple[str, str, str], ...]  # table columns: (metric, header, kind)
    paper: Mapping[str, Mapping[str, float]]
    primary_metric: str  # what "beats the baselines" is judged on
    notes: tuple[str, ...] = ()
    segmenter: Callable | None = None  # env -> labellers.SegmenterConfig
    # (tasks, env, one method's per-episode metrics) -> more {metric: f32[E]} that depend on the tasks too (the
    # forest's success on the paths the car can drive).  Applied after the evaluation cache, so stored
    # evaluations gain them without being re-run.
    task_metrics: Callable | None = None
    # Env config fields that differ in evaluation from collection and training (the forest's pursuit point):
    # evaluation-only settings, so datasets and models stay shared with the unchanged env.  ``RunConfig.eval_env``
    # goes on top of them.
    eval_env: Mapping[str, float] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class RunConfig:
    preset: str = "small"
    """'ci' (a minute or two, used by the tests), 'small' (the default: a full result on a 2-core CPU)
    or 'paper' (the paper's data sizes, horizon and CEM; meant for a GPU); the city and the halls also have
    'small_onpolicy' (`small` plus the on-policy stage, ~10 minutes longer), the forest 'medium' (4x `small`'s
    data and CAPs steps, ~2 hours on a 2-core CPU with its baselines) and 'large' (`medium` with 8x `small`'s
    CAPs steps, ~2.5 hours)."""
    seed: int = 0
    """Evaluation seed: the evaluated tasks (layouts, paths, goals) come from this seed's stream of ``--split``."""
    split: Literal["eval", "val"] = "eval"
    """Task split to evaluate on: 'eval' (the reported test) or 'val' (tasks of the same kind from a third
    stream, disjoint from training and from 'eval': for choosing rewards and planner settings)."""
    out: Path | None = None
    """Output folder of this run (default ``results/<experiment>/<preset>_seed<seed>``, with ``_val`` before
    ``_seed`` for the 'val' split and ``--eval-env``'s fields after it, e.g. ``_lookahead4``)."""
    data_dir: Path | None = None
    """Dataset and trained models, shared by every evaluation seed (default ``datasets/<experiment>/<preset>``)."""
    train_seed: int = 0
    """Seed of collection, labelling and training (independent of the evaluation seed)."""
    methods: tuple[str, ...] = ()
    """Evaluate only these methods (default: all of the experiment's)."""
    eval_env: dict[str, float] = dataclasses.field(default_factory=dict)
    """Env config fields changed for the evaluation only, as name-value pairs, on top of the experiment's own
    (``--eval-env lookahead 4``: the forest's pursuit point 4 m ahead).  Collection, labelling and training keep
    the experiment's env, so the stored dataset and models are reused; the fields must leave the env's spec
    (observations, actions) as it is, but for the planner's sampling box.  The default ``--out`` gets the fields'
    names and values appended."""
    progress: bool = True
    """Progress bars for every long stage."""
    jobs: int = 2
    """Jobs run at once, in threads: the models that train on the same data (CAPs, the baselines), then the
    evaluations, each method a job, the first CAPs reward (which compiles the program every CAPs reward shares)
    before the other CAPs rewards (0: all at once; 1: one after another).  The models and
    results are the same either way; at once is faster where one job leaves cores idle (XLA:CPU runs a
    convolution on one core).  The forest's `small` models on a 2-core CPU (``python -m experiments.bench jobs``):
    2 at once trained 1.47x as fast as one after another, 3 at once 1.61x while all three ran, but in a whole
    run CAPs, the longest, then trained on alone."""
    smoke: bool = False
    """Smoke test of the preset: its model, horizon, planner and training settings at the 'ci' preset's data
    sizes and step counts, so every stage runs in minutes (check ``--preset paper`` before a long GPU run).
    Default folders get ``_smoke`` after the preset name; the numbers mean nothing."""


def cli(main: Callable[[RunConfig], dict], description: str) -> dict:
    """An experiment's ``python -m`` entry point: parse the options (tyro), let XLA:CPU use 512-bit vectors
    on an AVX-512 host before JAX starts (``experiments.runtime``; ``XLA_FLAGS`` overrides), run."""
    cfg = tyro.cli(RunConfig, description=description)
    runtime.use_wide_vectors()
    return main(cfg)


def resolve_paths(exp: Experiment, cfg: RunConfig) -> tuple[Path, Path]:
    split = "" if cfg.split == "eval" else f"_{cfg.split}"
    name = f"{cfg.preset}_smoke" if cfg.smoke else cfg.preset  # a smoke run never touches the real run's data
    # An evaluation in a changed env gets its own default folder: it never replaces the unchanged env's results.
    changed = "".join(f"_{k}{v:g}" for k, v in sorted(cfg.eval_env.items()))
    run_dir = cfg.out if cfg.out is not None else Path("results") / exp.name / f"{name}{split}_seed{cfg.seed}{changed}"
    data_dir = cfg.data_dir if cfg.data_dir is not None else Path("datasets") / exp.name / f"{name}_train{cfg.train_seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    data_dir.mkdir(parents=True, exist_ok=True)
    return run_dir, data_dir


def log(exp: Experiment, message: str) -> None:
    print(f"[{exp.name}] {message}", flush=True)


# ------------------------------------------------------------------------------------------- stages


def collect_stage(exp: Experiment, preset: Preset, env, data_dir: Path, cfg: RunConfig) -> data.Dataset:
    """Uniform random driving over the plan box from the 'train' task stream (the paper's exploration
    phase; every method then trains on this same stored dataset: the strict off-policy test)."""
    path = data_dir / "dataset.zarr"
    t = time.time()
    ds = collect.collect(env, collect.random_policy(env.spec, preset.collect_hold), None, None, path=str(path),
                         num_steps=preset.collect_steps, num_robots=preset.collect_robots,
                         key=jax.random.key(cfg.train_seed), labelled_fraction=preset.labelled_fraction,
                         episode_length=preset.episode_length, policy_name=collect_policy_name(preset),
                         progress=cfg.progress, task_sampler=collect_task_sampler(preset, env))
    log(exp, f"dataset: {ds.num_episodes} episodes, {ds.num_steps} steps ({time.time() - t:.0f} s)")
    return ds


def onpolicy_stage(exp: Experiment, preset: Preset, env, model, params, data_dir: Path, cfg: RunConfig) -> data.Dataset:
    """The first CAPs model drives training tasks with exploration noise (``Preset.onpolicy_*``); the
    episodes go to ``onpolicy.zarr``.  The stored policy names the first model's params digest, so data
    of another first model are never reused."""
    method = onpolicy_method(exp, preset)
    cem = dataclasses.replace(cem_config(preset, env, preset.horizon), init_samples=preset.onpolicy_cem[0],
                              samples=preset.onpolicy_cem[1], iterations=preset.onpolicy_cem[2],
                              elites=preset.onpolicy_cem[3])
    sigma, epsilon = preset.onpolicy_noise
    schedule = collect.ExplorationSchedule(uniform_steps=0, sigma=((0, sigma),), epsilon=((0, epsilon),))
    policy = collect.exploration_policy(mpc.caps_policy(model, cem), env.spec, schedule=schedule)
    name = {"policy": "CAPs MPC with exploration noise", "reward": method.name, "weights": dict(method.weights),
            "goal_speed": method.goal_speed, "cem": list(preset.onpolicy_cem), "sigma": sigma, "epsilon": epsilon,
            "cem_return": preset.cem_return, "params_sha256": params_digest(params),
            # only when set, so that data collected before the option existed still match
            **({"cem_warm_start": True} if preset.cem_warm_start else {}),
            **({"cem_local_refit": True} if preset.cem_local_refit else {})}
    t = time.time()
    ds = collect.collect(env, policy, params, method_spec(method, model), path=str(data_dir / "onpolicy.zarr"),
                         num_steps=preset.onpolicy_steps, num_robots=preset.collect_robots,
                         key=jax.random.key(cfg.train_seed + 3), labelled_fraction=preset.labelled_fraction,
                         episode_length=preset.episode_length, policy_name=name, progress=cfg.progress,
                         update_spec=goals_from_env)
    log(exp, f"on-policy dataset: {ds.num_episodes} episodes, {ds.num_steps} steps ({time.time() - t:.0f} s)")
    return ds


def onpolicy_method(exp: Experiment, preset: Preset) -> Method:
    """The CAPs method whose reward drives the on-policy stage (``Preset.onpolicy_reward``)."""
    caps_methods = [m for m in exp.methods if m.kind == "caps"]
    if not preset.onpolicy_reward:
        return caps_methods[0]
    for m in caps_methods:
        if m.name == preset.onpolicy_reward:
            return m
    raise ValueError(f"Preset.onpolicy_reward must name a CAPs method of {exp.name!r} "
                     f"({', '.join(m.name for m in caps_methods)}), got {preset.onpolicy_reward!r}")


def collect_task_sampler(preset: Preset, env):
    """``key -> task`` of the random-action collection (None: the env's 'train' tasks as they are)."""
    if preset.collect_start == "task":
        return None
    if preset.collect_start == "anywhere":
        if not hasattr(env, "sample_task_anywhere"):
            raise ValueError(f"collect_start='anywhere' needs an env with sample_task_anywhere; "
                             f"{type(env).__name__} has none (use collect_start='task')")
        return _anywhere_sampler(env)
    raise ValueError(f"collect_start must be 'task' or 'anywhere', got {preset.collect_start!r}")


@functools.lru_cache(maxsize=8)
def _anywhere_sampler(env):
    # Cached per env: a resumed collection reuses the compiled rollout.
    return lambda key: env.sample_task_anywhere(key, "train")


def collect_policy_name(preset: Preset) -> str:
    """The collection policy as stored in the dataset (a stored dataset is reused only by the same policy)."""
    name = "uniform random over the plan box"
    if preset.collect_hold != 1.0:
        name = f"{name}, each action held {preset.collect_hold:g} steps on average"
    if preset.collect_start != "task":
        name = f"{name}, episodes starting {preset.collect_start} in the arena"
    return name


def label_stage(exp: Experiment, preset: Preset, env, ds: data.Dataset, data_dir: Path, train_ids, holdout_ids,
                cfg: RunConfig) -> dict:
    """Train the segmenter on the labelled frames of training episodes only, measure it on the labelled
    frames of held-out episodes, and write its cue labels beside every episode."""
    if not exp.learned_cues:
        return {}
    seg_cfg = exp.segmenter(env)
    path = data_dir / "segmenter"
    t = time.time()
    if path.exists():
        labeller = labellers.load_labeller(path)
    else:
        _, images, semantic = ds.labelled_frames(train_ids)
        if len(images) < 8:
            raise ValueError(f"only {len(images)} labelled frames in the training episodes; raise collect_steps "
                             f"or labelled_fraction (now {preset.labelled_fraction})")
        log(exp, f"segmenter: training on {len(images)} labelled frames "
                 f"({100 * len(images) / max(ds.num_steps, 1):.2f} % of the dataset)")
        params, _ = labellers.train_segmenter(seg_cfg, images, semantic, jax.random.key(cfg.train_seed),
                                              preset.segmenter_steps)
        labeller = labellers.make_cue_labeller(seg_cfg, params)
        labellers.save_labeller(path, labeller)
    _, images, semantic = ds.labelled_frames(holdout_ids)
    quality = labellers.evaluate_labeller(labeller, images, semantic) if len(images) else {}
    quality["holdout_frames"] = len(images)
    write_labels(exp, ds, labeller, path)
    log(exp, f"labeller: {json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in quality.items()})} "
             f"({time.time() - t:.0f} s)")
    return quality


def write_labels(exp: Experiment, ds: data.Dataset, labeller, labeller_path: Path) -> None:
    """The labeller's cue labels beside every episode of ``ds``, unless they are there already."""
    if "segmenter" not in ds.label_names or ds.label_info("segmenter")["num_steps"] < ds.num_steps:
        writable = data.Dataset.open(ds.path, "a")  # labels are written beside the (untouched) episodes
        data.relabel(writable, labeller, "segmenter", meta={"labeller": str(labeller_path)}, scene=exp.env_name)


def model_config(exp: Experiment, preset: Preset, env) -> capsjax.ModelConfig:
    return capsjax.ModelConfig.from_env_spec(env.spec, cues=exp.cues, horizon=preset.horizon, conv=preset.conv,
                                             obs_hidden=preset.obs_hidden, image_pool=preset.image_pool)


def train_config(preset: Preset, total_steps: int) -> capsjax.TrainConfig:
    """The optimiser settings of a model that trains ``total_steps`` in all under ``preset``."""
    return capsjax.TrainConfig(batch_size=preset.batch_size, learning_rate=preset.learning_rate,
                               lr_decay_steps=total_steps if preset.lr_decay else None)


def train_caps(exp: Experiment, preset: Preset, model, sampler, data_dir: Path, cfg: RunConfig, *,
               num_steps: int | None = None, name: str = "caps", state=None, member: int = 0):
    """CAPs to ``num_steps`` (default the preset's) in ``checkpoints/<name>``, from ``state`` if given
    (continued training) and resuming from the latest checkpoint there; returns the train state.
    ``member`` > 0 trains another member of an ensemble: the same data and settings, its own
    initialisation and batch order."""
    train_cfg = train_config(preset, preset.train_steps + preset.onpolicy_train_steps)
    ckpt_dir = data_dir / "checkpoints" / name
    key = jax.random.key(cfg.train_seed + 1)  # member 0 is the single model of ``ensemble=1``
    if member:
        key = jax.random.fold_in(key, member)
    t = time.time()
    with _advice_on_mismatch(ckpt_dir):
        state, metrics = training.fit(
            model, train_cfg, sampler.batches(preset.batch_size), num_steps or preset.train_steps,
            key=key, state=state, ckpt_dir=str(ckpt_dir.absolute()),
            save_every=preset.save_every, progress=cfg.progress and name, metadata=training_metadata(preset))
    log(exp, f"{name}: {int(state.step)} steps ({time.time() - t:.0f} s)")
    return state


def train_baseline(exp: Experiment, preset: Preset, kind: str, model_cfg, env, sampler, data_dir: Path, cfg: RunConfig):
    agent = baselines.BaselineAgent.create(model_cfg, exp.baseline_config(kind), env.spec.plan_low, env.spec.plan_high)
    train_cfg = train_config(preset, preset.baseline_steps)
    ckpt_dir = data_dir / "checkpoints" / kind
    t = time.time()
    with _advice_on_mismatch(ckpt_dir):
        state, _ = baselines.fit_offline(
            agent, train_cfg, sampler.batches(preset.batch_size), preset.baseline_steps,
            key=jax.random.key(cfg.train_seed + 2), ckpt_dir=str(ckpt_dir.absolute()),
            save_every=preset.save_every, metadata=training_metadata(preset), progress=cfg.progress and kind)
    log(exp, f"{kind}: {int(state.step)} steps ({time.time() - t:.0f} s)")
    return agent, state.params


def run_concurrently(jobs: Mapping[str, Callable[[], object]], workers: int, timings: dict, stage: str = "train") -> dict:
    """``{name: job()}``, the jobs run in up to ``workers`` threads at once (0: all of them), each one's wall
    time in ``timings['<stage>_<name>_s']`` and the whole stage's in ``timings['<stage>_s']``.

    Why threads: XLA:CPU runs a convolution on one core (measured on the forest's CNN: as fast on one core
    as on two), so a second model trains in the time the first leaves idle; JAX releases the GIL while a
    compiled step runs.  Each model's steps are the same computations in the same order, so the results
    are bit for bit those of one model after another (tests/test_experiments.py).  Every job runs to its end
    even when another fails (each has saved its checkpoints, so a rerun resumes them); then the first
    failure is raised."""
    if not isinstance(workers, int) or isinstance(workers, bool) or workers < 0:
        raise ValueError(f"jobs must be an int >= 0 (0: every job at once), got {workers!r}")
    if not jobs:
        return {}

    def timed(name, job):
        t = time.time()
        result = job()
        timings[f"{stage}_{name}_s"] = time.time() - t
        return result

    t = time.time()
    with concurrent.futures.ThreadPoolExecutor(max_workers=workers or len(jobs)) as pool:
        futures = {name: pool.submit(timed, name, job) for name, job in jobs.items()}
        concurrent.futures.wait(futures.values())
    timings[f"{stage}_s"] = timings.get(f"{stage}_s", 0.0) + time.time() - t
    return {name: future.result() for name, future in futures.items()}  # raises the first failure


def goals_from_env(state, spec: RewardSpec) -> RewardSpec:
    """Every scene reports the wanted heading (path tangent ahead, direction to the goal, the latest
    command) as ``info['goal_heading']`` in radians; the reward wants it as a unit vector.  Scenes
    with a path (the forest) also report the stretch ahead as ``info['goal_path']``."""
    h = state.info["goal_heading"]
    spec = spec.with_goals(goal_heading=jnp.stack([jnp.cos(h), jnp.sin(h)]))
    if "goal_path" in state.info:
        spec = spec.with_goals(goal_path=state.info["goal_path"])
    return spec


def cem_config(preset: Preset, env, horizon: int) -> capsjax.CEMConfig:
    """The planner of every method (CAPs at the preset's horizon, the one-step baselines at 1)."""
    init, samples, iterations, elites = preset.cem
    return capsjax.CEMConfig(env.spec.plan_low, env.spec.plan_high, horizon=horizon, init_samples=init,
                             samples=samples, iterations=iterations, elites=elites, return_mode=preset.cem_return,
                             warm_start=preset.cem_warm_start and horizon > 1, local_refit=preset.cem_local_refit)


def evaluate(exp: Experiment, preset: Preset, env, method: Method, policy: mpc.Policy, params, spec: RewardSpec,
             tasks, seed: int, *, record_images: bool = False) -> mpc.Trajectory:
    """Every eval task once, all robots in one jitted vmap (sharded over local devices).

    Params and reward spec are arguments of the compiled program (``sharding.run_episodes``), so methods
    sharing one ``policy`` object -- every CAPs reward of an experiment -- share one compile.
    ``record_images`` keeps every robot's camera frames (the first-person GIF's)."""
    n = preset.eval_episodes
    mesh = sharding.make_mesh(_largest_divisor(n, jax.local_device_count()))
    return sharding.run_episodes(env, policy, params, spec, tasks, eval_keys(preset, seed), num_steps=preset.eval_steps,
                                 mesh=mesh, update_spec=goals_from_env, record_images=record_images)


def eval_keys(preset: Preset, seed: int) -> jax.Array:
    """One key per evaluation episode (the same for every method, so methods meet the same luck)."""
    return jax.random.split(jax.random.key(2_000_000 + seed), preset.eval_episodes)


def first_episode(traj: mpc.Trajectory) -> mpc.Trajectory:
    """The first robot's episode of a ``[R, T]`` trajectory, cut after its last step (the GIF's)."""
    one = jax.tree.map(lambda x: np.asarray(x[0]), traj)
    steps = int(np.argmax(one.done)) + 1 if np.any(one.done) else len(one.done)
    return jax.tree.map(lambda x: x[:steps], one)


def _largest_divisor(n: int, most: int) -> int:
    return max(d for d in range(1, most + 1) if n % d == 0)


def eval_tasks(env, preset: Preset, seed: int, split: str = "eval"):
    """The evaluation tasks: the env's 'eval' stream (disjoint from every training task), seeded; or its
    'val' stream (tasks of the same kind, disjoint from both) for choosing settings."""
    keys = jax.random.split(jax.random.key(1_000_000 + seed), preset.eval_episodes)
    return jax.jit(jax.vmap(lambda k: env.sample_task(k, split)))(keys)


# --------------------------------------------------------------------------------------------- run


def run(exp: Experiment, presets: Mapping[str, Preset], cfg: RunConfig) -> dict:
    if cfg.preset not in presets:
        raise SystemExit(f"--preset must be one of {sorted(presets)}, got {cfg.preset!r}")
    unknown = sorted(set(cfg.methods) - {m.name for m in exp.methods})
    if unknown:
        raise SystemExit(f"--methods names unknown method(s) {unknown}; this experiment has "
                         f"{[m.name for m in exp.methods]}")
    preset = smoke_preset(presets[cfg.preset]) if cfg.smoke else presets[cfg.preset]
    if preset.onpolicy_steps:
        onpolicy_method(exp, preset)  # a bad onpolicy_reward fails now, not after collecting and training
    if not isinstance(preset.ensemble, int) or preset.ensemble < 1:
        raise SystemExit(f"Preset.ensemble must be an int >= 1 (models in the CAPs ensemble), got {preset.ensemble!r}")
    unknown_cues = sorted(set(preset.ensemble_max_cues) - {c.name for c in exp.cues})
    if unknown_cues or (preset.ensemble_max_cues and preset.ensemble == 1):
        raise SystemExit(f"Preset.ensemble_max_cues must name cues of the CAPs model ({[c.name for c in exp.cues]}) "
                         f"and needs ensemble > 1; got {list(preset.ensemble_max_cues)} with ensemble={preset.ensemble}")
    if preset.ensemble > 1 and preset.onpolicy_steps:
        raise SystemExit("Preset.ensemble > 1 with Preset.onpolicy_steps > 0 is not supported: the on-policy "
                         "stage continues one CAPs model; use ensemble=1 or onpolicy_steps=0")
    env = envs.make(exp.env_name, **dict(exp.env_overrides))
    eval_overrides = {**dict(exp.eval_env), **cfg.eval_env}
    eval_env = evaluation_env(exp, env, eval_overrides)  # checked before any folder is made
    run_dir, data_dir = resolve_paths(exp, cfg)
    timings: dict[str, float] = {}
    report.write_json(run_dir / "config.json", {
        "experiment": exp.name, "run": dataclasses.asdict(cfg), "preset": dataclasses.asdict(preset),
        "env": exp.env_name, "env_overrides": dict(exp.env_overrides), "eval_env": eval_overrides,
        "cues": [c.name for c in exp.cues],
        "methods": [dataclasses.asdict(m) for m in exp.methods], "device": jax.devices()[0].device_kind,
        "data_dir": str(data_dir)})

    t = time.time()
    ds = collect_stage(exp, preset, env, data_dir, cfg)
    train_ids, holdout_ids = ds.split_episodes(HOLDOUT_FRACTION, seed=cfg.train_seed)
    timings["collect_s"] = time.time() - t

    t = time.time()
    labeller_quality = label_stage(exp, preset, env, ds, data_dir, train_ids, holdout_ids, cfg)
    ds = data.Dataset.open(ds.path)  # reopened: sees labels written by this run
    timings["label_s"] = time.time() - t

    model = capsjax.CAPsModel(model_config(exp, preset, env))
    # What the CAPs methods plan with: the model, or the ensemble of ``preset.ensemble`` such models.
    caps_model = (capsjax.Ensemble(model, preset.ensemble, max_cues=preset.ensemble_max_cues)
                  if preset.ensemble > 1 else model)
    label_sources = {cue: "segmenter" for cue in exp.learned_cues}
    needed = sorted({c.source for c in exp.cues} | {"collision", "speed", "heading"})
    sampler = data.make_sampler(ds, horizon=preset.horizon, episodes=train_ids, label_sources=label_sources,
                                signals=tuple(s for s in needed if s not in label_sources), mirror=preset.mirror,
                                history=env.spec.history)
    methods = [m for m in exp.methods if not cfg.methods or m.name in cfg.methods]
    caps_needed = any(m.kind == "caps" for m in methods) or preset.onpolicy_steps
    baseline_kinds = sorted({m.kind for m in methods} - {"caps"})
    # The models that train on the same data train ``cfg.jobs`` at a time (``run_concurrently``): XLA:CPU runs
    # a convolution on one core, so on a 2-core CPU one model's training leaves a core mostly idle.
    jobs = {}
    if caps_needed:
        jobs["caps"] = functools.partial(train_caps, exp, preset, model, sampler, data_dir, cfg)
        for i in range(1, preset.ensemble):
            jobs[f"caps_member{i}"] = functools.partial(train_caps, exp, preset, model, sampler, data_dir, cfg,
                                                        name=f"caps_member{i}", member=i)
    if not preset.onpolicy_steps:  # otherwise the baselines wait for the on-policy data (below)
        jobs.update({kind: functools.partial(train_baseline, exp, preset, kind, model.config, env, sampler, data_dir,
                                             cfg) for kind in baseline_kinds})
    trained = run_concurrently(jobs, cfg.jobs, timings)
    params = {}
    if caps_needed:
        caps_state = trained["caps"]
        params["caps"] = caps_state.params
        if preset.ensemble > 1:
            params["caps"] = caps_model.stack([params["caps"]] + [trained[f"caps_member{i}"].params
                                                                  for i in range(1, preset.ensemble)])
    if preset.onpolicy_steps:
        t = time.time()
        ds_on = onpolicy_stage(exp, preset, env, model, params["caps"], data_dir, cfg)
        if exp.learned_cues:  # the same labeller labels the on-policy frames
            write_labels(exp, ds_on, labellers.load_labeller(data_dir / "segmenter"), data_dir / "segmenter")
            ds_on = data.Dataset.open(ds_on.path)
        on_train, _ = ds_on.split_episodes(HOLDOUT_FRACTION, seed=cfg.train_seed)
        sampler = data.concatenate_samplers(sampler, data.make_sampler(
            ds_on, horizon=preset.horizon, episodes=on_train, label_sources=label_sources,
            signals=tuple(s for s in needed if s not in label_sources), mirror=preset.mirror,
            history=env.spec.history))
        timings["collect_onpolicy_s"] = time.time() - t
        jobs = {"caps_onpolicy": functools.partial(
            train_caps, exp, preset, model, sampler, data_dir, cfg, name="caps_onpolicy", state=caps_state,
            num_steps=preset.train_steps + preset.onpolicy_train_steps)}
        jobs.update({kind: functools.partial(train_baseline, exp, preset, kind, model.config, env, sampler, data_dir,
                                             cfg) for kind in baseline_kinds})
        trained.update(run_concurrently(jobs, cfg.jobs, timings))
        params["caps"] = trained["caps_onpolicy"].params
    agents = {}
    for kind in baseline_kinds:
        agents[kind], params[kind] = trained[kind]

    holdout_loss = holdout_losses(caps_model, params.get("caps"), ds, holdout_ids, preset, label_sources, needed)

    env = eval_env  # from here on: evaluation
    tasks = eval_tasks(env, preset, cfg.seed, cfg.split)
    cem = cem_config(preset, env, preset.horizon)
    poses, per_episode, fpv = {}, {}, {}
    # One policy object per kind: the methods of a kind share one compiled program.
    policies = {kind: mpc.caps_policy(caps_model, cem) if kind == "caps" else
                baselines.baseline_policy(agents[kind], cem_config(preset, env, horizon=1))
                for kind in {m.kind for m in methods}}

    def evaluate_method(method: Method) -> None:
        t = time.time()
        cache = run_dir / "eval" / f"{method.name}.npz"
        key = eval_cache_key(method, preset, data_dir, cfg.split, env, params[method.kind])
        cached = _load_eval(cache, key)
        if cached is not None:
            poses[method.name], per_episode[method.name] = cached
            per_episode[method.name].update(task_metrics(exp, tasks, env, per_episode[method.name]))
            log(exp, f"eval {method.name}: reused {cache}")
            return
        # Every CAPs method keeps its camera frames (the GIF's), so that all share one compiled program.
        traj = jax.device_get(evaluate(exp, preset, env, method, policies[method.kind], params[method.kind],
                                       method_spec(method, caps_model), tasks, cfg.seed,
                                       record_images=method.kind == "caps"))
        if method.kind == "caps":
            fpv[method.name] = first_episode(traj)
        poses[method.name] = np.asarray(traj.pose)
        episodes = {k: np.asarray(v) for k, v in exp.episode_metrics(traj, env).items()}
        _save_eval(cache, key, poses[method.name], episodes)
        per_episode[method.name] = episodes | task_metrics(exp, tasks, env, episodes)
        log(exp, f"eval {method.name}: " + ", ".join(f"{k} {np.nanmean(v):.3f}" for k, v in per_episode[method.name].items())
            + f" ({time.time() - t:.0f} s)")

    # ``cfg.jobs`` evaluations at once, each method a job timed as ``eval_<method>_s``.  The first CAPs reward
    # goes alone among the CAPs rewards: it compiles the program they all share (``policies``), and the others
    # wait for it rather than compile it again; meanwhile the baselines run (their compiles take one core).
    caps_methods = [m for m in methods if m.kind == "caps"]
    first = caps_methods[:1] + [m for m in methods if m.kind != "caps"]
    for stage_methods in (first, caps_methods[1:]):
        run_concurrently({m.name: functools.partial(evaluate_method, m) for m in stage_methods}, cfg.jobs, timings,
                         stage="eval")
    per_episode = {m.name: per_episode[m.name] for m in methods}  # the experiment's order, whichever ended first
    poses = {m.name: poses[m.name] for m in methods}

    metrics = {name: report.summarize(values) for name, values in per_episode.items()}
    verdict = compare(exp, metrics)
    out = {
        "experiment": exp.name, "preset": cfg.preset, "seed": cfg.seed, "split": cfg.split, "train_seed": cfg.train_seed,
        "eval_env": eval_overrides, "metrics": metrics, "paper": exp.paper, "comparison": verdict,
        "labeller": labeller_quality,
        "holdout_loss": holdout_loss, "dataset": {"episodes": ds.num_episodes, "steps": ds.num_steps,
                                                  "train_episodes": len(train_ids), "holdout_episodes": len(holdout_ids)},
        "timings_s": timings, "device": jax.devices()[0].device_kind,
        "per_episode": {m: {k: v.tolist() for k, v in d.items()} for m, d in per_episode.items()},
    }
    report.write_json(run_dir / "metrics.json", out)
    notes = list(exp.notes) + [f"Preset `{cfg.preset}`, {cfg.split} seed {cfg.seed}, {preset.eval_episodes} {cfg.split} episodes of "
                               f"at most {preset.eval_steps} steps; cells: mean [95 % bootstrap CI over episodes]."]
    notes += [f"{m.name}: {m.description}" for m in methods if m.description]
    if eval_overrides:
        notes.append("Evaluated with env fields changed from training's: "
                     + ", ".join(f"{k} = {v:g}" for k, v in sorted(eval_overrides.items())) + ".")
    (run_dir / "table.md").write_text(report.table(metrics, exp.columns, exp.paper, title=f"{exp.name} ({cfg.preset})",
                                                   notes=notes))
    t = time.time()
    caps_method = next((m for m in methods if m.kind == "caps"), None)
    write_figures(exp, preset, env, run_dir, tasks, poses, caps_model, params.get("caps"), caps_method, cem, cfg.seed,
                  cfg.split, fpv=fpv.get(caps_method.name) if caps_method else None)
    timings["figures_s"] = time.time() - t
    report.write_json(run_dir / "metrics.json", dict(out, timings_s=timings))
    print((run_dir / "table.md").read_text())
    log(exp, f"wrote {run_dir}")
    return out


def evaluation_env(exp: Experiment, env, overrides: Mapping[str, float]):
    """The env the methods are evaluated in: the experiment's env with the number fields ``overrides``
    (``Experiment.eval_env`` with ``RunConfig.eval_env`` on top) replaced.  A trained model needs the
    observations and actions it was trained on, so a change to the env's spec is refused (change
    ``Experiment.env_overrides`` and retrain instead), except to the planner's sampling box (``plan_steer_deg``,
    a narrower box than the one the data was collected in)."""
    if not overrides:
        return env
    current = {f.name: getattr(env.config, f.name) for f in dataclasses.fields(env.config)}
    typed = {}
    for name, value in overrides.items():
        if name not in current:
            raise SystemExit(f"--eval-env names unknown config field {name!r} of env {exp.env_name!r}; valid: "
                             f"{', '.join(sorted(current))}")
        have = current[name]
        if isinstance(have, bool) or not isinstance(have, (int, float)):
            raise SystemExit(f"--eval-env field {name!r}: only number fields can be set; this env's {name} is {have!r}")
        if isinstance(have, int):
            if value != int(value):
                raise SystemExit(f"--eval-env field {name!r}: expected an integer, got {value!r}")
            value = int(value)
        typed[name] = value
    try:
        changed = envs.make(exp.env_name, **{**dict(exp.env_overrides), **typed})
    except ValueError as e:  # the config's own checks
        raise SystemExit(f"--eval-env: {e}") from None
    # The plan box is the planner's sampling range (models scale actions by the env's action box): it may change.
    differ = [f.name for f in dataclasses.fields(env.spec) if f.name not in ("plan_low", "plan_high")
              and getattr(env.spec, f.name) != getattr(changed.spec, f.name)]
    if differ:
        raise SystemExit(f"--eval-env {dict(overrides)} changes the env's spec field(s) {differ}: the trained models "
                         "need the observations and actions they were trained on; set such fields in the "
                         "experiment's env_overrides and retrain")
    return changed


def task_metrics(exp: Experiment, tasks, env, per_episode: dict) -> dict:
    if exp.task_metrics is None:
        return {}
    return {k: np.asarray(v) for k, v in exp.task_metrics(tasks, env, per_episode).items()}


def method_spec(method: Method, model) -> RewardSpec:
    return RewardSpec.from_terms(model, goal_speed=method.goal_speed, lane_offset=method.lane_offset,
                                 gated=method.gated, step_seconds=envs.base.CONTROL_DT, **dict(method.weights))


def compare(exp: Experiment, metrics: dict) -> dict:
    """Does each CAPs reward beat every baseline on the primary metric beyond both confidence intervals?"""
    key = exp.primary_metric
    caps = [m.name for m in exp.methods if m.kind == "caps" and m.name in metrics]
    others = [m.name for m in exp.methods if m.kind != "caps" and m.name in metrics]
    return {c: {o: bool(report.separated(metrics[c][key], metrics[o][key])) for o in others} for c in caps}


def holdout_losses(model, params, ds, holdout_ids, preset: Preset, label_sources, needed) -> dict:
    """CAPs' per-cue loss on windows of held-out episodes (never trained on).  For an ensemble: the members'
    mean of each loss, and each member's losses under ``members`` (the loss is defined per model)."""
    if params is None or len(holdout_ids) == 0:
        return {}
    if isinstance(model, capsjax.Ensemble):
        members = [holdout_losses(model.member, model.member_params(params, i), ds, holdout_ids, preset,
                                  label_sources, needed) for i in range(model.size)]
        if any("error" in m for m in members):
            return members[0]
        return dict({k: float(np.mean([m[k] for m in members])) for k in members[0]}, members=members)
    try:
        sampler = data.make_sampler(ds, horizon=preset.horizon, episodes=holdout_ids, label_sources=label_sources,
                                    signals=tuple(s for s in needed if s not in label_sources),
                                    history=model.config.history)
    except ValueError as e:  # e.g. every held-out episode shorter than the horizon
        return {"error": str(e)}
    # Many windows, not one batch: a batch of 256 gave two `medium` training runs held-out collision losses
    # of 0.067 and 0.084, where 10,240 windows gave 0.0845 and 0.0856 (2026-12-07).
    def losses(params_, sampler_, keys):  # buffers and params as arguments, not constants in the program
        return jax.lax.map(lambda k: capsjax.total_loss(model, params_, sampler_.sample(k, HOLDOUT_BATCH))[1], keys)

    per_batch = jax.jit(losses)(params, sampler, jax.random.split(jax.random.key(7), HOLDOUT_BATCHES))
    return {k: float(jnp.mean(v)) for k, v in per_batch.items()}


def write_figures(exp, preset, env, run_dir: Path, tasks, poses, model, caps_params, caps_method, cem, seed, split="eval",
                  fpv: mpc.Trajectory | None = None):
    """``trajectories.png`` and ``fpv.gif``: the GIF shows ``fpv`` (``first_episode`` of the CAPs method's
    evaluation, with its camera frames), or, when that evaluation was reused from the cache, the same episode
    driven again."""
    panels = []
    reset = jax.jit(env.reset)
    for i in range(min(3, preset.eval_episodes)):
        task = jax.tree.map(lambda x: x[i], tasks)
        first = reset(jax.random.key(0), task)
        drives = {name: pose[i] for name, pose in poses.items()}
        panels.append({"scene": first.physics.scene, "task": task, "drives": drives,
                       "first_pose": np.asarray(first.info["pose"]), "title": f"{split} task {i} (seed {seed})"})
    train_task = env.sample_task(jax.random.key(0), "train")
    panels.append({"scene": reset(jax.random.key(0), train_task).physics.scene, "task": train_task,
                   "title": "a training task (data collection)"})
    report.plot_trajectories(run_dir / "trajectories.png", panels, title=f"{exp.name}: bird's-eye view")
    if caps_method is not None and caps_params is not None:
        if fpv is None:
            policy = mpc.caps_policy(model, cem)
            one = lambda task, key: mpc.run_episode(env, policy, caps_params, method_spec(caps_method, model), task, key,
                                                    num_steps=preset.eval_steps, update_spec=goals_from_env,
                                                    record_images=True)
            traj = jax.jit(jax.vmap(one))(jax.tree.map(lambda x: x[:1], tasks), eval_keys(preset, seed)[:1])
            fpv = first_episode(jax.device_get(traj))
        report.write_fpv_gif(run_dir / "fpv.gif", fpv.image, fpv.preds, fpv.signals, title=caps_method.name)


def final(traj, name: str) -> np.ndarray:
    """A running metric's value at the end of each episode (states freeze once done)."""
    return np.asarray(traj.metrics[name])[:, -1]


def episode_mean(traj, signal: str) -> np.ndarray:
    """Mean of a signal over each episode's steps up to (and including) the step that ended it."""
    values, done = np.asarray(traj.signals[signal]), np.asarray(traj.done)
    active = np.concatenate([np.ones_like(done[:, :1]), ~done[:, :-1]], axis=1)
    return (values * active).sum(1) / np.maximum(active.sum(1), 1)


# Preset fields added after evaluations were stored, with the value they implicitly had: left out of the
# cache key at that value, so the stored evaluations stay valid.
_PRESET_ADDED_LATER = {"ensemble": 1, "ensemble_max_cues": ()}


def eval_cache_key(method: Method, preset: Preset, data_dir: Path, split: str, env, params) -> str:
    """What a stored evaluation depends on: the method, the preset, the data folder, the split, the env's
    config and the trained params themselves (a digest of their bytes), so a retrained model or a changed
    world is evaluated again rather than read back.  Code changes are not in it: evaluate into a new
    ``--out`` after changing the planner or the env's code.  The env's observation ``history`` is left out:
    a model of another history has other parameter shapes, so the params digest already tells them apart,
    and evaluations stored before the field existed stay valid (so do those stored before any later-added env
    field, at its old implicit value: ``collect.comparable_settings``)."""
    env_config = collect.comparable_settings(dataclasses.asdict(env.config))
    preset_settings = {k: v for k, v in dataclasses.asdict(preset).items()
                       if not (k in _PRESET_ADDED_LATER and v == _PRESET_ADDED_LATER[k])}
    return json.dumps({"method": dataclasses.asdict(method), "preset": preset_settings,
                       "data_dir": str(data_dir), "env": env_config,
                       "params_sha256": params_digest(params), "split": split},
                      sort_keys=True, default=str)


def params_digest(params) -> str:
    """sha256 of a params pytree's bytes (what a cached evaluation or on-policy dataset was made by)."""
    digest = hashlib.sha256()
    for leaf in jax.tree.leaves(jax.device_get(params)):
        digest.update(np.ascontiguousarray(leaf).tobytes())
    return digest.hexdigest()


def _save_eval(path: Path, key: str, pose: np.ndarray, per_episode: dict) -> None:
    """One method's evaluation (poses and per-episode metrics), keyed by everything that produced it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, key=np.asarray(key), pose=pose, **{f"metric/{k}": v for k, v in per_episode.items()})
    tmp.replace(path)


def _load_eval(path: Path, key: str):
    if not path.exists():
        return None
    with np.load(path) as f:
        if str(f["key"]) != key:
            return None  # another method definition or preset: evaluate again
        return f["pose"], {k.split("/", 1)[1]: f[k] for k in f.files if k.startswith("metric/")}
