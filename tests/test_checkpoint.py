"""Checkpoints (capsjax.checkpoint) and resumable training (training.fit): kill, resume, refuse, guard.

Run as a script (``python tests/test_checkpoint.py train CKPT_DIR NUM_STEPS OUT``) it is the training
process that the SIGKILL test starts and kills.
"""
import dataclasses
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import capsjax
from capsjax import checkpoint, training
from envs.fast import FastEnv, FastTask, random_windows

ENV = FastEnv()
TASK = FastTask(obstacles=jnp.array([[5.5, 5.5, 0.01]] * 4), start=jnp.zeros(3))
MODEL = capsjax.CAPsModel(capsjax.ModelConfig.from_env_spec(
    ENV.spec, conv=((4, 3, 2),), obs_hidden=(16, 16), action_hidden=(8, 8), head_hidden=4, horizon=4))
CFG = capsjax.TrainConfig(batch_size=8, learning_rate=1e-3)
SAVE_EVERY = 4
WINDOWS = 64


def make_sampler():
    data = jax.jit(random_windows, static_argnums=(0, 3, 4))(ENV, jax.random.key(1), TASK, WINDOWS, MODEL.horizon)

    def sample(key):  # a pure function of the key: the key in TrainState is the sampler's position
        idx = jax.random.randint(key, (CFG.batch_size,), 0, WINDOWS)
        return jax.tree.map(lambda x: x[idx], data)

    return sample


def _poisoned(sample):
    def nan_sample(key):
        batch = sample(key)
        return batch.replace(actions=batch.actions * jnp.nan)

    return nan_sample


def _flat(params) -> dict:
    return {jax.tree_util.keystr(p): np.asarray(x) for p, x in jax.tree_util.tree_flatten_with_path(params)[0]}


def _assert_trees_equal(a, b):
    fa, fb = _flat(a), _flat(b)
    assert fa.keys() == fb.keys()
    for k in fa:
        np.testing.assert_array_equal(fa[k], fb[k], err_msg=k)


def _manager(ckpt_dir, model=MODEL, cfg=CFG, **kwargs):
    return checkpoint.Checkpointer(ckpt_dir, config=checkpoint.training_config(model, cfg), **kwargs)


def _subprocess_env(cache_dir):
    # A shared persistent compilation cache: the resumed process reuses the killed one's executables.
    return dict(os.environ, PYTHONPATH=os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")]),
                JAX_PLATFORMS="cpu", JAX_COMPILATION_CACHE_DIR=str(cache_dir),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0", JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")


def _snapshot(directory) -> dict:
    """Every file's bytes under ``directory``: to show that nothing was deleted or rewritten."""
    return {str(p): p.read_bytes() for p in Path(directory).rglob("*") if p.is_file()}


def _finished_steps(ckpt_dir) -> list[int]:
    # Orbax renames a step's temporary directory to its number once the save is complete.
    return sorted(int(d) for d in os.listdir(ckpt_dir) if d.isdigit()) if os.path.isdir(ckpt_dir) else []


@pytest.fixture(scope="module")
def sample():
    return make_sampler()


@pytest.mark.slow  # two training subprocesses: ~3.5 CPU-minutes with the rest of this file on the 2-core machine
def test_killed_run_resumes_exactly(tmp_path, sample):
    ckpt, cache = tmp_path / "ckpt", tmp_path / "cache"
    script = os.path.abspath(__file__)
    env = _subprocess_env(cache)
    proc = subprocess.Popen([sys.executable, script, "train", str(ckpt), "1000000", ""], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 300
    try:
        while len(_finished_steps(ckpt)) < 2 and proc.poll() is None and time.time() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, f"the training process ended early:\n{proc.stdout.read()}"
        assert len(_finished_steps(ckpt)) >= 2, "no checkpoint appeared in time"
    finally:
        proc.send_signal(signal.SIGKILL)
        log = proc.communicate()[0]
    assert proc.returncode == -signal.SIGKILL
    reached = max([int(line.split()[1]) for line in log.splitlines() if line.startswith("step ")], default=0)
    saved = _finished_steps(ckpt)[-1]
    assert saved % SAVE_EVERY == 0 and saved >= reached - SAVE_EVERY  # at most one save interval lost

    # The uninterrupted reference: the same checkpoint, then two more intervals in this process.
    target = saved + 2 * SAVE_EVERY
    with _manager(ckpt) as manager:
        state, step = manager.restore(capsjax.init_train_state(MODEL, CFG, jax.random.key(99)))
    assert step == saved and int(state.step) == saved
    state, _ = training.fit(MODEL, CFG, sample, target, state=state, save_every=SAVE_EVERY)

    out = tmp_path / "resumed.npz"
    resumed = subprocess.run([sys.executable, script, "train", str(ckpt), str(target), str(out)], env=env,
                             capture_output=True, text=True, timeout=300, check=False)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    assert f"resumed from step {saved}" in resumed.stdout
    got = dict(np.load(out))
    want = _flat(state.params)
    assert got.keys() == want.keys()
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)  # exact on CPU

    # ... and the same as one run from scratch that was never killed.
    fresh, _ = training.fit(MODEL, CFG, sample, target, key=jax.random.key(2), save_every=SAVE_EVERY)
    _assert_trees_equal(fresh.params, state.params)


def test_a_directory_trained_past_num_steps_is_refused_unless_that_step_is_saved(tmp_path, sample):
    ckpt = tmp_path / "ckpt"
    long, _ = training.fit(MODEL, CFG, sample, 3 * SAVE_EVERY, key=jax.random.key(2), ckpt_dir=ckpt,
                           save_every=SAVE_EVERY, keep=2)  # keeps steps 8 and 12
    before = _snapshot(ckpt)
    # Step 8 is saved: that is the run of 8 steps, not the longer one.
    shorter, _ = training.fit(MODEL, CFG, sample, 2 * SAVE_EVERY, ckpt_dir=ckpt, save_every=SAVE_EVERY, keep=2)
    assert int(shorter.step) == 2 * SAVE_EVERY
    longer = _flat(long.params)
    assert any(not np.array_equal(x, longer[k]) for k, x in _flat(shorter.params).items())
    # Step 4 was deleted (keep=2): refused by name, nothing on disk touched.
    with pytest.raises(ValueError, match=r"past num_steps=4 \(steps \[8, 12\]\)"):
        training.fit(MODEL, CFG, sample, SAVE_EVERY, ckpt_dir=ckpt, save_every=SAVE_EVERY, keep=2)
    assert _snapshot(ckpt) == before


@dataclasses.dataclass(frozen=True)
class Windows:  # how the training windows were drawn, as a pipeline would pass it to fit's metadata
    mirror: bool = False


def test_fit_refuses_a_checkpoint_of_other_metadata_and_reads_an_older_one_as_the_defaults(tmp_path, sample):
    ckpt = tmp_path / "ckpt"
    first, _ = training.fit(MODEL, CFG, sample, SAVE_EVERY, key=jax.random.key(2), ckpt_dir=ckpt,
                            save_every=SAVE_EVERY)  # written without metadata, as before it existed
    before = _snapshot(ckpt)
    # Asking for the metadata's defaults resumes it: the older run did draw its windows that way.
    again, _ = training.fit(MODEL, CFG, sample, SAVE_EVERY, ckpt_dir=ckpt, save_every=SAVE_EVERY,
                            metadata={"Windows": Windows()})
    _assert_trees_equal(again.params, first.params)
    # Other training data are refused by name; nothing on disk is touched.
    with pytest.raises(checkpoint.ConfigMismatchError, match=r"Windows\.mirror: saved false != requested true"):
        training.fit(MODEL, CFG, sample, 2 * SAVE_EVERY, ckpt_dir=ckpt, save_every=SAVE_EVERY,
                     metadata={"Windows": Windows(mirror=True)})
    assert _snapshot(ckpt) == before


def test_nan_steps_are_skipped_counted_and_stop_the_run(tmp_path, sample):
    ckpt = tmp_path / "ckpt"
    good, _ = training.fit(MODEL, CFG, sample, SAVE_EVERY, key=jax.random.key(2), ckpt_dir=ckpt,
                           save_every=SAVE_EVERY)
    assert int(good.bad_steps) == 0
    before = _snapshot(ckpt)

    # Skipped and counted: params and optimiser state untouched, the sampler moves on.
    nan_sample = _poisoned(sample)
    skipped, metrics = training.fit(MODEL, CFG, nan_sample, 2 * SAVE_EVERY, state=good, save_every=SAVE_EVERY)
    assert int(skipped.bad_steps) == SAVE_EVERY and int(skipped.consecutive_bad) == SAVE_EVERY
    assert int(skipped.step) == 2 * SAVE_EVERY and bool(jnp.all(metrics["skipped"]))
    _assert_trees_equal(skipped.params, good.params)
    _assert_trees_equal(skipped.opt_state, good.opt_state)
    # A finite step resets the streak, not the total.
    recovered, _ = training.fit(MODEL, CFG, sample, 3 * SAVE_EVERY, state=skipped, save_every=SAVE_EVERY)
    assert int(recovered.consecutive_bad) == 0 and int(recovered.bad_steps) == SAVE_EVERY

    # Too many in a row: a clear error, nothing saved, the last good checkpoint is still the latest.
    with pytest.raises(training.NonFiniteTrainingError, match=r"max_bad_steps=3.*last good checkpoint is step 4"):
        training.fit(MODEL, CFG, nan_sample, 5 * SAVE_EVERY, ckpt_dir=ckpt, save_every=SAVE_EVERY,
                     max_bad_steps=3)
    assert _snapshot(ckpt) == before
    with _manager(ckpt) as manager:
        restored, step = manager.restore(good)
    assert step == SAVE_EVERY
    _assert_trees_equal(restored.params, good.params)


@pytest.fixture()
def two_steps(tmp_path):
    """A directory with checkpoints at steps 1 and 2 of distinct states."""
    state = capsjax.init_train_state(MODEL, CFG, jax.random.key(0))
    second = state.replace(params=jax.tree.map(lambda x: x + 1.0, state.params), step=state.step + 2)
    with _manager(tmp_path / "ckpt") as manager:
        manager.save(1, state.replace(step=state.step + 1))
        manager.save(2, second)
    return tmp_path / "ckpt", state, second


def test_another_model_config_is_refused_naming_the_field(two_steps):
    ckpt, state, _ = two_steps
    other = capsjax.CAPsModel(dataclasses.replace(MODEL.config, conv=((8, 3, 2),)))
    with _manager(ckpt, model=other) as manager:
        with pytest.raises(checkpoint.ConfigMismatchError, match=r"ModelConfig\.conv: saved \[\[4, 3, 2\]\] != requested \[\[8, 3, 2\]\]"):
            manager.restore(capsjax.init_train_state(other, CFG, jax.random.key(0)))
    with _manager(ckpt, cfg=capsjax.TrainConfig(batch_size=8, learning_rate=3e-3)) as manager:
        with pytest.raises(ValueError, match=r"TrainConfig\.learning_rate: saved 0\.001 != requested 0\.003"):
            manager.restore(state)
    # Without a config to compare, a state of other shapes is still refused by name, not deep in JAX.
    with checkpoint.Checkpointer(ckpt) as manager:
        with pytest.raises(ValueError, match=r"state\['params'\]\['params'\]\['conv0'\]\['bias'\] is saved as float32\[4\], expected float32\[8\]"):
            manager.restore(capsjax.init_train_state(other, CFG, jax.random.key(0)))


def test_a_config_field_added_later_counts_as_its_default(tmp_path):
    """A checkpoint saved before ``ModelConfig.image_pool`` existed restores when the field is at its
    default, and is refused, naming the field, when it is not."""
    state = capsjax.init_train_state(MODEL, CFG, jax.random.key(0))
    old = checkpoint.training_config(MODEL, CFG)
    del old["ModelConfig"]["image_pool"]  # what an older version wrote
    with checkpoint.Checkpointer(tmp_path, config=old) as manager:
        manager.save(1, state, force=True)
    defaults = checkpoint.training_defaults(MODEL, CFG)
    with _manager(tmp_path, defaults=defaults) as manager:
        restored, step = manager.restore(state)
    assert step == 1
    _assert_trees_equal(restored.params, state.params)
    with _manager(tmp_path) as manager:  # without defaults the absent field is a difference
        with pytest.raises(checkpoint.ConfigMismatchError, match=r"ModelConfig\.image_pool: saved \"<absent>\" != requested 1"):
            manager.restore(state)
    pooled = capsjax.CAPsModel(dataclasses.replace(MODEL.config, image_pool=2))
    with _manager(tmp_path, model=pooled, defaults=checkpoint.training_defaults(pooled, CFG)) as manager:
        with pytest.raises(checkpoint.ConfigMismatchError, match=r"ModelConfig\.image_pool: saved 1 != requested 2"):
            manager.restore(capsjax.init_train_state(pooled, CFG, jax.random.key(0)))


def _largest_file(step_dir) -> str:
    files = [os.path.join(r, f) for r, _, fs in os.walk(step_dir) for f in fs]
    return max(files, key=os.path.getsize)


def test_truncated_checkpoint_is_reported_and_older_ones_stay_restorable(two_steps):
    ckpt, state, _ = two_steps
    victim = _largest_file(ckpt / "2")
    with open(victim, "r+b") as f:
        f.truncate(os.path.getsize(victim) // 2)
    snapshot = _snapshot(ckpt)
    with _manager(ckpt) as manager:
        with pytest.raises(checkpoint.CorruptCheckpointError, match=rf"step 2 at {ckpt / '2'}"):
            manager.restore(state)
        restored, step = manager.restore(state, fallback=True)
        assert manager.all_steps() == [1, 2]
    assert step == 1 and int(restored.step) == 1
    _assert_trees_equal(restored.params, state.params)
    assert _snapshot(ckpt) == snapshot  # a failed restore neither deletes nor rewrites anything


def test_keeps_the_last_k_and_saves_every_n(tmp_path):
    state = capsjax.init_train_state(MODEL, CFG, jax.random.key(0))
    with _manager(tmp_path / "ckpt", save_every=2, keep=2) as manager:
        saved = [manager.save(s, state.replace(step=jnp.int32(s))) for s in range(2, 8)]
        manager.wait()
        assert saved == [True, False, True, False, True, False]
        assert manager.all_steps() == [4, 6] and manager.latest_step() == 6
        with pytest.raises(FileNotFoundError, match="no checkpoint step 2"):
            manager.restore(state, step=2)
    with pytest.raises(FileNotFoundError, match="no checkpoint in"):
        _manager(tmp_path / "empty").restore(state)


def test_managers_saving_at_once_from_threads_all_finish(tmp_path):
    """Models trained at once save from several threads; orbax's process-wide state for a save in flight made
    such saves wait 300 s for a barrier and fail, before saves were serialised (``checkpoint._SAVE_LOCK``)."""
    import threading

    state = {"w": jnp.ones((256, 512)), "b": jnp.zeros((512,))}
    start_together = threading.Barrier(3)
    errors = []

    def save_steps(name):
        try:
            with checkpoint.Checkpointer(tmp_path / name, keep=2) as manager:
                for step in range(1, 5):
                    start_together.wait(timeout=60)
                    assert manager.save(step, jax.tree.map(lambda x: x + step, state))
        except Exception as e:  # noqa: BLE001 (reported below, in the test's thread)
            errors.append(e)

    threads = [threading.Thread(target=save_steps, args=(name,), daemon=True) for name in "abc"]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert not errors and not any(t.is_alive() for t in threads), (errors, [t.is_alive() for t in threads])
    for name in "abc":
        manager = checkpoint.Checkpointer(tmp_path / name, keep=2)
        assert manager.all_steps() == [3, 4]
        restored, step = manager.restore(state)
        assert step == 4
        np.testing.assert_array_equal(restored["w"], state["w"] + 4)


def _train_main(ckpt_dir: str, num_steps: int, out: str) -> None:
    start = time.time()
    logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s", force=True)
    state, _ = training.fit(MODEL, CFG, make_sampler(), num_steps, key=jax.random.key(2), ckpt_dir=ckpt_dir,
                            save_every=SAVE_EVERY, keep=3)
    if out:
        np.savez(out, **_flat(state.params))
    print(f"trained in {time.time() - start:.1f} s")


if __name__ == "__main__":
    if sys.argv[1] == "train":
        _train_main(sys.argv[2], int(sys.argv[3]), sys.argv[4])
