import jax
import jax.numpy as jnp
import numpy as np
import pytest

import capsjax
from capsjax.ensemble import Ensemble
from capsjax.model import CAPsModel
from tests.test_model import SMALL, _obs


def _members(size):
    model = CAPsModel(SMALL)
    return model, [model.init(jax.random.key(10 + i)) for i in range(size)]


def test_rollout_is_the_members_mean_prediction():
    model, members = _members(3)
    ens = Ensemble(model, 3)
    params = ens.stack(members)
    obs = _obs(SMALL)
    actions = jax.random.uniform(jax.random.key(1), (5, SMALL.horizon, 2), minval=-3.0, maxval=3.0)
    got = ens.predict(params, obs, actions)
    each = [model.predict(p, obs, actions) for p in members]
    for cue in model.cue_names:
        want = np.mean([np.asarray(e[cue]) for e in each], axis=0)
        assert got[cue].shape == each[0][cue].shape
        np.testing.assert_allclose(np.asarray(got[cue]), want, rtol=1e-5, atol=1e-6)
    # The members really differ, so the mean is not one of them.
    assert not np.allclose(np.asarray(each[0]["collision"]), np.asarray(each[1]["collision"]))
    spread = ens.member_rollouts(params, ens.encode(params, obs), actions)["collision"]
    assert spread.shape == (3, 5, SMALL.horizon)


def test_one_member_predicts_as_the_model_itself():
    model, members = _members(1)
    ens = Ensemble(model, 1)
    obs, actions = _obs(SMALL, key=3), jnp.zeros((4, SMALL.horizon, 2))
    got, want = ens.predict(ens.stack(members), obs, actions), model.predict(members[0], obs, actions)
    for cue in model.cue_names:
        np.testing.assert_allclose(np.asarray(got[cue]), np.asarray(want[cue]), rtol=1e-6, atol=1e-7)


def test_init_and_member_params_round_trip():
    model = CAPsModel(SMALL)
    ens = Ensemble(model, 2)
    params = ens.init(jax.random.key(0))
    first, second = ens.member_params(params, 0), ens.member_params(params, 1)
    assert jax.tree.structure(first) == jax.tree.structure(model.init(jax.random.key(0)))
    assert not np.allclose(first["params"]["lstm_recurrent_kernel"], second["params"]["lstm_recurrent_kernel"])
    restacked = ens.stack([first, second])
    for a, b in zip(jax.tree.leaves(restacked), jax.tree.leaves(params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_bad_sizes_and_members_are_named():
    model, members = _members(2)
    with pytest.raises(ValueError, match="Ensemble.size"):
        Ensemble(model, 0)
    with pytest.raises(ValueError, match="members must hold 3"):
        Ensemble(model, 3).stack(members)
    other = CAPsModel(SMALL.__class__(**{**SMALL.__dict__, "obs_hidden": (32, 16)})).init(jax.random.key(0))
    with pytest.raises(ValueError, match=r"members\[1\] differs"):
        Ensemble(model, 2).stack([members[0], other])
    with pytest.raises(ValueError, match="leading member axis of length 3"):
        Ensemble(model, 3).encode(Ensemble(model, 2).stack(members), _obs(SMALL))


def test_the_planner_takes_an_ensemble_like_a_model():
    model, members = _members(2)
    ens = Ensemble(model, 2)
    params = ens.stack(members)
    cfg = capsjax.CEMConfig(model.action_low, model.action_high, horizon=SMALL.horizon, init_samples=64,
                            samples=32, iterations=2, elites=8, return_mode="mean")
    spec = capsjax.RewardSpec.from_terms(ens, collision=-1.0, heading_cos=1.0, goal_heading=(1.0, 0.0))
    action, _, info = capsjax.plan(ens, params, _obs(SMALL), spec, capsjax.init_plan_state(cfg), jax.random.key(0),
                                   cfg=cfg)
    assert action.shape == (2,) and bool(jnp.all(jnp.abs(action) <= jnp.asarray(model.action_high)))
    # The planner's reported prediction of its choice is the ensemble's (the members' mean).
    want = ens.rollout(params, ens.encode(params, _obs(SMALL)), info["actions"])
    np.testing.assert_allclose(np.asarray(info["preds"]["collision"]), np.asarray(want["collision"]), rtol=1e-5)


def test_max_cues_take_the_most_pessimistic_member():
    model, members = _members(3)
    ens = Ensemble(model, 3, max_cues=("collision",))
    params = ens.stack(members)
    obs = _obs(SMALL, key=5)
    actions = jax.random.uniform(jax.random.key(2), (6, SMALL.horizon, 2), minval=-3.0, maxval=3.0)
    each = [model.predict(p, obs, actions) for p in members]
    got = ens.predict(params, obs, actions)
    np.testing.assert_allclose(np.asarray(got["collision"]), np.max([np.asarray(e["collision"]) for e in each], 0),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(got["speed"]), np.mean([np.asarray(e["speed"]) for e in each], 0),
                               rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match=r"max_cues names \['colision'\]"):
        Ensemble(model, 3, max_cues=("colision",))
