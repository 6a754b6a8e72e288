"""Reward composition: a task is a weighted sum of per-cue terms over the predicted horizon.

    R = sum_h sum_k  w_k * phi_k(preds_h, actions_h, goals) * (1 - g_k * collision_h)

``phi_k`` come from a fixed library of terms (below); the weights ``w``, gates ``g`` and goals are
float32 arrays in a ``RewardSpec``, so changing the task never recompiles a jitted planner.  Gates
express the RC-car reward's product form: a gated term counts only while the car has not crashed.

Paper rewards in this form (sums over the horizon; the authors' code averages, same argmax):
* forest:  collision=500, heading_cos=1
* CARLA:   collision=50, speed=3, lane=5, steer=0.15, heading_angle=5, goal_speed=7
* RC car:  (1 - c) * [1 - (0.1/pi)|h - h_goal| + 0.05 door] - 0.01 |a|^2 is collision=1 (already
           1 - c), heading_angle=0.1 and door=0.05 with gated=("heading_angle", "door"), action=0.01

Beyond the paper, ``path`` composes two cues into a third quantity: the predicted speeds and headings
integrated over the horizon give where the car will be, scored by its distance to ``goal_path`` (a
polyline relative to the car, refreshed every control step like the goal heading).
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

Preds = dict  # {cue name: f32[..., H] or f32[..., H, 2]}


@dataclasses.dataclass(frozen=True)
class Term:
    """One reward term: ``fn(preds, norm_actions, spec) -> f32[..., H]``, needing the cues ``needs``."""

    name: str
    needs: tuple[str, ...]
    fn: Callable
    doc: str


def _unit(v, eps=1e-6):
    return v / jnp.maximum(jnp.linalg.norm(v, axis=-1, keepdims=True), eps)


def _heading_cosine(preds, spec):
    """Cosine between the predicted heading and the goal heading, in [-1, 1]."""
    v = _unit(jnp.clip(preds["heading"], -1 + 1e-4, 1 - 1e-4))
    u = _unit(spec.goal_heading)
    return jnp.clip(jnp.sum(v * u[..., None, :], axis=-1), -1.0, 1.0)


def _goal_speed(spec):
    return jnp.maximum(jnp.abs(spec.goal_speed), 1e-3)[..., None]


def _dead_reckoned_positions(preds, spec):
    """Positions f32[..., H, 2] (m, world-aligned, relative to the car now) integrated from the predicted
    speed and heading of every step: the cues compose into where the car will be."""
    step = (preds["speed"] * spec.step_seconds)[..., None] * _unit(preds["heading"])
    return jnp.cumsum(step, axis=-2)


def polyline_distance(points: jax.Array, path: jax.Array) -> jax.Array:
    """Distance f32[...] of each point ``[..., 2]`` to the polyline ``path`` f32[P, 2] (P >= 2)."""
    start, seg = path[:-1], path[1:] - path[:-1]  # [P-1, 2]
    rel = points[..., None, :] - start  # [..., P-1, 2]
    t = jnp.clip(jnp.sum(rel * seg, -1) / jnp.maximum(jnp.sum(seg * seg, -1), 1e-12), 0.0, 1.0)
    return jnp.min(jnp.linalg.norm(rel - t[..., None] * seg, axis=-1), axis=-1)


def _path_distance(preds, spec):
    distance = polyline_distance(_dead_reckoned_positions(preds, spec), spec.goal_path)
    return -jnp.maximum(distance - spec.path_tolerance, 0.0)


def _heading_angle(preds, actions, spec):
    angle = -jnp.arccos(_heading_cosine(preds, spec)) / jnp.pi
    # As the authors: no heading term when no goal heading is given (a zero vector).
    has_goal = jnp.linalg.norm(spec.goal_heading, axis=-1) >= 1e-2
    return jnp.where(has_goal[..., None], angle, 0.0)


TERMS: tuple[Term, ...] = (
    Term("collision", ("collision",), lambda p, a, s: 1.0 - p["collision"],
         "probability of not having collided (1 - c)"),
    Term("speed", ("speed",), lambda p, a, s: -jnp.abs(p["speed"] - s.goal_speed[..., None]) / _goal_speed(s),
         "-|v - v_goal| / v_goal"),
    Term("speed_sq", ("speed",), lambda p, a, s: -jnp.square((p["speed"] - s.goal_speed[..., None]) / _goal_speed(s)),
         "-((v - v_goal) / v_goal)^2"),
    Term("heading_cos", ("heading",), lambda p, a, s: _heading_cosine(p, s) - 1.0,
         "cos(h - h_goal) - 1 (forest)"),
    Term("heading_angle", ("heading",), _heading_angle,
         "-|h - h_goal| / pi (CARLA, RC car); 0 without a goal heading"),
    Term("path", ("speed", "heading"), lambda p, a, s: _path_distance(p, s),
         "-distance (m) beyond path_tolerance of the position dead-reckoned from predicted speed and "
         "heading to goal_path"),
    Term("lane", ("lane_seen", "lane_diff"),
         lambda p, a, s: p["lane_seen"] * (1.0 - jnp.abs(p["lane_diff"] - s.lane_offset[..., None])),
         "seen * (1 - |diff - lane_offset|): in the target lane"),
    Term("door", ("door_frac",), lambda p, a, s: p["door_frac"], "fraction of the image that is door"),
    Term("steer", (), lambda p, a, s: -jnp.square(a[..., 0]), "-steer^2, steering normalised to [-1, 1]"),
    Term("action", (), lambda p, a, s: -jnp.sum(jnp.square(a), axis=-1), "-|a|^2, actions normalised to [-1, 1]"),
)
TERM_NAMES = tuple(t.name for t in TERMS)


@struct.dataclass
class RewardSpec:
    """A task as data.  Build it with ``RewardSpec.from_terms``; every leaf is a float32 array."""

    weights: jax.Array  # f32[K], one per term of ``terms``
    gates: jax.Array  # f32[K] in [0, 1]: 1 multiplies the term by (1 - collision)
    goal_speed: jax.Array  # f32[]
    goal_heading: jax.Array  # f32[2], world-frame unit vector (cos, sin) of the wanted heading
    lane_offset: jax.Array  # f32[]: wanted lane_diff (0 = centred in the right lane)
    goal_path: jax.Array  # f32[P, 2]: the path to keep to (m, world-aligned, relative to the car now)
    step_seconds: jax.Array  # f32[]: one control step (s), to integrate predicted speed into positions
    path_tolerance: jax.Array  # f32[]: distance (m) from goal_path the path term leaves free
    action_mid: jax.Array  # f32[A]: actions are normalised to [-1, 1] by this mid and half range
    action_half: jax.Array  # f32[A]
    terms: tuple[str, ...] = struct.field(pytree_node=False, default=TERM_NAMES)

    @classmethod
    def from_terms(
        cls,
        model,
        *,
        goal_speed=0.0,
        goal_heading=(0.0, 0.0),
        lane_offset=0.0,
        goal_path=((0.0, 0.0), (0.0, 0.0)),
        step_seconds=0.0,
        path_tolerance=0.0,
        gated=(),
        **weights,
    ) -> "RewardSpec":
        """Weights by term name, validated against the model's cues.

        ``model`` is anything with ``cue_names``, ``action_low`` and ``action_high`` (a ``CAPsModel``).
        Every term of the library gets a slot (unused ones weigh 0), so specs built from different
        subsets share one compiled planner.  The ``path`` term needs ``step_seconds`` (the control
        step) to turn predicted speeds into distances; it counts only the distance beyond
        ``path_tolerance`` (m).
        """
        unknown = sorted(set(weights) - set(TERM_NAMES))
        if unknown:
            raise ValueError(f"unknown reward term(s) {unknown}; valid terms: {list(TERM_NAMES)}")
        unknown_gates = sorted(set(gated) - set(TERM_NAMES))
        if unknown_gates:
            raise ValueError(f"gated names unknown term(s) {unknown_gates}; valid terms: {list(TERM_NAMES)}")
        available = set(model.cue_names)
        for term in TERMS:
            w = weights.get(term.name, 0.0)
            if isinstance(w, jax.core.Tracer):  # traced weights are checked by the caller's data path
                continue
            if not np.all(np.isfinite(np.asarray(w, np.float64))):
                raise ValueError(f"weight of reward term {term.name!r} must be finite, got {w}")
            missing = [c for c in term.needs if c not in available]
            if missing and np.any(np.asarray(w) != 0):
                raise ValueError(
                    f"reward term {term.name!r} needs cue(s) {missing}, which the model does not predict; "
                    f"the model's cues are {list(model.cue_names)}"
                )
        path_weight = weights.get("path", 0.0)
        if not isinstance(path_weight, jax.core.Tracer) and np.any(np.asarray(path_weight) != 0):
            if not isinstance(step_seconds, jax.core.Tracer) and not np.all(np.asarray(step_seconds) > 0):
                raise ValueError(f"reward term 'path' needs step_seconds > 0 (the control step in seconds), "
                                 f"got {step_seconds}")
        if not isinstance(path_tolerance, jax.core.Tracer) and np.any(np.asarray(path_tolerance) < 0):
            raise ValueError(f"RewardSpec.path_tolerance must be >= 0 (m), got {path_tolerance}")
        low = np.asarray(model.action_low, np.float32)
        high = np.asarray(model.action_high, np.float32)
        return cls(
            weights=_f32([weights.get(n, 0.0) for n in TERM_NAMES], "weights", (len(TERM_NAMES),)),
            gates=_f32([1.0 if n in gated else 0.0 for n in TERM_NAMES], "gates", (len(TERM_NAMES),)),
            goal_speed=_f32(goal_speed, "goal_speed", ()),
            goal_heading=_f32(goal_heading, "goal_heading", (2,)),
            lane_offset=_f32(lane_offset, "lane_offset", ()),
            goal_path=_path(goal_path),
            step_seconds=_f32(step_seconds, "step_seconds", ()),
            path_tolerance=_f32(path_tolerance, "path_tolerance", ()),
            action_mid=jnp.asarray(0.5 * (low + high)),
            action_half=jnp.asarray(0.5 * (high - low)),
        )

    def with_goals(self, *, goal_speed=None, goal_heading=None, lane_offset=None, goal_path=None) -> "RewardSpec":
        """The same weights with new goals (e.g. the heading recomputed every control step)."""
        out = self
        if goal_speed is not None:
            out = out.replace(goal_speed=_f32(goal_speed, "goal_speed", ()))
        if goal_heading is not None:
            out = out.replace(goal_heading=_f32(goal_heading, "goal_heading", (2,), batch_ok=True))
        if lane_offset is not None:
            out = out.replace(lane_offset=_f32(lane_offset, "lane_offset", ()))
        if goal_path is not None:
            out = out.replace(goal_path=_path(goal_path))
        return out


def _path(value) -> jax.Array:
    """A goal path f32[P, 2] with P >= 2 vertices (any P: a new P compiles once more)."""
    out = jnp.asarray(value, jnp.float32)
    if out.ndim != 2 or out.shape[-1] != 2 or out.shape[0] < 2:
        raise ValueError(f"RewardSpec.goal_path must have shape (P, 2) with P >= 2, got {out.shape}")
    if not isinstance(value, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(value, np.float64))):
        raise ValueError("RewardSpec.goal_path must be finite")
    return out


def _f32(value, field: str, shape: tuple, batch_ok: bool = False) -> jax.Array:
    """Cast to a strongly typed float32 array (so Python floats, NumPy and JAX inputs hit one cache)."""
    if not isinstance(value, jax.core.Tracer):
        arr = np.asarray(value, np.float64)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"RewardSpec.{field} must be finite, got {value}")
    out = jnp.asarray(value, jnp.float32)
    ok = out.shape == shape or (batch_ok and out.shape[out.ndim - len(shape):] == shape)
    if not ok:
        raise ValueError(f"RewardSpec.{field} must have shape {shape}, got {out.shape}")
    return out


def term_values(preds: Preds, actions: jax.Array, spec: RewardSpec) -> jax.Array:
    """Per-term, per-step values ``f32[..., K, H]`` (zeros for terms whose cues are not predicted)."""
    norm_actions = (actions - spec.action_mid[..., None, :]) / spec.action_half[..., None, :]
    horizon_shape = actions.shape[:-1]
    by_name = {t.name: t for t in TERMS}
    values = []
    for name in spec.terms:
        term = by_name[name]
        if all(c in preds for c in term.needs):
            values.append(jnp.broadcast_to(term.fn(preds, norm_actions, spec), horizon_shape))
        else:
            values.append(jnp.zeros(horizon_shape, jnp.float32))
    return jnp.stack(values, axis=-2)


def value(preds: Preds, actions: jax.Array, spec: RewardSpec) -> jax.Array:
    """Total reward of each candidate: ``preds`` with leading dims ``[...]``, actions ``[..., H, A]`` -> ``[...]``."""
    per_term = term_values(preds, actions, spec)  # [..., K, H]
    survival = 1.0 - preds["collision"] if "collision" in preds else jnp.ones(actions.shape[:-1], jnp.float32)
    gate = 1.0 - spec.gates[..., :, None] * (1.0 - survival[..., None, :])
    weighted = spec.weights[..., :, None] * per_term * gate
    return jnp.sum(weighted, axis=(-2, -1))
