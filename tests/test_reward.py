import jax
import jax.numpy as jnp
import numpy as np
import pytest

from capsjax import reward
from capsjax.reward import RewardSpec


class _Model:
    cue_names = ("collision", "speed", "heading", "lane_seen", "lane_diff", "door_frac")
    action_low = (-30.0, 0.0)
    action_high = (30.0, 4.0)


def _preds(h=3, coll=0.0, speed=2.0, heading=(1.0, 0.0), seen=1.0, diff=0.0, door=0.1):
    f = lambda v: jnp.full((h,), v, jnp.float32)
    return {"collision": f(coll), "speed": f(speed), "heading": jnp.tile(jnp.asarray(heading, jnp.float32), (h, 1)),
            "lane_seen": f(seen), "lane_diff": f(diff), "door_frac": f(door)}


def test_forest_reward_matches_the_papers_formula():
    spec = RewardSpec.from_terms(_Model(), collision=500, heading_cos=1, goal_heading=(0.0, 1.0))
    preds = _preds(coll=0.1, heading=(np.cos(0.3 + np.pi / 2), np.sin(0.3 + np.pi / 2)))
    expected = 3 * (500 * 0.9 + np.cos(0.3) - 1)
    np.testing.assert_allclose(reward.value(preds, jnp.zeros((3, 2)) + jnp.array([0.0, 2.0]), spec), expected, rtol=1e-5)


def test_carla_reward_matches_the_papers_formula():
    spec = RewardSpec.from_terms(_Model(), collision=50, speed=3, lane=5, steer=0.15, heading_angle=5,
                                 goal_speed=7.0, goal_heading=(1.0, 0.0))
    preds = _preds(coll=0.2, speed=6.0, heading=(np.cos(0.5), np.sin(0.5)), seen=0.9, diff=0.2)
    actions = jnp.array([[15.0, 2.0]] * 3)  # steer 15 of +-30 -> 0.5 normalised
    expected = 3 * (50 * 0.8 - 3 * 1 / 7 + 5 * 0.9 * 0.8 - 0.15 * 0.25 - 5 * 0.5 / np.pi)
    np.testing.assert_allclose(reward.value(preds, actions, spec), expected, rtol=1e-4)


def test_rc_car_product_form_via_gates():
    spec = RewardSpec.from_terms(_Model(), collision=1, heading_angle=0.1, door=0.05, action=0.01,
                                 gated=("heading_angle", "door"), goal_heading=(1.0, 0.0))
    preds = _preds(coll=0.4, heading=(np.cos(1.0), np.sin(1.0)), door=0.2)
    actions = jnp.array([[30.0, 4.0]] * 3)  # normalised (1, 1): |a|^2 = 2
    expected = 3 * (0.6 * (1 - 0.1 / np.pi * 1.0 + 0.05 * 0.2) - 0.01 * 2)
    np.testing.assert_allclose(reward.value(preds, actions, spec), expected, rtol=1e-4)


def test_lane_offset_goal_moves_the_preferred_lane():
    near_centre = _preds(diff=0.0)
    shifted = _preds(diff=-0.6)
    same_side = RewardSpec.from_terms(_Model(), lane=1)
    other_side = RewardSpec.from_terms(_Model(), lane=1, lane_offset=-0.6)
    a = jnp.zeros((3, 2))
    assert reward.value(near_centre, a, same_side) > reward.value(shifted, a, same_side)
    assert reward.value(shifted, a, other_side) > reward.value(near_centre, a, other_side)


def test_no_goal_heading_means_no_heading_angle_term():
    spec = RewardSpec.from_terms(_Model(), heading_angle=5)
    np.testing.assert_allclose(reward.value(_preds(heading=(0.0, 1.0)), jnp.zeros((3, 2)), spec), 0.0)


def test_unknown_term_lists_the_valid_ones():
    with pytest.raises(ValueError, match="valid terms: .*collision"):
        RewardSpec.from_terms(_Model(), colision=1)


def test_term_needing_a_missing_cue_is_refused():
    class Small(_Model):
        cue_names = ("collision", "heading")

    with pytest.raises(ValueError, match="lane.*model's cues are"):
        RewardSpec.from_terms(Small(), lane=5)
    RewardSpec.from_terms(Small(), collision=1, heading_cos=1)  # fine


@pytest.mark.parametrize("kwargs, field", [
    (dict(collision=float("nan")), "collision"),
    (dict(speed=float("inf")), "speed"),
    (dict(goal_heading=(1.0, 0.0, 0.0)), "goal_heading"),
    (dict(goal_speed=(1.0, 2.0)), "goal_speed"),
    (dict(goal_speed=float("nan")), "goal_speed"),
    (dict(goal_path=((0.0, 0.0),)), "goal_path"),
    (dict(goal_path=((0.0, 0.0), (float("nan"), 1.0))), "goal_path"),
    (dict(path=1.0), "step_seconds"),
    (dict(path_tolerance=-1.0), "path_tolerance"),
])
def test_bad_specs_name_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        RewardSpec.from_terms(_Model(), **kwargs)


def test_batched_candidates():
    spec = RewardSpec.from_terms(_Model(), collision=1)
    preds = jax.tree.map(lambda x: jnp.stack([x, x]), _preds(coll=0.5))
    assert reward.value(preds, jnp.zeros((2, 3, 2)), spec).shape == (2,)


def test_nan_prediction_gives_nan_value_not_a_crash():
    spec = RewardSpec.from_terms(_Model(), collision=1)
    assert np.isnan(float(reward.value(_preds(coll=float("nan")), jnp.zeros((3, 2)), spec)))


def test_path_term_scores_the_dead_reckoned_distance_to_the_goal_path():
    # Driving +x at 2 m/s for 3 steps of 0.5 s reaches x = 1, 2, 3; a path along y = 1 is 1 m off every step.
    spec = RewardSpec.from_terms(_Model(), path=1.0, step_seconds=0.5, goal_path=((-1.0, 1.0), (10.0, 1.0)))
    a = jnp.zeros((3, 2))
    np.testing.assert_allclose(reward.value(_preds(speed=2.0, heading=(1.0, 0.0)), a, spec), -3.0, rtol=1e-5)
    # Past the path's end the distance is to its last vertex: a path ending at (1, 0) is 0, 1 and 2 m away.
    short = spec.with_goals(goal_path=((-1.0, 0.0), (1.0, 0.0)))
    np.testing.assert_allclose(reward.value(_preds(speed=2.0, heading=(1.0, 0.0)), a, short), -3.0, rtol=1e-5)
    # Heading along the path beats heading away from it, and the distance grows with speed.
    along = reward.value(_preds(heading=(1.0, 0.0)), a, spec.with_goals(goal_path=((0.0, 0.0), (9.0, 0.0))))
    away = reward.value(_preds(heading=(0.0, -1.0)), a, spec.with_goals(goal_path=((0.0, 0.0), (9.0, 0.0))))
    assert float(along) == pytest.approx(0.0, abs=1e-6) and float(away) < -5.0
    # A tolerance leaves the first metres free: 1 m off with 0.5 m free costs 0.5 per step.
    loose = RewardSpec.from_terms(_Model(), path=1.0, step_seconds=0.5, path_tolerance=0.5,
                                  goal_path=((-1.0, 1.0), (10.0, 1.0)))
    np.testing.assert_allclose(reward.value(_preds(speed=2.0, heading=(1.0, 0.0)), a, loose), -1.5, rtol=1e-5)


def test_polyline_distance_matches_a_brute_force_sampling():
    path = jnp.asarray([[0.0, 0.0], [2.0, 0.0], [2.0, 3.0], [-1.0, 4.0]])
    points = jax.random.uniform(jax.random.key(0), (50, 2), minval=-3.0, maxval=5.0)
    fine = jnp.concatenate([a + jnp.linspace(0, 1, 2001)[:, None] * (b - a) for a, b in zip(path[:-1], path[1:])])
    brute = jnp.min(jnp.linalg.norm(points[:, None] - fine[None], axis=-1), axis=1)
    np.testing.assert_allclose(reward.polyline_distance(points, path), brute, atol=3e-3)
