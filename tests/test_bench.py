"""The benchmark entry point and the env benchmark's device handling (the timings themselves are not
tested: speed is judged by the benchmarks' same-run ratios, never by timed unit tests)."""
import json
import os
import subprocess
import sys

import jax
import pytest

from experiments import bench
from experiments.benchmarks import envs as env_bench


def test_unknown_benchmark_names_the_choices():
    with pytest.raises(SystemExit, match="planner, envs, collect, scale, jobs"):
        bench.main(["nope"])


def test_emit_prints_one_json_line_with_the_device(capsys):
    record = bench.emit("x.y", 2, "x", batch=3)
    line = json.loads(capsys.readouterr().out)
    assert line == record and line["value"] == 2.0 and line["batch"] == 3 and line["platform"] == jax.default_backend()


def test_mesh_for_splits_a_batch_evenly():
    mesh, count = env_bench._mesh_for(1)
    assert count == 1 and mesh.devices.size == 1
    mesh, count = env_bench._mesh_for(4 * jax.local_device_count())
    assert count == jax.local_device_count()


@pytest.mark.slow
def test_env_benchmark_prints_every_figure_split_over_two_host_devices():
    out = subprocess.run(
        [sys.executable, "-m", "experiments.bench", "envs", "--scenes", "forest", "--batches", "2", "--steps", "2",
         "--repeats", "1", "--render-batch", "4", "--host-devices", "2"],
        capture_output=True, text=True, check=True, env=dict(os.environ, XLA_FLAGS="", JAX_PLATFORMS="cpu"))
    lines = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
    figures = {line["metric"]: line for line in lines}
    assert set(figures) == {f"envs.forest.{m}" for m in (
        "compile_s", "steps_per_s_2", "render_frames_per_s", "mjx_ray_frames_per_s", "render_speedup_vs_mjx_ray")}
    assert all(line["num_devices"] == 2 and line["value"] > 0 for line in lines)
    assert all("--xla_force_host_platform_device_count=2" in line["xla_flags"] for line in lines)
    assert figures["envs.forest.steps_per_s_2"]["sharded_over"] == 2
    assert figures["envs.forest.render_speedup_vs_mjx_ray"]["batch"] == 4


def test_ray_batch_larger_than_the_render_batch_is_refused(capsys):
    with pytest.raises(SystemExit):
        env_bench.main(["--ray-batch", "8", "--render-batch", "4", "--host-devices", "1"])
    assert "--ray-batch must be in [1, --render-batch = 4], got 8" in capsys.readouterr().err


@pytest.mark.slow
def test_jobs_benchmark_prints_the_alone_rates_and_the_same_run_speedups():
    out = subprocess.run([sys.executable, "-m", "experiments.bench", "jobs", "--steps", "2", "--collect-steps", "2000"],
                         capture_output=True, text=True, check=True, env=dict(os.environ, JAX_PLATFORMS="cpu"))
    figures = {line["metric"]: line for line in map(json.loads, filter(lambda s: s.startswith("{"), out.stdout.splitlines()))}
    assert set(figures) == {"jobs.steps_per_s.caps", "jobs.steps_per_s.gc_dql", "jobs.steps_per_s.gc_dql_sep",
                            "jobs.seconds.caps_gc_dql_at_once", "jobs.speedup.caps_gc_dql_at_once",
                            "jobs.seconds.caps_gc_dql_gc_dql_sep_at_once", "jobs.speedup.caps_gc_dql_gc_dql_sep_at_once"}
    assert all(line["value"] > 0 and line["steps"] == 2 for line in figures.values())
