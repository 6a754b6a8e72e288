import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

import capsjax
from capsjax import training
from envs.base import wrap_angle
from envs.fast import FastEnv, FastTask, random_windows

ENV = FastEnv()
# An open arena: collisions are with its walls, a known function of pose and actions (obstacle layouts
# would take far more data to learn from (x, y) alone).
TASK = FastTask(obstacles=jnp.array([[5.5, 5.5, 0.01]] * 4), start=jnp.zeros(3))
MODEL = capsjax.CAPsModel(capsjax.ModelConfig.from_env_spec(
    ENV.spec, conv=((16, 4, 2), (16, 3, 2)), obs_hidden=(64, 64), action_hidden=(16, 32), horizon=6))


def test_per_tensor_clipping_clips_each_tensor_separately():
    clip = training.clip_by_tensor_norm(1.0)
    grads = {"a": jnp.array([3.0, 4.0]), "b": jnp.array([0.3, 0.4])}
    out, _ = clip.update(grads, clip.init(grads))
    np.testing.assert_allclose(out["a"], [0.6, 0.8], rtol=1e-6)
    np.testing.assert_allclose(out["b"], [0.3, 0.4], rtol=1e-6)  # already under the norm: untouched


def test_optimizer_options():
    params = {"w": {"kernel": jnp.ones((2, 2))}, "b": jnp.ones(2)}
    cfg = capsjax.TrainConfig(clip_tensor_norm=None, clip_global_norm=1.0, weight_decay=0.1, learning_rate=0.1)
    opt = training.make_optimizer(cfg)
    zero = jax.tree.map(jnp.zeros_like, params)
    updates, _ = opt.update(zero, opt.init(params), params)
    assert float(jnp.abs(updates["w"]["kernel"]).sum()) > 0  # decoupled decay acts on kernels
    assert float(jnp.abs(updates["b"]).sum()) == 0  # ... and not on biases


def test_bad_train_config_is_refused():
    with pytest.raises(ValueError, match="learning_rate"):
        capsjax.TrainConfig(learning_rate=0.0)
    with pytest.raises(ValueError, match="clip_tensor_norm"):
        capsjax.TrainConfig(clip_tensor_norm=-1.0)
    for bad in (0, -5, 2.5, True):
        with pytest.raises(ValueError, match="lr_decay_steps"):
            capsjax.TrainConfig(lr_decay_steps=bad)


def test_cosine_decay_shrinks_the_step_to_zero_and_stays_there():
    params = {"b": jnp.zeros(3)}
    grads = {"b": jnp.ones(3)}  # a constant gradient: Adam's normalised step is ~1, so the step is the rate
    sizes = {}
    for decay in (None, 4):
        opt = training.make_optimizer(capsjax.TrainConfig(learning_rate=0.1, clip_tensor_norm=None,
                                                          lr_decay_steps=decay))
        state, steps = opt.init(params), []
        for _ in range(6):
            updates, state = opt.update(grads, state, params)
            steps.append(float(jnp.abs(updates["b"][0])))
        sizes[decay] = np.array(steps)
    np.testing.assert_allclose(sizes[None], 0.1, rtol=1e-3)  # the paper's constant rate
    cosine = 0.1 * 0.5 * (1 + np.cos(np.pi * np.arange(6).clip(max=4) / 4))
    np.testing.assert_allclose(sizes[4], cosine, rtol=1e-3, atol=1e-7)  # 0.1, 0.085, 0.05, 0.015, 0, 0


def test_a_resumed_run_continues_the_learning_rate_schedule(tmp_path):
    cfg = capsjax.TrainConfig(learning_rate=1e-3, batch_size=8, lr_decay_steps=4)
    sample = StoredWindows(random_windows(ENV, jax.random.key(1), TASK, 64, 6), cfg.batch_size)
    whole, _ = training.fit(MODEL, cfg, sample, 4, key=jax.random.key(2), save_every=2)
    ckpt = str(tmp_path / "ckpt")
    training.fit(MODEL, cfg, sample, 2, key=jax.random.key(2), ckpt_dir=ckpt, save_every=2)
    resumed, _ = training.fit(MODEL, cfg, sample, 4, key=jax.random.key(2), ckpt_dir=ckpt, save_every=2)
    for a, b in zip(jax.tree.leaves(whole.params), jax.tree.leaves(resumed.params)):
        np.testing.assert_array_equal(a, b)  # exact on CPU: the schedule's count came back with the state


def test_loss_needs_every_cue_signal():
    batch = random_windows(ENV, jax.random.key(1), TASK, 4, 6)
    batch = batch.replace(signals={k: v for k, v in batch.signals.items() if k != "speed"})
    with pytest.raises(ValueError, match="speed"):
        capsjax.total_loss(MODEL, MODEL.init(jax.random.key(0)), batch)


def test_learns_cues_of_actions_and_ranks_action_sequences():
    data = random_windows(ENV, jax.random.key(1), TASK, 1024, 6)
    cfg = capsjax.TrainConfig(learning_rate=3e-3, batch_size=64)

    def sample(key):
        idx = jax.random.randint(key, (cfg.batch_size,), 0, 1024)
        return jax.tree.map(lambda x: x[idx], data)

    state = capsjax.init_train_state(MODEL, cfg, jax.random.key(2))
    loss0, metrics0 = capsjax.total_loss(MODEL, state.params, data)
    train = capsjax.make_train(MODEL, cfg, sample, 250)
    for _ in range(3):
        state, _ = train(state)
    loss, metrics = capsjax.total_loss(MODEL, state.params, data)
    print({k: (float(metrics0[k]), float(metrics[k])) for k in metrics})
    assert float(loss) < 0.15 * float(loss0)
    for cue in ("speed", "heading"):  # exact functions of the actions: close to zero
        assert float(metrics[f"loss/{cue}"]) < 0.1 * float(metrics0[f"loss/{cue}"])
    assert int(state.step) == 750

    # Ranking on fresh states: steering left vs right, fast vs slow, and who crashes.
    test = random_windows(ENV, jax.random.key(7), TASK, 256, 6)
    predict = jax.jit(jax.vmap(MODEL.predict, in_axes=(None, 0, 0)))
    n = 256
    left = jnp.tile(jnp.array([30.0, 1.5]), (n, 6, 1))
    right = jnp.tile(jnp.array([-30.0, 1.5]), (n, 6, 1))
    p_left, p_right = predict(state.params, test.obs, left), predict(state.params, test.obs, right)
    turn = wrap_angle(jnp.arctan2(p_left["heading"][:, -1, 1], p_left["heading"][:, -1, 0])
                      - jnp.arctan2(p_right["heading"][:, -1, 1], p_right["heading"][:, -1, 0]))
    assert float(jnp.mean(turn > 0)) > 0.95
    fast = predict(state.params, test.obs, jnp.tile(jnp.array([0.0, 2.0]), (n, 6, 1)))["speed"][:, -1]
    slow = predict(state.params, test.obs, jnp.tile(jnp.array([0.0, 0.5]), (n, 6, 1)))["speed"][:, -1]
    assert float(jnp.mean(fast > slow)) > 0.95
    crash = predict(state.params, test.obs, test.actions)["collision"][:, -1]
    crashed = np.asarray(test.signals["collision"].max(-1) > 0.5)
    assert 0 < crashed.sum() < n
    # AUC of the predicted crash probability against what really happened.
    pos, neg = np.asarray(crash)[crashed], np.asarray(crash)[~crashed]
    auc = np.mean(pos[:, None] > neg[None, :])
    print("auc", auc)
    assert auc > 0.85


@struct.dataclass
class StoredWindows:
    """A pytree callable drawing batches from stored windows (as ``data.WindowSampler.batches`` does)."""

    windows: capsjax.Batch
    batch_size: int = struct.field(pytree_node=False)

    def __call__(self, key):
        idx = jax.random.randint(key, (self.batch_size,), 0, self.windows.actions.shape[0])
        return jax.tree.map(lambda x: x[idx], self.windows)


def test_array_split_keeps_structure_and_static_leaves_apart_from_arrays():
    tree = {"a": jnp.arange(3), "b": (np.ones(2), "name", 7), "c": jnp.zeros(())}
    arrays, split = training.ArraySplit.of(tree)
    assert len(arrays) == 3 and hash(split) == hash(training.ArraySplit.of(tree)[1])
    back = split.rebuild([x + 1 for x in arrays])
    assert back["b"][1:] == ("name", 7)
    np.testing.assert_array_equal(back["a"], [1, 2, 3])
    np.testing.assert_array_equal(back["b"][0], [2.0, 2.0])


def test_a_pytree_sampler_reaches_the_program_as_an_argument_not_a_constant():
    # XLA compiles a closed-over dataset into the program as constants (minutes of compile for a real
    # one): JAX warns past jax_captured_constants_warn_bytes, so a low threshold makes it visible here.
    windows = random_windows(ENV, jax.random.key(1), TASK, 64, 6)
    source = StoredWindows(windows, 8)
    cfg = capsjax.TrainConfig(batch_size=8)
    state = capsjax.init_train_state(MODEL, cfg, jax.random.key(2))
    before = jax.config.jax_captured_constants_warn_bytes
    jax.config.update("jax_captured_constants_warn_bytes", 10_000)
    try:
        with pytest.warns(UserWarning, match="constants were captured"):  # the closure: the check can fail
            closed, _ = capsjax.make_train(MODEL, cfg, lambda key: source(key), 1)(state)
        with warnings.catch_warnings():
            warnings.filterwarnings("error", message=".*constants were captured")
            passed, _ = capsjax.make_train(MODEL, cfg, source, 1)(state)
    finally:
        jax.config.update("jax_captured_constants_warn_bytes", before)
    for a, b in zip(jax.tree.leaves(closed.params), jax.tree.leaves(passed.params)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)  # the same step either way
