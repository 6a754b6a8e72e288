"""experiments.runtime: XLA flags chosen before JAX starts (what they do to speed is the benchmarks' job)."""
import os
import subprocess
import sys

import jax
import pytest

from experiments import runtime

AVX512 = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw\n"
AVX2 = "processor\t: 0\nflags\t\t: fpu sse2 avx2 fma\n"


def test_host_devices_after_jax_started_is_a_clear_error(monkeypatch):
    jax.devices()  # this process has started JAX
    monkeypatch.setenv("XLA_FLAGS", "")
    with pytest.raises(RuntimeError, match="set XLA_FLAGS=--xla_force_host_platform_device_count=3"):
        runtime.use_host_devices(3)
    with pytest.raises(ValueError, match="positive int, got 0"):
        runtime.use_host_devices(0)


def test_a_flag_the_caller_chose_is_kept(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=5 --xla_cpu_prefer_vector_width=256")
    assert not runtime.use_host_devices(3)  # no error although JAX started: the environment decides
    assert not runtime.use_wide_vectors(AVX512)
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=5 --xla_cpu_prefer_vector_width=256"


def test_wide_vectors_only_on_avx512(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "")
    assert runtime.cpu_has_avx512(AVX512) and not runtime.cpu_has_avx512(AVX2)
    assert not runtime.use_wide_vectors(AVX2)  # nothing to do, so no error although JAX started
    assert os.environ["XLA_FLAGS"] == ""
    with pytest.raises(RuntimeError, match="set XLA_FLAGS=--xla_cpu_prefer_vector_width=512"):
        runtime.use_wide_vectors(AVX512)


def test_flags_set_before_jax_starts_reach_the_backend():
    code = ("from experiments import runtime; import jax; "
            "assert runtime.use_host_devices(3); runtime.use_wide_vectors(); print(jax.device_count())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=dict(os.environ, XLA_FLAGS="", JAX_PLATFORMS="cpu"))
    assert out.stdout.strip().splitlines()[-1] == "3"
