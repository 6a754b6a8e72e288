"""Cue labels from segmentation: the oracle rules on a semantic class map, and learned labellers.

The paper derives its lane and door cues from pixel masks (caps-algorithm.md sections 8.3 and 8.4).
Here the masks come either from the camera's ground-truth semantic map (the oracle, exact) or from a
learned segmenter, and the same functions turn a class map into cues (``cue_labels``), so labeller
quality is measured against the oracle (``evaluate_labeller``) rather than assumed.

Oracle rules (top of the module): pure ``jnp`` on a single map ``u8[h, w]``; jit and vmap them.

Learned labeller (bottom): a compact fully convolutional encoder-decoder (``Segmenter``, Flax linen)
separates a few classes from "other" -- the city's {other, road, lane_line}, so the *same*
``right_lane_mask`` rule runs on the predicted map as on the true one; the halls' {other, door}.  It
trains (``train_segmenter``) on the ground-truth maps of a small labelled fraction of frames with a
class-balanced cross-entropy, optax Adam, all steps of a chunk under one jit, and then stores the
training maps' class frequencies beside its weights to undo the balancing at prediction time (see
``balanced_cross_entropy``).  ``make_cue_labeller``
turns trained params into a jitted ``images u8[b, h, w, c] -> {cue: f32[b]}`` for (re)labelling
datasets.  Why not the paper's FCN-16s on VGG-16: 134 M parameters pretrained on ImageNet do not train
on a 2-core CPU, and the clean renders need far less (26k-63k parameters here).

capsjax does not import ``envs``: class ids are arguments.  Envs pass ``envs.scene``'s constants
(``ROAD``, ``LANE_LINE``, ``DOOR``), so there is one class table in the project.
"""
from __future__ import annotations

import dataclasses
import functools
import json
from collections.abc import Callable
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

ROAD_MIN_FRAC = 0.05  # the paper's rule: a lane mask needs > 5 % road pixels ...
LINE_MIN_FRAC = 0.003  # ... and > 0.3 % lane-line pixels
LEARNED_SEEN_FRAC = 0.02  # learned masks: lane seen when the mask covers > 2 % of the image


def right_lane_mask(semantic: jax.Array, *, road_id: int, line_id: int) -> jax.Array:
    """bool[h, w]: the road pixels at or right of the leftmost lane-line pixel of the same row.

    The mask is empty unless road covers more than 5 % and lane lines more than 0.3 % of the image
    (section 8.3).  Rows without any line pixel contribute nothing (there is no lane boundary to be
    right of).
    """
    semantic = jnp.asarray(semantic)
    road = semantic == road_id
    line = semantic == line_id
    w = semantic.shape[-1]
    cols = jnp.arange(w)
    # Leftmost line column per row; rows without a line get w, so no column qualifies.
    leftmost = jnp.min(jnp.where(line, cols, w), axis=-1, keepdims=True)
    mask = road & (cols >= leftmost)
    enough = (jnp.mean(road) > ROAD_MIN_FRAC) & (jnp.mean(line) > LINE_MIN_FRAC)
    return mask & enough


def lane_cues_from_mask(mask: jax.Array, seen_threshold_frac: float | None = None) -> tuple[jax.Array, jax.Array]:
    """``(lane_seen, lane_diff)`` as f32 scalars from a lane mask bool[h, w].

    ``lane_seen`` is 1 when the mask is non-empty (the ground-truth rule) or, with
    ``seen_threshold_frac`` set (learned masks: ``LEARNED_SEEN_FRAC``), when it covers more than that
    fraction of the image.  ``lane_diff = (mean mask column - W/2) / (W/2)`` in [-1, 1] (column centres
    at j + 0.5, so a mask symmetric about the image centre gives exactly 0); positive means the lane is
    right of the image centre; 0 when unseen.
    """
    mask = jnp.asarray(mask).astype(jnp.float32)
    w = mask.shape[-1]
    count = jnp.sum(mask)
    if seen_threshold_frac is None:
        seen = count > 0
    else:
        seen = count > seen_threshold_frac * mask.size
    centres = jnp.arange(w, dtype=jnp.float32) + 0.5
    mean_col = jnp.sum(mask * centres) / jnp.maximum(count, 1.0)
    diff = jnp.where(seen, (mean_col - w / 2) / (w / 2), 0.0)
    return seen.astype(jnp.float32), diff.astype(jnp.float32)


def lane_cues(semantic: jax.Array, *, road_id: int, line_id: int) -> tuple[jax.Array, jax.Array]:
    """Oracle ``(lane_seen, lane_diff)`` from a semantic map: the paper's ground-truth rule."""
    return lane_cues_from_mask(right_lane_mask(semantic, road_id=road_id, line_id=line_id))


def door_frac(semantic: jax.Array, *, door_id: int) -> jax.Array:
    """f32 scalar: the fraction of the image's pixels that show a door."""
    return jnp.mean(jnp.asarray(semantic) == door_id).astype(jnp.float32)


# ------------------------------------------------------------------------------------ learned labellers

OTHER_ID = 255  # semantic id written for the predicted "other" class (no scene uses it)
CALIBRATION = "calibration"  # variable collection of the segmenter's class prior (not trained by gradient)
LANE_CUES = ("lane_seen", "lane_diff")
DOOR_CUES = ("door_frac",)


@dataclasses.dataclass(frozen=True)
class SegmenterConfig:
    """What a learned labeller reads and separates (static and hashable: one compiled net per config).

    ``scene`` names the env the labeller is for (``"city"``, ``"indoor"``): a labeller refuses frames of
    another scene.  ``image_shape`` is the camera frame ``(h, w, c)`` it reads (uint8).  The classes it
    separates from "other" follow from the cues: ``road_id`` and ``line_id`` (both or neither) give
    ``lane_seen`` / ``lane_diff`` by the paper's right-lane rule, ``door_id`` gives ``door_frac``.
    ``features`` are the channels of each resolution level of the encoder (level ``i`` at
    ``1 / (stem_stride * 2**i)`` of the input); ``stem_stride = 2`` halves the input first (fine for
    large doors, too coarse for thin lane lines).  ``seen_threshold_frac`` is the learned-mask
    lane-seen rule (section 8.4: the mask must cover more than 2 % of the image).
    """

    scene: str
    image_shape: tuple[int, int, int]
    road_id: int | None = None
    line_id: int | None = None
    door_id: int | None = None
    features: tuple[int, ...] = (8, 16, 32, 32)
    stem_stride: int = 1
    seen_threshold_frac: float = LEARNED_SEEN_FRAC

    def __post_init__(self):
        object.__setattr__(self, "image_shape", tuple(int(x) for x in self.image_shape))
        object.__setattr__(self, "features", tuple(int(x) for x in self.features))
        if not isinstance(self.scene, str) or not self.scene:
            raise ValueError(f"SegmenterConfig.scene must be an env name such as 'city', got {self.scene!r}")
        if len(self.image_shape) != 3 or min(self.image_shape) <= 0:
            raise ValueError(f"SegmenterConfig.image_shape must be (h, w, c) positive, got {self.image_shape}")
        if (self.road_id is None) != (self.line_id is None):
            raise ValueError(f"SegmenterConfig.road_id and line_id must be given together (the lane rule needs "
                             f"both), got road_id={self.road_id}, line_id={self.line_id}")
        if not self.class_ids:
            raise ValueError("SegmenterConfig needs road_id and line_id (lane cues) and/or door_id (door_frac)")
        for name in ("road_id", "line_id", "door_id"):
            v = getattr(self, name)
            if v is not None and not 0 <= v < OTHER_ID:
                raise ValueError(f"SegmenterConfig.{name} must be a semantic id in [0, {OTHER_ID}), got {v}")
        if len(set(self.class_ids)) != len(self.class_ids):
            raise ValueError(f"SegmenterConfig class ids must differ, got {self.class_ids}")
        if not self.features or min(self.features) <= 0:
            raise ValueError(f"SegmenterConfig.features must be positive channel counts, got {self.features}")
        if self.stem_stride not in (1, 2):
            raise ValueError(f"SegmenterConfig.stem_stride must be 1 or 2, got {self.stem_stride}")
        if not 0 <= self.seen_threshold_frac < 1:
            raise ValueError(f"SegmenterConfig.seen_threshold_frac must be in [0, 1), got {self.seen_threshold_frac}")

    @property
    def has_lane(self) -> bool:
        return self.road_id is not None

    @property
    def has_door(self) -> bool:
        return self.door_id is not None

    @property
    def class_ids(self) -> tuple[int, ...]:
        """Semantic ids of the separated classes; the network's class ``k + 1`` is ``class_ids[k]``."""
        ids = (self.road_id, self.line_id) if self.has_lane else ()
        return ids + ((self.door_id,) if self.has_door else ())

    @property
    def num_classes(self) -> int:
        return 1 + len(self.class_ids)  # class 0 is "other"

    @property
    def cue_names(self) -> tuple[str, ...]:
        return (LANE_CUES if self.has_lane else ()) + (DOOR_CUES if self.has_door else ())


def cue_labels(cfg: SegmenterConfig, semantic: jax.Array, seen_threshold_frac: float | None = None) -> dict[str, jax.Array]:
    """``{cue: f32[]}`` from one class map ``u8[h, w]`` of semantic ids: the cues ``cfg`` labels.

    On the camera's true map with ``seen_threshold_frac=None`` these are the oracle labels (the
    paper's ground-truth rule, exactly what the envs' signals hold); on a predicted map
    (``predict_semantic``) pass ``cfg.seen_threshold_frac``, the learned-mask seen rule.
    """
    out = {}
    if cfg.has_lane:
        mask = right_lane_mask(semantic, road_id=cfg.road_id, line_id=cfg.line_id)
        out["lane_seen"], out["lane_diff"] = lane_cues_from_mask(mask, seen_threshold_frac)
    if cfg.has_door:
        out["door_frac"] = door_frac(semantic, door_id=cfg.door_id)
    return out


def class_targets(cfg: SegmenterConfig, semantic: jax.Array) -> jax.Array:
    """u8[...]: the network's class index (0 = other) of every pixel of true semantic maps."""
    table = np.zeros(256, np.uint8)
    table[list(cfg.class_ids)] = np.arange(1, cfg.num_classes, dtype=np.uint8)
    return jnp.asarray(table)[jnp.asarray(semantic).astype(jnp.int32)]


def class_index_to_semantic(cfg: SegmenterConfig, class_index: jax.Array) -> jax.Array:
    """u8[...]: semantic ids of network class indices ("other" becomes ``OTHER_ID``)."""
    return jnp.asarray((OTHER_ID,) + cfg.class_ids, jnp.uint8)[class_index]


def check_images(cfg: SegmenterConfig, images, what: str = "images") -> None:
    """Raise a ValueError naming ``what`` unless ``images`` is ``uint8[b, h, w, c]`` of ``cfg.image_shape``."""
    shape, dtype = tuple(np.shape(images)), getattr(images, "dtype", None)
    if len(shape) != 4 or shape[1:] != cfg.image_shape or dtype != np.uint8:
        h, w, c = cfg.image_shape
        raise ValueError(f"{what} must be uint8[batch, {h}, {w}, {c}] (the {cfg.scene!r} labeller's "
                         f"SegmenterConfig.image_shape={cfg.image_shape}), got {dtype}{list(shape)}")


class _EncoderDecoder(nn.Module):
    """Strided 3x3 convs down, bilinear resize + 3x3 conv up with a skip from every level (U-Net style).

    The first level has one conv (it runs at full resolution, where convs cost the most on a CPU), the
    others two; SAME padding keeps odd sizes (50 -> 25 -> 13 ...) and the decoder resizes to each
    skip's exact size, so any image shape works.
    """

    features: tuple[int, ...]
    num_classes: int
    stem_stride: int

    @nn.compact
    def __call__(self, images: jax.Array, calibrated: bool = True) -> jax.Array:
        # Not trained by gradient: ``train_segmenter`` sets it to the training maps' log class frequencies.
        log_prior = self.variable(CALIBRATION, "log_prior", lambda: jnp.zeros((self.num_classes,), jnp.float32))
        x = images.astype(jnp.float32) / 127.5 - 1.0
        skips = []
        for level, f in enumerate(self.features):
            stride = self.stem_stride if level == 0 else 2
            x = nn.relu(nn.Conv(f, (3, 3), strides=stride)(x))
            if level > 0:
                x = nn.relu(nn.Conv(f, (3, 3))(x))
            skips.append(x)
        for f, skip in zip(self.features[-2::-1], skips[-2::-1]):
            x = jax.image.resize(x, skip.shape[:-1] + x.shape[-1:], "bilinear")
            x = nn.relu(nn.Conv(f, (3, 3))(jnp.concatenate([x, skip], axis=-1)))
        logits = nn.Conv(self.num_classes, (1, 1))(x)
        if logits.shape[1:3] != images.shape[1:3]:
            logits = jax.image.resize(logits, images.shape[:3] + logits.shape[-1:], "bilinear")
        return logits + log_prior.value if calibrated else logits


@dataclasses.dataclass(frozen=True)
class Segmenter:
    """Static, hashable segmenter definition with pure functions of a params pytree."""

    config: SegmenterConfig

    @property
    def network(self) -> _EncoderDecoder:
        cfg = self.config
        return _EncoderDecoder(cfg.features, cfg.num_classes, cfg.stem_stride)

    def init(self, key: jax.Array):
        """Variables ``{"params": weights, "calibration": {"log_prior": f32[num_classes]}}`` (a zero prior:
        an untrained net predicts its plain argmax)."""
        # Jitted: one compile instead of eagerly dispatching (and compiling) every initialiser op.
        return jax.jit(self.network.init)(key, jnp.zeros((1,) + self.config.image_shape, jnp.uint8))

    def apply(self, params, images: jax.Array, calibrated: bool = True) -> jax.Array:
        """f32[b, h, w, num_classes] logits of frames ``u8[b, h, w, c]``; ``calibrated`` adds the stored
        log class prior (the logits whose argmax is the prediction), otherwise the raw trained logits."""
        check_images(self.config, images)
        return self.network.apply(params, images, calibrated)

    def predict_semantic(self, params, images: jax.Array) -> jax.Array:
        """u8[b, h, w] predicted semantic ids (``OTHER_ID`` where none of the classes)."""
        return class_index_to_semantic(self.config, jnp.argmax(self.apply(params, images), axis=-1))


def balanced_cross_entropy(logits: jax.Array, targets: jax.Array) -> jax.Array:
    """Softmax cross-entropy with every class present in the batch weighted equally.

    The mean over present classes of each class's mean pixel loss, i.e. pixel weights inversely
    proportional to the class's frequency in the batch (the multi-class form of the paper's #neg/#pos
    positive weight): thin lane lines (~1 % of the pixels) count as much as the road, so they are learnt.

    The price: this loss is minimised by ``softmax(logits) ~ p(class | pixel) / prior(class)``, so its
    argmax over-predicts rare classes (lane lines came out about twice as thick as true, which flips
    the paper's "lines > 0.3 % of the image" rule and so lane_seen).  ``train_segmenter`` therefore
    stores ``log prior`` (the training maps' class frequencies) and the segmenter adds it to the logits
    before the argmax (logit adjustment; ``SegmenterTrainConfig.prior_correction``), which turns the
    balanced scores back into posteriors.
    """
    num_classes = logits.shape[-1]
    ce = optax.softmax_cross_entropy_with_integer_labels(logits, targets.astype(jnp.int32))
    onehot = jax.nn.one_hot(targets, num_classes, dtype=ce.dtype)
    counts = jnp.sum(onehot, axis=tuple(range(onehot.ndim - 1)))
    per_class = jnp.einsum("...k,...->k", onehot, ce) / jnp.maximum(counts, 1.0)
    present = counts > 0
    return jnp.sum(jnp.where(present, per_class, 0.0)) / jnp.maximum(jnp.sum(present), 1)


@dataclasses.dataclass(frozen=True)
class SegmenterTrainConfig:
    """Optimiser and sampling settings of ``train_segmenter``.

    Adam (eps 1e-4 as the paper's FCN) with a cosine decay of the learning rate over the run; a larger
    rate than the paper's 1e-4 because the net is small and trained from scratch for few steps.
    ``flip``: random horizontal flips (segmentation is flip-equivariant; the lane rule runs after it).
    ``prior_correction`` (tau): the stored calibration is ``tau * log(class frequency)`` of the training
    maps; 1 is the exact correction of the class-balanced loss (``balanced_cross_entropy``), 0 keeps
    the balanced argmax.
    """

    batch_size: int = 16
    learning_rate: float = 3e-3
    final_lr_fraction: float = 0.05
    adam_eps: float = 1e-4
    flip: bool = True
    prior_correction: float = 1.0
    chunk: int = 100  # steps per jitted call (progress is reported between chunks)

    def __post_init__(self):
        for name in ("batch_size", "chunk"):
            if getattr(self, name) <= 0:
                raise ValueError(f"SegmenterTrainConfig.{name} must be positive, got {getattr(self, name)}")
        for name in ("learning_rate", "adam_eps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SegmenterTrainConfig.{name} must be positive, got {getattr(self, name)}")
        if not 0 <= self.final_lr_fraction <= 1:
            raise ValueError(f"SegmenterTrainConfig.final_lr_fraction must be in [0, 1], got {self.final_lr_fraction}")
        if not 0 <= self.prior_correction <= 1:
            raise ValueError(f"SegmenterTrainConfig.prior_correction must be in [0, 1], got {self.prior_correction}")


def _check_semantic(cfg: SegmenterConfig, images, semantic) -> None:
    want = (np.shape(images)[0],) + cfg.image_shape[:2]
    if tuple(np.shape(semantic)) != want or not np.issubdtype(np.asarray(semantic).dtype, np.integer):
        raise ValueError(f"semantic must be an integer class map of shape {list(want)} (one per image), got "
                         f"{np.asarray(semantic).dtype}{list(np.shape(semantic))}")


def class_log_prior(cfg: SegmenterConfig, semantic) -> jax.Array:
    """f32[num_classes]: log of each network class's pixel frequency in true maps ``[n, h, w]``.

    A class absent from the maps gets the frequency of one pixel (finite, so it can still be predicted).
    """
    counts = np.bincount(np.asarray(class_targets(cfg, semantic)).ravel(), minlength=cfg.num_classes)
    return jnp.asarray(np.log(np.maximum(counts, 1) / max(int(counts.sum()), 1)), jnp.float32)


def train_segmenter(cfg: SegmenterConfig, images, semantic, key: jax.Array, steps: int,
                    train_cfg: SegmenterTrainConfig = SegmenterTrainConfig(), *, params=None,
                    progress: Callable[[int, float], None] | None = None):
    """Train the segmenter on labelled frames; returns ``(variables, losses f32[steps])``.

    ``images u8[n, h, w, c]`` and their true ``semantic`` maps ``[n, h, w]`` stay on the device; each
    step draws a batch uniformly with replacement and minimises ``balanced_cross_entropy`` of the raw
    logits.  Steps run in chunks (``training.repeat_steps``: one ``lax.scan`` on accelerators, jitted
    steps from a host loop on CPU); ``progress(steps_done, mean_loss_of_chunk)`` is called between
    chunks.  ``params`` (variables of an earlier run) continues training instead of a fresh init.  The
    returned variables carry the calibration ``prior_correction * class_log_prior`` of these maps.
    """
    check_images(cfg, images)
    _check_semantic(cfg, images, semantic)
    if steps <= 0:
        raise ValueError(f"steps must be positive, got {steps}")
    segmenter = Segmenter(cfg)
    init_key, key = jax.random.split(key)
    variables = segmenter.init(init_key) if params is None else params
    schedule = optax.cosine_decay_schedule(train_cfg.learning_rate, steps, alpha=train_cfg.final_lr_fraction)
    optimizer = optax.adam(schedule, eps=train_cfg.adam_eps)
    images = jnp.asarray(images)
    targets = class_targets(cfg, semantic)
    # The loss reads the raw logits, so the calibration it is applied with is only a placeholder.
    unused_calibration = {"log_prior": jnp.zeros((cfg.num_classes,), jnp.float32)}

    def loss_fn(weights, x, y):
        logits = segmenter.network.apply({"params": weights, CALIBRATION: unused_calibration}, x, False)
        return balanced_cross_entropy(logits, y)

    def step(carry, _, frames, frame_targets):
        weights, opt_state, k = carry
        k, k_idx, k_flip = jax.random.split(k, 3)
        idx = jax.random.randint(k_idx, (train_cfg.batch_size,), 0, frames.shape[0])
        x, y = frames[idx], frame_targets[idx]
        if train_cfg.flip:
            flip = jax.random.bernoulli(k_flip, 0.5, (train_cfg.batch_size,))
            x = jnp.where(flip[:, None, None, None], x[:, :, ::-1], x)
            y = jnp.where(flip[:, None, None], y[:, :, ::-1], y)
        loss, grads = jax.value_and_grad(loss_fn)(weights, x, y)
        updates, opt_state = optimizer.update(grads, opt_state, weights)
        return (optax.apply_updates(weights, updates), opt_state, k), loss

    from capsjax.training import repeat_steps  # one scan on accelerators, a host loop of jitted steps on CPU

    runners = {}  # one compiled runner per chunk length (at most two: the chunk and the remainder)
    weights = variables["params"]
    carry, losses, done = (weights, optimizer.init(weights), key), [], 0
    while done < steps:
        n = min(train_cfg.chunk, steps - done)
        if n not in runners:
            runners[n] = repeat_steps(lambda c, data: step(c, None, *data), n)
        carry, chunk_losses = runners[n](carry, (images, targets))
        losses.append(np.asarray(chunk_losses))
        done += n
        if progress is not None:
            progress(done, float(np.mean(losses[-1])))
    log_prior = train_cfg.prior_correction * class_log_prior(cfg, semantic)
    return {"params": carry[0], CALIBRATION: {"log_prior": log_prior}}, np.concatenate(losses)


def learned_cue_labels(cfg: SegmenterConfig, predicted: jax.Array) -> dict[str, jax.Array]:
    """``{cue: f32[b]}`` of predicted maps ``u8[b, h, w]``: ``cue_labels`` with the learned seen rule."""
    return jax.vmap(lambda s: cue_labels(cfg, s, cfg.seen_threshold_frac))(predicted)


@functools.partial(jax.jit, static_argnums=0)
def _predict_semantic(cfg: SegmenterConfig, params, images: jax.Array) -> jax.Array:
    return Segmenter(cfg).predict_semantic(params, images)


@functools.partial(jax.jit, static_argnums=0)
def _label_frames(cfg: SegmenterConfig, params, images: jax.Array) -> dict[str, jax.Array]:
    return learned_cue_labels(cfg, Segmenter(cfg).predict_semantic(params, images))


@dataclasses.dataclass(frozen=True, eq=False)
class CueLabeller:
    """A trained labeller: ``labeller(images u8[b, h, w, c]) -> {cue: f32[b]}`` (jitted, params traced).

    ``scene`` and ``cue_names`` say what it labels; ``check_scene`` refuses frames of another scene.
    """

    config: SegmenterConfig
    params: dict

    @property
    def scene(self) -> str:
        return self.config.scene

    @property
    def cue_names(self) -> tuple[str, ...]:
        return self.config.cue_names

    def check_scene(self, scene: str) -> None:
        if scene != self.config.scene:
            raise ValueError(f"scene: this labeller was trained for scene {self.config.scene!r} "
                             f"(SegmenterConfig.scene), the frames are from scene {scene!r}")

    def __call__(self, images) -> dict[str, jax.Array]:
        check_images(self.config, images)
        return _label_frames(self.config, self.params, jnp.asarray(images))


def make_cue_labeller(cfg: SegmenterConfig, params) -> CueLabeller:
    """The jitted cue labeller of trained segmenter ``params`` (for ``data.relabel`` and evaluation)."""
    return CueLabeller(cfg, params)


@functools.partial(jax.jit, static_argnums=0)
def _evaluation_sums(cfg: SegmenterConfig, predicted, semantic, valid) -> dict[str, jax.Array]:
    """Per-batch sums behind ``evaluate_predictions`` (padded frames have ``valid == False``)."""
    learned = learned_cue_labels(cfg, predicted)
    oracle = jax.vmap(lambda s: cue_labels(cfg, s))(semantic)
    v = valid.astype(jnp.float32)
    v_px = valid[:, None, None]

    def overlap(pred_mask, true_mask):
        return (jnp.sum(pred_mask & true_mask & v_px), jnp.sum((pred_mask | true_mask) & v_px))

    out = {"frames": jnp.sum(v)}
    for name, cls in (("road", cfg.road_id), ("line", cfg.line_id), ("door", cfg.door_id)):
        if cls is not None:
            out[f"{name}_inter"], out[f"{name}_union"] = overlap(predicted == cls, semantic == cls)
    if cfg.has_lane:
        lane = jax.vmap(lambda s: right_lane_mask(s, road_id=cfg.road_id, line_id=cfg.line_id))
        out["lane_inter"], out["lane_union"] = overlap(lane(predicted), lane(semantic))
        seen = oracle["lane_seen"] > 0
        err = jnp.abs(learned["lane_diff"] - oracle["lane_diff"]) * v
        out["lane_seen_correct"] = jnp.sum((learned["lane_seen"] == oracle["lane_seen"]) * v)
        out["lane_seen_frames"] = jnp.sum(seen * v)
        out["lane_diff_abs_seen"] = jnp.sum(err * seen)
        out["lane_diff_abs_all"] = jnp.sum(err)
    if cfg.has_door:
        out["door_frac_abs"] = jnp.sum(jnp.abs(learned["door_frac"] - oracle["door_frac"]) * v)
    return out


def _padded_batches(batch_size: int, *arrays):
    """Fixed-size batches of the leading axis (the last one zero-padded) and their ``valid`` masks, so a
    jitted function of a batch compiles once for any frame count."""
    if batch_size <= 0:
        raise ValueError(f"batch_size must be positive, got {batch_size}")
    n = arrays[0].shape[0]
    for start in range(0, n, batch_size):
        chunk = [np.asarray(a[start:start + batch_size]) for a in arrays]
        pad = batch_size - chunk[0].shape[0]
        yield [np.concatenate([c, np.zeros((pad,) + c.shape[1:], c.dtype)]) for c in chunk], np.arange(batch_size) < batch_size - pad


def evaluate_predictions(cfg: SegmenterConfig, predicted, semantic, *, batch_size: int = 256) -> dict[str, float]:
    """Quality of predicted semantic maps ``[n, h, w]`` against the true maps, as cue labels.

    Returns (keys depend on the cues): ``road_iou``, ``line_iou``, ``door_iou`` (pixel IoU of each
    separated class), ``lane_iou`` (IoU of the right-lane mask from the predicted vs the true map),
    ``lane_seen_accuracy``, ``lane_diff_mae`` (over frames where the oracle sees the lane),
    ``lane_diff_mae_all`` (over every frame; both are 0 when unseen), ``door_frac_mae``, ``frames`` and
    ``lane_seen_fraction`` (of frames, by the oracle).  IoUs pool intersections and unions over all
    frames.  Predicted cues use the learned seen rule, the oracle the ground-truth rule.
    """
    if np.shape(predicted) != np.shape(semantic) or tuple(np.shape(semantic)[1:]) != cfg.image_shape[:2] \
            or np.ndim(semantic) != 3:
        raise ValueError(f"predicted and semantic must both be class maps [n, {cfg.image_shape[0]}, "
                         f"{cfg.image_shape[1]}], got {list(np.shape(predicted))} and {list(np.shape(semantic))}")
    sums: dict[str, float] = {}
    for (p, s), valid in _padded_batches(batch_size, np.asarray(predicted, np.uint8), np.asarray(semantic, np.uint8)):
        for k, v in _evaluation_sums(cfg, p, s, valid).items():
            sums[k] = sums.get(k, 0.0) + float(v)
    frames = sums["frames"]
    out = {"frames": frames}
    for name in ("road", "line", "door", "lane"):
        if f"{name}_inter" in sums:
            out[f"{name}_iou"] = sums[f"{name}_inter"] / max(sums[f"{name}_union"], 1.0)
    if cfg.has_lane:
        out["lane_seen_accuracy"] = sums["lane_seen_correct"] / frames
        out["lane_seen_fraction"] = sums["lane_seen_frames"] / frames
        out["lane_diff_mae"] = sums["lane_diff_abs_seen"] / max(sums["lane_seen_frames"], 1.0)
        out["lane_diff_mae_all"] = sums["lane_diff_abs_all"] / frames
    if cfg.has_door:
        out["door_frac_mae"] = sums["door_frac_abs"] / frames
    return out


def predict_semantic(labeller: CueLabeller, images, *, batch_size: int = 64) -> np.ndarray:
    """u8[n, h, w] predicted semantic maps of any number of frames, in fixed-size jitted batches."""
    check_images(labeller.config, images)
    out = [np.asarray(_predict_semantic(labeller.config, labeller.params, x))[valid]
           for (x,), valid in _padded_batches(batch_size, images)]
    return np.concatenate(out) if out else np.zeros((0,) + labeller.config.image_shape[:2], np.uint8)


def evaluate_labeller(labeller: CueLabeller, images, semantic, *, batch_size: int = 64) -> dict[str, float]:
    """``evaluate_predictions`` of the labeller's maps of ``images`` against their true ``semantic``."""
    check_images(labeller.config, images)
    _check_semantic(labeller.config, images, semantic)
    return evaluate_predictions(labeller.config, predict_semantic(labeller, images, batch_size=batch_size), semantic)


def save_labeller(path, labeller: CueLabeller) -> Path:
    """Write a labeller to the new folder ``path``: ``config.json`` and orbax ``params/``.

    Never overwrites: an existing ``path`` is refused (labels already written name their labeller).
    """
    import orbax.checkpoint as ocp  # imported here: orbax is slow to import and only saving needs it

    path = Path(path).absolute()
    if path.exists():
        raise ValueError(f"path: {path} already exists; a saved labeller is never overwritten (pick a new folder)")
    path.mkdir(parents=True)
    (path / "config.json").write_text(json.dumps(dataclasses.asdict(labeller.config), indent=1))
    checkpointer = ocp.StandardCheckpointer()
    checkpointer.save(path / "params", labeller.params)
    checkpointer.wait_until_finished()
    return path


def load_labeller(path) -> CueLabeller:
    """The labeller ``save_labeller`` wrote to ``path``."""
    import orbax.checkpoint as ocp

    path = Path(path).absolute()
    if not (path / "config.json").is_file():
        raise ValueError(f"path: {path} holds no saved labeller (expected {path / 'config.json'})")
    cfg = SegmenterConfig(**json.loads((path / "config.json").read_text()))
    abstract = jax.eval_shape(Segmenter(cfg).init, jax.random.key(0))
    checkpointer = ocp.StandardCheckpointer()
    if CALIBRATION in checkpointer.metadata(path / "params").item_metadata.tree:
        params = checkpointer.restore(path / "params", abstract)
    else:  # saved before labellers stored a class prior: it predicts its plain (balanced) argmax, as then
        weights = checkpointer.restore(path / "params", {"params": abstract["params"]})["params"]
        params = {"params": weights, CALIBRATION: {"log_prior": jnp.zeros((cfg.num_classes,), jnp.float32)}}
    return CueLabeller(cfg, params)
