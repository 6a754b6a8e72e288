"""An ensemble of CAPs predictors: K models of one definition whose predictions are averaged.

Why: the forest's success moves by several paths of 32 between models that differ only in their training
run (a retraining with a rounding-level change of the data moved it by 5), so one model's predictions carry
a large share of training luck; averaging K independently trained models (deep ensembles) cancels part of
it.  The planner sees an ``Ensemble`` exactly like a ``CAPsModel`` (``encode``/``rollout`` on a params
pytree), so ``capsjax.plan`` and ``mpc.caps_policy`` take it unchanged.

Params are the members' params stacked on a leading axis of length ``size`` (``Ensemble.stack``).  Each
cue's prediction is the members' mean: the ensemble's predictive probability for a probability cue, the mean
unit vector for an angle cue (the reward normalises it), the mean value otherwise.  Cues named in
``max_cues`` take the members' maximum instead: for a cue the reward penalises (collision) that plans against
the most pessimistic member, so a sequence only one member sees crashing is avoided.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Sequence

import jax
import jax.numpy as jnp

from capsjax.model import CAPsModel, Carry


@dataclasses.dataclass(frozen=True)
class Ensemble:
    """Static, hashable: ``size`` members of the definition ``member``.

    >>> ens = Ensemble(model, 3); params = ens.stack([p0, p1, p2])
    >>> preds = ens.rollout(params, ens.encode(params, obs), actions)  # the members' mean
    """

    member: CAPsModel
    size: int
    max_cues: tuple[str, ...] = ()  # cues combined by the members' maximum instead of their mean

    def __post_init__(self):
        if not isinstance(self.size, int) or isinstance(self.size, bool) or self.size < 1:
            raise ValueError(f"Ensemble.size must be an int >= 1, got {self.size!r}")
        object.__setattr__(self, "max_cues", tuple(self.max_cues))
        unknown = sorted(set(self.max_cues) - set(self.member.cue_names))
        if unknown:
            raise ValueError(f"Ensemble.max_cues names {unknown}, not cues of the model ({list(self.member.cue_names)})")

    # The planner and the reward read these from any predictor.
    @property
    def config(self):
        return self.member.config

    @property
    def cues(self):
        return self.member.cues

    @property
    def cue_names(self) -> tuple[str, ...]:
        return self.member.cue_names

    @property
    def action_low(self) -> tuple[float, ...]:
        return self.member.action_low

    @property
    def action_high(self) -> tuple[float, ...]:
        return self.member.action_high

    @property
    def horizon(self) -> int:
        return self.member.horizon

    def init(self, key: jax.Array) -> Any:
        """Stacked params of ``size`` members, each initialised from its own key."""
        return jax.vmap(self.member.init)(jax.random.split(key, self.size))

    def stack(self, members: Sequence[Any]) -> Any:
        """Stacked params from a list of ``size`` members' params (each from ``member.init`` or training)."""
        if len(members) != self.size:
            raise ValueError(f"Ensemble.stack: members must hold {self.size} params pytrees, got {len(members)}")
        structure = jax.tree.structure(members[0])
        for i, params in enumerate(members[1:], 1):
            if jax.tree.structure(params) != structure or any(
                    jnp.shape(a) != jnp.shape(b) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(members[0]))):
                raise ValueError(f"Ensemble.stack: members[{i}] differs from members[0] in structure or shapes; "
                                 "every member must be of the one model definition")
        return jax.tree.map(lambda *leaves: jnp.stack(leaves), *members)

    def member_params(self, params, index: int) -> Any:
        """One member's params (e.g. to evaluate it alone)."""
        self._check_params(params)
        return jax.tree.map(lambda x: x[index], params)

    def _check_params(self, params) -> None:
        sizes = {jnp.shape(x)[0] if jnp.ndim(x) else None for x in jax.tree.leaves(params)}
        if sizes != {self.size}:
            raise ValueError(f"Ensemble params must have a leading member axis of length {self.size} on every "
                             f"leaf (Ensemble.stack), got leading sizes {sorted(sizes, key=str)}")

    def _map_members(self, fn, xs):
        # A CPU scores the members one after another, so each member's rollout keeps the working set the
        # planner's chunking was sized for (planner._chunk_size); an accelerator runs them as one batch.
        batch = 1 if jax.default_backend() == "cpu" else self.size
        return jax.lax.map(lambda args: fn(*args), xs, batch_size=batch)

    def check_observation(self, obs) -> None:
        self.member.check_observation(obs)

    def encode(self, params, obs) -> Carry:
        """Every member's LSTM state for one observation: a ``Carry`` with a leading member axis."""
        self._check_params(params)
        self.member.check_observation(obs)
        return self._map_members(lambda p: self.member.encode(p, obs), (params,))

    def member_rollouts(self, params, carry: Carry, actions: jax.Array) -> dict[str, jax.Array]:
        """Each member's predictions, ``{cue: f32[K, ..., H(, 2)]}`` (their spread is the members' disagreement)."""
        self._check_params(params)
        return self._map_members(lambda p, c: self.member.rollout(p, c, actions), (params, carry))

    def rollout(self, params, carry: Carry, actions: jax.Array) -> dict[str, jax.Array]:
        """The ensemble's prediction ``{cue: f32[..., H] (angles f32[..., H, 2])}`` for ``f32[..., H, A]``: the
        members' mean, or their maximum for ``max_cues``."""
        each = self.member_rollouts(params, carry, actions)
        return {name: (jnp.max if name in self.max_cues else jnp.mean)(x, axis=0) for name, x in each.items()}

    def predict(self, params, obs, actions) -> dict[str, jax.Array]:
        return self.rollout(params, self.encode(params, obs), actions)
