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
class-balanced cross-entropy, optax Adam, all steps of a chunk under one jit.  ``make_cue_labeller``
turns trained params into a jitted ``images u8[b, h, w, c] -> {cue: f32[b]}`` for (re)labelling
datasets.  Why not the paper's FCN-16s on VGG-16: 134 M parameters pretrained on ImageNet do not train
on a 2-core CPU, and the clean renders need far less (a few ten thousand parameters reach the targets).

capsjax does not import ``envs``: class ids are arguments.  Envs pass ``envs.scene``'s constants
(``ROAD``, ``LANE_LINE``, ``DOOR``), so there is one class table in the project.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

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
