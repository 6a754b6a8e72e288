"""What an experiment run writes: metrics with confidence intervals, the paper-vs-ours table, the
bird's-eye trajectory figure and a first-person GIF with the predicted cues beside the camera image.

Pure NumPy/matplotlib on host arrays; nothing here runs under jit.
"""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

CI_LEVEL = 0.95
BOOTSTRAP_RESAMPLES = 2000


def _group_labels(groups, size: int, what: str) -> np.ndarray | None:
    if groups is None:
        return None
    labels = np.asarray(groups).reshape(-1)
    if labels.size != size:
        raise ValueError(f"{what}: field 'groups' has {labels.size} labels for {size} values; expected one per value")
    return labels


def _two_stage_weights(labels: np.ndarray, resamples: int, rng: np.random.Generator) -> np.ndarray:
    """``f64[resamples, n]``: how often each value enters each resample of a two-stage bootstrap -- draw as many
    groups as there are, with replacement, then within each drawn group as many of its values as it holds."""
    names = np.unique(labels)
    members = [np.flatnonzero(labels == name) for name in names]
    weights = np.zeros((resamples, labels.size))
    drawn = rng.integers(0, len(members), size=(resamples, len(members)))
    for slot in range(len(members)):
        for group, member in enumerate(members):
            rows = np.flatnonzero(drawn[:, slot] == group)
            picks = member[rng.integers(0, member.size, size=(rows.size, member.size))]
            np.add.at(weights, (rows[:, None], picks), 1.0)
    return weights


def _several(labels: np.ndarray | None) -> bool:
    return labels is not None and np.unique(labels).size >= 2


def mean_ci(values, *, groups=None, level: float = CI_LEVEL, resamples: int = BOOTSTRAP_RESAMPLES,
            seed: int = 0) -> dict:
    """Mean of per-episode ``values`` with a percentile-bootstrap confidence interval over episodes.

    The bootstrap (rather than a normal approximation) because most of our metrics are rates of a few
    dozen 0/1 outcomes, often at 0 or 1, where the normal interval is meaningless.

    ``groups`` (one label per value, e.g. the training seed of the model that drove each episode) makes it a
    two-stage bootstrap: resample the groups, then the episodes within each drawn group.  Episodes of one
    trained model share that model's luck, so an interval over episodes alone leaves out how far a retrained
    model moves; with two or more groups this one includes it, and ``groups`` in the result holds each group's
    mean.  With few groups (three training seeds, say) the interval is itself rough: read it beside those.
    """
    x = np.asarray(values, np.float64).reshape(-1)
    labels = _group_labels(groups, x.size, "mean_ci")
    keep = np.isfinite(x)
    x = x[keep]
    labels = None if labels is None else labels[keep]
    if x.size == 0:
        return {"mean": float("nan"), "ci_low": float("nan"), "ci_high": float("nan"), "std": float("nan"), "n": 0}
    rng = np.random.default_rng(seed)
    if _several(labels):
        weights = _two_stage_weights(labels, resamples, rng)
        means = weights @ x / weights.sum(1)
    else:
        means = x[rng.integers(0, x.size, size=(resamples, x.size))].mean(1)
    alpha = (1 - level) / 2
    out = {
        "mean": float(x.mean()),
        "ci_low": float(np.quantile(means, alpha)),
        "ci_high": float(np.quantile(means, 1 - alpha)),
        "std": float(x.std()),
        "n": int(x.size),
    }
    if _several(labels):
        out["groups"] = {str(name): float(x[labels == name].mean()) for name in np.unique(labels)}
    return out


def relative_change_ci(a, b, *, groups=None, level: float = CI_LEVEL, resamples: int = BOOTSTRAP_RESAMPLES,
                       seed: int = 0) -> dict:
    """``mean(a) / mean(b) - 1`` for paired per-episode values, with a bootstrap interval that resamples the
    pairs together (e.g. the door share of one reward over another's, on the same loops); ``groups`` as in
    ``mean_ci``."""
    a = np.asarray(a, np.float64).reshape(-1)
    b = np.asarray(b, np.float64).reshape(-1)
    if a.shape != b.shape:
        raise ValueError(f"relative_change_ci: expected paired values, got {a.size} and {b.size}")
    labels = _group_labels(groups, a.size, "relative_change_ci")
    keep = np.isfinite(a) & np.isfinite(b)
    a, b = a[keep], b[keep]
    labels = None if labels is None else labels[keep]
    if a.size == 0 or b.mean() == 0:
        return {"mean": float("nan"), "ci_low": float("nan"), "ci_high": float("nan"), "n": int(a.size)}
    rng = np.random.default_rng(seed)
    if _several(labels):
        weights = _two_stage_weights(labels, resamples, rng)
        resampled_a, base = weights @ a / weights.sum(1), weights @ b / weights.sum(1)
    else:
        idx = rng.integers(0, a.size, size=(resamples, a.size))
        resampled_a, base = a[idx].mean(1), b[idx].mean(1)
    # A resample whose base mean is 0 has no relative change: it is left out rather than counted as infinite.
    ratios = np.where(base != 0, resampled_a / np.where(base != 0, base, 1.0) - 1, np.nan)
    alpha = (1 - level) / 2
    return {"mean": float(a.mean() / b.mean() - 1), "ci_low": float(np.nanquantile(ratios, alpha)),
            "ci_high": float(np.nanquantile(ratios, 1 - alpha)), "n": int(a.size)}


def summarize(per_episode: Mapping[str, np.ndarray], groups=None) -> dict:
    """``{metric: mean_ci(values, groups=groups)}`` for per-episode metric arrays."""
    return {name: mean_ci(values, groups=groups) for name, values in per_episode.items()}


def separated(a: dict, b: dict, higher_is_better: bool = True) -> bool:
    """True when ``a`` beats ``b`` beyond both confidence intervals (a's interval clear of b's)."""
    if higher_is_better:
        return a["ci_low"] > b["ci_high"]
    return a["ci_high"] < b["ci_low"]


def write_json(path: Path, obj) -> None:
    """Strict JSON (a NaN or infinity, e.g. a metric with no episode to average, is written as null)."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(_strict(obj), indent=2, default=_json_default, allow_nan=False))
    tmp.replace(path)  # atomic: an interrupted run never leaves half a file


def _strict(x):
    if dataclasses.is_dataclass(x) and not isinstance(x, type):  # e.g. a camera given as an env override
        x = dataclasses.asdict(x)
    if isinstance(x, np.ndarray):
        x = x.tolist()
    if isinstance(x, Mapping):
        return {k: _strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_strict(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    return x


def _json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    return str(x)


def format_value(stat: dict | None, kind: str) -> str:
    """``kind``: 'rate' (shown in %), 'number' (2 decimals) or 'pct' (already a percentage)."""
    if stat is None:
        return "-"
    m, lo, hi = stat["mean"], stat["ci_low"], stat["ci_high"]
    if not np.isfinite(m):
        return "-"
    if kind == "rate":
        return f"{100 * m:.0f} % [{100 * lo:.0f}, {100 * hi:.0f}]"
    if kind == "pct":
        return f"{m:.1f} [{lo:.1f}, {hi:.1f}]"
    return f"{m:.2f} [{lo:.2f}, {hi:.2f}]"


def table(
    metrics: Mapping[str, Mapping[str, dict]],
    columns: Sequence[tuple[str, str, str]],
    paper: Mapping[str, Mapping[str, float]] | None = None,
    *,
    title: str = "",
    notes: Sequence[str] = (),
) -> str:
    """A markdown table, one row per method with the paper's numbers beside ours.

    ``columns``: (metric key, header, kind) with kind as in ``format_value``.  ``paper[method][metric]``
    holds the paper's value in the same units as ours (rates in [0, 1]).  Cells show the mean and the
    95 % bootstrap interval over evaluation episodes.
    """
    header = ["method"] + [h for _, h, _ in columns]
    lines = [f"## {title}\n" if title else "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for method, stats in metrics.items():
        cells = [f"{method} (ours)"] + [format_value(stats.get(key), kind) for key, _, kind in columns]
        lines.append("| " + " | ".join(cells) + " |")
        if paper and method in paper:
            row = paper[method]
            cells = [f"{method} (paper)"]
            for key, _, kind in columns:
                v = row.get(key)
                cells.append("-" if v is None else (f"{100 * v:.0f} %" if kind == "rate" else f"{v:.2f}"))
            lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    lines += [f"- {n}" for n in notes]
    return "\n".join(line for line in lines if line is not None) + "\n"


def plot_trajectories(path: Path, panels: Sequence[dict], *, title: str = "") -> None:
    """One bird's-eye panel per entry of ``panels``: ``{'scene', 'task', 'drives': {label: poses},
    'title'}``, drawn with ``envs.show.draw_scene`` (the same drawing as the scene pictures)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from envs.show import draw_scene

    n = len(panels)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.5 * cols, 5.5 * rows), squeeze=False)
    for ax, panel in zip(axes.reshape(-1), panels):
        draw_scene(ax, panel["scene"], panel["task"], panel.get("drives"), panel.get("first_pose"))
        ax.set_title(panel.get("title", ""), fontsize=9)
    for ax in axes.reshape(-1)[n:]:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def _padded(lo: float, hi: float, fraction: float) -> tuple[float, float]:
    """Axis limits ``fraction`` of the range beyond ``lo`` and ``hi`` (at least a small width when they are equal)."""
    pad = fraction * max(hi - lo, 1e-3)
    return lo - pad, hi + pad


def write_fpv_gif(path: Path, images: np.ndarray, preds: Mapping[str, np.ndarray], signals: Mapping[str, np.ndarray],
                  *, fps: int = 4, title: str = "") -> None:
    """A first-person GIF: the camera frame of each step beside the chosen plan's predicted cues over the
    horizon (lines) and the true value at each step (dots).

    ``images`` u8[T, h, w, c] (the frame each decision saw); ``preds[name]`` f32[T, H] (angle cues
    f32[T, H, 2] are shown as angles); ``signals[name]`` f32[T], the truth after each step.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    images = np.asarray(images)
    shown = {}
    for name, p in preds.items():
        p = np.asarray(p)
        shown[name] = np.arctan2(p[..., 1], p[..., 0]) if p.ndim == 3 else p
    names = list(shown)
    fig, axes = plt.subplots(1, 1 + len(names), figsize=(3.2 * (1 + len(names)), 3.0))
    axes = np.atleast_1d(axes)
    gray = images.shape[-1] == 1
    frames = images[..., 0] if gray else images

    # Blitting: the axes, ticks and legends are drawn once and each frame redraws only the artists that move.
    # matplotlib's animation writers redraw the whole figure per frame, mostly the axes' ticks: a 120-step
    # forest episode's figures took 47 s that way against 16 s now.
    camera = axes[0].imshow(frames[0], cmap="gray" if gray else None, vmin=0, vmax=255, animated=True)
    caption = axes[0].set_title("", fontsize=8, animated=True)
    axes[0].axis("off")
    curves, moving = [], [camera, caption]
    for ax, name in zip(axes[1:], names):
        horizon = shown[name].shape[1]
        predicted, = ax.plot(np.arange(1, horizon + 1), shown[name][0], "-", color="tab:blue", label="predicted",
                             animated=True)
        true, = ax.plot([], [], "o", ms=3, color="tab:orange", label="true", animated=True)
        ax.set_xlim(*_padded(1, horizon, 0.05))
        ax.set_ylim(*_padded(np.nanmin(shown[name]), np.nanmax(shown[name]), 0.1))
        ax.set_title(name, fontsize=8)
        ax.set_xlabel("steps ahead", fontsize=7)
        legend = ax.legend(fontsize=6, loc="upper right")
        legend.set_animated(True)  # drawn after the lines each frame, so it stays on top of them
        truth = np.asarray(signals.get(name, np.full(len(images), np.nan)))
        curves.append((shown[name], truth, predicted, true))
        moving += [predicted, true, legend]

    fig.tight_layout()  # room for the axis labels
    canvas = fig.canvas
    canvas.draw()  # everything but the animated artists
    background = canvas.copy_from_bbox(fig.bbox)
    gif_frames = []
    for t in range(len(images)):
        camera.set_data(frames[t])
        caption.set_text(f"{title} step {t}")
        for pred, truth, predicted, true in curves:
            predicted.set_ydata(pred[t])
            future = truth[t:t + pred.shape[1]]  # truth[t] is the state after step t: the first predicted step
            true.set_data(np.arange(1, len(future) + 1), future)
        canvas.restore_region(background)
        for artist in moving:
            fig.draw_artist(artist)
        # RGB, not RGBA: the figure is opaque, and Pillow maps RGB to the GIF's palette with less banding.
        gif_frames.append(Image.fromarray(np.array(canvas.buffer_rgba())[..., :3]))
    gif_frames[0].save(path, save_all=True, append_images=gif_frames[1:], duration=int(1000 / fps), loop=0)
    plt.close(fig)
