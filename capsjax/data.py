"""Episode datasets on disk (zarr v3) and the window sampler the trainer draws from.

Store layout (one zarr group per dataset, a local directory)::

    <path>/zarr.json         attrs: schema_version, env_name, env_config, spec, policy, chunk_steps
    <path>/commit.json       the committed counts {num_episodes, num_steps, num_labelled}
    steps/image              u8[cap, h, w, c]  newest camera frame of observation t
    steps/vector             f32[cap, D]       vector state of observation t (same instant as the image)
    steps/action             f32[cap, A]       action executed at t (the terminal entry's is padding)
    steps/done               bool[cap]         True only on an episode's terminal entry
    steps/pose               f32[cap, 3]       x, y, yaw at t (for metrics and hindsight goals)
    steps/signal/<name>      f32[cap]          ground-truth signals of observation t
    episodes/start, length   i64[cap]          step range of each episode
    episodes/split           u8[cap]           0 = 'train', 1 = 'eval' task split
    episodes/task            u32[cap, 2]       key data the episode's task was drawn from (reproducible)
    labelled/step            i64[cap]          global step index of each "hand-labelled" frame
    labelled/semantic        u8[cap, h, w]     its ground-truth semantic class map
    labels/<name>/<cue>      f32[num_steps]    cue labels written by a labeller (``relabel``)

Crash safety.  Arrays are created once with a huge fixed capacity (``cap``), so appending never rewrites
array metadata; zarr's local store writes every chunk to a temporary file and renames it into place,
so a chunk shared by committed and new episodes is replaced atomically.  The episode data is written
first and ``commit.json`` last (temp file + ``os.replace``): a process killed at any point leaves the
previous commit intact, everything past it is ignored on open and overwritten by the next append.
Every chunk carries a crc32c checksum, so a corrupted or truncated chunk raises on read; ``verify``
maps such chunks to the episodes they hold and the sampler skips those episodes with a warning.
Nothing here ever deletes or rewrites a committed episode (only derived labels are re-writable).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import uuid
import warnings
from collections.abc import Callable, Iterator
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import zarr
from flax import struct
from zarr.codecs import BloscCodec, Crc32cCodec

SCHEMA_VERSION = 1
CAPACITY = 1 << 40  # fixed array length: zarr stores only written chunks, so the size costs nothing
EPISODE_CHUNK = 4096
LABELLED_CHUNK = 256
SPLITS = ("train", "eval", "val")  # envs.base.TASK_SPLITS, in the order stored episodes index it
_COMMIT = "commit.json"


def _compressors():
    # lz4 at level 1: cheap enough to keep up with collection on 2 cores; crc32c makes corruption loud.
    return [BloscCodec(cname="lz4", clevel=1, shuffle="shuffle"), Crc32cCodec()]


def _jsonable(obj: Any) -> Any:
    """Dataclasses, tuples and numpy scalars to plain JSON values (for attrs)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return repr(obj)


def _spec_from_attrs(d: dict):
    from envs.base import EnvSpec  # lazy: capsjax does not import envs at module load

    fields = {f.name for f in dataclasses.fields(EnvSpec)}
    kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in fields}
    return EnvSpec(**kwargs)


@dataclasses.dataclass(frozen=True)
class CorruptChunk:
    """A chunk that failed to read (checksum, truncation, decompression) or is missing."""

    field: str  # array path, e.g. 'steps/image'
    chunk: int  # chunk index along the first axis
    rows: tuple[int, int]  # [start, stop) along the first axis (steps, episodes or labelled frames)
    episodes: tuple[int, ...]  # the committed episodes whose data it holds
    error: str


class Dataset:
    """A crash-safe, append-only episode store.  Open with ``Dataset.create`` or ``Dataset.open``."""

    def __init__(self, path: str, group: zarr.Group, mode: str):
        self.path = os.fspath(path)
        self._group = group
        self.mode = mode
        attrs = dict(group.attrs)
        self.env_name: str = attrs["env_name"]
        self.env_config: dict = attrs["env_config"]
        self.policy = attrs["policy"]
        self.chunk_steps: int = int(attrs["chunk_steps"])
        self.spec = _spec_from_attrs(attrs["spec"])
        self.signal_names: tuple[str, ...] = tuple(attrs["signal_names"])
        self.has_semantic: bool = bool(attrs.get("has_semantic", True))
        self._load_commit()

    # ------------------------------------------------------------------------------ create / open

    @classmethod
    def create(cls, path, *, env_name: str, env_config: dict, spec, policy: str | dict,
               chunk_steps: int = 1024, has_semantic: bool = True) -> Dataset:
        """A new empty store at ``path``; refuses (FileExistsError) to touch an existing one."""
        path = os.fspath(path)
        if os.path.exists(path):
            raise FileExistsError(f"dataset path {path!r} already exists; open it with Dataset.open(path, 'a') "
                                  "to append (an existing dataset is never overwritten)")
        if int(chunk_steps) <= 0:
            raise ValueError(f"chunk_steps must be a positive integer, got {chunk_steps}")
        chunk_steps = int(chunk_steps)
        signal_names = tuple(spec.signal_names)
        h, w, c = spec.image_shape
        tmp = f"{path}.creating-{uuid.uuid4().hex}"
        group = zarr.open_group(tmp, mode="w-")
        group.attrs.update({
            "schema_version": SCHEMA_VERSION,
            "env_name": env_name,
            "env_config": _jsonable(env_config),
            "spec": _jsonable(spec),
            "policy": _jsonable(policy),
            "chunk_steps": chunk_steps,
            "signal_names": list(signal_names),
            "has_semantic": bool(has_semantic),
        })

        def array(name, shape, dtype, chunk):
            group.create_array(name, shape=(CAPACITY,) + tuple(shape), chunks=(chunk,) + tuple(shape),
                               dtype=dtype, compressors=_compressors(), fill_value=0)

        array("steps/image", (h, w, c), "uint8", chunk_steps)
        array("steps/vector", (spec.vector_dim,), "float32", chunk_steps)
        array("steps/action", (spec.action_dim,), "float32", chunk_steps)
        array("steps/done", (), "bool", chunk_steps)
        array("steps/pose", (3,), "float32", chunk_steps)
        for name in signal_names:
            array(f"steps/signal/{name}", (), "float32", chunk_steps)
        array("episodes/start", (), "int64", EPISODE_CHUNK)
        array("episodes/length", (), "int64", EPISODE_CHUNK)
        array("episodes/split", (), "uint8", EPISODE_CHUNK)
        array("episodes/task", (2,), "uint32", EPISODE_CHUNK)
        array("labelled/step", (), "int64", LABELLED_CHUNK)
        array("labelled/semantic", (h, w), "uint8", LABELLED_CHUNK)
        group.create_group("labels")
        _write_json_atomic(os.path.join(tmp, _COMMIT), {"num_episodes": 0, "num_steps": 0, "num_labelled": 0})
        # The store appears under its name only once complete (a crash during create leaves no half store).
        os.rename(tmp, path)
        return cls.open(path, "a")

    @classmethod
    def open(cls, path, mode: str = "r") -> Dataset:
        """Open an existing store (``mode`` 'r' read-only or 'a' to append); checks the schema version."""
        path = os.fspath(path)
        if mode not in ("r", "a"):
            raise ValueError(f"mode must be 'r' or 'a', got {mode!r}")
        if not os.path.isdir(path):
            raise FileNotFoundError(f"no dataset at {path!r}")
        group = zarr.open_group(path, mode="r" if mode == "r" else "r+")
        version = group.attrs.get("schema_version")
        if version is None:
            raise ValueError(f"dataset {path!r} has no 'schema_version' attribute; expected schema_version "
                             f"{SCHEMA_VERSION} (not a capsjax dataset?)")
        if version != SCHEMA_VERSION:
            raise ValueError(f"dataset {path!r} has schema_version {version}, expected {SCHEMA_VERSION}")
        if not os.path.exists(os.path.join(path, _COMMIT)):
            raise ValueError(f"dataset {path!r} lacks {_COMMIT}; expected a committed episode index")
        return cls(path, group, mode)

    # ------------------------------------------------------------------------------ committed index

    def _load_commit(self) -> None:
        with open(os.path.join(self.path, _COMMIT)) as f:
            commit = json.load(f)
        self.num_episodes: int = int(commit["num_episodes"])
        self.num_steps: int = int(commit["num_steps"])
        self.num_labelled: int = int(commit["num_labelled"])
        if self.num_episodes:
            self._starts = np.asarray(self._group["episodes/start"][: self.num_episodes], np.int64)
            self._lengths = np.asarray(self._group["episodes/length"][: self.num_episodes], np.int64)
        else:
            self._starts = self._lengths = np.zeros((0,), np.int64)

    def episode_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(start i64[E], length i64[E])`` of the committed episodes, in global step indices."""
        return self._starts.copy(), self._lengths.copy()

    def episode_splits(self) -> np.ndarray:
        """u8[E]: the task split of each committed episode (index into ``SPLITS``)."""
        return np.asarray(self._group["episodes/split"][: self.num_episodes])

    def episode_tasks(self) -> np.ndarray:
        """u32[E, 2]: the key data each episode's task was drawn from (``jax.random.wrap_key_data``)."""
        return np.asarray(self._group["episodes/task"][: self.num_episodes])

    def episode_of_step(self, steps) -> np.ndarray:
        """The committed episode holding each global step index."""
        return np.searchsorted(self._starts, np.asarray(steps), side="right") - 1

    # ------------------------------------------------------------------------------ writing

    def append_episodes(self, episodes: dict[str, np.ndarray], lengths) -> None:
        """Append complete episodes (concatenated along steps) and commit them.

        ``episodes`` holds per-step arrays ``image u8[N,h,w,c]``, ``vector f32[N,D]``, ``action f32[N,A]``,
        ``done bool[N]`` (True exactly on each episode's last entry), ``pose f32[N,3]`` and
        ``signal/<name> f32[N]`` for every signal of the spec; optionally ``labelled_index i64[n]``
        (indices into these N steps) with ``semantic u8[n,h,w]``, and per-episode ``split u8[E]`` and
        ``task u32[E,2]``.  ``lengths`` i64[E] sums to N.
        """
        if self.mode != "a":
            raise ValueError(f"dataset {self.path!r} is open with mode={self.mode!r}; expected mode='a' to append")
        lengths = np.asarray(lengths, np.int64).reshape(-1)
        if lengths.size == 0:
            return
        if np.any(lengths < 1):
            raise ValueError(f"lengths must all be >= 1, got {lengths.tolist()}")
        n = int(lengths.sum())
        h, w, c = self.spec.image_shape
        expected = {
            "image": ((n, h, w, c), np.uint8),
            "vector": ((n, self.spec.vector_dim), np.float32),
            "action": ((n, self.spec.action_dim), np.float32),
            "done": ((n,), bool),
            "pose": ((n, 3), np.float32),
            **{f"signal/{s}": ((n,), np.float32) for s in self.signal_names},
        }
        data = {}
        for key, (shape, dtype) in expected.items():
            if key not in episodes:
                raise ValueError(f"episodes lacks field {key!r}; expected {dtype.__name__}{list(shape)}")
            arr = np.asarray(episodes[key])
            if arr.shape != shape:
                raise ValueError(f"episodes[{key!r}] has shape {arr.shape}, expected {shape} (sum(lengths) = {n})")
            data[key] = arr.astype(dtype, copy=False)
        ends = np.cumsum(lengths) - 1
        expected_done = np.zeros(n, bool)
        expected_done[ends] = True
        if not np.array_equal(data["done"], expected_done):
            raise ValueError("episodes['done'] must be True exactly on each episode's last entry (the stored "
                             f"terminal observation); expected True at {ends.tolist()[:10]}...")
        e = lengths.size
        split = np.asarray(episodes.get("split", np.zeros(e, np.uint8)), np.uint8).reshape(-1)
        task = np.asarray(episodes.get("task", np.zeros((e, 2), np.uint32)), np.uint32)
        if split.shape != (e,) or task.shape != (e, 2):
            raise ValueError(f"episodes['split'] / ['task'] have shapes {split.shape} / {task.shape}, expected "
                             f"({e},) / ({e}, 2)")
        lab_index = np.asarray(episodes.get("labelled_index", np.zeros(0, np.int64)), np.int64).reshape(-1)
        semantic = np.asarray(episodes.get("semantic", np.zeros((0, h, w), np.uint8)), np.uint8)
        if semantic.shape != (lab_index.size, h, w):
            raise ValueError(f"episodes['semantic'] has shape {semantic.shape}, expected {(lab_index.size, h, w)}")
        if lab_index.size and (lab_index.min() < 0 or lab_index.max() >= n or np.any(np.diff(lab_index) <= 0)):
            raise ValueError(f"episodes['labelled_index'] must be increasing indices in [0, {n}), got {lab_index[:10]}")

        # Step data first, then the episode index, then the commit: nothing is visible until the last line.
        # Chunks equal to the fill value are written too, so a missing chunk file always means damage.
        with zarr.config.set({"array.write_empty_chunks": True}):
            self._write(data, lengths, split, task, lab_index, semantic)

    def _write(self, data, lengths, split, task, lab_index, semantic) -> None:
        n, e = int(lengths.sum()), lengths.size
        s0, e0, l0 = self.num_steps, self.num_episodes, self.num_labelled
        g = self._group
        for key, arr in data.items():
            g[f"steps/{key}"][s0: s0 + n] = arr
        g["episodes/start"][e0: e0 + e] = s0 + np.concatenate([[0], np.cumsum(lengths)[:-1]])
        g["episodes/length"][e0: e0 + e] = lengths
        g["episodes/split"][e0: e0 + e] = split
        g["episodes/task"][e0: e0 + e] = task
        if lab_index.size:
            g["labelled/step"][l0: l0 + lab_index.size] = s0 + lab_index
            g["labelled/semantic"][l0: l0 + lab_index.size] = semantic
        _write_json_atomic(os.path.join(self.path, _COMMIT),
                           {"num_episodes": e0 + e, "num_steps": s0 + n, "num_labelled": l0 + lab_index.size})
        self._load_commit()

    # ------------------------------------------------------------------------------ reading

    def _check_episode(self, i) -> int:
        i = int(i)
        if not 0 <= i < self.num_episodes:
            raise IndexError(f"episode {i} out of range; the dataset has {self.num_episodes} committed episodes")
        return i

    def step_fields(self) -> tuple[str, ...]:
        return ("image", "vector", "action", "done", "pose") + tuple(f"signal/{s}" for s in self.signal_names)

    def read_steps(self, field: str, start: int, stop: int) -> np.ndarray:
        """Rows ``[start, stop)`` of a per-step field ('image', 'vector', ..., 'signal/<name>')."""
        if field not in self.step_fields():
            raise ValueError(f"unknown field {field!r}; expected one of {self.step_fields()}")
        if not 0 <= start <= stop <= self.num_steps:
            raise IndexError(f"steps [{start}, {stop}) out of the committed range [0, {self.num_steps})")
        return np.asarray(self._group[f"steps/{field}"][start:stop])

    def read_episode(self, i) -> dict[str, np.ndarray]:
        """Every per-step field of episode ``i``, plus its labelled frames ('labelled_index' local)."""
        i = self._check_episode(i)
        a, n = int(self._starts[i]), int(self._lengths[i])
        out = {f: self.read_steps(f, a, a + n) for f in self.step_fields()}
        steps, _, semantic = self._labelled_in(np.array([i]))
        out["labelled_index"] = steps - a
        out["semantic"] = semantic
        out["split"] = SPLITS[int(self._group["episodes/split"][i])]
        out["task"] = np.asarray(self._group["episodes/task"][i])
        return out

    def _labelled_in(self, episodes) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.num_labelled == 0:
            h, w, _ = self.spec.image_shape
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, h, w), np.uint8)
        steps = np.asarray(self._group["labelled/step"][: self.num_labelled])
        rows = np.flatnonzero(np.isin(self.episode_of_step(steps), episodes))
        if rows.size == 0:
            h, w, _ = self.spec.image_shape
            return np.zeros(0, np.int64), rows, np.zeros((0, h, w), np.uint8)
        semantic = np.asarray(self._group["labelled/semantic"][rows.min(): rows.max() + 1])[rows - rows.min()]
        return steps[rows], rows, semantic

    def labelled_frames(self, episodes=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(global step i64[n], image u8[n,h,w,c], semantic u8[n,h,w])`` of the "hand-labelled" frames
        (of ``episodes``, default all committed)."""
        if not self.has_semantic:
            raise ValueError(f"dataset {self.path!r} (env {self.env_name!r}) has no semantic maps "
                             "(has_semantic=False): its env renders no class map")
        episodes = np.arange(self.num_episodes) if episodes is None else np.asarray(episodes)
        steps, _, semantic = self._labelled_in(episodes)
        # One read per chunk holding labelled frames (zarr's orthogonal indexing would size an index
        # over the whole fixed capacity).
        images = np.zeros((steps.size,) + tuple(self.spec.image_shape), np.uint8)
        chunk_of = steps // self.chunk_steps
        for c in np.unique(chunk_of):
            rows = np.flatnonzero(chunk_of == c)
            lo, hi = int(steps[rows].min()), int(steps[rows].max()) + 1
            images[rows] = self.read_steps("image", lo, hi)[steps[rows] - lo]
        return steps, images, semantic

    def _step_ranges(self, episodes) -> list[tuple[int, int]]:
        """Merged contiguous [start, stop) step ranges of ``episodes`` (default: all committed)."""
        if episodes is None:
            return [(0, self.num_steps)] if self.num_steps else []
        ids = np.unique(np.asarray(episodes, np.int64))
        for i in ids:
            self._check_episode(i)
        ranges: list[tuple[int, int]] = []
        for i in ids:
            a, b = int(self._starts[i]), int(self._starts[i] + self._lengths[i])
            if ranges and ranges[-1][1] == a:
                ranges[-1] = (ranges[-1][0], b)
            else:
                ranges.append((a, b))
        return ranges

    def iter_images(self, batch_size: int, episodes=None) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Yield ``(global step i64[b], image u8[b,h,w,c])`` over the episodes' steps, ``b <= batch_size``
        (reads one batch at a time, never the whole store)."""
        if batch_size <= 0:
            raise ValueError(f"batch_size must be positive, got {batch_size}")
        for a, b in self._step_ranges(episodes):
            for s in range(a, b, batch_size):
                t = min(s + batch_size, b)
                yield np.arange(s, t, dtype=np.int64), self.read_steps("image", s, t)

    def gather_steps(self, field: str, episodes) -> tuple[np.ndarray, set[int]]:
        """The field's rows of ``episodes`` (sorted ids) concatenated, read chunk by chunk; episodes hit by
        an unreadable chunk are returned in the second value (their rows are zeros)."""
        ids = np.asarray(sorted({int(i) for i in episodes}), np.int64)
        arr = self._group[field if field.startswith("steps/") else f"steps/{field}"]
        starts, lengths = self._starts[ids], self._lengths[ids]
        offsets = np.concatenate([[0], np.cumsum(lengths)])
        out = np.zeros((int(offsets[-1]),) + tuple(arr.shape[1:]), arr.dtype)
        bad: set[int] = set()
        c = self.chunk_steps
        chunk_ids = np.unique(np.concatenate(
            [np.arange(s // c, (s + n - 1) // c + 1) for s, n in zip(starts, lengths)])) if ids.size else []
        for ci in chunk_ids:
            a, b = int(ci) * c, min((int(ci) + 1) * c, self.num_steps)
            hit = np.flatnonzero((starts < b) & (starts + lengths > a))
            try:
                if not self._chunk_exists(arr, int(ci)):
                    raise KeyError("chunk file missing")
                block = np.asarray(arr[a:b])
            except Exception:  # noqa: BLE001 -- any decode/checksum/IO failure marks the chunk corrupt
                bad.update(int(ids[j]) for j in hit)
                continue
            for j in hit:
                lo, hi = max(a, starts[j]), min(b, starts[j] + lengths[j])
                out[offsets[j] + lo - starts[j]: offsets[j] + hi - starts[j]] = block[lo - a: hi - a]
        return out, bad

    def _chunk_exists(self, arr, chunk: int) -> bool:
        coords = (chunk,) + (0,) * (arr.ndim - 1)
        return os.path.exists(os.path.join(self.path, arr.path, arr.metadata.encode_chunk_key(coords)))

    # ------------------------------------------------------------------------------ labels

    def write_labels(self, name: str, labels: dict[str, np.ndarray], meta: dict) -> None:
        """Cue labels ``f32[num_steps]`` per cue under ``labels/<name>/``; re-writing a name replaces it
        (labels are derived data: the recorded episodes are never touched)."""
        if self.mode != "a":
            raise ValueError(f"dataset {self.path!r} is open with mode={self.mode!r}; expected mode='a' to write labels")
        if not name or "/" in name or name.startswith("."):
            raise ValueError(f"label set name must be a plain non-empty name, got {name!r}")
        if not labels:
            raise ValueError("labels is empty; expected {cue: f32[num_steps]}")
        cols = {}
        for cue, value in labels.items():
            value = np.asarray(value, np.float32)
            if value.shape != (self.num_steps,):
                raise ValueError(f"labels[{cue!r}] has shape {value.shape}, expected ({self.num_steps},) (num_steps)")
            cols[cue] = value
        labels_dir = os.path.join(self.path, "labels")
        tmp_name = f".{name}.writing-{uuid.uuid4().hex}"
        group = zarr.open_group(self.path, mode="r+")["labels"].create_group(tmp_name)
        group.attrs.update({"meta": _jsonable(meta), "num_steps": self.num_steps, "cues": sorted(cols)})
        with zarr.config.set({"array.write_empty_chunks": True}):
            for cue, value in cols.items():
                a = group.create_array(cue, shape=value.shape, chunks=(self.chunk_steps,), dtype="float32",
                                       compressors=_compressors(), fill_value=0)
                a[:] = value
        # Swap the finished set into place; the old one (if any) is moved aside first, then removed.
        final = os.path.join(labels_dir, name)
        old = None
        if os.path.exists(final):
            old = os.path.join(labels_dir, f".{name}.old-{uuid.uuid4().hex}")
            os.rename(final, old)
        os.rename(os.path.join(labels_dir, tmp_name), final)
        if old is not None:
            shutil.rmtree(old)

    @property
    def label_names(self) -> tuple[str, ...]:
        """The label sets written so far (``labels/<name>``)."""
        labels_dir = os.path.join(self.path, "labels")
        return tuple(sorted(d for d in os.listdir(labels_dir)
                            if not d.startswith(".") and os.path.isdir(os.path.join(labels_dir, d))))

    def label_info(self, name: str) -> dict:
        """``{'meta', 'num_steps', 'cues'}`` of label set ``name``."""
        if name not in self.label_names:
            raise ValueError(f"no label set {name!r} in {self.path!r}; expected one of {self.label_names}")
        return dict(zarr.open_group(os.path.join(self.path, "labels", name), mode="r").attrs)

    def read_labels(self, name: str, cue: str | None = None):
        """One cue's labels f32[n] (or all cues as a dict) of label set ``name``."""
        info = self.label_info(name)
        if cue is None:
            return {c: self.read_labels(name, c) for c in info["cues"]}
        if cue not in info["cues"]:
            raise ValueError(f"label set {name!r} has no cue {cue!r}; expected one of {info['cues']}")
        return np.asarray(zarr.open_array(os.path.join(self.path, "labels", name, cue), mode="r")[:])

    # ------------------------------------------------------------------------------ integrity, splits

    def verify(self) -> list[CorruptChunk]:
        """Read every committed chunk of every array; report unreadable or missing ones with the
        committed episodes they hold (an empty list means the store is intact)."""
        g = self._group
        out: list[CorruptChunk] = []
        step_arrays = [f"steps/{f}" for f in self.step_fields()]
        step_arrays += [f"labels/{n}/{c}" for n in self.label_names for c in self.label_info(n)["cues"]]
        try:
            lab_steps = np.asarray(g["labelled/step"][: self.num_labelled])
        except Exception:  # noqa: BLE001 -- the loop below reports the bad chunk; episodes then unknown
            lab_steps = None
        for name, rows, kind in ([(a, self.num_steps, "steps") for a in step_arrays]
                                 + [(f"episodes/{f}", self.num_episodes, "episodes") for f in ("start", "length", "split", "task")]
                                 + [(f"labelled/{f}", self.num_labelled, "labelled") for f in ("step", "semantic")]):
            arr = g[name] if not name.startswith("labels/") else zarr.open_array(os.path.join(self.path, name), mode="r")
            c = arr.chunks[0]
            for ci in range(math.ceil(rows / c)):
                a, b = ci * c, min((ci + 1) * c, rows)
                try:
                    if not os.path.exists(os.path.join(self.path, name, arr.metadata.encode_chunk_key((ci,) + (0,) * (arr.ndim - 1)))):
                        raise KeyError("chunk file missing")
                    arr[a:b]
                except Exception as err:  # noqa: BLE001 -- any failure to decode is corruption to report
                    if kind == "steps":
                        eps = np.flatnonzero((self._starts < b) & (self._starts + self._lengths > a))
                    elif kind == "episodes":
                        eps = np.arange(a, b)
                    else:
                        eps = np.unique(self.episode_of_step(lab_steps[a:b])) if lab_steps is not None else np.arange(0)
                    out.append(CorruptChunk(name, ci, (a, b), tuple(int(e) for e in eps), f"{type(err).__name__}: {err}"))
        return out

    def split_episodes(self, holdout_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """``(train_ids, holdout_ids)``: a random split of the committed episodes (disjoint, sorted)."""
        if not 0.0 <= holdout_fraction < 1.0:
            raise ValueError(f"holdout_fraction must be in [0, 1), got {holdout_fraction}")
        if self.num_episodes == 0:
            raise ValueError(f"dataset {self.path!r} is empty (num_episodes=0); expected at least 1 episode")
        perm = np.random.default_rng(seed).permutation(self.num_episodes)
        k = int(round(holdout_fraction * self.num_episodes))
        if holdout_fraction > 0 and self.num_episodes >= 2:
            k = min(max(k, 1), self.num_episodes - 1)
        return np.sort(perm[k:]), np.sort(perm[:k])


def _write_json_atomic(path: str, obj: dict) -> None:
    tmp = f"{path}.{uuid.uuid4().hex}.tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


# ---------------------------------------------------------------------------------------- relabelling


def relabel(ds: Dataset, label_fn: Callable, name: str, *, batch_size: int = 256, meta: dict | None = None,
            scene: str | None = None) -> dict[str, np.ndarray]:
    """Label every committed step with ``label_fn(images u8[b,h,w,c]) -> {cue: f32[b]}`` and store the
    result as ``labels/<name>``.  Jitted once at a fixed batch shape (the last batch is padded), so a new
    labeller is one call away and needs no recollection.  ``scene`` names the env the labeller was
    trained for; it must match the dataset's."""
    if scene is not None and scene != ds.env_name:
        raise ValueError(f"scene is {scene!r} but the dataset was recorded in {ds.env_name!r}; expected "
                         f"scene={ds.env_name!r} (a labeller must match the dataset's scene)")
    if ds.num_steps == 0:
        raise ValueError(f"dataset {ds.path!r} is empty (num_steps=0); expected recorded episodes to label")
    fn = jax.jit(label_fn)
    out: dict[str, np.ndarray] = {}
    for steps, images in ds.iter_images(batch_size):
        b = images.shape[0]
        if b < batch_size:  # pad to the compiled shape
            images = np.concatenate([images, np.zeros((batch_size - b,) + images.shape[1:], images.dtype)])
        result = jax.device_get(fn(images))
        for cue, value in result.items():
            value = np.asarray(value, np.float32)
            if value.shape != (batch_size,):
                raise ValueError(f"label_fn output {cue!r} has shape {value.shape}, expected ({batch_size},)")
            out.setdefault(cue, np.zeros(ds.num_steps, np.float32))[steps] = value[:b]
    ds.write_labels(name, out, dict(meta or {}, scene=ds.env_name))
    return out


# ---------------------------------------------------------------------------------------- window sampler


@struct.dataclass
class WindowSampler:
    """Training windows from a device-resident buffer of whole episodes (flat arrays + valid starts).

    Hand-written rather than flashbax's trajectory buffer: flashbax samples fixed-length sequences
    from per-env rows and knows nothing of episode boundaries, so the paper's window semantics (zero
    history before the start, labels up to and including the terminal observation, random actions past
    the end, starts never on the terminal entry, uniform over valid starts) would need masks rebuilt
    on top of it anyway; a flat buffer with an index of valid starts gives all of it with a few
    vectorised gathers under jit.
    """

    images: jax.Array  # u8[N, h, w, c]
    vector: jax.Array  # f32[N, D]
    action: jax.Array  # f32[N, A]
    pose: jax.Array  # f32[N, 3]
    signals: dict  # name -> f32[N]
    episode_start: jax.Array  # i32[N]: flat index of the step's episode's first entry
    episode_end: jax.Array  # i32[N]: flat index of its terminal entry
    starts: jax.Array  # i32[M]: valid window starts
    plan_low: jax.Array  # f32[A]
    plan_high: jax.Array  # f32[A]
    horizon: int = struct.field(pytree_node=False)
    history: int = struct.field(pytree_node=False)
    # Mirror augmentation (``make_sampler(mirror=True)``): per-quantity signs under a left-right mirror.
    mirror: bool = struct.field(pytree_node=False, default=False)
    vector_sign: jax.Array | None = None  # f32[D]
    action_sign: jax.Array | None = None  # f32[A]
    signal_sign: dict | None = None  # name -> f32 scalar

    @property
    def num_windows(self) -> int:
        return int(self.starts.shape[0])

    def _history(self, t: jax.Array, flip: jax.Array | None):
        idx = t[:, None] - (self.history - 1) + jnp.arange(self.history)  # [B, L], oldest first
        inside = idx >= self.episode_start[t][:, None]
        safe = jnp.clip(idx, 0, self.images.shape[0] - 1)
        images = jnp.where(inside[..., None, None, None], self.images[safe], jnp.zeros((), jnp.uint8))
        vector = jnp.where(inside[..., None], self.vector[safe], 0.0)
        if flip is not None:
            images = jnp.where(flip[:, None, None, None, None], images[..., ::-1, :], images)
            vector = vector * jnp.where(flip[:, None, None], self.vector_sign, 1.0)
        from envs.base import (
            Observation,  # lazy: capsjax does not import envs at module load
        )

        return Observation(images=images, vector=vector)

    def windows(self, t: jax.Array, key: jax.Array, flip: jax.Array | None = None):
        """The batch of windows starting at flat indices ``t`` i32[B] (``sample`` draws them).

        ``flip`` bool[B] (mirror samplers only): which windows to mirror left-right -- frames flipped
        along their width, and every vector entry, executed action, signal and pose coordinate that
        changes sign under the mirror y -> -y negated (``MIRROR_SIGNS``).  Actions past an episode's
        end stay uniform draws from the plan box."""
        from capsjax.losses import Batch

        if flip is not None and not self.mirror:
            raise ValueError("flip needs a sampler made with make_sampler(mirror=True)")

        h = self.horizon
        end = self.episode_end[t]  # [B]
        k = jnp.arange(h)
        future = t[:, None] + 1 + k  # observation t+k+1
        valid = future <= end[:, None]
        # Past the terminal entry the terminal values repeat: a crash's collision stays 1 (absorbing),
        # a time-out's stays 0; the other cues are masked there.
        idx = jnp.minimum(future, end[:, None])
        signals = {name: v[idx] for name, v in self.signals.items()}
        if flip is not None:
            signals = {name: v * jnp.where(flip[:, None], self.signal_sign[name], 1.0) for name, v in signals.items()}
        act_idx = t[:, None] + k
        executed = act_idx < end[:, None]  # the terminal entry's action was never executed
        random = jax.random.uniform(key, act_idx.shape + self.plan_low.shape, minval=self.plan_low,
                                    maxval=self.plan_high)
        taken = self.action[jnp.minimum(act_idx, end[:, None])]
        pose, final_xy = self.pose[t], self.pose[end][:, :2]
        if flip is not None:
            taken = taken * jnp.where(flip[:, None, None], self.action_sign, 1.0)
            mirror_y = jnp.where(flip, -1.0, 1.0)[:, None]
            pose = pose * jnp.concatenate([jnp.ones_like(mirror_y), mirror_y, mirror_y], axis=1)
            final_xy = final_xy * jnp.concatenate([jnp.ones_like(mirror_y), mirror_y], axis=1)
        actions = jnp.where(executed[..., None], taken, random)
        return Batch(
            obs=self._history(t, flip), actions=actions, signals=signals, valid=valid,
            done=future == end[:, None], next_obs=self._history(t + 1, flip),
            context={"pose": pose, "final_xy": final_xy},
        )

    def sample(self, key: jax.Array, batch_size: int):
        """``capsjax.losses.Batch`` of ``batch_size`` windows, starts uniform over all valid starts.
        Pure: jit it with ``batch_size`` static (``jax.jit(WindowSampler.sample, static_argnums=2)``)."""
        flip = None
        if self.mirror:  # half of the windows mirrored (the extra split only here: other streams unchanged)
            key, k_flip = jax.random.split(key)
            flip = jax.random.bernoulli(k_flip, 0.5, (batch_size,))
        k_start, k_act = jax.random.split(key)
        t = self.starts[jax.random.randint(k_start, (batch_size,), 0, self.starts.shape[0])]
        return self.windows(t, k_act, flip)

    def batches(self, batch_size: int) -> "BatchSource":
        """This sampler bound to ``batch_size``: ``source(key) -> Batch``, a pytree callable to hand to
        ``training.fit`` / ``baselines.fit_offline`` (which then pass the buffers to the compiled step as
        arguments instead of compiling the dataset into it)."""
        if not isinstance(batch_size, int) or isinstance(batch_size, bool) or batch_size <= 0:
            raise ValueError(f"batch_size must be a positive int, got {batch_size!r}")
        return BatchSource(self, batch_size)


@struct.dataclass
class BatchSource:
    """``source(key) -> Batch`` of ``batch_size`` windows of ``sampler`` (``WindowSampler.batches``).

    A pytree rather than a closure so that jitted training sees the sampler's buffers as arguments
    (``training.ArraySplit``)."""

    sampler: WindowSampler
    batch_size: int = struct.field(pytree_node=False)

    def __call__(self, key: jax.Array):
        return self.sampler.sample(key, self.batch_size)


def concatenate_samplers(*samplers: WindowSampler) -> WindowSampler:
    """One sampler over the episodes of several (e.g. a random-action dataset and an on-policy one
    collected later in the same env): windows are drawn uniformly over all of their valid starts, so
    each dataset is sampled in proportion to its size.  They must agree on the horizon, history, plan
    box, signals and mirroring."""
    if not samplers:
        raise ValueError("concatenate_samplers needs at least one sampler")
    first = samplers[0]
    for i, s in enumerate(samplers[1:], 1):
        for field in ("horizon", "history", "mirror"):
            if getattr(s, field) != getattr(first, field):
                raise ValueError(f"concatenate_samplers: sampler {i} has {field} {getattr(s, field)!r}, "
                                 f"sampler 0 has {getattr(first, field)!r}; expected equal")
        if sorted(s.signals) != sorted(first.signals):
            raise ValueError(f"concatenate_samplers: sampler {i} has signals {sorted(s.signals)}, sampler 0 has "
                             f"{sorted(first.signals)}; expected the same names")
        for field in ("plan_low", "plan_high", "vector_sign", "action_sign"):
            a, b = getattr(first, field), getattr(s, field)
            if (a is None) != (b is None) or (a is not None and not np.array_equal(np.asarray(a), np.asarray(b))):
                raise ValueError(f"concatenate_samplers: sampler {i} has {field} {b}, sampler 0 has {a}; expected equal")
    offsets = np.cumsum([0] + [int(s.images.shape[0]) for s in samplers[:-1]])
    if int(offsets[-1]) + int(samplers[-1].images.shape[0]) >= 2**31:
        raise ValueError("the samplers hold more steps than the int32 index allows; pass fewer episodes")
    cat = lambda field: jnp.concatenate([getattr(s, field) for s in samplers])
    shifted = lambda field: jnp.concatenate([getattr(s, field) + jnp.int32(o) for s, o in zip(samplers, offsets)])
    return first.replace(
        images=cat("images"), vector=cat("vector"), action=cat("action"), pose=cat("pose"),
        signals={k: jnp.concatenate([s.signals[k] for s in samplers]) for k in first.signals},
        episode_start=shifted("episode_start"), episode_end=shifted("episode_end"), starts=shifted("starts"))


# How a named vector entry, action or signal changes when the world is mirrored left-right (y -> -y,
# so yaw -> -yaw and a left turn becomes a right one): kept (+1) or negated (-1).  Right-lane cues
# (lane_seen, lane_diff) are deliberately absent: the mirror of right-hand traffic is left-hand traffic,
# so they have no mirrored label and a sampler asked to mirror them refuses.
MIRROR_SIGNS = {"collision": 1.0, "speed": 1.0, "door_frac": 1.0, "x": 1.0, "heading": -1.0, "y": -1.0,
                "steer_deg": -1.0}


def make_sampler(ds: Dataset, *, horizon: int, episodes=None, label_sources: dict[str, str] | None = None,
                 plan_low=None, plan_high=None, signals: tuple[str, ...] | None = None,
                 max_bytes: int = 8 << 30, mirror: bool = False,
                 mirror_signs: dict[str, float] | None = None, history: int | None = None) -> WindowSampler:
    """Load ``episodes`` (default: all committed) into a ``WindowSampler`` on the default device.

    ``signals`` (default: the spec's) are the ground-truth cues; ``label_sources`` maps a cue to a label
    set written by ``relabel`` (``{'lane_seen': 'segmenter'}``), which replaces (or adds) that cue.
    ``plan_low/high`` (default: the spec's plan box) is where actions past an episode's end are drawn.
    Episodes with an unreadable chunk are skipped with a warning.  Refuses to load more than
    ``max_bytes`` (pass fewer episodes or raise the limit).

    ``mirror``: each sampled window is mirrored left-right with probability 1/2 (see
    ``WindowSampler.windows``), a data augmentation valid wherever the world's rules are symmetric
    (driving among obstacles, heading commands; not right-hand traffic).  ``mirror_signs`` (default
    ``MIRROR_SIGNS``) says how each vector key, action name and signal changes; a name it lacks is
    refused, never guessed.

    ``history`` (default: the spec's) is how many frames, oldest first, each window's observation stacks.
    The dataset stores one frame per step, so any history can be drawn from it: a model with a longer
    memory than the collecting env's trains on the same dataset.
    """
    horizon = int(horizon)
    if horizon < 1:
        raise ValueError(f"horizon must be >= 1, got {horizon}")
    history = ds.spec.history if history is None else int(history)
    if history < 1:
        raise ValueError(f"history must be >= 1 frame, got {history}")
    if ds.num_episodes == 0:
        raise ValueError(f"dataset {ds.path!r} is empty (num_episodes=0); expected at least one committed episode")
    ids = np.arange(ds.num_episodes) if episodes is None else np.unique(np.asarray(episodes, np.int64))
    if ids.size == 0:
        raise ValueError("episodes is empty; expected at least one episode id")
    for i in ids:
        ds._check_episode(i)
    starts_all, lengths_all = ds.episode_bounds()
    longest = int(lengths_all[ids].max())
    # A window needs its start t <= T-2 and H future observations; with H >= every T no episode holds one.
    if horizon >= longest:
        raise ValueError(f"horizon {horizon} is not shorter than any episode (longest has {longest} entries); "
                         f"expected horizon <= {longest - 1}")
    signals = tuple(ds.signal_names if signals is None else signals)
    for s in signals:
        if s not in ds.signal_names:
            raise ValueError(f"signals names {s!r}, which the dataset does not record; expected one of {ds.signal_names}")
    label_sources = dict(label_sources or {})
    for cue, name in label_sources.items():
        info = ds.label_info(name)
        if cue not in info["cues"]:
            raise ValueError(f"label_sources[{cue!r}] = {name!r}, but that label set has cues {info['cues']}")
        needed = int((starts_all[ids] + lengths_all[ids]).max())
        if info["num_steps"] < needed:
            raise ValueError(f"label set {name!r} covers {info['num_steps']} steps, expected >= {needed}; "
                             "relabel the dataset after appending episodes")
    h, w, c = ds.spec.image_shape
    per_step = h * w * c + 4 * (ds.spec.vector_dim + ds.spec.action_dim + 3 + len(signals) + len(label_sources) + 2)
    total = int(lengths_all[ids].sum()) * per_step
    if total > max_bytes:
        raise ValueError(f"the episodes need {total / 2**30:.2f} GiB on device, more than max_bytes="
                         f"{max_bytes / 2**30:.2f} GiB; pass fewer episodes or a larger max_bytes")

    fields = {"image": "steps/image", "vector": "steps/vector", "action": "steps/action", "pose": "steps/pose"}
    fields.update({f"signal/{s}": f"steps/signal/{s}" for s in signals if s not in label_sources})
    fields.update({f"signal/{cue}": f"labels/{name}/{cue}" for cue, name in label_sources.items()})
    loaded, bad = {}, set()
    for key, field in fields.items():
        if field.startswith("labels/"):
            data = ds.read_labels(field.split("/")[1], field.split("/")[2])
            starts, lengths = starts_all[ids], lengths_all[ids]
            loaded[key] = np.concatenate([data[s: s + n] for s, n in zip(starts, lengths)])
        else:
            loaded[key], b = ds.gather_steps(field, ids)
            bad |= b
    lengths = lengths_all[ids]
    if bad:
        warnings.warn(f"skipping {len(bad)} episode(s) with unreadable chunks: {sorted(bad)[:20]} "
                      f"(run Dataset.verify() for details)", RuntimeWarning, stacklevel=2)
        keep_rows = np.repeat(~np.isin(ids, sorted(bad)), lengths)
        loaded = {k: v[keep_rows] for k, v in loaded.items()}
        keep = ~np.isin(ids, sorted(bad))
        ids, lengths = ids[keep], lengths[keep]
        if ids.size == 0:
            raise ValueError("every requested episode has an unreadable chunk; nothing left to sample")
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    n = int(offsets[-1])
    if n >= 2**31:
        raise ValueError(f"{n} steps exceed the sampler's int32 index; pass fewer episodes")
    ep_start = np.repeat(offsets[:-1], lengths).astype(np.int32)
    ep_end = np.repeat(offsets[1:] - 1, lengths).astype(np.int32)
    # Valid starts: every entry but the terminal one (t in [0, T-2]).
    window_starts = np.flatnonzero(np.arange(n) < ep_end).astype(np.int32)
    if window_starts.size == 0:
        raise ValueError("no valid window start: every episode has a single entry; expected episodes of length >= 2")
    spec = ds.spec
    low = np.asarray(spec.plan_low if plan_low is None else plan_low, np.float32)
    high = np.asarray(spec.plan_high if plan_high is None else plan_high, np.float32)
    if low.shape != (spec.action_dim,) or high.shape != (spec.action_dim,):
        raise ValueError(f"plan_low/plan_high must have shape ({spec.action_dim},), got {low.shape} / {high.shape}")
    signal_arrays = {k.split("/", 1)[1]: v for k, v in loaded.items() if k.startswith("signal/")}
    mirror_fields = {}
    if mirror:
        signs = dict(MIRROR_SIGNS if mirror_signs is None else mirror_signs)
        names = [("vector key", k) for k in spec.vector_keys] + [("action", a) for a in spec.action_names]
        names += [("signal", k) for k in signal_arrays]
        for kind, name in names:
            if name not in signs:
                raise ValueError(f"mirror=True, but mirror_signs has no sign for {kind} {name!r} (how it changes "
                                 f"under a left-right mirror: +1 kept, -1 negated); it knows {sorted(signs)}")
            if signs[name] not in (1.0, -1.0):
                raise ValueError(f"mirror_signs[{name!r}] must be +1 or -1, got {signs[name]!r}")
        mirror_fields = dict(
            mirror=True, vector_sign=jnp.asarray([signs[k] for k in spec.vector_keys], jnp.float32),
            action_sign=jnp.asarray([signs[a] for a in spec.action_names], jnp.float32),
            signal_sign={k: jnp.float32(signs[k]) for k in signal_arrays})
    return WindowSampler(
        images=jnp.asarray(loaded["image"]), vector=jnp.asarray(loaded["vector"]),
        action=jnp.asarray(loaded["action"]), pose=jnp.asarray(loaded["pose"]),
        signals={k: jnp.asarray(v) for k, v in signal_arrays.items()},
        episode_start=jnp.asarray(ep_start), episode_end=jnp.asarray(ep_end), starts=jnp.asarray(window_starts),
        plan_low=jnp.asarray(low), plan_high=jnp.asarray(high), horizon=horizon, history=history,
        **mirror_fields,
    )
