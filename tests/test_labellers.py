"""Oracle cue labellers on hand-made semantic maps."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from capsjax.labellers import (LEARNED_SEEN_FRAC, door_frac, lane_cues, lane_cues_from_mask,
                               right_lane_mask)

# Ids as envs.scene defines them (the test passes them explicitly, like the envs do).
GRASS, ROAD, LINE, DOOR = 1, 2, 3, 11
H, W = 10, 20


def road_map(line_col: int, road_cols=(0, W)) -> np.ndarray:
    sem = np.full((H, W), GRASS, np.uint8)
    sem[5:, road_cols[0]:road_cols[1]] = ROAD
    sem[5:, line_col] = LINE
    return sem


def test_right_lane_mask_is_road_right_of_leftmost_line():
    sem = road_map(line_col=8)
    sem[7, 15] = LINE  # a second line further right in one row: the leftmost one counts
    mask = np.asarray(right_lane_mask(jnp.asarray(sem), road_id=ROAD, line_id=LINE))
    expected = np.zeros((H, W), bool)
    expected[5:, 9:] = True
    expected[7, 15] = False  # a line pixel is not road
    np.testing.assert_array_equal(mask, expected)


def test_right_lane_mask_rows_without_line_are_empty():
    sem = road_map(line_col=8)
    sem[9, 8] = ROAD  # the bottom row has no line pixel
    mask = np.asarray(right_lane_mask(jnp.asarray(sem), road_id=ROAD, line_id=LINE))
    assert not mask[9].any() and mask[8, 9:].all()


def test_right_lane_mask_thresholds():
    # Road below 5 % of the image: empty although a line is visible.
    sem = np.full((H, W), GRASS, np.uint8)
    sem[9, 0] = LINE
    sem[9, 1:10] = ROAD  # 9 / 200 = 4.5 %
    assert not np.asarray(right_lane_mask(jnp.asarray(sem), road_id=ROAD, line_id=LINE)).any()
    sem[8, 1:10] = ROAD  # 9 %: now enough road, and the line (0.5 %) is enough too
    assert np.asarray(right_lane_mask(jnp.asarray(sem), road_id=ROAD, line_id=LINE)).any()
    # Lane lines must cover more than 0.3 %: one pixel in 400 (0.25 %) is too little.
    big = np.full((20, 20), ROAD, np.uint8)
    big[10, 5] = LINE
    assert not np.asarray(right_lane_mask(jnp.asarray(big), road_id=ROAD, line_id=LINE)).any()
    big[11, 5] = LINE  # 0.5 %
    assert np.asarray(right_lane_mask(jnp.asarray(big), road_id=ROAD, line_id=LINE)).any()


def test_lane_diff_sign_and_range():
    right = lane_cues(jnp.asarray(road_map(line_col=12)), road_id=ROAD, line_id=LINE)
    left = lane_cues(jnp.asarray(road_map(line_col=1, road_cols=(0, 8))), road_id=ROAD, line_id=LINE)
    assert float(right[0]) == 1.0 and float(left[0]) == 1.0
    assert 0 < float(right[1]) <= 1  # lane right of the image centre: positive
    assert -1 <= float(left[1]) < 0
    # Exact value: road columns 13..19 -> mean centre 16.5 -> (16.5 - 10) / 10.
    np.testing.assert_allclose(float(right[1]), 0.65, rtol=1e-6)


def test_lane_cues_unseen_and_symmetric():
    seen, diff = lane_cues_from_mask(jnp.zeros((H, W), bool))
    assert float(seen) == 0.0 and float(diff) == 0.0
    seen, diff = lane_cues_from_mask(jnp.ones((H, W), bool))
    assert float(seen) == 1.0 and abs(float(diff)) < 1e-7


def test_learned_mask_threshold():
    mask = np.zeros((H, W), bool)
    mask[0, :4] = True  # 2 % of 200 pixels: not more than the threshold
    assert float(lane_cues_from_mask(jnp.asarray(mask), LEARNED_SEEN_FRAC)[0]) == 0.0
    mask[1, 0] = True
    seen, diff = lane_cues_from_mask(jnp.asarray(mask), LEARNED_SEEN_FRAC)
    assert float(seen) == 1.0 and float(diff) < 0


def test_door_frac():
    sem = np.zeros((H, W), np.uint8)
    sem[:, :5] = DOOR
    np.testing.assert_allclose(float(door_frac(jnp.asarray(sem), door_id=DOOR)), 0.25)


def test_jit_and_vmap():
    maps = jnp.asarray(np.stack([road_map(c) for c in (3, 8, 12, 16)]))

    @jax.jit
    def cues(sem):
        seen, diff = lane_cues(sem, road_id=ROAD, line_id=LINE)
        return seen, diff, door_frac(sem, door_id=DOOR)

    seen, diff, door = jax.vmap(cues)(maps)
    assert seen.shape == (4,) and seen.dtype == jnp.float32
    assert np.all(np.diff(np.asarray(diff)) > 0)  # the line moves right, so does the lane
    assert np.all(np.asarray(door) == 0)


@pytest.mark.parametrize("dtype", [np.uint8, np.int32])
def test_accepts_int_maps(dtype):
    sem = road_map(8).astype(dtype)
    assert float(lane_cues(jnp.asarray(sem), road_id=ROAD, line_id=LINE)[0]) == 1.0
