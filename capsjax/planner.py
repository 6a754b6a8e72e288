"""Model-predictive action selection: CEM (the paper's) and random shooting over H-step sequences.

``plan(model, params, obs, spec, plan_state, key, cfg=...)`` is pure and jittable; vmap it over robots
(each with its own observation, ``RewardSpec`` and key).  ``capsjax.plan`` is this function jitted
once per ``CEMConfig`` (and model definition): reward weights, goals, observations and keys are traced
arguments, so a new task never recompiles.

Paper defaults (caps-algorithm.md section 5.1): a uniform first iteration of 4096 sequences, three more
of 1024 from a full-covariance Gaussian, 128 elites, samples clipped to the box, execute the first
action of the best sample of the last iteration.  Options the paper lacks: diagonal covariance, the
textbook centred covariance (default; ``centred=False`` is the paper's uncentred second moment, for
parity), a warm start from the previous plan shifted by one step, returning the elite mean (or the mean of
the elites nearest the best, which never averages two modes) instead of the best sample, refitting each
iteration to those nearest elites only (so the search follows one mode), and random shooting.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
from flax import struct

from capsjax import reward as reward_lib

COVARIANCES = ("full", "diag")
RETURN_MODES = ("best", "mean", "local_mean")
OPTIMIZERS = ("cem", "random")


@dataclasses.dataclass(frozen=True)
class CEMConfig:
    """Static planner settings (a new one compiles a new planner; everything else is traced)."""

    action_low: tuple[float, ...]  # the action-selection box
    action_high: tuple[float, ...]
    horizon: int = 12
    init_samples: int = 4096  # iteration 0, uniform over the box
    samples: int = 1024  # each later iteration, Gaussian
    iterations: int = 4  # including iteration 0
    elites: int = 128
    covariance: str = "full"
    centred: bool = True  # False: the paper's uncentred E^T E / K (parity mode)
    cov_reg: float = 1e-4
    warm_start: bool = False
    warm_start_std: float = 0.2  # std of warm-start samples, as a fraction of the box half-range
    return_mode: str = "best"
    # Refit each iteration's Gaussian to the half of its elites nearest the best one instead of to all of
    # them, so that the search follows one mode (see 'local_mean'; not the paper's).
    local_refit: bool = False
    optimizer: str = "cem"
    candidate_chunk: int = 0  # candidates scored per sequential chunk; 0 = auto (1024 on CPU, all on GPU)

    def __post_init__(self):
        # Lists or arrays are accepted and stored as float tuples: the config must hash (it is static).
        low = tuple(float(x) for x in self.action_low)
        high = tuple(float(x) for x in self.action_high)
        object.__setattr__(self, "action_low", low)
        object.__setattr__(self, "action_high", high)
        if len(low) == 0 or len(low) != len(high):
            raise ValueError(f"CEMConfig.action_low/high must be non-empty and of equal length, got {low} / {high}")
        if any(not lo < hi for lo, hi in zip(low, high)):
            raise ValueError(f"CEMConfig.action_low must be < action_high in every dimension, got {low} / {high}")
        for name in ("horizon", "init_samples", "samples", "iterations", "elites"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0:
                raise ValueError(f"CEMConfig.{name} must be a positive int, got {v!r}")
        if self.optimizer == "cem" and self.elites > min(self.init_samples, self.samples if self.iterations > 1 else self.init_samples):
            raise ValueError(
                f"CEMConfig.elites ({self.elites}) must not exceed the samples per iteration "
                f"(init_samples={self.init_samples}, samples={self.samples})"
            )
        if self.covariance not in COVARIANCES:
            raise ValueError(f"CEMConfig.covariance must be one of {COVARIANCES}, got {self.covariance!r}")
        if self.return_mode not in RETURN_MODES:
            raise ValueError(f"CEMConfig.return_mode must be one of {RETURN_MODES}, got {self.return_mode!r}")
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"CEMConfig.optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if not isinstance(self.candidate_chunk, int) or self.candidate_chunk < 0:
            raise ValueError(f"CEMConfig.candidate_chunk must be an int >= 0 (0 = auto), got {self.candidate_chunk!r}")
        for name, low in (("cov_reg", 0.0), ("warm_start_std", None)):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or (v < low if low is not None else v <= 0):
                raise ValueError(f"CEMConfig.{name} must be a finite number {'>= 0' if low is not None else '> 0'}, got {v!r}")

    @property
    def action_dim(self) -> int:
        return len(self.action_low)

    @classmethod
    def paper(cls, action_low, action_high, horizon: int = 12) -> "CEMConfig":
        """The authors' exact settings, uncentred covariance included."""
        return cls(tuple(action_low), tuple(action_high), horizon=horizon, centred=False)


@struct.dataclass
class PlanState:
    """What one robot's planner carries between control steps (for the warm start)."""

    previous: jax.Array  # f32[H, A]: the last executed plan
    has_previous: jax.Array  # bool[]


def init_plan_state(cfg: CEMConfig) -> PlanState:
    mid = 0.5 * (jnp.asarray(cfg.action_low, jnp.float32) + jnp.asarray(cfg.action_high, jnp.float32))
    return PlanState(previous=jnp.broadcast_to(mid, (cfg.horizon, cfg.action_dim)), has_previous=jnp.zeros((), bool))


def check_compatible(model, cfg: CEMConfig) -> None:
    if cfg.action_dim != len(model.action_low):
        raise ValueError(
            f"CEMConfig.action_low has {cfg.action_dim} entries but the model takes {len(model.action_low)} actions"
        )
    max_h = getattr(model, "horizon", None)
    if max_h is not None and cfg.horizon > max_h:
        raise ValueError(f"CEMConfig.horizon ({cfg.horizon}) exceeds the model's trained horizon ({max_h})")


def _chunk_size(cfg: CEMConfig, num: int) -> int:
    """Candidates per sequential chunk: on a CPU the LSTM's per-step working set must stay in cache
    (measured on the 2-core CPU: scoring 4,096 candidates at once 120 ms, in chunks of 1,024 78 ms, of
    256 100 ms); accelerators want all at once."""
    chunk = cfg.candidate_chunk or (1024 if jax.default_backend() == "cpu" else num)
    chunk = min(chunk, num)
    while num % chunk:  # static shapes: use the largest divisor not above the request
        chunk -= 1
    return chunk


def _score(model, params, carry, spec, seqs, cfg: CEMConfig):
    """Reward of each candidate ``seqs f32[M, H, A]``; non-finite scores become -inf (never chosen)."""
    num = seqs.shape[0]
    chunk = _chunk_size(cfg, num)

    def value_of(batch):  # one batched, time-major rollout per chunk
        return reward_lib.value(model.rollout(params, carry, batch), batch, spec)

    if chunk == num:
        values = value_of(seqs)
    else:
        values = jax.lax.map(value_of, seqs.reshape((num // chunk, chunk) + seqs.shape[1:])).reshape(num)
    return jnp.where(jnp.isfinite(values), values, -jnp.inf)


def _refit(elites: jax.Array, cfg: CEMConfig):
    """Mean and covariance factor of the elites ``[K, D]`` (Cholesky for 'full', std for 'diag')."""
    mean = elites.mean(0)
    centred = elites - mean if cfg.centred else elites
    if cfg.covariance == "full":
        cov = centred.T @ centred / elites.shape[0] + cfg.cov_reg * jnp.eye(elites.shape[1])
        return mean, jnp.linalg.cholesky(cov)
    return mean, jnp.sqrt(jnp.mean(jnp.square(centred), 0) + cfg.cov_reg)


def _sample_gaussian(key, mean, factor, n, cfg: CEMConfig):
    noise = jax.random.normal(key, (n, mean.shape[0]))
    return mean + (noise @ factor.T if cfg.covariance == "full" else noise * factor)


def cem_search(score, key, plan_state: PlanState, *, cfg: CEMConfig):
    """The sampling optimiser alone: ``(chosen f32[H, A], top_values f32[K])``.

    ``score(seqs f32[M, H, A]) -> f32[M]`` rates candidate sequences (higher is better); CAPs scores them
    with predicted cues under a reward, the Q-learning baselines with their Q-function (H = 1).
    Iteration 0 samples uniformly over the box (half around the previous plan with ``warm_start``), later
    iterations from a Gaussian refitted to the elites; every sample is clipped to the box.
    """
    horizon, adim = cfg.horizon, cfg.action_dim
    dim = horizon * adim
    low = jnp.tile(jnp.asarray(cfg.action_low, jnp.float32), horizon)
    high = jnp.tile(jnp.asarray(cfg.action_high, jnp.float32), horizon)

    def score_flat(flat):
        return score(flat.reshape(-1, horizon, adim))

    key_uniform, key_warm, key_iters = jax.random.split(key, 3)
    first = jax.random.uniform(key_uniform, (cfg.init_samples, dim), minval=low, maxval=high)
    if cfg.warm_start:
        # Half the first population around the previous plan shifted by one step (last action repeated).
        shifted = jnp.concatenate([plan_state.previous[1:], plan_state.previous[-1:]], 0).reshape(-1)
        std = cfg.warm_start_std * 0.5 * (high - low)
        n_warm = cfg.init_samples // 2
        warm = shifted + std * jax.random.normal(key_warm, (n_warm, dim))
        warm = warm.at[0].set(shifted)
        first = jnp.where(plan_state.has_previous, first.at[:n_warm].set(warm), first)
    first = jnp.clip(first, low, high)
    values = score_flat(first)

    if cfg.optimizer == "random" or cfg.iterations == 1:
        population, values = first, values
    else:
        def refit(pop, vals):
            _, idx = jax.lax.top_k(vals, cfg.elites)  # best first
            return _refit(_nearest_half(pop[idx], low, high) if cfg.local_refit else pop[idx], cfg)

        mean, factor = refit(first, values)

        def iteration(carry_, key_i):
            mean_, factor_ = carry_
            pop = jnp.clip(_sample_gaussian(key_i, mean_, factor_, cfg.samples, cfg), low, high)
            vals = score_flat(pop)
            return refit(pop, vals), (pop, vals)

        keys = jax.random.split(key_iters, cfg.iterations - 1)
        # All but the last iteration only refit; the last also returns its population for the choice.
        (mean, factor), _ = jax.lax.scan(iteration, (mean, factor), keys[:-1])
        population = jnp.clip(_sample_gaussian(keys[-1], mean, factor, cfg.samples, cfg), low, high)
        values = score_flat(population)

    top_values, top_idx = jax.lax.top_k(values, min(cfg.elites, values.shape[0]))
    elites = population[top_idx]  # best first
    if cfg.return_mode == "best":
        chosen = elites[0]
    elif cfg.return_mode == "mean":
        chosen = jnp.clip(elites.mean(0), low, high)
    else:  # 'local_mean': smooths the best sample's noise without crossing to another mode
        chosen = jnp.clip(_nearest_half(elites, low, high).mean(0), low, high)
    return chosen.reshape(horizon, adim), top_values


def _nearest_half(elites: jax.Array, low: jax.Array, high: jax.Array) -> jax.Array:
    """The half of ``elites`` ``[K, D]`` (best first) nearest the best one, distances in box half-ranges.

    Why: the elites may hold two modes (round an obstacle on the left or on the right) whose mean is the
    crash between them; the elites nearest the best all lie in the best one's mode."""
    offsets = (elites - elites[0]) / (0.5 * (high - low))
    _, near = jax.lax.top_k(-jnp.sum(jnp.square(offsets), -1), max(1, elites.shape[0] // 2))
    return elites[near]


def plan(model, params, obs, spec: reward_lib.RewardSpec, plan_state: PlanState, key, *, cfg: CEMConfig):
    """One MPC decision for one robot: ``(action f32[A], plan_state, info)``.

    ``info`` holds ``actions`` (the chosen sequence), ``preds`` (its predicted cues), ``value`` and
    ``elite_value`` (mean reward of the last elites).
    """
    check_compatible(model, cfg)
    carry = model.encode(params, obs)  # once per observation; tiled implicitly by the batched rollout
    chosen, top_values = cem_search(lambda seqs: _score(model, params, carry, spec, seqs, cfg), key, plan_state, cfg=cfg)
    preds = model.rollout(params, carry, chosen)
    chosen_value = reward_lib.value(preds, chosen, spec)
    info = {
        "actions": chosen,
        "preds": preds,
        "value": chosen_value,
        "elite_value": jnp.mean(jnp.where(jnp.isfinite(top_values), top_values, jnp.nan)),
    }
    new_state = PlanState(previous=chosen, has_previous=jnp.ones((), bool))
    return chosen[0], new_state, info


@functools.partial(jax.jit, static_argnums=(0,), static_argnames=("cfg",))
def jit_plan(model, params, obs, spec, plan_state, key, *, cfg: CEMConfig):
    """``plan`` compiled once per (model definition, CEMConfig); see ``plan``."""
    return plan(model, params, obs, spec, plan_state, key, cfg=cfg)


def plan_batch(model, params, obs, spec, plan_state, key, *, cfg: CEMConfig):
    """``plan`` for many robots: every argument but ``params`` has a leading robot axis.

    On an accelerator the robots are vmapped (one wide batch).  On a CPU one robot's plan already
    keeps the cores busy and a wider batch only overflows the caches, so robots are mapped in
    sequence (``lax.map``) and per-robot throughput stays that of a single robot.
    """
    one = lambda args: plan(model, params, *args, cfg=cfg)
    robots = jax.tree.leaves(key)[0].shape[0] if jax.tree.leaves(key) else 1
    batch_size = 1 if jax.default_backend() == "cpu" else robots
    return jax.lax.map(one, (obs, spec, plan_state, key), batch_size=batch_size)


jit_plan_batch = jax.jit(plan_batch, static_argnums=(0,), static_argnames=("cfg",))
