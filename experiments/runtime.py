"""XLA settings an entry point chooses before JAX starts its backend (XLA reads ``XLA_FLAGS`` once).

* ``use_host_devices(n)``: split a CPU host into ``n`` XLA devices, so that ``jax.sharding`` spreads a
  batch over the cores (the env benchmark's ``--host-devices``).
* ``use_wide_vectors()``: on a CPU with AVX-512, let XLA's code generator use 512-bit vectors.  XLA:CPU
  prefers 256-bit vectors by default (wide vectors lower the clock on some older Intel parts), which
  leaves half of each vector unit idle in the renderer's and the physics' elementwise loops: measured on
  this project's AMD EPYC host, 512-bit vectors render forest frames 1.3-1.4x and city frames ~1.45x
  faster, step the forest env ~1.2x faster and cast ``mjx.ray`` ~1.15x faster (README, Design).
  Matrix products and convolutions run in libraries that choose their own vector width.

Both respect a value already in ``XLA_FLAGS`` (the caller's environment decides, e.g.
``XLA_FLAGS=--xla_cpu_prefer_vector_width=256`` to compare), and refuse with a clear error once JAX has
started, when a new flag could no longer take effect.  They are for programs (``python -m
experiments...``), never called on import: the library sets no global state.
"""
from __future__ import annotations

import os

HOST_DEVICES_FLAG = "--xla_force_host_platform_device_count"
VECTOR_WIDTH_FLAG = "--xla_cpu_prefer_vector_width"


def _jax_started() -> bool:
    import jax._src.xla_bridge as xla_bridge  # noqa: PLC0415 (only to tell whether JAX has started)

    return xla_bridge.backends_are_initialized()


def set_xla_flag(flag: str, value, *, option: str) -> bool:
    """Append ``flag=value`` to ``XLA_FLAGS`` unless it is there already; True if it was added.

    ``option`` names what asked for it in the error raised when JAX has started already."""
    flags = os.environ.get("XLA_FLAGS", "")
    if flag in flags:
        return False  # the caller chose already
    if _jax_started():
        raise RuntimeError(f"{option}: JAX has started already, so {flag} can no longer take effect; set "
                           f"XLA_FLAGS={flag}={value} in the environment instead")
    os.environ["XLA_FLAGS"] = f"{flags} {flag}={value}".strip()
    return True


def use_host_devices(count: int) -> bool:
    """Split a CPU host into ``count`` XLA devices (before JAX starts)."""
    if not isinstance(count, int) or count < 1:
        raise ValueError(f"host device count must be a positive int, got {count!r}")
    return set_xla_flag(HOST_DEVICES_FLAG, count, option=f"--host-devices {count}")


def cpu_has_avx512(cpuinfo: str | None = None) -> bool:
    """Whether this host's CPU has AVX-512F (Linux ``/proc/cpuinfo``; False where it cannot be read)."""
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo") as f:
                cpuinfo = f.read()
        except OSError:
            return False
    return any(line.startswith("flags") and "avx512f" in line.split() for line in cpuinfo.splitlines())


def use_wide_vectors(cpuinfo: str | None = None) -> bool:
    """512-bit vectors in XLA:CPU's generated loops when the CPU has AVX-512 (before JAX starts)."""
    if not cpu_has_avx512(cpuinfo):
        return False
    return set_xla_flag(VECTOR_WIDTH_FLAG, 512, option="512-bit vectors (experiments.runtime.use_wide_vectors)")
