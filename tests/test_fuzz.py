"""Property-based tests (hypothesis) of bad input to the public API: every bad value gets a ValueError
(or TypeError) that names the field and what was expected; nothing saved is damaged; nothing hangs.

All checks here are trace-time or host-side validation, so examples are cheap (no compilation), except
the truncated-checkpoint property, which restores a tiny state.
"""
import dataclasses
import math
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import capsjax
from capsjax import checkpoint, planner
from capsjax.reward import TERM_NAMES, RewardSpec
from envs.base import Observation
from envs.fast import FastEnv

ENV = FastEnv()
MODEL = capsjax.CAPsModel(capsjax.ModelConfig.from_env_spec(
    ENV.spec, conv=((4, 3, 2),), obs_hidden=(16, 16), action_hidden=(8, 8), head_hidden=4, horizon=4))
FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
non_finite = st.sampled_from([math.nan, math.inf, -math.inf])
names = st.text(alphabet="abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=12)


# ---------------------------------------------------------------------------------------- reward specs


@FUZZ
@given(name=names.filter(lambda n: n not in TERM_NAMES and n not in ("goal_speed", "goal_heading", "lane_offset", "gated", "model")),
       weight=st.floats(-10, 10))
def test_unknown_reward_term_is_named(name, weight):
    with pytest.raises(ValueError, match=rf"unknown reward term\(s\) \['{name}'\]; valid terms"):
        RewardSpec.from_terms(MODEL, **{name: weight})


@FUZZ
@given(term=st.sampled_from(["lane", "door"]), weight=st.floats(0.1, 10))
def test_term_whose_cue_the_model_lacks_is_named(term, weight):
    with pytest.raises(ValueError, match=rf"reward term '{term}' needs cue\(s\).*the model's cues are"):
        RewardSpec.from_terms(MODEL, **{term: weight})


@FUZZ
@given(term=st.sampled_from(["collision", "speed", "heading_cos", "steer", "action"]), weight=non_finite)
def test_non_finite_weight_is_named(term, weight):
    with pytest.raises(ValueError, match=rf"weight of reward term '{term}' must be finite"):
        RewardSpec.from_terms(MODEL, **{term: weight})


@FUZZ
@given(field=st.sampled_from(["goal_speed", "goal_heading", "lane_offset"]),
       shape=st.lists(st.integers(0, 3), max_size=3).map(tuple), bad_value=st.booleans())
def test_wrong_goal_shape_or_value_is_named(field, shape, bad_value):
    want = (2,) if field == "goal_heading" else ()
    if shape == want and not bad_value:
        shape = want + (1,)
    value = np.full(shape, np.nan if bad_value else 0.5)
    expected = "must be finite" if bad_value and value.size else rf"must have shape {re_tuple(want)}"
    with pytest.raises(ValueError, match=rf"RewardSpec\.{field} {expected}"):
        RewardSpec.from_terms(MODEL, collision=1.0, **{field: value})


def re_tuple(t) -> str:
    return str(t).replace("(", r"\(").replace(")", r"\)")


# ------------------------------------------------------------------------------------- planner configs

COUNTS = ("horizon", "init_samples", "samples", "iterations", "elites")


@FUZZ
@given(field=st.sampled_from(COUNTS), value=st.one_of(st.integers(-100, 0), st.floats(-5, 5), st.none(), st.text(max_size=3)))
def test_non_positive_or_non_integer_counts_are_named(field, value):
    with pytest.raises(ValueError, match=rf"CEMConfig\.{field} must be a positive int, got"):
        planner.CEMConfig((-1.0, 0.0), (1.0, 1.0), **{field: value})


@FUZZ
@given(samples=st.integers(1, 64), extra=st.integers(1, 64))
def test_more_elites_than_samples_is_refused(samples, extra):
    with pytest.raises(ValueError, match=rf"CEMConfig\.elites \({samples + extra}\) must not exceed the samples"):
        planner.CEMConfig((-1.0, 0.0), (1.0, 1.0), init_samples=samples, samples=samples, elites=samples + extra)


@FUZZ
@given(extra=st.integers(1, 20))
def test_planning_horizon_above_the_model_is_refused(extra):
    cfg = planner.CEMConfig(ENV.spec.plan_low, ENV.spec.plan_high, horizon=MODEL.horizon + extra,
                            init_samples=16, samples=16, elites=4)
    with pytest.raises(ValueError, match=rf"CEMConfig\.horizon \({MODEL.horizon + extra}\) exceeds the model's trained horizon \({MODEL.horizon}\)"):
        planner.check_compatible(MODEL, cfg)


@FUZZ
@given(field=st.sampled_from(["candidate_chunk", "cov_reg", "warm_start_std"]),
       value=st.one_of(st.floats(-10, -1e-3), non_finite, st.text(max_size=2), st.none()))
def test_other_bad_planner_settings_are_named(field, value):
    if field == "candidate_chunk" and isinstance(value, float) and math.isinf(value) and value > 0:
        value = -1.0
    if field == "warm_start_std" and value == math.inf:
        value = 0.0
    if field == "cov_reg" and value == math.inf:
        value = -1.0
    with pytest.raises((ValueError, TypeError), match=rf"CEMConfig\.{field}"):
        planner.CEMConfig((-1.0, 0.0), (1.0, 1.0), **{field: value})


@FUZZ
@given(lows=st.lists(st.floats(-5, 5), min_size=1, max_size=3), gap=st.floats(-5, 0))
def test_empty_or_inverted_action_box_is_refused(lows, gap):
    with pytest.raises(ValueError, match=r"CEMConfig\.action_low"):
        planner.CEMConfig(tuple(lows), tuple(lo + gap for lo in lows))


# ----------------------------------------------------------------------------------------- observations

H, W, C = ENV.spec.image_shape
L, D = ENV.spec.history, len(ENV.spec.vector_keys)


@FUZZ
@given(shape=st.lists(st.integers(1, 40), min_size=1, max_size=5).map(tuple),
       dtype=st.sampled_from([np.uint8, np.float32, np.int32, np.float16]))
def test_observation_images_of_wrong_shape_or_dtype_are_named(shape, dtype):
    if shape == (L, H, W, C) and dtype == np.uint8:
        shape = (L + 1, H, W, C)
    obs = Observation(images=jnp.zeros(shape, dtype), vector=jnp.zeros((L, D)))
    with pytest.raises(ValueError, match=rf"obs\.images must be uint8\[{L}, {H}, {W}, {C}\], got"):
        MODEL.check_observation(obs)


@FUZZ
@given(shape=st.lists(st.integers(1, 8), min_size=0, max_size=3).map(tuple))
def test_observation_vector_of_wrong_shape_is_named(shape):
    if shape == (L, D):
        shape = (L, D + 1)
    obs = Observation(images=jnp.zeros((L, H, W, C), jnp.uint8), vector=jnp.zeros(shape))
    with pytest.raises(ValueError, match=rf"obs\.vector must have shape \({L}, {D}\)"):
        MODEL.check_observation(obs)


@FUZZ
@given(dtype=st.sampled_from([np.int32, np.bool_, np.complex64]))
def test_observation_vector_of_wrong_dtype_is_named(dtype):
    obs = Observation(images=jnp.zeros((L, H, W, C), jnp.uint8), vector=jnp.zeros((L, D), dtype))
    with pytest.raises(ValueError, match=r"obs\.vector must be a float array"):
        MODEL.check_observation(obs)


# ------------------------------------------------------------------------------------ train / model config


@FUZZ
@given(field=st.sampled_from(["learning_rate", "adam_eps", "batch_size"]),
       value=st.one_of(st.floats(-10, 0), non_finite))
def test_bad_train_config_is_named(field, value):
    if field == "batch_size":
        value = int(value) if math.isfinite(value) else 0  # batch_size is an int
    with pytest.raises(ValueError, match=rf"TrainConfig\.{field} must be positive"):
        capsjax.TrainConfig(**{field: value})


@FUZZ
@given(field=st.sampled_from(["history", "horizon", "head_hidden"]), value=st.integers(-5, 0))
def test_bad_model_config_is_named(field, value):
    with pytest.raises(ValueError, match=rf"ModelConfig\.{field} must be positive"):
        dataclasses.replace(MODEL.config, **{field: value})


# ---------------------------------------------------------------------------------- truncated checkpoints


@pytest.fixture(scope="module")
def saved_checkpoint(tmp_path_factory):
    directory = tmp_path_factory.mktemp("ckpt")
    state = {"w": jnp.arange(4096, dtype=jnp.float32), "step": jnp.int32(7), "key": jax.random.key(3)}
    with checkpoint.Checkpointer(directory, config={"run": "fuzz"}) as manager:
        manager.save(1, state)
        manager.save(2, jax.tree.map(lambda x: x + 1 if x.dtype != jax.random.key(0).dtype else x, state))
    files = sorted(os.path.join(r, f) for r, _, fs in os.walk(directory / "2") for f in fs)
    return directory, state, files


def _snapshot(directory) -> dict:
    return {str(p): p.read_bytes() for p in Path(directory).rglob("*") if p.is_file()}


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_truncated_checkpoint_is_reported_by_step_and_path(saved_checkpoint, data):
    directory, state, files = saved_checkpoint
    victim = data.draw(st.sampled_from(files), label="file")
    original = Path(victim).read_bytes()
    cut = data.draw(st.integers(0, max(len(original) - 1, 0)), label="keep bytes")
    step1 = _snapshot(directory / "1")
    try:
        with open(victim, "r+b") as f:
            f.truncate(cut)
        with checkpoint.Checkpointer(directory, config={"run": "fuzz"}) as manager:
            try:
                restored, step = manager.restore(state)
            except checkpoint.CorruptCheckpointError as e:
                assert f"step 2 at {directory / '2'}" in str(e)
                restored, step = manager.restore(state, fallback=True)  # the older step still reads
                assert step == 1
                np.testing.assert_array_equal(restored["w"], state["w"])
            else:  # a file the restore does not need: the data must then be intact
                assert step == 2
                np.testing.assert_array_equal(restored["w"], state["w"] + 1)
    finally:
        Path(victim).write_bytes(original)
    assert _snapshot(directory / "1") == step1  # the older checkpoint is untouched
