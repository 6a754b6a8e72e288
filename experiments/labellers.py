"""``python -m experiments.labellers``: train the learned lane / door labellers on <= 1 % of the frames
and measure them against the oracle on held-out episodes.

Frames.  For each scene, robots drive the MJX env with uniformly random actions from the planning box
(vmap over robots, ``lax.scan`` over steps, auto-reset after a crash or ``episode_length`` steps):
``--train-robots x --train-steps-per-robot`` steps on *training* tasks stand for the collected dataset
(25,600 steps by default), and ``--train-frames`` of them (256 = 1.0 %; the paper's labelled fraction
was 0.2 %) are drawn at random to be the hand-labelled frames the segmenter trains on (class-balanced
loss, then the training maps' class prior stored for calibrated predictions: ``--prior-correction``).
Only the poses are kept while driving; the drawn frames are rendered afterwards with their true class
maps (the camera is exact, so this is the frame the robot saw).  Evaluation frames come from *held-out episodes*
on the 'eval' split: disjoint layout seeds (and, in the halls, the other driving direction).

Outputs (``--out``/``<scene>/``): the labeller (``config.json`` + orbax ``params/``, reloadable with
``capsjax.labellers.load_labeller`` to relabel a dataset), ``metrics.json``, ``masks.png`` (a few
held-out frames: image, true map, predicted map, true and predicted lane / door masks).  JSON lines
(``experiments.bench.emit``): ``labeller.lane_iou``, ``labeller.door_iou``,
``labeller.lane_seen_accuracy``, ``labeller.lane_diff_mae``, ``labeller.door_frac_mae`` and more,
each with the scene, the frame counts and the device in the context.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import tyro
from tqdm import tqdm

import envs
from capsjax import labellers
from envs import base
from envs.camera import render
from envs.scene import DOOR, LANE_LINE, ROAD
from experiments import runtime
from experiments.bench import emit

MAX_LABELLED_FRACTION = 0.01  # the bound: train on at most 1 % of the dataset's frames


@dataclasses.dataclass(frozen=True)
class Config:
    """Settings of the labeller experiment."""

    scene: str = "both"
    """'city' (lane cues), 'indoor' (door_frac) or 'both'."""
    train_frames: int = 256
    """Labelled frames the segmenter trains on (must be <= 1 % of the dataset's steps)."""
    steps: int | None = None
    """Gradient steps (default per scene: 600 city, 400 indoor)."""
    seed: int = 0
    out: Path = Path("results/labellers")
    """Output folder; each run writes ``<out>/seed<seed>/<scene>/`` (refused if it exists)."""
    train_robots: int = 64
    """Robots driving the training tasks; with ``train_steps_per_robot`` the dataset size."""
    train_steps_per_robot: int = 400
    eval_robots: int = 16
    """Robots driving held-out episodes on the 'eval' split."""
    eval_steps_per_robot: int = 128
    eval_frames: int = 1024
    """Held-out frames evaluated (drawn from the eval robots' steps)."""
    episode_length: int = 128
    """Control steps before an episode is cut (crashes end it sooner)."""
    batch_size: int = 8
    prior_correction: float = 1.0
    """Calibration of the class-balanced segmenter: its logits get ``tau * log(class frequency)`` of the
    training maps before the argmax (1: the exact correction of the balanced loss; 0: none, the balanced
    argmax, which over-predicts thin lane lines)."""


# Per scene: which classes the segmenter separates, its size, and its default number of steps.  The city
# keeps full resolution (lane lines are 1-2 pixels wide); door panels are large, so the halls' net halves
# the 128 x 96 input first.
SCENE_SETTINGS = {
    "city": dict(classes=dict(road_id=ROAD, line_id=LANE_LINE), features=(8, 16, 32, 32), stem_stride=1, steps=600),
    "indoor": dict(classes=dict(door_id=DOOR), features=(8, 16, 32), stem_stride=2, steps=400),
}


def segmenter_config(scene: str, env) -> labellers.SegmenterConfig:
    s = SCENE_SETTINGS[scene]
    return labellers.SegmenterConfig(scene=scene, image_shape=env.spec.image_shape, features=s["features"],
                                     stem_stride=s["stem_stride"], **s["classes"])


def drive_poses(env, split: str, robots: int, steps: int, episode_length: int, key: jax.Array):
    """``(tasks [robots], poses f32[robots, steps, 3])``: random-action drives, one task per robot."""
    wrapped = base.VmapWrapper(base.AutoResetWrapper(base.EpisodeWrapper(env, episode_length)))
    k_task, k_reset, k_act = jax.random.split(key, 3)
    tasks = wrapped.sample_task(jax.random.split(k_task, robots), split)
    low, high = jnp.asarray(env.spec.plan_low), jnp.asarray(env.spec.plan_high)

    @jax.jit
    def run(tasks, reset_keys, action_key):
        state = wrapped.reset(reset_keys, tasks)

        def body(state, k):
            action = jax.random.uniform(k, (robots, low.shape[0]), minval=low, maxval=high)
            state = wrapped.step(state, action)
            return state, state.info["pose"]

        _, poses = jax.lax.scan(body, state, jax.random.split(action_key, steps))
        return jnp.swapaxes(poses, 0, 1)

    return tasks, run(tasks, jax.random.split(k_reset, robots), k_act)


def render_frames(env, tasks, poses: jax.Array, robot: np.ndarray, step: np.ndarray, chunk: int = 256):
    """``(images u8[n, h, w, c], semantic u8[n, h, w])`` of the chosen (robot, step) frames."""
    camera = env.config.camera

    @jax.jit
    def one_chunk(tasks, pose):
        return jax.vmap(lambda t, p: render(env.layout(t), p, camera)[:2])(tasks, pose)

    images, semantic = [], []
    for start in range(0, len(robot), chunk):
        r, s = robot[start:start + chunk], step[start:start + chunk]
        pad = chunk - len(r)  # fixed chunk shape: one compile
        r, s = np.pad(r, (0, pad)), np.pad(s, (0, pad))
        img, sem = one_chunk(jax.tree.map(lambda x, r=r: x[r], tasks), poses[r, s])
        images.append(np.asarray(img)[:chunk - pad])
        semantic.append(np.asarray(sem)[:chunk - pad])
    return np.concatenate(images), np.concatenate(semantic)


def draw_frames(rng: np.random.Generator, robots: int, steps: int, n: int):
    """``n`` distinct (robot, step) pairs drawn uniformly."""
    flat = rng.choice(robots * steps, size=n, replace=False)
    return flat // steps, flat % steps


def save_masks_png(path: Path, cfg: labellers.SegmenterConfig, images, true_sem, pred_sem) -> None:
    """Rows of frames: image, true and predicted classes, true and predicted cue masks (lane or door)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def cue_mask(sem):
        if cfg.has_lane:
            return np.asarray(jax.vmap(lambda s: labellers.right_lane_mask(s, road_id=cfg.road_id, line_id=cfg.line_id))(sem))
        return sem == cfg.door_id

    classes = lambda sem: np.asarray(labellers.class_targets(cfg, sem))
    columns = [("image", images[..., 0] if images.shape[-1] == 1 else images, "gray"),
               ("true classes", classes(true_sem), "viridis"), ("predicted classes", classes(pred_sem), "viridis"),
               ("true " + ("right lane" if cfg.has_lane else "door"), cue_mask(true_sem), "gray"),
               ("predicted", cue_mask(pred_sem), "gray")]
    n = images.shape[0]
    fig, axes = plt.subplots(n, len(columns), figsize=(2.4 * len(columns), 1.6 * n * images.shape[1] / images.shape[2] * 2))
    for i in range(n):
        for j, (title, data, cmap) in enumerate(columns):
            ax = axes[i, j]
            ax.imshow(data[i], cmap=cmap, vmin=0, vmax=max(1, cfg.num_classes - 1) if "classes" in title else None)
            ax.set_xticks([]), ax.set_yticks([])
            if i == 0:
                ax.set_title(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run_scene(cfg: Config, scene: str, run_dir: Path) -> dict:
    env = envs.make(scene)
    seg_cfg = segmenter_config(scene, env)
    dataset_steps = cfg.train_robots * cfg.train_steps_per_robot
    fraction = cfg.train_frames / dataset_steps
    if fraction > MAX_LABELLED_FRACTION:
        raise ValueError(f"train_frames: {cfg.train_frames} labelled frames are {fraction:.2%} of the {dataset_steps} "
                         f"dataset steps; at most {MAX_LABELLED_FRACTION:.0%} (raise --train-robots or "
                         f"--train-steps-per-robot, or lower --train-frames)")
    eval_total = cfg.eval_robots * cfg.eval_steps_per_robot
    if cfg.eval_frames > eval_total:
        raise ValueError(f"eval_frames: {cfg.eval_frames} exceeds the {eval_total} held-out steps "
                         f"(eval_robots x eval_steps_per_robot)")
    steps = cfg.steps if cfg.steps is not None else SCENE_SETTINGS[scene]["steps"]
    key = jax.random.key(cfg.seed)
    k_train, k_eval, k_fit = jax.random.split(key, 3)
    rng = np.random.default_rng(cfg.seed)
    timings = {}

    t = time.time()
    tasks, poses = drive_poses(env, "train", cfg.train_robots, cfg.train_steps_per_robot, cfg.episode_length, k_train)
    robot, step = draw_frames(rng, cfg.train_robots, cfg.train_steps_per_robot, cfg.train_frames)
    train_images, train_sem = render_frames(env, tasks, poses, robot, step)
    eval_tasks, eval_poses = drive_poses(env, "eval", cfg.eval_robots, cfg.eval_steps_per_robot, cfg.episode_length, k_eval)
    robot, step = draw_frames(rng, cfg.eval_robots, cfg.eval_steps_per_robot, cfg.eval_frames)
    eval_images, eval_sem = render_frames(env, eval_tasks, eval_poses, robot, step)
    timings["data_s"] = time.time() - t
    print(f"[labellers/{scene}] dataset {dataset_steps} steps ({cfg.train_robots} robots), {cfg.train_frames} "
          f"labelled training frames ({fraction:.2%}); {cfg.eval_frames} held-out frames; {timings['data_s']:.0f}s")

    t = time.time()
    bar = tqdm(total=steps, desc=f"train {scene} segmenter", unit="step")

    def progress(done, loss):
        bar.update(done - bar.n)
        bar.set_postfix(loss=f"{loss:.4f}")

    train_cfg = labellers.SegmenterTrainConfig(batch_size=cfg.batch_size, prior_correction=cfg.prior_correction)
    params, losses = labellers.train_segmenter(seg_cfg, train_images, train_sem, k_fit, steps, train_cfg, progress=progress)
    bar.close()
    timings["train_s"] = time.time() - t

    t = time.time()
    labeller = labellers.make_cue_labeller(seg_cfg, params)
    predicted = labellers.predict_semantic(labeller, eval_images)
    metrics = labellers.evaluate_predictions(seg_cfg, predicted, eval_sem)
    timings["eval_s"] = time.time() - t

    scene_dir = run_dir / scene
    labellers.save_labeller(scene_dir / "labeller", labeller)
    shown = np.linspace(0, cfg.eval_frames - 1, 6).astype(int)
    save_masks_png(scene_dir / "masks.png", seg_cfg, eval_images[shown], eval_sem[shown], predicted[shown])
    context = dict(scene=scene, train_frames=cfg.train_frames, dataset_steps=dataset_steps,
                   labelled_fraction=fraction, eval_frames=cfg.eval_frames, steps=steps, seed=cfg.seed,
                   features=list(seg_cfg.features), stem_stride=seg_cfg.stem_stride,
                   prior_correction=cfg.prior_correction,
                   train_s=round(timings["train_s"], 1))
    for name, value in metrics.items():
        if name != "frames":
            unit = "IoU" if name.endswith("_iou") else "mean_abs_error" if "_mae" in name else "fraction"
            emit(f"labeller.{name}", value, unit, **context)
    emit("labeller.final_loss", float(np.mean(losses[-50:])), "balanced_ce", **context)
    record = dict(metrics=metrics, timings=timings, context=context, config=dataclasses.asdict(seg_cfg))
    (scene_dir / "metrics.json").write_text(json.dumps(record, indent=1))
    print(f"[labellers/{scene}] data {timings['data_s']:.0f}s, training {timings['train_s']:.0f}s, "
          f"evaluation {timings['eval_s']:.0f}s -> {scene_dir}")
    return record


def main(cfg: Config) -> dict:
    scenes = {"both": ("city", "indoor"), "city": ("city",), "indoor": ("indoor",)}.get(cfg.scene)
    if scenes is None:
        raise SystemExit(f"--scene must be 'city', 'indoor' or 'both', got {cfg.scene!r}")
    run_dir = cfg.out / f"seed{cfg.seed}"
    for scene in scenes:
        if (run_dir / scene).exists():
            raise SystemExit(f"--out: {run_dir / scene} exists; results are never overwritten (pick another --out or --seed)")
    return {scene: run_scene(cfg, scene, run_dir) for scene in scenes}


if __name__ == "__main__":
    runtime.use_wide_vectors()  # as every entry point (experiments/runtime.py); XLA_FLAGS overrides
    main(tyro.cli(Config))
