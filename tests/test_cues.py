import jax.numpy as jnp
import numpy as np
import pytest

from capsjax import cues


def test_collision_labels_are_absorbing_and_never_masked():
    signal = jnp.array([0.0, 1.0, 0.0, 0.0])  # crash at step 1; later values are padding
    valid = jnp.array([True, True, False, False])
    target, mask = cues.COLLISION.labels(signal, valid)
    np.testing.assert_array_equal(target[:, 0], [0, 1, 1, 1])
    np.testing.assert_array_equal(mask, [1, 1, 1, 1])


def test_collision_after_timeout_stays_zero_even_if_padding_says_otherwise():
    # After a time-out the padded steps may come from another episode: they must not count.
    target, mask = cues.COLLISION.labels(jnp.array([0.0, 0.0, 1.0]), jnp.array([True, False, False]))
    np.testing.assert_array_equal(target[:, 0], [0, 0, 0])
    np.testing.assert_array_equal(mask, [1, 1, 1])


def test_other_cues_masked_after_terminal_terminal_included():
    valid = jnp.array([True, True, False])
    target, mask = cues.SPEED.labels(jnp.array([1.0, 2.0, 3.0]), valid)
    np.testing.assert_array_equal(mask, [1, 1, 0])
    np.testing.assert_array_equal(target[:, 0], [1, 2, 3])


def test_heading_labels_are_cos_sin():
    target, _ = cues.HEADING.labels(jnp.array([0.0, np.pi / 2]), jnp.array([True, True]))
    np.testing.assert_allclose(target, [[1, 0], [0, 1]], atol=1e-6)


@pytest.mark.parametrize("cue", [cues.HEADING, cues.HEADING_PAPER])
def test_residual_heading_is_centred_on_current_heading(cue):
    keys = ("collision", "heading", "speed")
    anchor = cue.anchor(jnp.array([0.0, np.pi / 2, 1.0]), keys)
    np.testing.assert_allclose(anchor, [0.0, 1.0], atol=1e-6)
    pred = cue.activate(jnp.zeros((3, 2)), anchor[None])  # zero pre-activation = no change
    np.testing.assert_allclose(pred, np.tile([0.0, 1.0], (3, 1)), atol=1e-6)


def test_paper_residual_is_additive_in_the_world_frame():
    big = cues.HEADING_PAPER.activate(jnp.full((1, 2), 50.0), jnp.array([[0.0, 1.0]]))
    np.testing.assert_allclose(big, [[2.0, 3.0]], atol=1e-4)  # bounded change of +-residual_scale


def test_ego_residual_is_rotated_by_the_current_heading():
    # Facing north, a change of (0, +1) in the car's frame (to its left) points west in the world.
    raw = jnp.array([[0.0, np.arctanh(0.5)]])  # 2 * tanh -> (0, 1)
    np.testing.assert_allclose(cues.HEADING.activate(raw, jnp.array([[0.0, 1.0]])), [[-1.0, 1.0]], atol=1e-5)


def test_binary_loss_is_cross_entropy_on_logits():
    loss = cues.COLLISION.loss(jnp.array([[0.0]]), jnp.array([[1.0]]), jnp.zeros((1,)))
    np.testing.assert_allclose(loss, [np.log(2.0)], rtol=1e-6)


def test_mse_loss_has_half_factor_and_scale():
    cue = cues.Cue("dist", kind="scalar", activation="linear", scale=2.0)
    loss = cue.loss(jnp.array([[3.0]]), jnp.array([[1.0]]), jnp.zeros((1,)))
    np.testing.assert_allclose(loss, [0.5], rtol=1e-6)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(kind="vector"), "kind"),
        (dict(kind="binary", activation="linear"), "sigmoid"),
        (dict(kind="scalar", activation="residual"), "residual"),
        (dict(kind="scalar", absorbing=True), "absorbing"),
        (dict(scale=0.0), "scale"),
    ],
)
def test_bad_cue_definitions_are_refused(kwargs, field):
    with pytest.raises(ValueError, match=field):
        cues.Cue("x", **kwargs)


def test_duplicate_cue_names_refused():
    with pytest.raises(ValueError, match="unique"):
        cues.check_unique((cues.SPEED, cues.SPEED))
