"""capsjax.data: the crash-safe episode store, relabelling and the window sampler (hand-made episodes)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import zarr

from capsjax import cues, data
from envs.base import TASK_SPLITS, EnvSpec

# One compiled function each for the module (eager mode would compile every primitive separately).
SAMPLE = jax.jit(data.WindowSampler.sample, static_argnums=2)
WINDOWS = jax.jit(data.WindowSampler.windows)

SPEC = EnvSpec(
    image_shape=(4, 6, 1), vector_keys=("collision", "heading", "speed"), vector_low=(0.0, -3.2, -4.0),
    vector_high=(1.0, 3.2, 4.0), action_names=("steer", "speed"), action_low=(-45.0, -4.0), action_high=(45.0, 4.0),
    plan_low=(-30.0, 0.5), plan_high=(30.0, 3.0), signal_names=("collision", "speed", "heading"),
)


def episode_batch(lengths, *, first_step=0, crash=None, labelled=()):
    """Episodes whose every value encodes its global step index s (so any misalignment shows).

    Step s: image filled with s % 251, vector (collision, s, -s), action (s, -s), pose (s, 2s, 0),
    signals collision / speed = s / heading = -s; the terminal entry of a crash episode has collision 1.
    """
    n = int(sum(lengths))
    s = np.arange(first_step, first_step + n)
    ends = np.cumsum(lengths) - 1
    done = np.zeros(n, bool)
    done[ends] = True
    collision = np.zeros(n, np.float32)
    for j, crashed in enumerate(crash or [False] * len(lengths)):
        if crashed:
            collision[ends[j]] = 1.0
    batch = {
        "image": np.broadcast_to((s % 251).astype(np.uint8)[:, None, None, None], (n, 4, 6, 1)).copy(),
        "vector": np.stack([collision, s, -s], -1).astype(np.float32),
        "action": np.stack([s, -s], -1).astype(np.float32),
        "done": done,
        "pose": np.stack([s, 2 * s, 0 * s], -1).astype(np.float32),
        "signal/collision": collision,
        "signal/speed": s.astype(np.float32),
        "signal/heading": -s.astype(np.float32),
        "task": np.stack([np.arange(len(lengths)), np.arange(len(lengths))], -1).astype(np.uint32),
    }
    if labelled:
        batch["labelled_index"] = np.asarray(labelled, np.int64)
        batch["semantic"] = np.stack([np.full((4, 6), 7 + i, np.uint8) for i in range(len(labelled))])
    return batch


def make_dataset(path, lengths, crash=None, chunk_steps=8, labelled=()):
    ds = data.Dataset.create(path, env_name="fast", env_config={"a": 1}, spec=SPEC, policy="test",
                             chunk_steps=chunk_steps)
    ds.append_episodes(episode_batch(lengths, crash=crash, labelled=labelled), lengths)
    return ds


def test_round_trip_and_append(tmp_path):
    path = tmp_path / "d.zarr"
    ds = make_dataset(path, [5, 7], labelled=(1, 9))
    ds.append_episodes(episode_batch([4], first_step=12), [4])
    ds = data.Dataset.open(path)
    assert (ds.num_episodes, ds.num_steps, ds.num_labelled) == (3, 16, 2)
    assert ds.env_name == "fast" and ds.spec == SPEC and ds.env_config == {"a": 1} and ds.policy == "test"
    starts, lengths = ds.episode_bounds()
    np.testing.assert_array_equal(starts, [0, 5, 12])
    np.testing.assert_array_equal(lengths, [5, 7, 4])
    ep = ds.read_episode(1)
    expected = episode_batch([16])
    for key in ("image", "vector", "action", "pose", "signal/speed", "signal/heading"):
        np.testing.assert_array_equal(ep[key], expected[key][5:12])
    np.testing.assert_array_equal(ep["done"], [False] * 6 + [True])
    np.testing.assert_array_equal(ep["labelled_index"], [4])  # global step 9
    steps, images, semantic = ds.labelled_frames()
    np.testing.assert_array_equal(steps, [1, 9])
    np.testing.assert_array_equal(images[:, 0, 0, 0], [1, 9])
    np.testing.assert_array_equal(semantic[:, 0, 0], [7, 8])
    got = np.concatenate([idx for idx, _ in ds.iter_images(5)])
    np.testing.assert_array_equal(got, np.arange(16))
    idx, imgs = zip(*ds.iter_images(3, episodes=[2]))
    np.testing.assert_array_equal(np.concatenate(idx), np.arange(12, 16))
    np.testing.assert_array_equal(np.concatenate(imgs)[:, 0, 0, 0], np.arange(12, 16))
    with pytest.raises(ValueError, match="mode='a'"):
        ds.append_episodes(episode_batch([3]), [3])


def test_bad_input_is_refused(tmp_path):
    path = tmp_path / "d.zarr"
    ds = make_dataset(path, [5])
    with pytest.raises(FileExistsError, match="already exists"):
        make_dataset(path, [5])
    bad = episode_batch([4])
    del bad["pose"]
    with pytest.raises(ValueError, match="'pose'"):
        ds.append_episodes(bad, [4])
    bad = episode_batch([4])
    bad["done"][1] = True
    with pytest.raises(ValueError, match="done"):
        ds.append_episodes(bad, [4])
    with pytest.raises(ValueError, match="shape"):
        ds.append_episodes(episode_batch([4]), [5])
    assert data.Dataset.open(path).num_steps == 5  # nothing was written by the refused calls
    # Schema version: wrong, then missing.
    zarr.open_group(path, mode="r+").attrs["schema_version"] = data.SCHEMA_VERSION + 1
    with pytest.raises(ValueError, match=f"schema_version {data.SCHEMA_VERSION + 1}, expected {data.SCHEMA_VERSION}"):
        data.Dataset.open(path)
    group = zarr.open_group(path, mode="r+")
    del group.attrs["schema_version"]
    with pytest.raises(ValueError, match="no 'schema_version'"):
        data.Dataset.open(path)


def test_empty_dataset_and_horizon_too_long(tmp_path):
    empty = data.Dataset.create(tmp_path / "e.zarr", env_name="fast", env_config={}, spec=SPEC, policy="test")
    with pytest.raises(ValueError, match="empty"):
        data.make_sampler(empty, horizon=3)
    with pytest.raises(ValueError, match="empty"):
        empty.split_episodes(0.2, seed=0)
    ds = make_dataset(tmp_path / "d.zarr", [4, 6])
    with pytest.raises(ValueError, match="horizon 6 .*longest has 6 entries.*horizon <= 5"):
        data.make_sampler(ds, horizon=6)
    data.make_sampler(ds, horizon=5)  # just fits


def test_windows_follow_the_paper_done_handling(tmp_path):
    # Episode 0 (steps 0-5) ends in a crash at its terminal entry; episode 1 (6-10) times out.
    ds = make_dataset(tmp_path / "d.zarr", [6, 5], crash=[True, False])
    sampler = data.make_sampler(ds, horizon=4)
    np.testing.assert_array_equal(np.asarray(sampler.starts), [0, 1, 2, 3, 4, 6, 7, 8, 9])
    batch = WINDOWS(sampler, jnp.array([3, 1, 8, 6]), jax.random.key(0))
    # Window at t=3: observations 4, 5 are in the episode (5 is the terminal one), 6 and 7 are not.
    np.testing.assert_array_equal(batch.valid[0], [True, True, False, False])
    np.testing.assert_array_equal(batch.done[0], [False, True, False, False])
    np.testing.assert_array_equal(batch.signals["speed"][0][:2], [4, 5])
    target, mask = cues.COLLISION.labels(batch.signals["collision"], batch.valid)
    np.testing.assert_array_equal(target[0, :, 0], [0, 1, 1, 1])  # absorbing after the crash
    np.testing.assert_array_equal(mask[0], [1, 1, 1, 1])  # collision is never masked
    np.testing.assert_array_equal(target[2, :, 0], [0, 0, 0, 0])  # a time-out stays 0 after the end
    _, speed_mask = cues.SPEED.labels(batch.signals["speed"], batch.valid)
    np.testing.assert_array_equal(speed_mask[0], [1, 1, 0, 0])
    # Actions a_t..a_{t+H-1}: executed ones are recorded, the terminal entry's and later ones are random.
    np.testing.assert_array_equal(batch.actions[0, :2, 0], [3, 4])
    low, high = np.array(SPEC.plan_low), np.array(SPEC.plan_high)
    pad = np.asarray(batch.actions[0, 2:])
    assert np.all((pad >= low) & (pad <= high)) and not np.allclose(pad[0], pad[1])
    np.testing.assert_array_equal(batch.actions[1, :, 0], [1, 2, 3, 4])
    # History t-3..t, zeros before the episode start (window at t=1 and at t=6, the next episode's first).
    np.testing.assert_array_equal(batch.obs.vector[0, :, 1], [0, 1, 2, 3])
    np.testing.assert_array_equal(batch.obs.vector[1, :, 1], [0, 0, 0, 1])
    np.testing.assert_array_equal(batch.obs.images[1, :, 0, 0, 0], [0, 0, 0, 1])
    np.testing.assert_array_equal(batch.obs.vector[3, :, 1], [0, 0, 0, 6])
    np.testing.assert_array_equal(batch.next_obs.vector[3, :, 1], [0, 0, 6, 7])
    # Context: pose at t and the episode's final position (hindsight goals).
    np.testing.assert_array_equal(batch.context["pose"][0], [3, 6, 0])
    np.testing.assert_array_equal(batch.context["final_xy"][0], [5, 10])
    np.testing.assert_array_equal(batch.context["final_xy"][2], [10, 20])


def test_windows_stack_any_history_from_the_stored_frames(tmp_path):
    # One frame is stored per step, so a model with a longer memory than the collecting env's (history 4 in
    # SPEC) trains on the same dataset: frames t-5..t, zeros before the episode start.
    ds = make_dataset(tmp_path / "d.zarr", [6, 5], crash=[True, False])
    sampler = data.make_sampler(ds, horizon=4, history=6)
    batch = WINDOWS(sampler, jnp.array([3, 8]), jax.random.key(0))
    assert batch.obs.images.shape == (2, 6, 4, 6, 1) and batch.obs.vector.shape == (2, 6, 3)
    np.testing.assert_array_equal(batch.obs.vector[0, :, 1], [0, 0, 0, 1, 2, 3])
    np.testing.assert_array_equal(batch.obs.images[1, :, 0, 0, 0], [0, 0, 0, 6, 7, 8])
    np.testing.assert_array_equal(batch.next_obs.vector[1, :, 1], [0, 0, 6, 7, 8, 9])
    with pytest.raises(ValueError, match="history must be >= 1"):
        data.make_sampler(ds, horizon=4, history=0)


def test_mirrored_windows_flip_frames_and_negate_what_the_mirror_negates(tmp_path):
    ds = make_dataset(tmp_path / "d.zarr", [6, 5], crash=[True, False])
    # Frames that are not left-right symmetric: column j of step s holds (s + 10 j) % 251.
    ds = data.Dataset.open(ds.path)
    signs = dict(data.MIRROR_SIGNS, steer=-1.0)  # this spec calls its steering action "steer"
    plain = data.make_sampler(ds, horizon=4)
    mirrored = data.make_sampler(ds, horizon=4, mirror=True, mirror_signs=signs)
    cols = jnp.arange(6, dtype=jnp.uint8)[None, None, :, None] * 10
    plain = plain.replace(images=plain.images + cols)
    mirrored = mirrored.replace(images=mirrored.images + cols)
    t, key = jnp.array([3, 8]), jax.random.key(0)
    a = WINDOWS(plain, t, key)
    b = WINDOWS(mirrored, t, key, jnp.array([True, False]))
    np.testing.assert_array_equal(b.obs.images[0], a.obs.images[0][..., ::-1, :])
    np.testing.assert_array_equal(b.next_obs.images[0], a.next_obs.images[0][..., ::-1, :])
    np.testing.assert_array_equal(b.obs.images[1], a.obs.images[1])  # not flipped: unchanged
    np.testing.assert_array_equal(b.obs.vector[0], a.obs.vector[0] * np.array([1, -1, 1]))  # heading negated
    np.testing.assert_array_equal(b.signals["heading"][0], -a.signals["heading"][0])
    np.testing.assert_array_equal(b.signals["speed"][0], a.signals["speed"][0])
    np.testing.assert_array_equal(b.signals["collision"][0], a.signals["collision"][0])
    # Executed actions: steering negated, speed kept; the random padding past the end is not mirrored.
    np.testing.assert_array_equal(b.actions[0, :2], a.actions[0, :2] * np.array([-1, 1]))
    np.testing.assert_array_equal(b.actions[0, 2:], a.actions[0, 2:])
    np.testing.assert_array_equal(b.context["pose"][0], a.context["pose"][0] * np.array([1, -1, -1]))
    np.testing.assert_array_equal(b.context["final_xy"][0], a.context["final_xy"][0] * np.array([1, -1]))
    for name in ("actions", "valid", "done"):
        np.testing.assert_array_equal(getattr(b, name)[1], getattr(a, name)[1])
    # sample() mirrors about half of the windows.
    batch = SAMPLE(mirrored, jax.random.key(3), 4000)
    y = np.asarray(batch.context["pose"][:, 1])  # 2 s, negated when mirrored (s = 0 is ambiguous: left out)
    assert 0.45 < (y[y != 0] < 0).mean() < 0.55
    with pytest.raises(ValueError, match="flip needs a sampler made with make_sampler"):
        plain.windows(t, key, jnp.array([True, False]))


def test_mirror_refuses_a_quantity_without_a_known_sign(tmp_path):
    ds = make_dataset(tmp_path / "d.zarr", [6, 5])
    with pytest.raises(ValueError, match="no sign for action 'steer'"):
        data.make_sampler(ds, horizon=3, mirror=True)
    brightness = lambda images: {"lane_diff": jnp.mean(images, axis=(1, 2, 3)) / 255.0}
    data.relabel(ds, brightness, "seg", batch_size=5, meta={}, scene="fast")
    signs = dict(data.MIRROR_SIGNS, steer=-1.0)
    with pytest.raises(ValueError, match="no sign for signal 'lane_diff'"):  # right-hand traffic has no mirror
        data.make_sampler(ds, horizon=3, label_sources={"lane_diff": "seg"}, mirror=True, mirror_signs=signs)
    with pytest.raises(ValueError, match=r"mirror_signs\['speed'\] must be \+1 or -1"):
        data.make_sampler(ds, horizon=3, mirror=True, mirror_signs=dict(signs, speed=0.5))


def test_sampling_is_uniform_over_valid_starts_and_jittable(tmp_path):
    ds = make_dataset(tmp_path / "d.zarr", [3, 9, 5, 2])
    sampler = data.make_sampler(ds, horizon=2)
    batch = SAMPLE(sampler, jax.random.key(0), 20_000)
    t = np.asarray(batch.context["pose"][:, 0]).astype(int)  # pose x = global step
    valid_starts = [0, 1, 3, 4, 5, 6, 7, 8, 9, 10, 12, 13, 14, 15, 17]
    counts = np.bincount(t, minlength=19)
    assert set(np.flatnonzero(counts)) == set(valid_starts)  # never a terminal entry
    expected = 20_000 / len(valid_starts)
    assert np.all(np.abs(counts[valid_starts] - expected) < 5 * np.sqrt(expected))
    assert batch.obs.images.shape == (20_000, 4, 4, 6, 1) and batch.actions.shape == (20_000, 2, 2)


def test_stored_split_codes_follow_the_env_task_splits():
    # Episodes store their split as an index into data.SPLITS: the order must be the envs' and only grow.
    assert data.SPLITS == TASK_SPLITS and data.SPLITS[:2] == ("train", "eval")


def test_holdout_split_is_disjoint_by_episode(tmp_path):
    ds = make_dataset(tmp_path / "d.zarr", [3] * 20)
    train, holdout = ds.split_episodes(0.25, seed=1)
    assert len(holdout) == 5 and len(train) == 15
    assert not set(train) & set(holdout) and set(train) | set(holdout) == set(range(20))
    assert np.array_equal(ds.split_episodes(0.25, seed=1)[1], holdout)
    sampler = data.make_sampler(ds, horizon=2, episodes=holdout)
    batch = SAMPLE(sampler, jax.random.key(0), 500)
    episodes = np.asarray(batch.context["pose"][:, 0]).astype(int) // 3
    assert set(episodes) <= set(holdout)


def test_relabel_writes_labels_and_refuses_a_wrong_scene(tmp_path):
    ds = make_dataset(tmp_path / "d.zarr", [5, 7])
    brightness = lambda images: {"lane_seen": jnp.mean(images, axis=(1, 2, 3)) / 255.0}
    labels = data.relabel(ds, brightness, "seg", batch_size=5, meta={"model": "v1"}, scene="fast")
    np.testing.assert_allclose(labels["lane_seen"], np.arange(12) / 255.0, rtol=1e-6)
    info = ds.label_info("seg")
    assert ds.label_names == ("seg",)
    assert info["meta"] == {"model": "v1", "scene": "fast"} and info["num_steps"] == 12
    # Relabelling with a new labeller replaces the set; episodes are untouched.
    data.relabel(ds, lambda im: {"lane_seen": jnp.ones(im.shape[0])}, "seg", batch_size=4, meta={"model": "v2"})
    np.testing.assert_array_equal(data.Dataset.open(ds.path).read_labels("seg", "lane_seen"), np.ones(12))
    np.testing.assert_array_equal(ds.read_episode(0)["signal/speed"], np.arange(5))
    with pytest.raises(ValueError, match="scene is 'city'.*expected scene='fast'"):
        data.relabel(ds, brightness, "seg", meta={}, scene="city")
    # The sampler reads a cue from a label set instead of the recorded signals.
    sampler = data.make_sampler(ds, horizon=3, label_sources={"lane_seen": "seg"})
    batch = WINDOWS(sampler, jnp.array([0]), jax.random.key(0))
    np.testing.assert_array_equal(batch.signals["lane_seen"][0], [1, 1, 1])
    with pytest.raises(ValueError, match="no label set 'nope'"):
        data.make_sampler(ds, horizon=3, label_sources={"lane_seen": "nope"})
    with pytest.raises(ValueError, match=r"labels\['x'\] has shape"):
        ds.write_labels("bad", {"x": np.zeros(3)}, meta={})


def _chunk_file(path, array, chunk):
    return os.path.join(path, array, "c", str(chunk), *(["0"] * (zarr.open_array(os.path.join(path, array)).ndim - 1)))


def test_corrupted_and_truncated_chunks_are_reported_with_their_episodes(tmp_path):
    path = str(tmp_path / "d.zarr")
    ds = make_dataset(path, [5, 7, 6, 6], chunk_steps=8)  # episodes at steps 0-4, 5-11, 12-17, 18-23
    assert ds.verify() == []
    # Flip a byte in image chunk 1 (steps 8-15: episodes 1 and 2); truncate speed chunk 2 (16-23: 2, 3).
    f = _chunk_file(path, "steps/image", 1)
    with open(f, "rb") as fh:
        raw = bytearray(fh.read())
    raw[len(raw) // 2] ^= 0xFF
    with open(f, "wb") as fh:
        fh.write(bytes(raw))
    os.truncate(_chunk_file(path, "steps/signal/speed", 2), 5)
    report = {(c.field, c.chunk): c.episodes for c in data.Dataset.open(path).verify()}
    assert report == {("steps/image", 1): (1, 2), ("steps/signal/speed", 2): (2, 3)}
    ds = data.Dataset.open(path)
    np.testing.assert_array_equal(ds.read_episode(0)["image"][:, 0, 0, 0], np.arange(5))  # the rest is usable
    with pytest.warns(RuntimeWarning, match=r"skipping 3 episode\(s\).*\[1, 2, 3\]"):
        sampler = data.make_sampler(ds, horizon=2)
    np.testing.assert_array_equal(np.asarray(sampler.vector[:, 1]), np.arange(5))


WRITER = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {root!r})
    from tests.test_data import episode_batch
    from capsjax import data
    ds = data.Dataset.open({path!r}, "a")
    while True:
        lengths = [3 + ds.num_episodes % 4, 5]
        ds.append_episodes(episode_batch(lengths, first_step=ds.num_steps), lengths)
""")


def test_sigkill_mid_write_keeps_committed_episodes_and_resumes(tmp_path):
    path = str(tmp_path / "d.zarr")
    make_dataset(path, [5], chunk_steps=4)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.Popen([sys.executable, "-c", WRITER.format(root=root, path=path)])
    try:
        deadline = time.time() + 60
        while data.Dataset.open(path).num_episodes < 12 and time.time() < deadline:
            time.sleep(0.05)
        time.sleep(0.13)  # land somewhere inside a later append
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    ds = data.Dataset.open(path)
    assert ds.num_episodes >= 12
    assert ds.verify() == []
    starts, lengths = ds.episode_bounds()
    assert starts[-1] + lengths[-1] == ds.num_steps
    every = np.concatenate([ds.read_episode(i)["vector"][:, 1] for i in range(ds.num_episodes)])
    np.testing.assert_array_equal(every, np.arange(ds.num_steps))  # every committed step, in order
    # Re-running appends after the last committed episode (anything half-written is overwritten).
    before = ds.num_steps
    ds = data.Dataset.open(path, "a")
    ds.append_episodes(episode_batch([4], first_step=before), [4])
    ds = data.Dataset.open(path)
    assert ds.num_steps == before + 4 and ds.verify() == []
    np.testing.assert_array_equal(ds.read_episode(ds.num_episodes - 1)["vector"][:, 1], np.arange(before, before + 4))


def test_batch_source_draws_what_sample_draws_and_is_a_pytree_of_the_buffers(tmp_path):
    sampler = data.make_sampler(make_dataset(tmp_path / "d.zarr", [3, 9, 5]), horizon=2)
    source = sampler.batches(16)
    key = jax.random.key(3)
    for got, want in zip(jax.tree.leaves(jax.jit(lambda s, k: s(k))(source, key)),
                         jax.tree.leaves(SAMPLE(sampler, key, 16))):
        np.testing.assert_array_equal(got, want)
    # The buffers are leaves (so jitted training passes them as arguments), the batch size is static.
    assert any(leaf is sampler.images for leaf in jax.tree.leaves(source))
    assert jax.tree.structure(source) != jax.tree.structure(sampler.batches(8))
    for bad in (0, -1, 2.0, True):
        with pytest.raises(ValueError, match="batch_size"):
            sampler.batches(bad)


def test_concatenated_samplers_keep_each_datasets_windows_and_episode_bounds(tmp_path):
    a = data.make_sampler(make_dataset(tmp_path / "a.zarr", [3, 9, 5]), horizon=2)
    b = data.make_sampler(make_dataset(tmp_path / "b.zarr", [6, 4], crash=[True, False]), horizon=2)
    both = data.concatenate_samplers(a, b)
    assert both.num_windows == a.num_windows + b.num_windows
    n_a = int(a.images.shape[0])
    key = jax.random.key(0)
    # A window of the second dataset, read through the concatenation, is the same window as before
    # (history zero-padded at its own episode start, labels stopping at its own terminal entry).
    for t_b in (0, 3, 5, 6, 8):
        got = both.windows(jnp.asarray([n_a + t_b], jnp.int32), key)
        want = b.windows(jnp.asarray([t_b], jnp.int32), key)
        for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_array_equal(g, w)
    for t_a in (0, 4, 15):
        got, want = both.windows(jnp.asarray([t_a], jnp.int32), key), a.windows(jnp.asarray([t_a], jnp.int32), key)
        for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_array_equal(g, w)
    # Sampling is uniform over the valid starts of both (so each dataset in proportion to its windows).
    np.testing.assert_array_equal(both.starts, np.concatenate([a.starts, np.asarray(b.starts) + n_a]))
    assert SAMPLE(both, jax.random.key(1), 64).obs.images.shape[0] == 64
    with pytest.raises(ValueError, match="horizon"):
        data.concatenate_samplers(a, data.make_sampler(make_dataset(tmp_path / "c.zarr", [6, 4]), horizon=3))
    with pytest.raises(ValueError, match="signals"):
        data.concatenate_samplers(a, data.make_sampler(make_dataset(tmp_path / "d.zarr", [6, 4]), horizon=2,
                                                       signals=("collision",)))
    with pytest.raises(ValueError, match="at least one"):
        data.concatenate_samplers()
