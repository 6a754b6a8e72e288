"""``python -m experiments.forest``: the paper's forest experiment (caps-algorithm.md sections 9.1, 10).

Data: uniform random driving in forest layouts whose tasks are *circular* paths (the training task
stream).  Every method trains on this one stored dataset (the strict off-policy test, Q2).  Evaluation:
follow *sinusoidal* paths in layouts from the disjoint evaluation stream, the goal heading pointing at the
path 8 m ahead (``EXPERIMENT.eval_env``).  Every preset trains on half
of its windows mirrored left-right (``Preset.mirror``: the forest has no handedness, so a mirrored window
is as real as the original; it lowered the held-out collision loss by a quarter).  Metrics (the paper's table):
``success_rate`` (finished the path without a collision) and ``path_distance_mean`` (mean distance
from the path, m).  CAPs drives with the paper's forest reward ``500 (1 - c) + cos(h - h_goal) - 1``;
GC-DQL and GC-DQL-sep with the paper's baseline reward (its speed goal 2 m/s).  Beyond the paper
(Q1): the same CAPs model follows the paths at a goal speed of 2 m/s (about twice its speed
under the paper's reward), a reward term no training step
and no paper experiment used; and it keeps to the path itself (``caps_path``): the predicted speeds and
headings compose into the positions the car will pass, and the reward subtracts their distance from the
path (``reward`` term ``path``), a quantity no cue predicts.
"""
from __future__ import annotations

import dataclasses

import jax
import numpy as np

from capsjax import baselines, cues
from envs.scenes import common
from experiments import pipeline
from experiments.pipeline import Method, Preset

SMALL = Preset(collect_steps=60_000, collect_robots=64, episode_length=200, train_steps=20_000,
               baseline_steps=10_000, eval_episodes=32, eval_steps=120, cem=(1024, 256, 3, 32), horizon=12,
               learning_rate=5e-4, save_every=1000, cem_return="local_mean", cem_local_refit=True, mirror=True)
# The planner's warm start (``cem_warm_start``) is chosen for `medium` and `large` only: on 64 'val' paths
# (2026-12-05, an AVX-512 host; CAPs success over val seeds 0 and 1, without -> with) `medium` 56 -> 72 %,
# `large` 66 -> 78 %, but `small` 58 -> 38 %: with `small`'s weaker model the refined plan is a slow one
# (0.81 against 1.08 m/s) that still crashes.
# `medium` and `large` were measured with the elite mean ('mean') and CEM refitting to all its elites;
# 'local_mean' and ``cem_local_refit`` (chosen for `small` later) were then tried on `large` (2026-12-06, an
# AVX-512 host, the 64 'val' paths, its model retrained from scratch: 26 + 24 of 64 with this planner, the
# counts of 2026-12-05): local mean + local refit with the warm start 24 + 25, without it 21 + 24; the local
# mean alone with the warm start 29 + 23.  None adds the 4 paths set as the rule before the run, so `medium`
# and `large` keep the planner measured above.
MEDIUM = dataclasses.replace(SMALL, collect_steps=240_000, train_steps=80_000, baseline_steps=40_000,
                             save_every=5000, cem_warm_start=True, cem_return="mean", cem_local_refit=False)

PRESETS = {
    "ci": pipeline.ci_preset(mirror=True, cem_return="local_mean", cem_local_refit=True),  # the small preset's knobs
    # 32 evaluation paths (16 left 95 % intervals of +-20 points on success).  Chosen on the 'val' split
    # (32 paths, never 'eval'): CAPs 20k steps (10k: 56 % success there, 20k: 66 %, 30k: 69 %, too
    # little for its 4 minutes) and the planner returning the elite mean (the best sample: 47 %, both at
    # 10k).  Then (2026-12-05, an AVX-512 host, 64 'val' paths over val seeds 0 and 1, this preset's model):
    # the mean of the elites nearest the best ('local_mean') 67 % (23 + 20 of 64), the elite mean 58 %
    # (22 + 15), the best sample 48 % (15 + 16).  Every crash of the elite mean there was into the arena's
    # walls, foreseen steps ahead: facing a wall, turning left and turning right are both good plans and
    # their mean is the straight one (docs/forest.md).  A wider steering box (+-45 degrees in collection and
    # planning, for tighter turns) gave a worse model (held-out collision loss 0.153 against 0.102) and
    # 38 % against 72 % on val seed 0.
    # Then (2026-12-06, an AVX-512 host, the same 64 'val' paths and model): CEM refitting each iteration's
    # Gaussian to the half of its elites nearest the best one (``cem_local_refit``), so that the search
    # follows one mode instead of sampling between two, 77 % (26 + 23 of 64) against 67 % (23 + 20); no
    # crash 77 % against 67 %.  Also tried there and not better: the learning rate decayed by a cosine
    # over the 20k steps (``lr_decay``) from 5e-4, 67 % (23 + 20; held-out collision loss 0.099 against
    # 0.102), and from 1e-3, 59 % (20 + 18; 0.115).  With the local refit, 64 elites instead of 32 (so the
    # refit's 32 points span all 24 plan dimensions): 61 % (20 + 19), 2026-12-06.
    # The baselines keep 10k steps each: 20k (equal steps, measured once: docs/forest.md) takes the run to
    # ~34 minutes, over the `small` budget.  Also tried on 'val', and worse: twice the data (120k steps,
    # 56 %) and the paper's horizon H = 16 (38 %); a 4th CEM iteration (56 %), 16 elites (53 %), 512
    # samples (47 %); random actions held 4 steps on average in collection (59 %); over 64 'val' paths
    # 20k steps of on-policy CAPs data plus 10k more CAPs steps (62.5 %, the preset 64 %), episodes
    # starting anywhere in the arena (56 %), collision weight 200 or 50 instead of 500 (61 %, 55 %).
    # The planner's own noise there: two other planner keys gave 59 % and 56 % (key 0: 66 %).
    # Also on 128 'val' paths (2026-12-06, an AVX-512 host, evaluation only): collision risk below 0.05 per step
    # left free, -13 points; plans within 0.05 summed risk of the population's safest ranked by heading alone,
    # -10 points (-5.5 with the speed held near 1 m/s): fewer wall crashes, many more tree crashes (docs/forest.md).
    # Retrained with three training seeds (2026-12-06, 384 paired 'val' paths): episodes starting anywhere,
    # -4.9 points [-11.7, +1.8], as many wall crashes; random actions held 2 steps, -22 [-32, -12] on one seed.
    # Half of the training windows mirrored left-right (``mirror``; the forest has no handedness), chosen
    # on 64 'val' paths on one host (2026-12-04): success 45 % -> 55 %, held-out collision loss 0.141 ->
    # 0.105, at no cost in time.  The same settings without mirroring gave 64 % on 'val' on the host of
    # 2026-12-02: hosts differ by as much as settings do, so compare only runs of one host.  Measured
    # afterwards on 'eval' (docs/forest.md): 48 % mirrored vs 58 % unmirrored, 52 % each over 'val' and 'eval'.
    # Tried on 'val' (2026-12-06, an AVX-512 host; rule: a paired success interval above zero) and not adopted:
    # 8 frames of memory (env ``history=8``, retrained on the same dataset): 31 of 64 paths against 49, paired
    # -28 points [-42, -14], held-out collision loss 0.126 against 0.102; the pursuit point 3 or 4 m ahead
    # (env ``lookahead``, evaluation only): 83 of 128 each against 79, +3 points [-5, +12].
    # The 4 m pursuit point on three training seeds (2026-12-06, 384 paired paths): +5.7 points [-0.3, +11.7].
    # On four more training seeds, a host without AVX-512 (512 paired paths): +5.1 points [-0.2, +11.1]; kept at 2 m.
    # 6 m on those four models (2026-12-07, the same rule fixed before the run): +7.6 points [+1.4, +14.3] over 512
    # paired 'val' paths, nearer the path (-0.29 m): adopted, as ``EXPERIMENT.eval_env`` (evaluation only).
    # 8 m against 6 m on the two `medium` models (2026-12-07, the same rule fixed before the run, 128 paired 'val'
    # paths): +8 points [+1, +16], as near the path (+0.01 m): adopted.  Not measured on `small`'s 'val'.
    "small": SMALL,
    # Four times `small`'s data and CAPs steps (three data steps per CAPs step, as in `small`): far over the
    # 30-minute budget (CAPs alone ~50 minutes on the 2-core CPU, ~2 hours with the baselines), hence a preset
    # of its own.
    # Chosen on 'val' (64 paths, 2026-12-04, a host without AVX-512; CAPs success over val seeds 0 and 1):
    # `small` 55 %; this data at 40k CAPs steps 58 % (62.5, 53); at 80k steps 75 % (84, 66).
    # With the 6 m pursuit point of ``EXPERIMENT.eval_env`` (2026-12-07, a host without AVX-512, one training run,
    # measured after 6 m was adopted, so nothing chosen here): 'val' 88 % (2 m on the same model 67 %), then
    # 'eval' 81 % (52 of 64; 2 m 44 %).  A second training run: 'eval' 53 % (34 of 64); 67 % over both.
    # Most of that run's failures were side hits: obstacles 76-107 degrees off the heading, outside the camera's
    # 120 degrees, struck while turning back to the path after passing them (docs/forest.md).  Hence the 8 m point above:
    # 'eval' 83 % and 67 % with these two runs, 89 % with a third (trained after the choice); 80 % over the three.
    "medium": MEDIUM,
    # `medium`'s data (the same dataset: same collection settings and seed) with twice its CAPs steps; the
    # baselines keep `medium`'s 40k.  The learning rate is constant and the batch keys live in the train
    # state, so this equals `medium`'s run continued from its 80k checkpoint (how it was measured).  Chosen
    # on 'val' (64 paths, 2026-12-05, an AVX-512 host; CAPs success over val seeds 0 and 1, held-out
    # collision loss): 80k 56 % (0.087), 120k 56 % (0.072), 160k 66 % (0.064); 240k 69 % (0.064) is within
    # the planner's noise with the loss flat, so not worth 26 more minutes.  CAPs alone ~52 minutes.
    "large": dataclasses.replace(MEDIUM, train_steps=160_000),
    "paper": Preset(collect_steps=800_000, collect_robots=256, episode_length=400, train_steps=360_000,
                    baseline_steps=360_000, eval_episodes=48, eval_steps=160, cem=(4096, 1024, 4, 128), horizon=16,
                    save_every=10_000, mirror=True),
}

BASELINE_REWARD = dict(weights={"collision": 500.0, "heading_cos": 1.0, "speed_sq": 1.0}, goal_speed=2.0)

EXPERIMENT = pipeline.Experiment(
    name="forest",
    env_name="forest",
    env_overrides={},
    # The goal heading points at the path 8 m ahead of the car, not 2 m (chosen on 'val' in steps 2 -> 6 -> 8 m, see
    # PRESETS): a gentler return to the path after going round an obstacle, which the car has passed out of its
    # camera's view.  Random collection never reads it, so only evaluation changes.
    eval_env={"lookahead": 8.0},
    cues=(cues.COLLISION, cues.HEADING, cues.SPEED),
    learned_cues=(),
    baseline_config=baselines.BaselineConfig.forest,
    methods=(
        Method("caps", "caps", {"collision": 500.0, "heading_cos": 1.0},
               description="the paper's forest reward 500 (1 - c) + cos(h - h_goal) - 1"),
        Method("gc_dql", "gc_dql", **BASELINE_REWARD,
               description="one Q on -500 on a crash, else cos(h - h_goal) - 1 - ((v - 2) / 2)^2"),
        Method("gc_dql_sep", "gc_dql_sep", **BASELINE_REWARD,
               description="one head per sub-reward, combined with the same weights"),
        Method("caps_2ms", "caps", {"collision": 500.0, "heading_cos": 1.0, "speed": 1.0}, goal_speed=2.0, novel=True,
               description="novel reward (Q1): the same model follows the path at a goal speed of 2 m/s"),
        Method("caps_path", "caps", {"collision": 500.0, "heading_cos": 1.0, "path": 1.0}, novel=True,
               description="novel reward (Q1): minus the distance (m) from the path of the positions "
                           "dead-reckoned from the predicted speed and heading"),
    ),
    episode_metrics=None,  # set below
    columns=(("success_rate", "success", "rate"), ("success_drivable", "success, drivable paths", "rate"),
             ("path_distance_mean", "distance from path (m)", "number"),
             ("progress", "path covered", "rate"), ("no_crash_rate", "no crash", "rate"),
             ("speed_mean", "mean speed (m/s)", "number")),
    paper={"caps": {"success_rate": 0.75, "path_distance_mean": 2.02},
           "gc_dql": {"success_rate": 0.0, "path_distance_mean": 5.01},
           "gc_dql_sep": {"success_rate": 0.083, "path_distance_mean": 6.03}},
    primary_metric="success_rate",
    notes=("Paper numbers: CAPs, GC-DQL and GC-DQL-sep in the paper's Panda3D forest (caps-algorithm.md section 10).",),
)


def episode_metrics(traj, env) -> dict:
    crash = pipeline.final(traj, "crash") > 0.5
    done = np.asarray(traj.done)[:, -1]
    finished = done & ~crash
    return {
        "success_rate": finished.astype(np.float32),
        "path_distance_mean": pipeline.final(traj, "mean_path_distance"),
        "progress": pipeline.final(traj, "progress"),
        "no_crash_rate": (~crash).astype(np.float32),
        "speed_mean": pipeline.episode_mean(traj, "speed"),
    }


def task_metrics(tasks, env, per_episode: dict) -> dict:
    """Success on the paths whose sharpest bend the car can drive, beside the paper's success on all of them.

    The evaluation sinusoids (amplitude 1-3 m, wavelength 8-16 m) can bend with a radius down to ~0.5 m, and
    nearly half of them (62 of 128 'val', 29 of 64 'eval' paths) bend more tightly than the car turns at the plan box's steering limit (1.80 m).  On those
    the car must leave the path, and the paths end 3 m from a wall.  The paper's success counts every path and
    stays the primary metric; ``success_drivable`` is the same per-episode success with the other paths left
    out (NaN, which the intervals skip), so the table shows how much of the shortfall the tight bends make.
    """
    bend = np.asarray(jax.vmap(common.sharpest_bend)(tasks.path))
    drivable = bend >= env.config.car.turning_radius(env.config.plan_steer_deg)
    return {"sharpest_bend_m": bend,
            "success_drivable": np.where(drivable, per_episode["success_rate"], np.nan).astype(np.float32)}


EXPERIMENT = pipeline.dataclasses.replace(EXPERIMENT, episode_metrics=episode_metrics, task_metrics=task_metrics)


def main(cfg: pipeline.RunConfig) -> dict:
    return pipeline.run(EXPERIMENT, PRESETS, cfg)


if __name__ == "__main__":
    pipeline.cli(main, __doc__)
