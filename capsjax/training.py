"""Supervised training of the CAPs predictor with optax, one step or many under one jit.

The paper's optimiser: Adam (lr 1e-4, eps 1e-4), gradients clipped *per tensor* to norm 10 (each
variable separately, not the global norm), an L2 term scaled by 1 / #params.  Global-norm clipping and
decoupled weight decay are options.

Dependability (``fit``):
* **NaN guard.** A step whose loss or any gradient is not finite leaves params and optimiser state
  as they were and is counted (``TrainState.bad_steps``, ``consecutive_bad``); ``fit`` stops with
  ``NonFiniteTrainingError`` after ``max_bad_steps`` in a row, without saving the bad state.
* **Resume.** ``fit`` saves the whole ``TrainState`` every ``save_every`` steps with orbax
  (``capsjax.checkpoint``) and restores the latest checkpoint when started again.  The sampler's
  position is ``TrainState.key``: every batch is a pure function of the key split off it, so restoring
  the key restores where the sampler was, and a resumed run continues exactly.
* **Many devices.** With a ``mesh`` the batch is sharded over its devices and the state replicated;
  the step is the same function and XLA inserts the gradient all-reduce (``capsjax.sharding``).
"""
from __future__ import annotations

import dataclasses
import functools
import logging
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from capsjax import losses
from capsjax import sharding as sharding_lib

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    learning_rate: float = 1e-4
    adam_eps: float = 1e-4
    adam_b1: float = 0.9
    adam_b2: float = 0.999
    clip_tensor_norm: float | None = 10.0  # per-tensor clipping (the paper); None disables
    clip_global_norm: float | None = None
    l2_coeff: float = 0.125  # the paper's L2: l2_coeff / #params * sum ||W||^2 over kernels
    weight_decay: float = 0.0  # decoupled (AdamW-style), applied to kernels only
    batch_size: int = 32
    # Cosine decay of the learning rate from ``learning_rate`` to zero over this many steps (held at zero
    # after them); None keeps it constant, as the paper does.  The schedule's step count lives in the
    # optimiser state, so a resumed run continues the schedule exactly.
    lr_decay_steps: int | None = None

    def __post_init__(self):
        for name in ("learning_rate", "adam_eps"):
            if not 0 < getattr(self, name) < float("inf"):
                raise ValueError(f"TrainConfig.{name} must be positive and finite, got {getattr(self, name)}")
        if self.batch_size <= 0:
            raise ValueError(f"TrainConfig.batch_size must be positive, got {self.batch_size}")
        steps = self.lr_decay_steps
        if steps is not None and (not isinstance(steps, int) or isinstance(steps, bool) or steps <= 0):
            raise ValueError(f"TrainConfig.lr_decay_steps must be a positive int or None, got {self.lr_decay_steps!r}")
        for name in ("clip_tensor_norm", "clip_global_norm"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ValueError(f"TrainConfig.{name} must be positive or None, got {v}")


def _zero_count():
    return jnp.zeros((), jnp.int32)


@struct.dataclass
class TrainState:
    params: dict
    opt_state: optax.OptState
    step: jax.Array  # i32[]: steps attempted (skipped non-finite steps included)
    key: jax.Array  # the sampler's position: each step's batch is drawn from a key split off this one
    bad_steps: jax.Array = struct.field(default_factory=_zero_count)  # i32[]: non-finite steps skipped
    consecutive_bad: jax.Array = struct.field(default_factory=_zero_count)  # i32[]: ... in a row, now


class NonFiniteTrainingError(RuntimeError):
    """Too many non-finite training steps in a row; the state was not saved."""


def clip_by_tensor_norm(max_norm: float) -> optax.GradientTransformation:
    """Scale each gradient tensor separately to norm <= ``max_norm``.

    Written here because optax clips by global norm or by block RMS, not by each tensor's L2 norm,
    which is what the authors' TensorFlow code did (``tf.clip_by_norm`` per variable).
    """

    def clip(g):
        norm = jnp.sqrt(jnp.sum(jnp.square(g)))
        return g * jnp.minimum(1.0, max_norm / jnp.maximum(norm, 1e-12))

    return optax.stateless(lambda updates, params=None: jax.tree.map(clip, updates))


def _kernel_mask(params):
    return jax.tree_util.tree_map_with_path(lambda p, _: jax.tree_util.keystr(p).endswith("kernel']"), params)


def make_optimizer(cfg: TrainConfig) -> optax.GradientTransformation:
    parts = []
    if cfg.clip_tensor_norm is not None:
        parts.append(clip_by_tensor_norm(cfg.clip_tensor_norm))
    if cfg.clip_global_norm is not None:
        parts.append(optax.clip_by_global_norm(cfg.clip_global_norm))
    parts.append(optax.scale_by_adam(b1=cfg.adam_b1, b2=cfg.adam_b2, eps=cfg.adam_eps))
    if cfg.weight_decay:
        parts.append(optax.add_decayed_weights(cfg.weight_decay, mask=_kernel_mask))
    learning_rate = cfg.learning_rate
    if cfg.lr_decay_steps is not None:
        learning_rate = optax.cosine_decay_schedule(cfg.learning_rate, cfg.lr_decay_steps)
    parts.append(optax.scale_by_learning_rate(learning_rate))
    return optax.chain(*parts)


@functools.partial(jax.jit, static_argnums=0)
def _init_params(model, key):
    # Jitted (once per model definition): one compile instead of hundreds of eagerly dispatched ops.
    return model.init(key)


def init_train_state(model, cfg: TrainConfig, key: jax.Array) -> TrainState:
    init_key, key = jax.random.split(key)
    params = _init_params(model, init_key)
    return TrainState(params=params, opt_state=make_optimizer(cfg).init(params), step=jnp.zeros((), jnp.int32), key=key)


def _all_finite(tree) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(tree)]))


def make_train_step(model, cfg: TrainConfig) -> Callable:
    """``train_step(state, batch) -> (state, metrics)``: pure, jit it (or scan it) as you like.

    A step whose loss or gradients are not finite is skipped (params and optimiser state unchanged)
    and counted in ``bad_steps`` / ``consecutive_bad``; ``metrics['skipped']`` flags it.
    """
    optimizer = make_optimizer(cfg)

    def train_step(state: TrainState, batch: losses.Batch):
        grad_fn = jax.value_and_grad(lambda p: losses.total_loss(model, p, batch, cfg.l2_coeff), has_aux=True)
        (loss, metrics), grads = grad_fn(state.params)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        finite = jnp.isfinite(loss) & _all_finite(grads)
        # Select rather than branch: both sides are already computed and a select keeps one code path.
        keep_new = lambda new, old: jnp.where(finite, new, old)
        params = jax.tree.map(keep_new, params, state.params)
        opt_state = jax.tree.map(keep_new, opt_state, state.opt_state)
        bad = (~finite).astype(jnp.int32)
        consecutive = jnp.where(finite, 0, state.consecutive_bad + 1)
        metrics["grad_norm"] = optax.global_norm(grads)
        metrics["skipped"] = ~finite
        metrics["consecutive_bad"] = consecutive
        return state.replace(params=params, opt_state=opt_state, step=state.step + 1,
                             bad_steps=state.bad_steps + bad, consecutive_bad=consecutive), metrics

    return train_step


def make_train(model, cfg: TrainConfig, sample_batch: Callable, num_steps: int, *, mesh=None) -> Callable:
    """``train(state) -> (state, metrics[num_steps])``: ``num_steps`` jitted steps (``repeat_steps``).

    ``sample_batch(key) -> Batch`` draws a batch of ``cfg.batch_size`` windows.  Pass a pytree callable
    such as ``WindowSampler.batches(cfg.batch_size)`` (``capsjax.data``): its buffers then reach the
    compiled program as arguments (``ArraySplit``).  A plain closure over a sampler works too, but
    compiles the whole dataset into the program as constants (``ArraySplit`` says what that costs).
    Call ``train`` repeatedly for logging or checkpointing between chunks.

    With a ``mesh`` (``capsjax.sharding.make_mesh``) each batch is sharded over the mesh's devices
    along its window axis and the state (and the sampler's buffers) replicated: the same step,
    data-parallel.
    """
    if not isinstance(num_steps, int) or num_steps <= 0:
        raise ValueError(f"num_steps must be a positive int, got {num_steps!r}")
    if mesh is not None and cfg.batch_size % mesh.devices.size:
        raise ValueError(
            f"TrainConfig.batch_size ({cfg.batch_size}) must be a multiple of the mesh's {mesh.devices.size} devices"
        )
    arrays, split = ArraySplit.of(sample_batch)
    run = _train_program(model, cfg, split, num_steps, mesh)
    if mesh is not None:
        arrays = jax.device_put(arrays, sharding_lib.replicated_sharding(mesh))
    return functools.partial(run, data=arrays)


@functools.lru_cache(maxsize=32)
def _train_program(model, cfg: TrainConfig, split: "ArraySplit", num_steps: int, mesh):
    # Cached on the sampler's structure, not its buffers: repeated ``fit`` calls with the same model,
    # config and kind of sampler (resuming, evaluating in between) reuse one compiled chunk.
    train_step = make_train_step(model, cfg)

    def body(state, arrays):
        key, batch_key = jax.random.split(state.key)
        batch = split.rebuild(arrays)(batch_key)
        if mesh is not None:
            batch = jax.lax.with_sharding_constraint(batch, sharding_lib.leading_sharding(mesh))
        return train_step(state.replace(key=key), batch)

    if mesh is None:
        return repeat_steps(body, num_steps)
    replicated = sharding_lib.replicated_sharding(mesh)
    return repeat_steps(body, num_steps, in_shardings=replicated, out_shardings=replicated)


@dataclasses.dataclass(frozen=True)
class ArraySplit:
    """A pytree's structure and non-array leaves (hashable), apart from its arrays.

    Why: a jitted function that *closes over* arrays compiles them into its program as constants.  For a
    training sampler that is the whole dataset, and XLA then spends minutes on it: one training step over
    the halls' 60k frames (2 GiB) took 116 s to compile as a closure and 9 s with the frames passed as an
    argument.  ``ArraySplit.of(tree)`` returns the arrays (to pass as arguments) and the rest (static);
    ``rebuild(arrays)`` inside the jitted function puts the tree back together.
    """

    treedef: object
    static_leaves: tuple  # the non-array leaves, None where an array goes

    @classmethod
    def of(cls, tree) -> tuple[list, "ArraySplit"]:
        leaves, treedef = jax.tree.flatten(tree)
        is_array = [isinstance(x, (jax.Array, np.ndarray)) for x in leaves]
        arrays = [x for x, a in zip(leaves, is_array) if a]
        return arrays, cls(treedef, tuple(None if a else x for x, a in zip(leaves, is_array)))

    def rebuild(self, arrays):
        it = iter(arrays)
        leaves = [next(it) if x is None else x for x in self.static_leaves]
        return jax.tree.unflatten(self.treedef, leaves)


def repeat_steps(body: Callable, num_steps: int, **jit_kwargs) -> Callable:
    """``run(state, data=None) -> (state, metrics stacked over steps)``: ``body(state, data) -> (state,
    metrics)`` applied ``num_steps`` times.  ``data`` (a pytree, e.g. a sampler's buffers from
    ``ArraySplit.of``) is an argument of the compiled program, never a constant in it.

    On accelerators the steps run as one ``lax.scan`` under jit.  On CPU each step is one jitted call
    from a host loop instead: XLA:CPU runs convolution gradients inside a while loop about ten times
    slower than at the top level of a program (measured here on forest images, batch 32: a CNN
    gradient took 0.45 s alone and 5.2 s per iteration inside ``scan``), and a dispatch costs far less
    than a step.  Both paths give the same states and metrics.
    """
    if jax.default_backend() != "cpu":
        scanned = jax.jit(lambda state, data: jax.lax.scan(lambda s, _: body(s, data), state, None,
                                                           length=num_steps), **jit_kwargs)
        return lambda state, data=None: scanned(state, data)
    step = jax.jit(body, **jit_kwargs)

    def run(state, data=None):
        history = []
        for _ in range(num_steps):
            state, metrics = step(state, data)
            history.append(metrics)
        return state, jax.tree.map(lambda *xs: jnp.stack(xs), *history)

    return run


def progress_bar(progress: bool | str, total: int, initial: int):
    """A tqdm bar of training steps (labelled when ``progress`` is a string), or None when it is falsy."""
    if not progress:
        return None
    import tqdm

    return tqdm.tqdm(total=total, initial=initial, unit="step", desc=progress if isinstance(progress, str) else None)


def fit(
    model,
    cfg: TrainConfig,
    sample_batch: Callable,
    num_steps: int,
    *,
    key: jax.Array | None = None,
    state: TrainState | None = None,
    ckpt_dir=None,
    save_every: int = 1000,
    keep: int = 3,
    max_bad_steps: int = 10,
    mesh=None,
    progress: bool | str = False,
    metadata: dict | None = None,
):
    """Train to ``num_steps`` total steps, resumably: ``(state, metrics)`` with the last chunk's metrics.

    The start is, in order of precedence: the latest checkpoint in ``ckpt_dir`` (a resumed run; one past
    ``num_steps`` is refused unless step ``num_steps`` itself is saved), else
    ``state``, else a fresh ``init_train_state(model, cfg, key)``.  Steps run in chunks of up to
    ``save_every`` under one jit (``make_train``); after each chunk the state is checked and, with a
    ``ckpt_dir``, saved (orbax keeps the last ``keep``).  The model and train configs (and ``metadata``,
    e.g. how the training windows were drawn) are saved beside each checkpoint and a checkpoint of
    another config is refused; a dataclass section of ``metadata`` missing from an older checkpoint counts
    as its defaults (``checkpoint.training_defaults``).

    ``progress``: a tqdm bar of the steps (a string labels it, so that models trained at once in threads tell
    their bars apart).

    Raises ``NonFiniteTrainingError`` once ``max_bad_steps`` steps in a row had a non-finite loss or
    gradient; the state of that chunk is not saved, so the last good checkpoint stays the latest.
    """
    from capsjax import checkpoint  # imported here: checkpoint.py imports this module

    for name, value in (("num_steps", num_steps), ("save_every", save_every), ("keep", keep),
                        ("max_bad_steps", max_bad_steps)):
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise ValueError(f"fit: {name} must be a positive int, got {value!r}")
    if state is None:
        state = init_train_state(model, cfg, key if key is not None else jax.random.key(0))
    if mesh is not None:
        state = sharding_lib.replicate(state, mesh)
    manager = None
    if ckpt_dir is not None:
        manager = checkpoint.Checkpointer(ckpt_dir, save_every=save_every, keep=keep,
                                          config=checkpoint.training_config(model, cfg, metadata),
                                          defaults=checkpoint.training_defaults(model, cfg, metadata))
        state, restored = manager.resume(state, num_steps, who="fit")
        if restored is not None:
            log.info("resumed from step %d in %s", restored, ckpt_dir)
    metrics = {}
    bar = progress_bar(progress, num_steps, int(state.step))
    trains = {}  # one per chunk length (at most three): with a mesh, the buffers are replicated once each
    try:
        while int(state.step) < num_steps:
            done = int(state.step)
            length = min(save_every - done % save_every, num_steps - done)  # end chunks on save points
            if length not in trains:
                trains[length] = make_train(model, cfg, sample_batch, length, mesh=mesh)
            new_state, metrics = trains[length](state)
            worst = int(jnp.max(metrics["consecutive_bad"]))
            if worst >= max_bad_steps:
                raise NonFiniteTrainingError(
                    f"{worst} training steps in a row had a non-finite loss or gradient (max_bad_steps="
                    f"{max_bad_steps}) between steps {done} and {int(new_state.step)}; stopped without saving, "
                    f"the last good checkpoint is step {manager.latest_step() if manager else None}"
                )
            state = new_state
            if manager is not None:
                manager.save(int(state.step), state, force=int(state.step) == num_steps)
            if bar is not None:
                bar.update(length)
                bar.set_postfix(loss=float(metrics["loss"][-1]), skipped=int(state.bad_steps))
            log.info("step %d loss %.4g skipped %d", int(state.step), float(metrics["loss"][-1]), int(state.bad_steps))
    finally:
        if bar is not None:
            bar.close()
        if manager is not None:
            manager.close()
    return state, metrics
