"""Supervised training of the CAPs predictor with optax, one step or many under one jit.

The paper's optimiser: Adam (lr 1e-4, eps 1e-4), gradients clipped *per tensor* to norm 10 (each
variable separately, not the global norm), an L2 term scaled by 1 / #params.  Global-norm clipping and
decoupled weight decay are options.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import optax
from flax import struct

from capsjax import losses


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    learning_rate: float = 1e-4
    adam_eps: float = 1e-4
    adam_b1: float = 0.9
    adam_b2: float = 0.999
    clip_tensor_norm: float | None = 10.0  # per-tensor clipping (the paper); None disables
    clip_global_norm: float | None = None
    l2_coeff: float = 0.125  # the paper's L2: l2_coeff / #params * sum ||W||^2 over kernels
    weight_decay: float = 0.0  # decoupled (AdamW-style), applied to kernels only
    batch_size: int = 32

    def __post_init__(self):
        for name in ("learning_rate", "adam_eps"):
            if not getattr(self, name) > 0:
                raise ValueError(f"TrainConfig.{name} must be positive, got {getattr(self, name)}")
        if self.batch_size <= 0:
            raise ValueError(f"TrainConfig.batch_size must be positive, got {self.batch_size}")
        for name in ("clip_tensor_norm", "clip_global_norm"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ValueError(f"TrainConfig.{name} must be positive or None, got {v}")


@struct.dataclass
class TrainState:
    params: dict
    opt_state: optax.OptState
    step: jax.Array  # i32[]
    key: jax.Array


def clip_by_tensor_norm(max_norm: float) -> optax.GradientTransformation:
    """Scale each gradient tensor separately to norm <= ``max_norm``.

    Written here because optax clips by global norm or by block RMS, not by each tensor's L2 norm,
    which is what the authors' TensorFlow code did (``tf.clip_by_norm`` per variable).
    """

    def clip(g):
        norm = jnp.sqrt(jnp.sum(jnp.square(g)))
        return g * jnp.minimum(1.0, max_norm / jnp.maximum(norm, 1e-12))

    return optax.stateless(lambda updates, params=None: jax.tree.map(clip, updates))


def _kernel_mask(params):
    return jax.tree_util.tree_map_with_path(lambda p, _: jax.tree_util.keystr(p).endswith("kernel']"), params)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    parts = []
    if cfg.clip_tensor_norm is not None:
        parts.append(clip_by_tensor_norm(cfg.clip_tensor_norm))
    if cfg.clip_global_norm is not None:
        parts.append(optax.clip_by_global_norm(cfg.clip_global_norm))
    parts.append(optax.scale_by_adam(b1=cfg.adam_b1, b2=cfg.adam_b2, eps=cfg.adam_eps))
    if cfg.weight_decay:
        parts.append(optax.add_decayed_weights(cfg.weight_decay, mask=_kernel_mask))
    parts.append(optax.scale_by_learning_rate(cfg.learning_rate))
    return optax.chain(*parts)


def init_train_state(model, cfg: TrainConfig, key: jax.Array) -> TrainState:
    init_key, key = jax.random.split(key)
    params = model.init(init_key)
    return TrainState(params=params, opt_state=make_optimizer(cfg).init(params), step=jnp.zeros((), jnp.int32), key=key)


def make_train_step(model, cfg: TrainConfig) -> Callable:
    """``train_step(state, batch) -> (state, metrics)``: pure, jit it (or scan it) as you like."""
    optimizer = make_optimizer(cfg)

    def train_step(state: TrainState, batch: losses.Batch):
        grad_fn = jax.value_and_grad(lambda p: losses.total_loss(model, p, batch, cfg.l2_coeff), has_aux=True)
        (_, metrics), grads = grad_fn(state.params)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        metrics["grad_norm"] = optax.global_norm(grads)
        return state.replace(params=params, opt_state=opt_state, step=state.step + 1), metrics

    return train_step


def make_train(model, cfg: TrainConfig, sample_batch: Callable, num_steps: int) -> Callable:
    """``train(state) -> (state, metrics[num_steps])``: ``num_steps`` steps under one jit (``lax.scan``).

    ``sample_batch(key) -> Batch`` draws a batch of ``cfg.batch_size`` windows (a pure function, e.g.
    a jitted window sampler over a device-resident buffer).  Call ``train`` repeatedly for logging or
    checkpointing between chunks.
    """
    if num_steps <= 0:
        raise ValueError(f"num_steps must be positive, got {num_steps}")
    train_step = make_train_step(model, cfg)

    def body(state, _):
        key, batch_key = jax.random.split(state.key)
        state, metrics = train_step(state.replace(key=key), sample_batch(batch_key))
        return state, metrics

    @jax.jit
    def train(state: TrainState):
        return jax.lax.scan(body, state, None, length=num_steps)

    return train
