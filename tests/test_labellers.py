"""Cue labellers: the oracle rules on hand-made semantic maps; the learned segmenter and its evaluation."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from capsjax.labellers import (
    CALIBRATION,
    LEARNED_SEEN_FRAC,
    OTHER_ID,
    CueLabeller,
    Segmenter,
    SegmenterConfig,
    SegmenterTrainConfig,
    balanced_cross_entropy,
    class_index_to_semantic,
    class_log_prior,
    class_targets,
    cue_labels,
    door_frac,
    evaluate_labeller,
    evaluate_predictions,
    lane_cues,
    lane_cues_from_mask,
    learned_cue_labels,
    load_labeller,
    make_cue_labeller,
    right_lane_mask,
    save_labeller,
    train_segmenter,
)

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


# ------------------------------------------------------------------------------------ learned labellers


WALL = 8
LANE_CFG = SegmenterConfig("city", (H, W, 1), road_id=ROAD, line_id=LINE, features=(4, 4))
DOOR_CFG = SegmenterConfig("indoor", (12, 16, 3), door_id=DOOR, features=(8, 8))


def lane_maps() -> np.ndarray:
    """Maps whose right-lane masks are empty or cover well over 2 % (where both seen rules agree)."""
    maps = [road_map(c) for c in (2, 8, 12, 17)]
    maps.append(road_map(5, road_cols=(0, 14)))
    no_line = np.full((H, W), GRASS, np.uint8)
    no_line[5:] = ROAD
    maps.append(no_line)
    edge = road_map(9)
    edge[5:, 3] = 4  # an EDGE_LINE-like class the lane rule ignores
    maps.append(edge)
    return np.stack(maps)


def door_frames(n: int, rng: np.random.Generator):
    """Synthetic halls: noisy grey walls with brown door panels of random size and place."""
    h, w, _ = DOOR_CFG.image_shape
    sem = np.full((n, h, w), WALL, np.uint8)
    for i in range(n):
        for _ in range(rng.integers(0, 3)):
            y0, x0 = rng.integers(0, h - 5), rng.integers(0, w - 3)
            sem[i, y0:y0 + rng.integers(5, h - y0 + 1), x0:x0 + rng.integers(3, 7)] = DOOR
    grey = np.repeat(rng.integers(90, 200, (n, h, w, 1)), 3, axis=-1)
    brown = np.asarray([140, 77, 30]) * rng.uniform(0.8, 1.2, (n, 1, 1, 1))
    images = np.where((sem == DOOR)[..., None], brown, grey)
    return np.clip(images, 0, 255).astype(np.uint8), sem


def test_true_map_as_prediction_gives_the_oracle_cues():
    maps = lane_maps()
    # A perfect segmenter's output: the true map reduced to the network's classes and back to ids.
    predicted = class_index_to_semantic(LANE_CFG, class_targets(LANE_CFG, jnp.asarray(maps)))
    assert set(np.unique(np.asarray(predicted))) <= {OTHER_ID, ROAD, LINE}
    learned = learned_cue_labels(LANE_CFG, predicted)
    for i, sem in enumerate(maps):
        seen, diff = lane_cues(jnp.asarray(sem), road_id=ROAD, line_id=LINE)  # the envs' oracle signals
        oracle = cue_labels(LANE_CFG, jnp.asarray(sem))
        assert float(oracle["lane_seen"]) == float(seen) and float(oracle["lane_diff"]) == float(diff)
        assert float(learned["lane_seen"][i]) == float(seen)
        np.testing.assert_allclose(float(learned["lane_diff"][i]), float(diff), atol=1e-7)
    metrics = evaluate_predictions(LANE_CFG, np.asarray(predicted), maps, batch_size=3)
    assert metrics["lane_iou"] == metrics["road_iou"] == metrics["line_iou"] == 1.0
    assert metrics["lane_seen_accuracy"] == 1.0 and metrics["lane_diff_mae"] == 0.0 and metrics["frames"] == len(maps)


def test_evaluation_counts_errors():
    maps = lane_maps()
    wrong = maps.copy()
    wrong[0, 5:, 2] = ROAD  # the line of frame 0 missed: its lane is not seen
    wrong[1, 5:, 1] = LINE  # a false line left of frame 1's line: its lane mask grows to the left
    m = evaluate_predictions(LANE_CFG, wrong, maps, batch_size=4)
    assert m["lane_seen_accuracy"] == pytest.approx(1 - 1 / len(maps))
    assert m["lane_iou"] < 1 and m["line_iou"] < 1 and m["lane_diff_mae"] > 0
    # The learned seen rule differs from the oracle's: a mask of 2 % or less counts as unseen.
    tiny = np.full((1, H, W), GRASS, np.uint8)
    tiny[0, 3:, :] = ROAD
    tiny[0, 3:, 15] = LINE
    tiny[0, 3:9, 16:] = GRASS  # the right lane: 4 road pixels in the bottom row (2 %)
    assert evaluate_predictions(LANE_CFG, tiny, tiny)["lane_seen_accuracy"] == 0.0
    # Door metrics.
    sem = np.full((2, 12, 16), WALL, np.uint8)
    sem[:, :, :6] = DOOR
    pred = sem.copy()
    pred[1, :, :3] = WALL
    d = evaluate_predictions(DOOR_CFG, pred, sem)
    assert d["door_iou"] == pytest.approx((12 * 6 + 12 * 3) / (2 * 12 * 6))
    assert d["door_frac_mae"] == pytest.approx(0.5 * 3 / 16)


def test_balanced_cross_entropy_weights_classes_equally():
    rng = np.random.default_rng(0)
    logits = jnp.asarray(rng.normal(size=(2, 5, 6, 3)), jnp.float32)
    targets = np.zeros((2, 5, 6), np.uint8)
    targets[0, 0, :2] = 2  # 2 pixels of class 2, none of class 1
    ce = np.asarray(optax_ce(logits, targets))
    expected = 0.5 * (ce[targets == 0].mean() + ce[targets == 2].mean())
    np.testing.assert_allclose(float(balanced_cross_entropy(logits, jnp.asarray(targets))), expected, rtol=1e-5)


def test_class_prior_turns_balanced_scores_into_posteriors():
    """Free logits fitted with the balanced loss to pixels whose classes have frequencies (0.9, 0.08, 0.02)
    score every class alike (the balanced minimiser); adding the stored log prior gives back the true
    posterior, so the argmax no longer over-predicts the rare classes."""
    cfg = SegmenterConfig("city", (4, 50, 1), road_id=ROAD, line_id=LINE)
    sem = np.full((1, 4, 50), GRASS, np.uint8)
    sem[0, :, :4] = ROAD  # 8 % road
    sem[0, 0, 4:8] = LINE  # 2 % line
    targets = class_targets(cfg, sem)
    logits = jnp.zeros(3)
    grad = jax.jit(jax.grad(lambda z: balanced_cross_entropy(jnp.broadcast_to(z, targets.shape + (3,)), targets)))
    for _ in range(300):
        logits = logits - 1.0 * grad(logits)
    np.testing.assert_allclose(np.asarray(jax.nn.softmax(logits)), [1 / 3] * 3, atol=1e-3)
    np.testing.assert_allclose(np.asarray(class_log_prior(cfg, sem)), np.log([0.9, 0.08, 0.02]), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(jax.nn.softmax(logits + class_log_prior(cfg, sem))), [0.9, 0.08, 0.02],
                               atol=1e-3)
    # A class absent from the maps keeps a finite prior (one pixel's worth).
    assert np.isfinite(np.asarray(class_log_prior(cfg, np.full((1, 4, 50), GRASS, np.uint8)))).all()


def test_stored_prior_moves_the_prediction(lane_labeller):
    images = np.random.default_rng(0).integers(0, 255, (2, H, W, 1)).astype(np.uint8)
    params = lane_labeller.params
    np.testing.assert_array_equal(np.asarray(params[CALIBRATION]["log_prior"]), 0.0)  # untrained: plain argmax
    raw = Segmenter(LANE_CFG).apply(params, images, calibrated=False)
    np.testing.assert_array_equal(np.asarray(Segmenter(LANE_CFG).apply(params, images)), np.asarray(raw))
    line_everywhere = {**params, CALIBRATION: {"log_prior": jnp.asarray([0.0, 0.0, 1e3])}}
    predicted = Segmenter(LANE_CFG).predict_semantic(line_everywhere, images)
    assert (np.asarray(predicted) == LINE).all()


def optax_ce(logits, targets):
    logp = jax.nn.log_softmax(logits)
    return -jnp.take_along_axis(logp, jnp.asarray(targets, jnp.int32)[..., None], axis=-1)[..., 0]


def test_segmenter_learns_synthetic_doors():
    rng = np.random.default_rng(0)
    images, sem = door_frames(64, rng)
    test_images, test_sem = door_frames(32, rng)
    steps = 100
    params, losses = train_segmenter(DOOR_CFG, images, sem, jax.random.key(0), steps,
                                     SegmenterTrainConfig(batch_size=8, learning_rate=1e-2, chunk=steps))
    assert losses.shape == (steps,) and np.mean(losses[-10:]) < 0.5 * np.mean(losses[:10])
    np.testing.assert_allclose(np.asarray(params[CALIBRATION]["log_prior"]), np.asarray(class_log_prior(DOOR_CFG, sem)))
    labeller = make_cue_labeller(DOOR_CFG, params)
    m = evaluate_labeller(labeller, test_images, test_sem, batch_size=16)
    assert m["door_iou"] > 0.8 and m["door_frac_mae"] < 0.03, m
    cues = labeller(test_images[:5])
    assert set(cues) == {"door_frac"} and cues["door_frac"].shape == (5,) and cues["door_frac"].dtype == jnp.float32


@pytest.fixture(scope="module")
def lane_labeller():
    return make_cue_labeller(LANE_CFG, Segmenter(LANE_CFG).init(jax.random.key(0)))


def test_labeller_refuses_wrong_images(lane_labeller):
    with pytest.raises(ValueError, match=r"images must be uint8\[batch, 10, 20, 1\].*'city'.*got uint8\[2, 10, 21, 1\]"):
        lane_labeller(np.zeros((2, H, W + 1, 1), np.uint8))
    with pytest.raises(ValueError, match=r"images must be uint8.*got float32"):
        lane_labeller(np.zeros((2, H, W, 1), np.float32))
    with pytest.raises(ValueError, match="images must be uint8"):
        lane_labeller(np.zeros((H, W, 1), np.uint8))  # one frame without its batch axis
    with pytest.raises(ValueError, match=r"semantic must be .* shape \[3, 10, 20\]"):
        train_segmenter(LANE_CFG, np.zeros((3, H, W, 1), np.uint8), np.zeros((3, W, H), np.uint8), jax.random.key(0), 1)


def test_labeller_refuses_another_scene(lane_labeller):
    lane_labeller.check_scene("city")
    with pytest.raises(ValueError, match=r"scene: this labeller was trained for scene 'city'.*from scene 'indoor'"):
        lane_labeller.check_scene("indoor")


@pytest.mark.parametrize("kwargs, match", [
    (dict(road_id=ROAD), "road_id and line_id"),
    (dict(), "needs road_id and line_id"),
    (dict(door_id=DOOR, image_shape=(10, 20)), r"image_shape must be \(h, w, c\)"),
    (dict(door_id=300), r"door_id must be a semantic id in \[0, 255\)"),
    (dict(road_id=ROAD, line_id=ROAD), "must differ"),
    (dict(door_id=DOOR, stem_stride=4), "stem_stride"),
])
def test_config_validation(kwargs, match):
    kwargs = dict(dict(scene="city", image_shape=(H, W, 1)), **kwargs)
    with pytest.raises(ValueError, match=match):
        SegmenterConfig(**kwargs)


def test_config_cues_and_classes():
    assert LANE_CFG.cue_names == ("lane_seen", "lane_diff") and LANE_CFG.class_ids == (ROAD, LINE)
    both = SegmenterConfig("x", (H, W, 3), road_id=ROAD, line_id=LINE, door_id=DOOR)
    assert both.cue_names == ("lane_seen", "lane_diff", "door_frac") and both.num_classes == 4
    sem = np.asarray([[ROAD, LINE, DOOR, GRASS]], np.uint8)
    np.testing.assert_array_equal(np.asarray(class_targets(both, sem)), [[1, 2, 3, 0]])


def test_save_and_load_labeller(tmp_path, lane_labeller):
    images = np.random.default_rng(0).integers(0, 255, (3, H, W, 1)).astype(np.uint8)
    path = save_labeller(tmp_path / "lab", lane_labeller)
    loaded = load_labeller(path)
    assert isinstance(loaded, CueLabeller) and loaded.config == LANE_CFG
    for k, v in lane_labeller(images).items():
        np.testing.assert_array_equal(np.asarray(loaded(images)[k]), np.asarray(v))
    before = sorted((p.relative_to(path), p.stat().st_mtime_ns) for p in path.rglob("*"))
    with pytest.raises(ValueError, match="already exists"):
        save_labeller(path, lane_labeller)
    assert sorted((p.relative_to(path), p.stat().st_mtime_ns) for p in path.rglob("*")) == before
    with pytest.raises(ValueError, match="holds no saved labeller"):
        load_labeller(tmp_path / "nothing")


def test_load_labeller_saved_without_class_prior(tmp_path, lane_labeller):
    """A labeller saved before labellers stored a class prior still loads, and predicts as it did then."""
    import orbax.checkpoint as ocp

    images = np.random.default_rng(1).integers(0, 255, (3, H, W, 1)).astype(np.uint8)
    trained = {**lane_labeller.params, CALIBRATION: {"log_prior": jnp.asarray([0.0, -1.0, -4.0])}}
    old = save_labeller(tmp_path / "old", CueLabeller(LANE_CFG, {"params": trained["params"]}))
    loaded = load_labeller(old)
    np.testing.assert_array_equal(np.asarray(loaded.params[CALIBRATION]["log_prior"]), 0.0)
    np.testing.assert_array_equal(np.asarray(loaded(images)["lane_diff"]), np.asarray(lane_labeller(images)["lane_diff"]))
    assert ocp.StandardCheckpointer().metadata(old / "params").item_metadata.tree.keys() == {"params"}  # untouched
    new = load_labeller(save_labeller(tmp_path / "new", CueLabeller(LANE_CFG, trained)))
    np.testing.assert_array_equal(np.asarray(new.params[CALIBRATION]["log_prior"]), [0.0, -1.0, -4.0])
