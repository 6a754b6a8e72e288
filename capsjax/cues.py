"""The cue table: what each predicted event cue is, how it is activated, labelled and scored.

A ``Cue`` is declarative and hashable (it lives in the static model definition).  It says
* which per-step ground-truth ``signal`` its labels come from (a key of ``EnvState.signals`` /
  the dataset's signal columns),
* its ``kind``: 'binary' (one head, sigmoid, cross-entropy), 'scalar' (one head, MSE) or 'angle'
  (two heads for cos and sin, MSE, as the paper's heading_cos / heading_sin),
* its ``activation`` of the head's pre-activation p: 'sigmoid', 'linear', 'tanh', or 'residual'
  (angle only: ``residual_scale * tanh(p) + (cos, sin)`` of the current value read from the vector
  state key ``anchor_key``: the paper's trick of predicting a bounded change around the present),
* its label rule: ``absorbing`` cues (collision) take the cumulative OR over the horizon and are
  trained on every step, even after the episode ended; all others are masked after the terminal
  step, the terminal step itself included,
  With ``residual_frame='ego'`` (the default heading cue) the bounded change is expressed in the
  car's frame at time t and rotated into the world: ``R(theta_t) @ ((1, 0) + scale * tanh(p))``.  The
  output and the loss are the same world-frame quantities as the paper's (a rotation keeps squared
  errors), but the network no longer has to learn the rotation by the current heading itself, which it
  does poorly from a normalised angle input; ``HEADING_PAPER`` keeps the paper's additive form.
* ``scale``: squared errors are computed on ``(prediction - label) / scale`` so cues of different
  units weigh alike (1 reproduces the paper).

Users add their own cue by constructing a ``Cue`` and passing it to ``ModelConfig(cues=...)``; no
library code changes.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax

KINDS = ("binary", "scalar", "angle")
ACTIVATIONS = ("sigmoid", "linear", "tanh", "residual")


@dataclasses.dataclass(frozen=True)
class Cue:
    name: str
    kind: str = "scalar"
    activation: str = "linear"
    signal: str | None = None  # defaults to ``name``
    absorbing: bool = False
    anchor_key: str | None = None  # vector-state key anchoring a 'residual' activation
    residual_scale: float = 2.0
    residual_frame: str = "world"  # 'world' (the paper's) or 'ego' (see the module docstring)
    scale: float = 1.0

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"Cue {self.name!r}: kind must be one of {KINDS}, got {self.kind!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"Cue {self.name!r}: activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        if self.kind == "binary" and self.activation != "sigmoid":
            raise ValueError(f"Cue {self.name!r}: a binary cue needs activation 'sigmoid', got {self.activation!r}")
        if (self.activation == "residual") != (self.kind == "angle" and self.anchor_key is not None):
            raise ValueError(
                f"Cue {self.name!r}: activation 'residual' is for angle cues with an anchor_key "
                f"(got kind={self.kind!r}, activation={self.activation!r}, anchor_key={self.anchor_key!r})"
            )
        if self.residual_frame not in ("world", "ego"):
            raise ValueError(f"Cue {self.name!r}: residual_frame must be 'world' or 'ego', got {self.residual_frame!r}")
        if self.absorbing and self.kind != "binary":
            raise ValueError(f"Cue {self.name!r}: only binary cues can be absorbing")
        if not self.scale > 0:
            raise ValueError(f"Cue {self.name!r}: scale must be positive, got {self.scale}")

    @property
    def source(self) -> str:
        return self.signal or self.name

    @property
    def dim(self) -> int:
        """Number of network heads (and of values per step in the prediction)."""
        return 2 if self.kind == "angle" else 1

    def anchor(self, vector_now: jax.Array, vector_keys: tuple[str, ...]) -> jax.Array:
        """The value a residual prediction is centred on, from the raw current vector state ``f32[D]``."""
        if self.activation != "residual":
            return jnp.zeros((self.dim,), jnp.float32)
        if self.anchor_key not in vector_keys:
            raise ValueError(f"Cue {self.name!r}: anchor_key {self.anchor_key!r} is not a vector key {vector_keys}")
        angle = vector_now[..., vector_keys.index(self.anchor_key)]
        return jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1)

    def activate(self, raw: jax.Array, anchor: jax.Array) -> jax.Array:
        """Pre-activations ``[..., dim]`` to predictions: ``[...]`` for one head, ``[..., 2]`` for angles."""
        if self.activation == "sigmoid":
            out = jax.nn.sigmoid(raw)
        elif self.activation == "tanh":
            out = jnp.tanh(raw)
        elif self.activation == "residual" and self.residual_frame == "ego":
            change = self.residual_scale * jnp.tanh(raw)
            ego_x, ego_y = 1.0 + change[..., 0], change[..., 1]
            cos, sin = anchor[..., 0], anchor[..., 1]
            out = jnp.stack([ego_x * cos - ego_y * sin, ego_x * sin + ego_y * cos], axis=-1)
        elif self.activation == "residual":
            out = self.residual_scale * jnp.tanh(raw) + anchor
        else:
            out = raw
        return out if self.kind == "angle" else out[..., 0]

    def labels(self, signal: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Targets and loss mask from future signal values ``f32[..., H]`` and ``valid`` ``bool[..., H]``.

        ``valid[k]`` says observation t+k+1 belongs to the episode (the terminal one included).
        Returns ``(target [..., H, dim], mask [..., H])``.
        """
        signal = jnp.asarray(signal, jnp.float32)
        valid = jnp.asarray(valid, bool)
        if self.absorbing:
            # Cumulative OR of the in-episode events: after a crash the label stays 1 to the horizon's end,
            # after a time-out the padded steps stay 0; never masked.
            happened = jnp.where(valid, signal > 0.5, False)
            target = jax.lax.cummax(happened.astype(jnp.float32), axis=happened.ndim - 1)
            return target[..., None], jnp.ones_like(target)
        if self.kind == "angle":
            target = jnp.stack([jnp.cos(signal), jnp.sin(signal)], axis=-1)
        else:
            target = signal[..., None]
        return target, valid.astype(jnp.float32)

    def loss(self, raw: jax.Array, target: jax.Array, anchor: jax.Array) -> jax.Array:
        """Per-step loss ``[..., H]`` (summed over the cue's heads) before masking."""
        if self.kind == "binary":
            return optax.sigmoid_binary_cross_entropy(raw, target).sum(-1)
        pred = self.activate(raw, anchor)
        pred = pred if self.kind == "angle" else pred[..., None]
        return 0.5 * jnp.square((pred - target) / self.scale).sum(-1)


# The standard cues.  Collision, speed and heading are self-supervised from the vector state; the lane
# and door cues come from a segmentation labeller (learned, or the oracle semantic map).
COLLISION = Cue("collision", kind="binary", activation="sigmoid", absorbing=True)
SPEED = Cue("speed", kind="scalar", activation="linear")
HEADING = Cue("heading", kind="angle", activation="residual", anchor_key="heading", residual_frame="ego")
HEADING_PAPER = Cue("heading", kind="angle", activation="residual", anchor_key="heading", residual_frame="world")
LANE_SEEN = Cue("lane_seen", kind="binary", activation="sigmoid")
LANE_DIFF = Cue("lane_diff", kind="scalar", activation="tanh")
DOOR_FRAC = Cue("door_frac", kind="scalar", activation="sigmoid", scale=0.1)

STANDARD_CUES = (COLLISION, SPEED, HEADING, LANE_SEEN, LANE_DIFF, DOOR_FRAC)


def check_unique(cues: tuple[Cue, ...]) -> None:
    names = [c.name for c in cues]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"cue names must be unique, repeated: {dup}")
    if not cues:
        raise ValueError("a model needs at least one cue")
