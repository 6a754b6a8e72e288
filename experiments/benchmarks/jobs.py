"""``python -m experiments.bench jobs``: the models of one dataset trained one after another, and at once in threads.

What ``--jobs`` of the experiments buys (``experiments.pipeline.run_concurrently``).  The models are the forest
`small` preset's CAPs, GC-DQL and GC-DQL-sep; their windows come from a forest dataset of ``--collect-steps``
uniform random steps collected into a temporary directory, sampled as the preset samples them (mirrored).
After every program has compiled, each model trains ``--steps`` steps alone, then each group of models at once,
each in its own thread.  JSON lines (``experiments.bench.emit``):

* ``jobs.steps_per_s.<model>``: training steps per second of one model alone;
* ``jobs.seconds.<group>_at_once``: wall time of the group's models, ``--steps`` steps each, at once;
* ``jobs.speedup.<group>_at_once``: the same-run ratio, the models' summed time alone over that wall time
  (1.0: nothing gained; the number of models: every model as fast as alone).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time

import jax

from experiments.bench import emit

MODELS = ("caps", "gc_dql", "gc_dql_sep")


def _trainers(env, sampler, steps: int) -> dict:
    """``{model: train() -> params}``: ``steps`` steps of each model from its initial state (compiled)."""
    import capsjax
    from capsjax import baselines, training
    from experiments import forest, pipeline

    exp, preset = forest.EXPERIMENT, forest.PRESETS["small"]
    model = capsjax.CAPsModel(pipeline.model_config(exp, preset, env))
    batches = sampler.batches(preset.batch_size)
    caps_cfg = pipeline.train_config(preset, preset.train_steps)
    caps_state = capsjax.init_train_state(model, caps_cfg, jax.random.key(0))
    caps_train = training.make_train(model, caps_cfg, batches, steps)
    trainers = {"caps": lambda: caps_train(caps_state)[0].params}
    for kind in MODELS[1:]:
        agent = baselines.BaselineAgent.create(model.config, exp.baseline_config(kind), env.spec.plan_low,
                                               env.spec.plan_high)
        cfg = pipeline.train_config(preset, preset.baseline_steps)
        state = baselines.agent.init_state(agent, cfg, jax.random.key(0))
        train = baselines.agent.make_offline_train(agent, cfg, batches, steps)
        trainers[kind] = lambda train=train, state=state: train(state)[0].params
    return trainers


def _at_once(trainers: dict, names: tuple[str, ...]) -> float:
    """Wall time of the named trainers run at once, one thread each."""
    threads = [threading.Thread(target=lambda n=n: jax.block_until_ready(trainers[n]())) for n in names]
    start = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m experiments.bench jobs")
    parser.add_argument("--steps", type=int, default=400, help="training steps of each model per measurement")
    parser.add_argument("--collect-steps", type=int, default=6400, help="random forest steps to train on")
    args = parser.parse_args(argv)
    for name in ("steps", "collect_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")

    import envs
    from capsjax import collect, data
    from experiments import forest

    env = envs.make("forest")
    preset = forest.PRESETS["small"]
    with tempfile.TemporaryDirectory() as tmp:
        ds = collect.collect(env, collect.random_policy(env.spec), None, None, path=os.path.join(tmp, "forest.zarr"),
                             num_steps=args.collect_steps, num_robots=64, key=jax.random.key(0), progress=False)
        sampler = data.make_sampler(ds, horizon=preset.horizon, mirror=preset.mirror, history=env.spec.history,
                                    signals=("collision", "heading", "speed"))
        trainers = _trainers(env, sampler, args.steps)
        for train in trainers.values():
            jax.block_until_ready(train())  # compile
        context = dict(steps=args.steps, collect_steps=args.collect_steps, preset="forest small",
                       cpu_count=os.cpu_count(), load_avg_1m=os.getloadavg()[0])
        alone = {}
        for name, train in trainers.items():
            start = time.perf_counter()
            jax.block_until_ready(train())
            alone[name] = time.perf_counter() - start
            emit(f"jobs.steps_per_s.{name}", args.steps / alone[name], "steps/s", **context)
        for group in (("caps", "gc_dql"), MODELS):
            label = "_".join(group)
            wall = _at_once(trainers, group)
            emit(f"jobs.seconds.{label}_at_once", wall, "s", models=list(group), **context)
            emit(f"jobs.speedup.{label}_at_once", sum(alone[n] for n in group) / wall, "x", models=list(group),
                 reference="the same models one after another, this run", **context)
