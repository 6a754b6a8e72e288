"""Checkpoints of any training state pytree: a thin layer over ``orbax.checkpoint.CheckpointManager``.

Orbax does the work: a save is written to a temporary directory and renamed when complete (a killed
run leaves no half checkpoint under a step's name), every ``save_every`` steps, keeping the last
``keep``.  This module adds what a dependable resume needs on top:

* the run's configuration (model and train config, as JSON) is saved beside every state and compared
  on restore: a checkpoint of another model is refused with ``ConfigMismatchError`` naming the field,
  e.g. ``ModelConfig.conv: saved [[32, 5, 2]] != requested [[16, 4, 2]]``, before JAX sees a shape;
* restore targets an abstract state (shapes, dtypes and *shardings* of the state you want), so a
  checkpoint written on 4 devices restores onto 1 and vice versa;
* an unreadable step (truncated or corrupted files) raises ``CorruptCheckpointError`` naming the step
  and its path; ``fallback=True`` then restores the newest older step that reads.  Nothing is ever
  deleted or rewritten by a failed restore.

``capsjax.training.fit`` uses it for CAPs; any other trainer (the baselines) can pass its own state.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import threading
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp

log = logging.getLogger(__name__)


class CorruptCheckpointError(ValueError):
    """A checkpoint step exists but cannot be read (truncated, corrupted or of another structure)."""


class ConfigMismatchError(ValueError):
    """The checkpoint was written by a run with another configuration."""


def to_json(value) -> Any:
    """A JSON-compatible copy of a config: dataclasses become dicts, tuples lists, floats stay floats."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, (np.generic, np.ndarray)):
        return to_json(value.tolist())
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    raise TypeError(f"config value {value!r} of type {type(value).__name__} cannot be saved as JSON")


def training_config(model, train_config, extra: dict | None = None) -> dict:
    """The configuration saved beside a CAPs training state (``ModelConfig`` and ``TrainConfig``)."""
    config = {"ModelConfig": to_json(model.config), "TrainConfig": to_json(train_config)}
    config.update(to_json(extra or {}))
    return config


def training_defaults(model, train_config, extra: dict | None = None) -> dict:
    """Each config section's field defaults, in ``training_config``'s layout (dataclasses only).

    A checkpoint written before a config field existed lacks it; on restore the field counts as its
    default (``Checkpointer(defaults=...)``), so adding a field with a default (one that keeps the old
    behaviour) leaves older checkpoints restorable, and a non-default value is still refused."""
    sections = {"ModelConfig": model.config, "TrainConfig": train_config, **(extra or {})}
    out = {}
    for name, value in sections.items():
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            out[name] = {f.name: to_json(f.default) for f in dataclasses.fields(value)
                         if f.default is not dataclasses.MISSING}
    return out


def with_defaults(saved: dict, defaults: dict | None) -> dict:
    """``saved`` with each section's absent fields set to their defaults (see ``training_defaults``); a
    whole section absent (written before that section existed) counts as all its defaults."""
    if not defaults:
        return saved
    out = dict(saved)
    for section, fields in defaults.items():
        if section not in out:
            out[section] = dict(fields)
        elif isinstance(out[section], dict):
            out[section] = {**fields, **out[section]}
    return out


def first_difference(saved, requested, path: str = ""):
    """``(path, saved, requested)`` of the first field that differs, or None."""
    if isinstance(saved, dict) and isinstance(requested, dict):
        for k in list(saved) + [k for k in requested if k not in saved]:
            if k not in saved or k not in requested:
                return f"{path}.{k}".lstrip("."), saved.get(k, "<absent>"), requested.get(k, "<absent>")
            found = first_difference(saved[k], requested[k], f"{path}.{k}")
            if found:
                return found
        return None
    if isinstance(saved, list) and isinstance(requested, list) and len(saved) == len(requested):
        # Report the whole list (``conv: [[32,5,2],...] != [...]``) unless it holds dicts (cues): then the entry.
        if any(isinstance(s, dict) for s in saved):
            for i, (s, r) in enumerate(zip(saved, requested)):
                found = first_difference(s, r, f"{path}[{i}]")
                if found:
                    return found
            return None
    return None if saved == requested else (path.lstrip("."), saved, requested)


def _leaf_name(path) -> str:
    parts = []
    for entry in path:
        for attr in ("key", "name", "idx"):
            if hasattr(entry, attr):
                parts.append(f"[{getattr(entry, attr)!r}]")
                break
    return "".join(parts)


def _storage_shape(leaf) -> tuple[tuple, Any]:
    """Shape and dtype a leaf is stored as (a typed PRNG key is stored as its key data)."""
    if jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key):
        out = jax.eval_shape(jax.random.key_data, leaf)
        return tuple(out.shape), out.dtype
    return tuple(leaf.shape), leaf.dtype


def abstract_state(target, sharding=None):
    """``ShapeDtypeStruct``s of ``target`` with the sharding to restore onto.

    ``sharding``: one ``jax.sharding.Sharding`` for every leaf, or None to keep each concrete leaf's
    own sharding (place ``target`` where you want the restored state, e.g. ``sharding.replicate``).
    """

    def one(x):
        s = sharding if sharding is not None else getattr(x, "sharding", None)
        if s is None:
            s = jax.sharding.SingleDeviceSharding(jax.devices()[0])
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=s)

    return jax.tree.map(one, target)


# Orbax keeps process-wide state for a save in flight (operation ids and the barrier keys derived from them,
# temporary directory names).  Two managers saving at once from threads (models trained at once:
# ``experiments.pipeline.run_concurrently``) collided: one save waited 300 s for a barrier key and failed, another
# found a temporary directory not empty.  So the saves of a process run one at a time, each on disk before the
# next starts: a process-wide lock guarding orbax's process-wide state (saving a model's state takes well under
# a second, so training barely waits).
_SAVE_LOCK = threading.Lock()


class Checkpointer:
    """Save every ``save_every`` steps, keep the last ``keep``, restore the latest (or a given) step.

    ``config`` (a JSON-able dict, e.g. ``training_config(model, cfg)``) is stored with every step and
    must equal the saved one on restore; pass ``config=None`` to skip that check (e.g. to inspect a
    checkpoint of unknown origin).  ``defaults`` (``training_defaults``) fill fields that a config saved
    by an older version lacks.  Use as a context manager, or call ``close()``.  A save is on disk when
    ``save`` returns, and saves from several threads (several managers) run one after another
    (``_SAVE_LOCK``); ``async_save`` chooses orbax's writer.
    """

    def __init__(self, directory, *, save_every: int = 1, keep: int | None = 3, config: dict | None = None,
                 defaults: dict | None = None, async_save: bool = True):
        if not isinstance(save_every, int) or save_every <= 0:
            raise ValueError(f"Checkpointer.save_every must be a positive int, got {save_every!r}")
        if keep is not None and (not isinstance(keep, int) or keep <= 0):
            raise ValueError(f"Checkpointer.keep must be a positive int or None (keep all), got {keep!r}")
        self.directory = os.path.abspath(os.fspath(directory))
        self.config = to_json(config) if config is not None else None
        self.defaults = defaults  # fields a saved config may lack (``training_defaults``)
        options = ocp.CheckpointManagerOptions(
            save_interval_steps=save_every, max_to_keep=keep, create=True, enable_async_checkpointing=async_save
        )
        # Handlers given up front so a fresh manager can read metadata of steps it did not write.
        handlers = {"state": ocp.StandardCheckpointHandler(), "config": ocp.JsonCheckpointHandler()}
        self._manager = ocp.CheckpointManager(self.directory, options=options, item_handlers=handlers)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def step_path(self, step: int) -> str:
        return os.path.join(self.directory, str(step))

    def all_steps(self) -> list[int]:
        return sorted(self._manager.all_steps())

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def save(self, step: int, state, *, force: bool = False) -> bool:
        """Save ``state`` as ``step`` if it is a save step (a multiple of ``save_every``) or ``force``."""
        args = ocp.args.Composite(state=ocp.args.StandardSave(state), config=ocp.args.JsonSave(self.config or {}))
        with _SAVE_LOCK:
            saved = self._manager.save(int(step), args=args, force=force)
            self._manager.wait_until_finished()
        return saved

    def wait(self) -> None:
        """Block until asynchronous saves are on disk."""
        self._manager.wait_until_finished()

    def close(self) -> None:
        with _SAVE_LOCK:
            self._manager.close()

    def saved_config(self, step: int) -> dict:
        try:
            return self._manager.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore()))["config"]
        except Exception as e:  # orbax/tensorstore raise many types; name the step instead
            raise CorruptCheckpointError(
                f"checkpoint step {step} at {self.step_path(step)} is unreadable (its config): {type(e).__name__}: {e}"
            ) from e

    def restore(self, target, step: int | None = None, *, sharding=None, fallback: bool = False):
        """``(state, step)``: the checkpoint ``step`` (the latest when None) restored like ``target``.

        ``target`` is a state of the wanted structure (concrete arrays or ``ShapeDtypeStruct``s), placed
        where the restored state should live; or give ``sharding`` for all leaves.  With ``fallback``
        an unreadable latest step is skipped (logged) for the newest older one that reads.
        """
        if step is not None:
            candidates = [int(step)]
            if candidates[0] not in self._manager.all_steps():
                raise FileNotFoundError(f"no checkpoint step {step} in {self.directory}; steps: {self.all_steps()}")
        else:
            candidates = sorted(self._manager.all_steps(), reverse=True)
            if not candidates:
                raise FileNotFoundError(f"no checkpoint in {self.directory}")
        abstract = abstract_state(target, sharding)
        for i, s in enumerate(candidates):
            try:
                return self._restore_step(abstract, s), s
            except CorruptCheckpointError as e:
                if not fallback or i == len(candidates) - 1:
                    raise
                log.warning("%s; falling back to step %d", e, candidates[i + 1])
        raise AssertionError("unreachable")

    def resume(self, target, num_steps: int, *, who: str = "fit"):
        """``(state, step)`` to continue a run of ``num_steps`` steps from: ``target`` itself (step None)
        when the directory is empty, else the latest checkpoint up to ``num_steps``.

        A directory trained past ``num_steps`` (e.g. by a longer preset) must not silently hand back the
        longer run: its exact ``num_steps`` checkpoint is used, otherwise this refuses (and keeps it)."""
        latest = self.latest_step()
        if latest is None:
            return target, None
        if latest > num_steps and num_steps not in self.all_steps():
            raise ValueError(
                f"{who}: ckpt_dir {self.directory} holds checkpoints past num_steps={num_steps} (steps "
                f"{self.all_steps()}) but not step {num_steps}; train into another ckpt_dir or ask "
                f"for num_steps>={latest}")
        return self.restore(target, step=min(latest, num_steps))

    def _restore_step(self, abstract, step: int):
        path = self.step_path(step)
        if self.config is not None:
            saved = with_defaults(self.saved_config(step), self.defaults)
            diff = first_difference(saved, self.config)
            if diff:
                field, was, want = diff
                raise ConfigMismatchError(
                    f"checkpoint step {step} at {path} was written with another configuration: "
                    f"{field}: saved {json.dumps(was)} != requested {json.dumps(want)}"
                )
        try:
            metadata = self._manager.item_metadata(step)["state"]
            saved_tree = metadata.tree if hasattr(metadata, "tree") else metadata
        except Exception as e:
            raise CorruptCheckpointError(
                f"checkpoint step {step} at {path} is unreadable (its metadata): {type(e).__name__}: {e}"
            ) from e
        self._check_structure(saved_tree, abstract, step, path)
        try:
            restored = self._manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))
        except Exception as e:
            raise CorruptCheckpointError(
                f"checkpoint step {step} at {path} is unreadable (truncated or corrupted?): {type(e).__name__}: {e}"
            ) from e
        return restored["state"]

    @staticmethod
    def _check_structure(saved_tree, abstract, step: int, path: str) -> None:
        """Same leaves, shapes and dtypes as the target, or an error naming the first leaf that differs."""
        # Orbax's metadata turns dataclasses and named tuples into dicts: compare paths as plain names.
        want = {_leaf_name(p): leaf for p, leaf in jax.tree_util.tree_flatten_with_path(abstract)[0]}
        have = {_leaf_name(p): leaf for p, leaf in jax.tree_util.tree_flatten_with_path(saved_tree)[0]}
        missing, extra = sorted(set(want) - set(have)), sorted(set(have) - set(want))
        if missing or extra:
            raise ConfigMismatchError(
                f"checkpoint step {step} at {path} holds another state structure: missing leaves {missing[:5]}, "
                f"unexpected leaves {extra[:5]}"
            )
        for name, leaf in want.items():
            shape, dtype = _storage_shape(leaf)
            saved = have[name]
            if tuple(saved.shape) != shape or np.dtype(saved.dtype) != np.dtype(dtype):
                raise ConfigMismatchError(
                    f"checkpoint step {step} at {path}: state{name} is saved as {np.dtype(saved.dtype)}"
                    f"{list(saved.shape)}, expected {np.dtype(dtype)}{list(shape)}"
                )
