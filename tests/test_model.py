import jax
import jax.numpy as jnp
import numpy as np
import pytest

from capsjax import cues
from capsjax.model import CAPsModel, ModelConfig, count_params, rollout_flops
from envs.base import Observation

CARLA = ModelConfig(
    image_shape=(50, 100, 1), vector_keys=tuple(f"v{i}" for i in range(8)) + ("heading",),
    vector_low=(-1.0,) * 9, vector_high=(1.0,) * 9, action_low=(-1.0, -1.0), action_high=(1.0, 1.0),
    cues=(cues.COLLISION, cues.SPEED, cues.HEADING, cues.LANE_SEEN, cues.LANE_DIFF),
)
SMALL = ModelConfig(
    image_shape=(16, 32, 1), vector_keys=("collision", "heading", "speed"), vector_low=(0.0, -np.pi, -3.0),
    vector_high=(1.0, np.pi, 3.0), action_low=(-45.0, -3.0), action_high=(45.0, 3.0),
    cues=(cues.COLLISION, cues.SPEED, cues.HEADING), conv=((8, 4, 2), (8, 3, 2)), obs_hidden=(32, 32),
    action_hidden=(8, 16), horizon=6,
)


def _obs(cfg, key=0):
    k1, k2 = jax.random.split(jax.random.key(key))
    images = jax.random.randint(k1, (cfg.history,) + cfg.image_shape, 0, 256).astype(jnp.uint8)
    vector = jax.random.uniform(k2, (cfg.history, len(cfg.vector_keys)), minval=-1, maxval=1)
    return Observation(images, vector)


def test_paper_sizes_give_the_papers_parameter_count():
    params = CAPsModel(CARLA).init(jax.random.key(0))
    # caps-algorithm.md section 2.6: ~234k for the CARLA CAPs model (6 heads: heading is cos + sin).
    assert 233_000 < count_params(params) < 236_000
    p = params["params"]
    assert p["lstm_recurrent_kernel"].shape == (64, 256)
    assert p["lstm_input_kernel"].shape == (128, 256)
    assert p["head_out_kernel"].shape == (6, 16)
    np.testing.assert_allclose(float(p["lstm_alpha"].mean()), 1.0, atol=0.05)
    np.testing.assert_allclose(float(p["lstm_beta_h"].mean()), 0.5, atol=0.05)


def test_shapes_and_activations():
    model = CAPsModel(SMALL)
    params = model.init(jax.random.key(0))
    preds = model.predict(params, _obs(SMALL), jnp.zeros((5, 2)))
    assert preds["collision"].shape == (5,) and preds["speed"].shape == (5,)
    assert preds["heading"].shape == (5, 2)
    assert bool(jnp.all((preds["collision"] > 0) & (preds["collision"] < 1)))


def _reference_rollout(model, params, obs, actions):
    """A direct, step-by-step transcription of the paper's equations, for comparison."""
    cfg, p = model.config, params["params"]
    carry = model.encode(params, obs)
    c, h = carry.c, carry.h
    low, high = np.array(cfg.action_low), np.array(cfg.action_high)
    outs = []
    for a in actions:
        x = (a - (low + high) / 2) / (high - low)
        for i in range(len(cfg.action_hidden)):
            x = jax.nn.relu(x @ p[f"act{i}"]["kernel"] + p[f"act{i}"]["bias"])
        wx, uh = x @ p["lstm_input_kernel"], h @ p["lstm_recurrent_kernel"]
        z = jnp.tanh(p["lstm_alpha"] * wx * uh + p["lstm_beta_h"] * uh + p["lstm_beta_x"] * wx + p["lstm_bias"])
        i_, j, f, o = jnp.split(z, 4)
        c = c * jax.nn.sigmoid(f + 1) + jax.nn.sigmoid(i_) * jnp.tanh(j)
        h = jnp.tanh(c) * jax.nn.sigmoid(o)
        heads = []
        for k in range(cfg.num_heads):
            hid = jax.nn.relu(h @ p["head_hidden_kernel"][:, k * 16:(k + 1) * 16] + p["head_hidden_bias"][k * 16:(k + 1) * 16])
            heads.append(hid @ p["head_out_kernel"][k] + p["head_out_bias"][k])
        outs.append(jnp.stack(heads))
    return jnp.stack(outs)


def test_rollout_matches_the_papers_equations_step_by_step():
    cfg = ModelConfig(**{**SMALL.__dict__, "head_hidden": 16})
    model = CAPsModel(cfg)
    params = model.init(jax.random.key(1))
    obs = _obs(cfg, 3)
    actions = jax.random.uniform(jax.random.key(2), (6, 2), minval=-30, maxval=30)
    fast = model.rollout_raw(params, model.encode(params, obs), actions)
    np.testing.assert_allclose(fast, _reference_rollout(model, params, obs, actions), rtol=2e-4, atol=2e-5)


def test_vmapped_rollout_does_not_recompute_the_cnn():
    model = CAPsModel(SMALL)
    params = model.init(jax.random.key(0))
    carry = model.encode(params, _obs(SMALL))
    jaxpr = jax.make_jaxpr(jax.vmap(model.rollout, in_axes=(None, None, 0)))(params, carry, jnp.zeros((64, 6, 2)))
    assert "conv_general_dilated" not in str(jaxpr)


def test_wrong_observation_shape_is_a_clear_error():
    model = CAPsModel(SMALL)
    params = model.init(jax.random.key(0))
    bad = Observation(jnp.zeros((3, 16, 32, 1), jnp.uint8), jnp.zeros((4, 3)))
    with pytest.raises(ValueError, match="obs.images"):
        model.encode(params, bad)
    bad = Observation(jnp.zeros((4, 16, 32, 1), jnp.uint8), jnp.zeros((4, 5)))
    with pytest.raises(ValueError, match="obs.vector"):
        model.encode(params, bad)


def test_config_validation_names_the_field():
    with pytest.raises(ValueError, match="anchor"):
        ModelConfig(**{**SMALL.__dict__, "vector_keys": ("a", "b", "c")})
    with pytest.raises(ValueError, match="action_low"):
        ModelConfig(**{**SMALL.__dict__, "action_low": (1.0, 1.0), "action_high": (0.0, 0.0)})
    with pytest.raises(ValueError, match="image_pool=3 must divide the frame size 16x32"):
        ModelConfig(**{**SMALL.__dict__, "image_pool": 3})
    with pytest.raises(ValueError, match="image_pool must be positive"):
        ModelConfig(**{**SMALL.__dict__, "image_pool": 0})


def test_image_pool_feeds_the_cnn_block_averaged_frames():
    """Pooling by p equals running the unpooled model on frames made of p x p blocks of equal pixels
    whose value is the block mean, and shrinks the CNN's output (fewer obs-MLP inputs)."""
    pooled_cfg = ModelConfig(**{**SMALL.__dict__, "image_pool": 2})
    small_cfg = ModelConfig(**{**SMALL.__dict__, "image_shape": (8, 16, 1)})
    pooled, small = CAPsModel(pooled_cfg), CAPsModel(small_cfg)
    params = small.init(jax.random.key(0))
    assert jax.tree.map(jnp.shape, pooled.init(jax.random.key(0))) == jax.tree.map(jnp.shape, params)
    # Frames of 2x2 blocks of one even value: their block means are exact bytes.
    blocks = jax.random.randint(jax.random.key(1), (4, 8, 16, 1), 0, 128).astype(jnp.uint8) * 2
    obs = _obs(SMALL)
    big = Observation(jnp.repeat(jnp.repeat(blocks, 2, axis=1), 2, axis=2), obs.vector)
    a = pooled.encode(params, big)
    b = small.encode(params, Observation(blocks, obs.vector))
    np.testing.assert_allclose(a.h, b.h, atol=1e-5)
    np.testing.assert_allclose(a.c, b.c, atol=1e-5)


def test_user_defined_cue_needs_no_library_change():
    dist = cues.Cue("obstacle_distance", kind="scalar", activation="linear", scale=5.0)
    model = CAPsModel(ModelConfig(**{**SMALL.__dict__, "cues": SMALL.cues + (dist,)}))
    params = model.init(jax.random.key(0))
    preds = model.predict(params, _obs(SMALL), jnp.zeros((4, 2)))
    assert preds["obstacle_distance"].shape == (4,)


def test_flop_count_is_dominated_by_the_lstm_matmuls():
    per_step = rollout_flops(CARLA, 1)
    assert 2 * 128 * 256 + 2 * 64 * 256 < per_step < 2 * (128 * 256 + 64 * 256) * 1.2
