"""``python -m experiments.pool``: one table over several evaluation seeds, and paired differences between runs.

Each run of an experiment evaluates one seed (32 forest paths, 15 city goals, 8 halls loops), and a single
seed's interval is wide.  This pools the per-episode results that every run stores in ``metrics.json``:

    python -m experiments.pool results/forest/small_seed0 results/forest/small_seed1 --out results/forest/small_pooled

writes ``metrics.json`` and ``table.md`` over all their episodes (intervals recomputed over the pooled
episodes, the baselines comparison redone).  With ``--against`` it compares two variants evaluated on the same
tasks (same experiment, split and seeds, and where the runs stored their poses the same start in every
episode; the variants may differ in any setting: a planner, reward or model memory chosen on 'val', say):

    python -m experiments.pool results/forest/a_val_seed0 results/forest/a_val_seed1 \\
        --against results/forest/b_val_seed0 results/forest/b_val_seed1

and prints, per method and metric, the mean of the per-episode difference (runs minus ``--against``) with a
bootstrap interval over the paired episodes.  Pairing by task removes the spread between tasks, so the
interval is much narrower than the gap between two unpaired intervals.  Nothing is re-evaluated.
"""
from __future__ import annotations

import dataclasses
import importlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro

from experiments import pipeline, report

# Fields that must agree for episodes of several runs to be pooled into one sample of one setting.  The
# preset is compared by its settings (config.json) where both runs stored them, so that a variant evaluated
# under a scratch name pools with the same settings run under the preset's own name.  The training seed may
# differ: runs of several training seeds pool into one sample of the setting, with intervals that resample
# the training runs too (``report.mean_ci``'s groups).
POOL_KEYS = ("experiment", "split")


@dataclasses.dataclass(frozen=True)
class PoolConfig:
    runs: Annotated[tuple[Path, ...], tyro.conf.Positional]
    """Run folders (each with the ``metrics.json`` an experiment writes) of one preset, one split and
    distinct evaluation seeds."""
    against: tuple[Path, ...] = ()
    """Run folders of another variant on the same tasks (the same experiment, split and seeds): report the
    paired per-episode differences of ``runs`` minus these."""
    pair: tuple[str, str] | None = None
    """Two methods of the runs (e.g. ``caps_heading_door_x4 caps_heading``): per metric, their paired
    per-episode difference (first minus second) and the relative change of the mean (first / second - 1),
    both over the pooled episodes, which are the same tasks for every method of a run."""
    out: Path | None = None
    """Write the pooled ``metrics.json`` and ``table.md`` here (default: only print the table)."""


@dataclasses.dataclass(frozen=True)
class Run:
    path: Path
    metrics: dict  # the run's metrics.json
    env_overrides: str | None  # from config.json, when the run wrote one
    eval_env: str | None  # the run's evaluation-only env fields (config.json's 'eval_env'), when it wrote them
    preset_settings: dict | None  # the Preset's fields, from config.json

    @property
    def seed(self) -> int:
        return int(self.metrics["seed"])

    @property
    def train_seed(self) -> int:
        return int(self.metrics["train_seed"])

    @property
    def key(self) -> tuple[int, int]:
        """(training seed, evaluation seed): what one run contributes, and what pairs two variants' runs."""
        return self.train_seed, self.seed


def load_run(path: Path) -> Run:
    """A run folder's stored results, with a clear error when it is not one."""
    path = Path(path)
    file = path / "metrics.json"
    if not file.is_file():
        raise FileNotFoundError(f"run folder {path}: no metrics.json (expected the folder an experiment run wrote)")
    metrics = json.loads(file.read_text())
    missing = [k for k in (*POOL_KEYS, "train_seed", "preset", "seed", "per_episode") if k not in metrics]
    if missing:
        raise ValueError(f"{file}: missing field(s) {missing}; runs written before per-episode results were "
                         "stored cannot be pooled")
    config = path / "config.json"
    stored = json.loads(config.read_text()) if config.is_file() else {}
    overrides = stored.get("env_overrides")
    settings = stored.get("preset")
    eval_env = stored.get("eval_env", {} if stored else None)  # written since the option exists; absent: none
    return Run(path, metrics, None if overrides is None else json.dumps(overrides, sort_keys=True),
               None if eval_env is None else json.dumps(eval_env, sort_keys=True),
               settings if isinstance(settings, dict) else None)


def _require_same(runs: Sequence[Run], keys: Sequence[str], what: str, *, env: bool = True) -> None:
    for key in keys:
        values = {json.dumps(r.metrics[key]) for r in runs}
        if len(values) > 1:
            detail = ", ".join(f"{r.path}: {r.metrics[key]!r}" for r in runs)
            raise ValueError(f"{what}: field '{key}' differs between runs ({detail}); expected one value")
    if env:
        _require_same_env(runs, what)


def _require_same_env(runs: Sequence[Run], what: str) -> None:
    for field in ("env_overrides", "eval_env"):
        values = {getattr(r, field) for r in runs if getattr(r, field) is not None}
        if len(values) > 1:
            raise ValueError(f"{what}: field '{field}' in config.json differs between runs ({sorted(values)}); "
                             "they were not evaluated in the same env")


def _require_same_preset(runs: Sequence[Run], what: str) -> None:
    """One preset: the same settings where the runs stored them, else the same name.  A field that only one
    run has was added to ``Preset`` later, with a default that keeps the older runs' behaviour."""
    first = runs[0]
    for run in runs[1:]:
        if first.preset_settings is not None and run.preset_settings is not None:
            differ = sorted(k for k in first.preset_settings.keys() & run.preset_settings.keys()
                            if first.preset_settings[k] != run.preset_settings[k])
            if differ:
                raise ValueError(f"{what}: field 'preset' settings {differ} differ between {first.path} and {run.path}; "
                                 "expected runs of one preset")
        elif first.metrics["preset"] != run.metrics["preset"]:
            raise ValueError(f"{what}: field 'preset' differs ({first.path}: {first.metrics['preset']!r}, "
                             f"{run.path}: {run.metrics['preset']!r}); expected one preset")


def _require_distinct_seeds(runs: Sequence[Run], what: str) -> None:
    keys = [r.key for r in runs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"{what}: field 'seed' repeats for one training seed ((train_seed, seed): {keys}); pooling "
                         "one evaluation twice would count its episodes twice -- expected distinct evaluation seeds "
                         "per training seed")


def _common_methods(runs: Sequence[Run]) -> list[str]:
    """Methods evaluated in every run, in the first run's order."""
    return [m for m in runs[0].metrics["per_episode"] if all(m in r.metrics["per_episode"] for r in runs)]


def _ordered(runs: Sequence[Run]) -> list[Run]:
    return sorted(runs, key=lambda r: r.key)


def _episode_count(run: Run) -> int:
    """Episodes in one run (every method of a run drives the same tasks, every metric has one value each)."""
    first_method = next(iter(run.metrics["per_episode"].values()))
    return len(next(iter(first_method.values())))


def _training_groups(runs: Sequence[Run]) -> np.ndarray | None:
    """Each pooled episode's training seed (in ``pooled_episodes``' order) where the runs hold several, else
    None: then every episode comes from one trained model and the intervals resample episodes only."""
    runs = _ordered(runs)
    if len({r.train_seed for r in runs}) < 2:
        return None
    return np.concatenate([np.full(_episode_count(r), r.train_seed) for r in runs])


def pooled_episodes(runs: Sequence[Run]) -> dict[str, dict[str, np.ndarray]]:
    """``{method: {metric: values}}`` over the episodes of all ``runs``, ordered by (training seed, seed)."""
    runs = _ordered(runs)
    out = {}
    for method in _common_methods(runs):
        names = [k for k in runs[0].metrics["per_episode"][method]
                 if all(k in r.metrics["per_episode"][method] for r in runs)]
        out[method] = {k: np.concatenate([np.asarray(r.metrics["per_episode"][method][k], np.float64) for r in runs])
                       for k in names}
    return out


def pool(runs: Sequence[Run]) -> dict:
    """The runs' episodes as one result: what ``metrics.json`` holds for a single run, over every seed."""
    if not runs:
        raise ValueError("runs: expected at least one run folder")
    _require_same(runs, POOL_KEYS, "pooling")
    _require_same_preset(runs, "pooling")
    _require_distinct_seeds(runs, "pooling")
    per_episode = pooled_episodes(runs)
    metrics = {m: report.summarize(v, groups=_training_groups(runs)) for m, v in per_episode.items()}
    first = runs[0].metrics
    exp = experiment(first["experiment"])
    return {
        **{k: first[k] for k in POOL_KEYS},
        "preset": first["preset"],
        "seeds": sorted({r.seed for r in runs}),
        "train_seeds": sorted({r.train_seed for r in runs}),
        "runs": [str(r.path) for r in _ordered(runs)],
        "metrics": metrics,
        "paper": first.get("paper", {}),
        "comparison": pipeline.compare(exp, metrics),
        "per_episode": {m: {k: v.tolist() for k, v in d.items()} for m, d in per_episode.items()},
    }


# The stored trajectories begin after the first control step, which moves the car at most ~0.75 m (3 m/s for
# 0.25 s): episodes of one task start within this distance of each other, those of different tasks metres apart.
SAME_START_M = 1.0


def start_positions(run: Run) -> np.ndarray | None:
    """Every episode's first recorded position ``f32[E, 2]``, from the run's stored evaluations
    (``eval/<method>.npz``; every method of a run drives the same tasks), or None where it stored none."""
    for file in sorted((run.path / "eval").glob("*.npz")):
        with np.load(file) as stored:
            if "pose" in stored.files:
                return np.asarray(stored["pose"][:, 0, :2])
    return None


def _require_same_tasks(runs: Sequence[Run], against: Sequence[Run]) -> None:
    """Two variants may differ in any setting, an env setting that leaves the tasks alone included (the
    observation's history, say), as long as they ran the same tasks: each episode must start at the same place
    in both.  Where a run stored no poses, both must have the same env overrides instead."""
    for a, b in zip(_ordered(runs), _ordered(against)):
        pos_a, pos_b = start_positions(a), start_positions(b)
        if pos_a is None or pos_b is None:
            _require_same_env([a, b], "paired comparison")
        elif pos_a.shape != pos_b.shape or np.max(np.linalg.norm(pos_a - pos_b, axis=-1)) > SAME_START_M:
            raise ValueError(f"against: the episodes of {b.path} do not start where those of {a.path} do (seed {a.seed}); "
                             "expected the same tasks (an env setting that changes the tasks differs between them?)")


def paired_differences(runs: Sequence[Run], against: Sequence[Run]) -> dict[str, dict[str, dict]]:
    """``{method: {metric: mean_ci(runs - against)}}`` over episodes paired by (training seed, seed, episode
    index): each variant's model of one training seed drives the same tasks as the other's of that seed."""
    for group, what in ((runs, "runs"), (against, "against")):
        if not group:
            raise ValueError(f"{what}: expected at least one run folder")
        _require_same_preset(group, what)
        _require_distinct_seeds(group, what)
        _require_same_env(group, what)
    _require_same([*runs, *against], ("experiment", "split"), "paired comparison", env=False)  # tasks: below
    keys_a, keys_b = sorted(r.key for r in runs), sorted(r.key for r in against)
    if keys_a != keys_b:
        raise ValueError(f"against: fields 'train_seed' and 'seed' must match the runs' (train_seed, seed) {keys_a} "
                         f"(the same tasks for models of the same training seeds), got {keys_b}")
    _require_same_tasks(runs, against)
    a, b = pooled_episodes(runs), pooled_episodes(against)
    groups = _training_groups(runs)
    out = {}
    for method in (m for m in a if m in b):
        out[method] = {}
        for metric in (k for k in a[method] if k in b[method]):
            if a[method][metric].shape != b[method][metric].shape:
                raise ValueError(f"against: method '{method}' metric '{metric}' has {b[method][metric].size} episodes, "
                                 f"the runs {a[method][metric].size}; expected the same episodes on the same tasks")
            out[method][metric] = report.mean_ci(a[method][metric] - b[method][metric], groups=groups)
    return out


def method_pair(pooled: dict, first: str, second: str, groups=None) -> dict[str, dict[str, dict]]:
    """``{metric: {"difference": mean_ci(first - second), "relative": relative_change_ci(first, second)}}``;
    ``groups``: each episode's training seed where the pool holds several (``report.mean_ci``)."""
    episodes = pooled["per_episode"]
    for name in (first, second):
        if name not in episodes:
            raise ValueError(f"pair: method {name!r} was not evaluated in every run; expected one of {sorted(episodes)}")
    a, b = episodes[first], episodes[second]
    return {k: {"difference": report.mean_ci(np.subtract(a[k], b[k]), groups=groups),
                "relative": report.relative_change_ci(a[k], b[k], groups=groups)}
            for k in a if k in b}


def experiment(name: str):
    """The ``Experiment`` of ``experiments/<name>.py`` (its table columns, paper numbers, comparison rule)."""
    try:
        module = importlib.import_module(f"experiments.{name}")
    except ModuleNotFoundError as err:
        raise ValueError(f"field 'experiment': unknown experiment {name!r}; expected forest, city or indoor") from err
    return module.EXPERIMENT


def difference_table(diffs: dict[str, dict[str, dict]], columns) -> str:
    header = ["method"] + [h for _, h, _ in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for method, stats in diffs.items():
        cells = [method]
        for key, _, kind in columns:
            s = stats.get(key)
            if s is None:
                cells.append("-")
            else:
                scale, digits, unit = (100, 0, " pts") if kind == "rate" else (1, 2, "")
                cell = f"{_signed(scale * s['mean'], digits)}{unit}"
                if "ci_low" in s:
                    cell += f" [{_signed(scale * s['ci_low'], digits)}, {_signed(scale * s['ci_high'], digits)}]"
                cells.append(cell)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _by_group(diffs: dict[str, dict[str, dict]]) -> dict[str, dict[str, dict]]:
    """``{"<method>, training seed <g>": {metric: {"mean": m}}}`` from the group means that
    ``report.mean_ci`` returns, for a table row per training seed (means only)."""
    rows: dict[str, dict[str, dict]] = {}
    for method, stats in diffs.items():
        for metric, stat in stats.items():
            for group, mean in stat.get("groups", {}).items():
                rows.setdefault(f"{method}, training seed {group}", {})[metric] = {"mean": mean}
    return rows


def _signed(x: float, digits: int) -> str:
    x = round(x, digits) + 0.0  # + 0.0 turns a rounded -0.0 into 0.0, so it prints as +0
    return f"{x:+.{digits}f}"


def main(cfg: PoolConfig) -> dict:
    runs = [load_run(p) for p in cfg.runs]
    pooled = pool(runs)
    exp = experiment(pooled["experiment"])
    seeds = ", ".join(map(str, pooled["seeds"]))
    n = {m: next(iter(s.values()))["n"] for m, s in pooled["metrics"].items()}
    groups = _training_groups(runs)
    if groups is None:
        over = "the pooled episodes"
    else:
        over = "the training runs, then the episodes of each drawn run"
        seeds += f"; training seeds {', '.join(map(str, pooled['train_seeds']))}"
    notes = [f"Preset `{pooled['preset']}`, {pooled['split']} seeds {seeds} pooled ({max(n.values(), default=0)} "
             f"episodes per method); cells: mean [95 % bootstrap CI over {over}]."]
    text = report.table(pooled["metrics"], exp.columns, pooled["paper"],
                        title=f"{exp.name} ({pooled['preset']}, {pooled['split']} seeds {seeds})", notes=notes)
    if cfg.against:
        pooled["against"] = [str(p) for p in cfg.against]
        pooled["paired_difference"] = paired_differences(runs, [load_run(p) for p in cfg.against])
        text += (f"\nPaired differences per episode, runs minus --against ({', '.join(map(str, cfg.against))}), "
                 f"mean [95 % bootstrap CI over {'the paired episodes' if groups is None else over}]:\n\n"
                 + difference_table(pooled["paired_difference"], exp.columns))
        if groups is not None:
            text += "\nThe same, each training seed's mean alone:\n\n" + difference_table(
                _by_group(pooled["paired_difference"]), exp.columns)
    if cfg.pair is not None:
        first, second = cfg.pair
        pooled["pair"] = {"methods": [first, second], "metrics": method_pair(pooled, first, second, groups)}
        text += (f"\n{first} against {second} on the same episodes, mean [95 % bootstrap CI over "
                 f"{'the paired episodes' if groups is None else over}]:\n\n")
        text += "| metric | difference | relative change of the mean |\n|---|---|---|\n"
        for metric, stats in pooled["pair"]["metrics"].items():
            d, r = stats["difference"], stats["relative"]
            text += (f"| {metric} | {_signed(d['mean'], 3)} [{_signed(d['ci_low'], 3)}, {_signed(d['ci_high'], 3)}] | "
                     f"{_signed(100 * r['mean'], 0)} % [{_signed(100 * r['ci_low'], 0)}, {_signed(100 * r['ci_high'], 0)}] |\n")
    if cfg.out is not None:
        cfg.out.mkdir(parents=True, exist_ok=True)
        report.write_json(cfg.out / "metrics.json", pooled)
        (cfg.out / "table.md").write_text(text)
    print(text)
    return pooled


if __name__ == "__main__":
    main(tyro.cli(PoolConfig, description=__doc__.split("\n\n")[0]))
