"""Benchmarks: ``python -m experiments.bench NAME [options]``.

Every benchmark prints JSON lines, one per figure::

    {"metric": "planner.plan_ms_p50", "value": 71.2, "unit": "ms", "device": "cpu", ...config}

Speed targets are judged by ratios to a reference measured in the same run (machines are shared and
noisy), never by timed unit tests.  On an AVX-512 CPU every benchmark compiles with 512-bit vectors, as
the experiments do (``experiments/runtime.py``); the lines record the ``XLA_FLAGS`` they ran with.
"""
from __future__ import annotations

import importlib
import json
import os
import platform
import sys

import jax

from experiments import runtime

BENCHMARKS = ("planner", "envs", "collect", "scale", "jobs")


def device_context() -> dict:
    """Where a figure was measured: put into every JSON line's context."""
    devices = jax.devices()
    return {
        "device": devices[0].device_kind,
        "platform": devices[0].platform,
        "num_devices": len(devices),
        "host": platform.node(),
        "jax": jax.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def emit(metric: str, value: float, unit: str, **context) -> dict:
    """Print one JSON line for one figure and return it."""
    record = {"metric": metric, "value": float(value), "unit": unit, **device_context(), **context}
    print(json.dumps(record), flush=True)
    return record


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in BENCHMARKS:
        raise SystemExit(f"usage: python -m experiments.bench NAME [options]; NAME is one of {', '.join(BENCHMARKS)}")
    runtime.use_wide_vectors()  # what the experiments use too (experiments/runtime.py); XLA_FLAGS overrides
    importlib.import_module(f"experiments.benchmarks.{argv[0]}").main(argv[1:])


if __name__ == "__main__":
    main()
