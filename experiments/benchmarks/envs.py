"""Env throughput: ``python -m experiments.bench envs [--scenes forest,city,indoor] [--batches 1,64,256] ...``

Per scene, JSON lines (``experiments.bench.emit``):

* ``envs.<scene>.steps_per_s_<B>``: control steps per second for B robots stepping together (``vmap``
  of ``env.step``: 0.25 s of MJX physics in substeps plus one camera frame and the signals), timed over
  ``--steps`` steps inside one ``lax.scan`` after compilation;
* ``envs.<scene>.render_frames_per_s``: ``envs.camera.render`` alone, ``--render-batch`` views at once;
* ``envs.<scene>.mjx_ray_frames_per_s``: the same views by ``mjx.ray`` per pixel (``--ray-batch`` views,
  the full scene's MJCF), and ``envs.<scene>.render_speedup_vs_mjx_ray``: the ratio of the two at the same
  batch (``--ray-batch``), i.e. per pixel;
* ``envs.<scene>.compile_s``: wall time spent compiling the scene's functions.

Compilation dominates the run time (MJX's step takes most of a minute to compile on a 2-core CPU): the
scene's functions are compiled in parallel threads first, and ``--batches`` / ``--scenes`` shrink the run.
Timings are medians over ``--repeats`` samples, each of back-to-back calls for at least 0.3 s.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import time

import jax
import jax.numpy as jnp
import numpy as np

import envs
from envs.camera import mjx_ray_depth, render
from experiments.bench import emit


def _median_time(fn, repeats: int, min_seconds: float = 0.3) -> float:
    """Median over ``repeats`` samples of the seconds per call; each sample calls ``fn`` back to back
    for at least ``min_seconds`` (a single millisecond call is mostly timer and scheduler noise)."""
    jax.block_until_ready(fn())  # warm: first-call allocations are not part of the figure
    times = []
    for _ in range(repeats):
        calls, start = 0, time.perf_counter()
        while True:
            jax.block_until_ready(fn())
            calls += 1
            if time.perf_counter() - start >= min_seconds:
                break
        times.append((time.perf_counter() - start) / calls)
    return float(np.median(times))


def bench_scene(name: str, batches: list[int], steps: int, repeats: int, render_batch: int, ray_batch: int) -> None:
    env = envs.make(name)
    spec = env.spec
    low, high = np.asarray(spec.plan_low, np.float32), np.asarray(spec.plan_high, np.float32)
    context = dict(scene=name, substeps=env.config.car.substeps, image=list(spec.image_shape))

    def rollout(state, actions):
        def body(s, a):
            return jax.vmap(env.step)(s, a), None

        return jax.lax.scan(body, state, actions)[0]

    # Inputs per batch size: tasks from distinct seeds (distinct layouts), random plan-box actions.
    inputs, compiled = {}, {}
    for b in batches:
        keys = jax.random.split(jax.random.key(b), b)
        tasks = jax.vmap(lambda k: env.sample_task(k, "train"))(keys)
        state = jax.jit(jax.vmap(env.reset))(keys, tasks)
        u = np.random.default_rng(b).uniform(size=(steps, b, spec.action_dim)).astype(np.float32)
        inputs[b] = (state, jnp.asarray(low + u * (high - low)))

    scene = jax.tree.map(lambda x: x[0], inputs[batches[0]][0].physics.scene)
    poses = jax.vmap(lambda k: _free_pose(env, inputs[batches[0]][0], k))(jax.random.split(jax.random.key(7), render_batch))
    cam = env.config.camera
    render_fn = jax.jit(jax.vmap(lambda p: render(scene, p, cam)))

    import mujoco
    from mujoco import mjx

    from envs.car import full_mjcf

    mj_model = mujoco.MjModel.from_xml_string(full_mjcf(env.config.car, scene, name=name))
    model = mjx.put_model(mj_model, impl="jax")
    data = mjx.kinematics(model, mjx.make_data(model))
    ray_fn = jax.jit(jax.vmap(lambda p: mjx_ray_depth(model, data, p, cam)))

    jobs = {("steps", b): (jax.jit(rollout), inputs[b]) for b in batches}
    jobs[("render", render_batch)] = (render_fn, (poses,))
    jobs[("render", ray_batch)] = (render_fn, (poses[:ray_batch],))
    jobs[("ray", ray_batch)] = (ray_fn, (poses[:ray_batch],))
    start = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        futures = {k: pool.submit(lambda f=f, a=a: f.lower(*a).compile()) for k, (f, a) in jobs.items()}
        compiled = {k: fut.result() for k, fut in futures.items()}
    emit(f"envs.{name}.compile_s", time.perf_counter() - start, "s", **context)

    for b in batches:
        fn, args = compiled[("steps", b)], inputs[b]
        seconds = _median_time(lambda: fn(*args), repeats)
        emit(f"envs.{name}.steps_per_s_{b}", b * steps / seconds, "steps/s", batch=b, steps=steps, **context)
    frames = _median_time(lambda: compiled[("render", render_batch)](poses), repeats)
    emit(f"envs.{name}.render_frames_per_s", render_batch / frames, "frames/s", batch=render_batch, **context)
    small = _median_time(lambda: compiled[("render", ray_batch)](poses[:ray_batch]), repeats)
    ray = _median_time(lambda: compiled[("ray", ray_batch)](poses[:ray_batch]), max(1, repeats // 2))
    emit(f"envs.{name}.mjx_ray_frames_per_s", ray_batch / ray, "frames/s", batch=ray_batch, ngeom=mj_model.ngeom,
         **context)
    emit(f"envs.{name}.render_speedup_vs_mjx_ray", ray / small, "x", batch=ray_batch, **context)


def _free_pose(env, state, key):
    """A camera pose near the first robot's start, turned by a random angle (a view of the scene)."""
    pose = state.info["pose"][0]
    return pose.at[2].add(jax.random.uniform(key, (), minval=-jnp.pi, maxval=jnp.pi))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench envs", description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(envs.SCENES))
    parser.add_argument("--batches", default="1,64,256", help="robot batch sizes")
    parser.add_argument("--steps", type=int, default=8, help="control steps per timed rollout")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--render-batch", type=int, default=256)
    parser.add_argument("--ray-batch", type=int, default=4, help="views for the mjx.ray comparison")
    args = parser.parse_args(argv)
    batches = [int(b) for b in args.batches.split(",") if b]
    for name in args.scenes.split(","):
        bench_scene(name, batches, args.steps, args.repeats, args.render_batch, args.ray_batch)


if __name__ == "__main__":
    main()
