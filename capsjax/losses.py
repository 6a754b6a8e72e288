"""The CAPs training loss: per-cue masked means over (batch, step), summed over cues, plus the paper's L2.

Each cue's loss is divided by its mask's *global* sum over the batch (not per sequence), as the
authors do; collision is never masked (its label is absorbing), every other cue is masked after the
terminal step.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Batch:
    """Training windows: B sequences of horizon H.

    ``signals[name]`` holds the ground truth of observations t+1..t+H (arbitrary padding where
    ``valid`` is False); ``valid[b, k]`` says observation t+k+1 is in the window's episode (the terminal
    observation included).
    """

    obs: Any  # an Observation: images u8[B, L, h, w, c], vector f32[B, L, D]
    actions: jax.Array  # f32[B, H, A]
    signals: dict  # name -> f32[B, H]
    valid: jax.Array  # bool[B, H]
    # Optional extras for bootstrapped (Q-learning) baselines and goal relabelling; CAPs ignores them.
    done: Any = None  # bool[B, H]: observation t+k+1 is its episode's terminal one
    next_obs: Any = None  # the Observation history ending at t+1 (same shapes as ``obs``)
    context: Any = None  # dict of per-window extras, e.g. 'pose' f32[B, 3] at t, 'final_xy' f32[B, 2]


def l2_penalty(params, coeff: float) -> jax.Array:
    """``coeff / P * sum ||W||^2`` over kernels (conv, dense and LSTM W/U), P = number of parameters.

    The paper's weight decay is (0.5 / P) * sum 0.25 ||W||^2, i.e. coeff = 0.125.
    """
    leaves = jax.tree_util.tree_leaves_with_path(params)
    total = sum(x.size for _, x in leaves)
    sq = sum(jnp.sum(jnp.square(x)) for path, x in leaves if jax.tree_util.keystr(path).endswith("kernel']"))
    return coeff / total * sq


def total_loss(model, params, batch: Batch, l2_coeff: float = 0.125):
    """``(loss, metrics)`` of ``model`` on ``batch``; metrics hold each cue's loss and the L2 term."""
    cfg = model.config
    for cue in cfg.cues:
        if cue.source not in batch.signals:
            raise ValueError(
                f"batch.signals lacks {cue.source!r} (needed by cue {cue.name!r}); it has {sorted(batch.signals)}"
            )

    def one(obs, actions):
        carry = model.encode(params, obs)
        return model.rollout_raw(params, carry, actions), carry.anchors

    raw, anchors = jax.vmap(one)(batch.obs, batch.actions)  # [B, H, heads], [B, heads]
    slices = cfg.head_slices()
    metrics, loss = {}, 0.0
    for cue in cfg.cues:
        target, mask = cue.labels(batch.signals[cue.source], batch.valid)
        sl = slices[cue.name]
        per_step = cue.loss(raw[..., sl], target, anchors[:, None, sl])
        cue_loss = jnp.sum(per_step * mask) / jnp.maximum(jnp.sum(mask), 1.0)
        metrics[f"loss/{cue.name}"] = cue_loss
        loss = loss + cue_loss
    metrics["loss/cues"] = loss
    if l2_coeff:
        l2 = l2_penalty(params, l2_coeff)
        metrics["loss/l2"] = l2
        loss = loss + l2
    metrics["loss"] = loss
    return loss, metrics
