"""The CAPs predictor: images + vector history -> LSTM state; planned actions -> per-cue predictions.

Architecture and sizes follow the authors' code (caps-algorithm.md section 2) by default:
* 4-frame image history, normalised (x - 128) / 128 and stacked on channels (index c * L + l), a
  4-layer SAME-padded ReLU CNN (64/8x8/4, 32/4x4/2, 32/3x3/2, 32/3x3/2), Glorot-uniform, zero bias;
* the vector history normalised by its box and flattened time-major, concatenated to the CNN features;
* an observation MLP 256 -> 128 (ReLU) whose output is split into the LSTM's (c0, h0), so 64 units;
* a per-step action embedding 16 -> 128 (ReLU) of actions normalised by the full action range;
* a multiplicative-integration LSTM (z = tanh(a*Wx*Uh + b1*Uh + b2*Wx + b), gates sigma(tanh(.)),
  forget bias 1) with the paper's truncated-normal initialisations of a, b1, b2, b;
* one Dense 16 -> 1 head per cue output (an angle cue has two heads, cos and sin).

Speed (the planner runs this for thousands of candidates per control step): ``encode`` runs once per
observation; ``rollout`` embeds every action and projects every LSTM input in one matmul *outside*
the scan, so the scan body holds only the 64 x 256 recurrent matmul and the gate arithmetic, and all
heads run in one batched matmul after the scan.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from capsjax import cues as cues_lib

PAPER_CONV = ((64, 8, 4), (32, 4, 2), (32, 3, 2), (32, 3, 2))  # (filters, kernel, stride)


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Static model definition: observation/action spaces, layer sizes and the cue table."""

    image_shape: tuple[int, int, int]  # (h, w, c) of one frame
    vector_keys: tuple[str, ...]
    vector_low: tuple[float, ...]
    vector_high: tuple[float, ...]
    action_low: tuple[float, ...]  # env action space: actions are normalised by its full range
    action_high: tuple[float, ...]
    cues: tuple[cues_lib.Cue, ...] = (cues_lib.COLLISION, cues_lib.HEADING)
    history: int = 4
    horizon: int = 12  # the training horizon; rollouts may use any length up to it
    conv: tuple[tuple[int, int, int], ...] = PAPER_CONV
    # Average-pool each frame by this factor before the CNN (1: none, the paper's).  A CPU-budget knob:
    # 2 quarters the CNN's work on the halls' 96x128 frames (the CNN dominates a training step).
    image_pool: int = 1
    obs_hidden: tuple[int, ...] = (256, 128)
    action_hidden: tuple[int, ...] = (16, 128)
    head_hidden: int = 16

    def __post_init__(self):
        # Lists or arrays are accepted and stored as tuples: the config must hash (it is static).
        for name in ("vector_low", "vector_high", "action_low", "action_high"):
            object.__setattr__(self, name, tuple(float(x) for x in getattr(self, name)))
        object.__setattr__(self, "image_shape", tuple(int(x) for x in self.image_shape))
        object.__setattr__(self, "vector_keys", tuple(self.vector_keys))
        object.__setattr__(self, "cues", tuple(self.cues))
        if len(self.image_shape) != 3 or min(self.image_shape) <= 0:
            raise ValueError(f"ModelConfig.image_shape must be (h, w, c) positive, got {self.image_shape}")
        if not (len(self.vector_low) == len(self.vector_high) == len(self.vector_keys)):
            raise ValueError("ModelConfig.vector_low/high must have one entry per vector key")
        if len(self.action_low) != len(self.action_high) or not self.action_low:
            raise ValueError("ModelConfig.action_low/high must be non-empty and of equal length")
        if any(lo >= hi for lo, hi in zip(self.action_low, self.action_high)):
            raise ValueError(f"ModelConfig.action_low must be < action_high, got {self.action_low}, {self.action_high}")
        if self.obs_hidden[-1] % 2:
            raise ValueError(f"ModelConfig.obs_hidden[-1] must be even (split into LSTM c and h), got {self.obs_hidden}")
        for name in ("history", "horizon", "head_hidden", "image_pool"):
            if getattr(self, name) <= 0:
                raise ValueError(f"ModelConfig.{name} must be positive, got {getattr(self, name)}")
        h, w = self.image_shape[:2]
        if h % self.image_pool or w % self.image_pool:
            raise ValueError(f"ModelConfig.image_pool={self.image_pool} must divide the frame size {h}x{w}")
        cues_lib.check_unique(self.cues)
        for cue in self.cues:
            if cue.activation == "residual" and cue.anchor_key not in self.vector_keys:
                raise ValueError(
                    f"cue {cue.name!r} anchors on vector key {cue.anchor_key!r}, not among {self.vector_keys}"
                )

    @classmethod
    def from_env_spec(cls, spec, cues=None, **overrides) -> "ModelConfig":
        """Spaces from an ``envs.base.EnvSpec``; ``cues`` default to the standard cues the env can label."""
        if cues is None:
            cues = tuple(c for c in cues_lib.STANDARD_CUES if c.source in spec.signal_names)
        return cls(
            image_shape=tuple(spec.image_shape), vector_keys=tuple(spec.vector_keys),
            vector_low=tuple(spec.vector_low), vector_high=tuple(spec.vector_high),
            action_low=tuple(spec.action_low), action_high=tuple(spec.action_high),
            history=spec.history, cues=tuple(cues), **overrides,
        )

    @property
    def lstm_units(self) -> int:
        return self.obs_hidden[-1] // 2

    @property
    def action_dim(self) -> int:
        return len(self.action_low)

    @property
    def num_heads(self) -> int:
        return sum(c.dim for c in self.cues)

    def head_slices(self) -> dict[str, slice]:
        out, start = {}, 0
        for cue in self.cues:
            out[cue.name] = slice(start, start + cue.dim)
            start += cue.dim
        return out


@struct.dataclass
class Carry:
    """What ``encode`` hands to ``rollout``: the LSTM state and the residual anchors of each cue."""

    c: jax.Array  # f32[U]
    h: jax.Array  # f32[U]
    anchors: jax.Array  # f32[num_heads]: the residual centre per head (0 for non-residual heads)


def _sigmoid(x):
    # Through tanh: one vectorised transcendental (XLA's CPU logistic costs an exp and a divide).
    return 0.5 * jnp.tanh(0.5 * x) + 0.5


def _truncated_normal(mean: float, std: float):
    def init(key, shape, dtype=jnp.float32):
        return mean + std * jax.random.truncated_normal(key, -2.0, 2.0, shape, dtype)

    return init


class _Network(nn.Module):
    """Parameter owner; the public API is ``CAPsModel`` below (params in, arrays out)."""

    cfg: ModelConfig

    def setup(self):
        cfg = self.cfg
        glorot, zeros = nn.initializers.glorot_uniform(), nn.initializers.zeros
        self.convs = [
            nn.Conv(f, (k, k), strides=(s, s), padding="SAME", kernel_init=glorot, bias_init=zeros, name=f"conv{i}")
            for i, (f, k, s) in enumerate(cfg.conv)
        ]
        self.obs_mlp = [nn.Dense(n, kernel_init=glorot, bias_init=zeros, name=f"obs{i}") for i, n in enumerate(cfg.obs_hidden)]
        self.act_mlp = [
            nn.Dense(n, kernel_init=glorot, bias_init=zeros, name=f"act{i}") for i, n in enumerate(cfg.action_hidden)
        ]
        units = cfg.lstm_units
        # Multiplicative-integration LSTM parameters (names end in "kernel" where the paper applies L2).
        self.input_kernel = self.param("lstm_input_kernel", glorot, (cfg.action_hidden[-1], 4 * units))
        self.recurrent_kernel = self.param("lstm_recurrent_kernel", glorot, (units, 4 * units))
        self.alpha = self.param("lstm_alpha", _truncated_normal(1.0, 0.1), (4 * units,))
        self.beta_h = self.param("lstm_beta_h", _truncated_normal(0.5, 0.1), (4 * units,))
        self.beta_x = self.param("lstm_beta_x", _truncated_normal(0.5, 0.1), (4 * units,))
        self.bias = self.param("lstm_bias", _truncated_normal(0.0, 0.1), (4 * units,))
        heads, hidden = cfg.num_heads, cfg.head_hidden
        # All heads stacked so they run as one matmul (per-head weights stay independent).
        self.head_kernel = self.param("head_hidden_kernel", glorot, (units, heads * hidden))
        self.head_bias = self.param("head_hidden_bias", zeros, (heads * hidden,))
        # Glorot-uniform as for a Dense(hidden -> 1) per head.
        limit = math.sqrt(6.0 / (hidden + 1))
        self.head_out_kernel = self.param(
            "head_out_kernel", lambda k, s: jax.random.uniform(k, s, jnp.float32, -limit, limit), (heads, hidden)
        )
        self.head_out_bias = self.param("head_out_bias", zeros, (heads,))

    def encode(self, images: jax.Array, vector: jax.Array) -> Carry:
        cfg = self.cfg
        # u8[L, h, w, c] -> f32[h, w, c*L] with channel index c*L + l, as the authors stack frames.
        x = (images.astype(jnp.float32) - 128.0) / 128.0
        x = jnp.transpose(x, (1, 2, 3, 0)).reshape(x.shape[1], x.shape[2], -1)
        if cfg.image_pool > 1:
            p = cfg.image_pool
            x = nn.avg_pool(x, (p, p), strides=(p, p))
        for conv in self.convs:
            x = nn.relu(conv(x))
        low = jnp.asarray(cfg.vector_low, jnp.float32)
        high = jnp.asarray(cfg.vector_high, jnp.float32)
        v = (vector - 0.5 * (low + high)) / (0.5 * (high - low))
        z = jnp.concatenate([x.reshape(-1), v.reshape(-1)])
        for dense in self.obs_mlp:
            z = nn.relu(dense(z))
        units = cfg.lstm_units
        anchors = jnp.concatenate([cue.anchor(vector[-1], cfg.vector_keys) for cue in cfg.cues])
        return Carry(c=z[:units], h=z[units:], anchors=anchors)

    def rollout_raw(self, carry: Carry, actions: jax.Array) -> jax.Array:
        """Pre-activations ``f32[..., H, num_heads]`` for action sequences ``f32[..., H, A]``.

        Leading dims are candidates sharing one ``carry`` (the CNN ran once).  Internally time-major
        ([H, M, .]) so each scan step reads one contiguous slab and no large transpose is needed.
        """
        cfg = self.cfg
        lead = actions.shape[:-2]
        horizon = actions.shape[-2]
        acts = jnp.moveaxis(actions.reshape((-1,) + actions.shape[-2:]), 1, 0)  # [H, M, A] (small)
        low = jnp.asarray(cfg.action_low, jnp.float32)
        high = jnp.asarray(cfg.action_high, jnp.float32)
        x = (acts - 0.5 * (low + high)) / (high - low)  # full range, as the paper: in [-0.5, 0.5]
        for dense in self.act_mlp:
            x = nn.relu(dense(x))
        wx = x @ self.input_kernel  # [H, M, 4U]: every step's input projection in one matmul
        alpha, beta_h, beta_x, bias, recurrent = self.alpha, self.beta_h, self.beta_x, self.bias, self.recurrent_kernel
        num = wx.shape[1]

        def cell(state, wx_k):
            c, h = state
            uh = h @ recurrent
            # z = tanh(alpha*Wx*Uh + beta_h*Uh + beta_x*Wx + b); the Wx-only terms fuse into this loop
            # body, so only Wx (not two derived arrays) streams from memory.
            z = jnp.tanh((alpha * wx_k + beta_h) * uh + (beta_x * wx_k + bias))
            i, j, f, o = jnp.split(z, 4, axis=-1)
            c = c * _sigmoid(f + 1.0) + _sigmoid(i) * jnp.tanh(j)
            h = jnp.tanh(c) * _sigmoid(o)
            return (c, h), h

        init = (jnp.broadcast_to(carry.c, (num, cfg.lstm_units)), jnp.broadcast_to(carry.h, (num, cfg.lstm_units)))
        _, hs = jax.lax.scan(cell, init, wx, unroll=True)  # [H, M, U]; unrolled: the horizon is short and static
        hidden = nn.relu(hs @ self.head_kernel + self.head_bias)  # [H, M, heads*hidden], all heads at once
        hidden = hidden.reshape(hs.shape[:2] + (cfg.num_heads, cfg.head_hidden))
        raw = jnp.einsum("tmhk,hk->mth", hidden, self.head_out_kernel) + self.head_out_bias  # [M, H, heads]
        return raw.reshape(lead + (horizon, cfg.num_heads))

    def __call__(self, images, vector, actions):
        return self.rollout_raw(self.encode(images, vector), actions)


@dataclasses.dataclass(frozen=True)
class CAPsModel:
    """Static, hashable model definition with pure functions of a params pytree.

    >>> model = CAPsModel(cfg); params = model.init(key)
    >>> carry = model.encode(params, obs); preds = model.rollout(params, carry, actions)
    """

    config: ModelConfig

    @property
    def network(self) -> _Network:
        return _Network(self.config)

    @property
    def cues(self) -> tuple[cues_lib.Cue, ...]:
        return self.config.cues

    @property
    def cue_names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.config.cues)

    @property
    def action_low(self) -> tuple[float, ...]:
        return self.config.action_low

    @property
    def action_high(self) -> tuple[float, ...]:
        return self.config.action_high

    @property
    def horizon(self) -> int:
        return self.config.horizon

    def init(self, key: jax.Array) -> Any:
        cfg = self.config
        images = jnp.zeros((cfg.history,) + cfg.image_shape, jnp.uint8)
        vector = jnp.zeros((cfg.history, len(cfg.vector_keys)), jnp.float32)
        actions = jnp.zeros((cfg.horizon, cfg.action_dim), jnp.float32)
        return self.network.init(key, images, vector, actions)

    def check_observation(self, obs) -> None:
        """Trace-time check of one robot's observation; raises a ValueError naming the field."""
        cfg = self.config
        want_images = (cfg.history,) + tuple(cfg.image_shape)
        if tuple(obs.images.shape) != want_images or obs.images.dtype != jnp.uint8:
            raise ValueError(f"obs.images must be uint8{list(want_images)}, got {obs.images.dtype}{list(obs.images.shape)}")
        if not jnp.issubdtype(obs.vector.dtype, jnp.floating):
            raise ValueError(f"obs.vector must be a float array (float32), got {obs.vector.dtype}")
        want_vector = (cfg.history, len(cfg.vector_keys))
        if tuple(obs.vector.shape) != want_vector:
            raise ValueError(f"obs.vector must have shape {want_vector} (keys {cfg.vector_keys}), got {tuple(obs.vector.shape)}")

    def encode(self, params, obs) -> Carry:
        """Once per observation (one robot): CNN + vector MLP -> LSTM state."""
        self.check_observation(obs)
        return self.network.apply(params, obs.images, jnp.asarray(obs.vector, jnp.float32), method=_Network.encode)

    def rollout_raw(self, params, carry: Carry, actions: jax.Array) -> jax.Array:
        return self.network.apply(params, carry, jnp.asarray(actions, jnp.float32), method=_Network.rollout_raw)

    def activate(self, raw: jax.Array, anchors: jax.Array) -> dict[str, jax.Array]:
        """Pre-activations ``[..., H, heads]`` -> ``{cue: [..., H] or [..., H, 2]}``."""
        slices = self.config.head_slices()
        return {
            cue.name: cue.activate(raw[..., slices[cue.name]], anchors[..., None, slices[cue.name]])
            for cue in self.config.cues
        }

    def rollout(self, params, carry: Carry, actions: jax.Array) -> dict[str, jax.Array]:
        """Predictions ``{cue: f32[..., H] (angles f32[..., H, 2])}`` for sequences ``f32[..., H, A]``.

        Leading dims of ``actions`` are candidates sharing ``carry`` (one observation): pass all of a
        planner's candidates at once (fastest), or vmap over them with ``carry`` unbatched; either way
        the CNN is not recomputed.
        """
        return self.activate(self.rollout_raw(params, carry, actions), carry.anchors)

    def predict(self, params, obs, actions) -> dict[str, jax.Array]:
        return self.rollout(params, self.encode(params, obs), actions)


def count_params(params) -> int:
    return int(sum(math.prod(x.shape) for x in jax.tree.leaves(params)))


def rollout_flops(cfg: ModelConfig, horizon: int) -> int:
    """Analytic multiply-add FLOPs (2 per MAC) of one candidate rollout; used by the planner benchmark."""
    flops, width = 0, cfg.action_dim
    for n in cfg.action_hidden:
        flops += 2 * width * n
        width = n
    units = cfg.lstm_units
    flops += 2 * width * 4 * units  # input projection
    flops += 2 * units * 4 * units  # recurrent matmul
    flops += 2 * units * cfg.num_heads * cfg.head_hidden + 2 * cfg.num_heads * cfg.head_hidden
    return flops * horizon
