"""``python -m experiments.indoor``: the paper's RC-car experiment in our indoor halls (caps-algorithm.md 9.3, 10).

The car is RC-sized like the paper's (``envs.scenes.indoor.RC_CAR``: 0.5 x 0.3 m in 3 m hallways).
Data: uniform random steering at the fixed 0.5 m/s (the paper drove with collision avoidance) around the
loop counter-clockwise, in training door layouts.  Cues: collision, heading, and door_frac labelled by the
learned segmenter (trained on the 0.2 % of frames stored with their true semantic map; Q3).  Evaluation:
the loop clockwise with heading commands two seconds before each intersection, in door layouts from the
disjoint evaluation stream, under three rewards of one trained model -- collision; collision + heading;
collision + heading + door (the paper's RC-car reward ``(1 - c) [1 - 0.1 |h - h_goal| / pi + 0.05 door]
- 0.01 |a|^2``) -- beside DQL (collision only) and GC-DQL.  Metrics: % route traversed, % no crash, %
successful turns, mean % of the image that is door.  The paper's reward once more with its door weight
raised to ``DOOR_WEIGHT`` and to ``DOOR_WEIGHT_LOW``, and collision + heading with the heading weight raised
to ``HEADING_WEIGHT`` (all chosen on the 'val' split, on two hosts whose models differ).  Beyond the paper
(Q1): the same model told to *avoid* looking at doors (door weight ``-DOOR_WEIGHT``).

Every preset mirrors half of the training windows left-right (``Preset.mirror``): the data go around the
loop one way only, so without it right turns are rare in training while the evaluation makes them at every
corner.  ``small`` also average-pools the 96x128 frames by 2 before the CNN (``image_pool``), which cuts
a training step from ~100 to ~40 ms on the 2-core CPU and keeps the run within its 30-minute budget;
``paper`` keeps the full frames.  ``small_onpolicy`` adds the pipeline's on-policy stage, driven by the
collision + heading reward on the training loop (closer to the paper's data, which came from CAPs driving).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from capsjax import baselines, cues
from experiments import labellers as labeller_experiment
from experiments import pipeline
from experiments.pipeline import Method, Preset

# The elite mean chosen on the 'val' split (8 clockwise loops, never 'eval'): paper reward no crash
# 62 %, the best sample 38 %.  The forest's CEM local refit (``cem_local_refit``) was tried here at
# evaluation only (2026-12-06, an AVX-512 host, 16 'val' loops; loops without a crash over collision +
# heading, the paper reward and door DOOR_WEIGHT): 33 of 48 against 38 of 48 without it, so not kept.
SMALL = Preset(collect_steps=60_000, collect_robots=64, episode_length=300, train_steps=6000,
               baseline_steps=3000, eval_episodes=8, eval_steps=640, cem=(512, 128, 3, 32), horizon=12,
               learning_rate=5e-4, labelled_fraction=0.005, segmenter_steps=400, save_every=1000,
               image_pool=2, mirror=True, cem_return="mean")

PRESETS = {
    "ci": pipeline.ci_preset(image_pool=2, mirror=True, cem_return="mean"),  # exercises the small preset's knobs
    "small": SMALL,
    # `small` plus the on-policy stage driven by the collision + heading reward on the training loop
    # (counter-clockwise): the car's own corner turns, and its crashes on them, enter the data.  Chosen on
    # 'val' (16 loops, one host without AVX-512, docs/indoor.md): paper reward no crash 0 % (`small`), 0 % (on-policy
    # on the collision reward), 44 % (this); 12k CAPs steps in all, as `small` at 12k (also 0 %).
    # The planner's local mean ('local_mean', which never averages a left and a right turn into a straight
    # one) was tried here and not kept (an AVX-512 host, 2026-12-05, docs/indoor.md).  At evaluation only, with this
    # preset's model, it looked better on 16 'val' loops (loops without a crash, elite mean -> local mean:
    # caps_heading 15 -> 16, caps_heading_door_x4 14 -> 15).  But the preset's on-policy stage plans with the
    # same return mode, so adopting it retrains the model.  The retrained preset on val seed 0 gave
    # caps_heading 3 of 8 (the elite-mean preset: 7 of 8), so it keeps the elite mean.
    "small_onpolicy": dataclasses.replace(SMALL, onpolicy_steps=16_000, onpolicy_train_steps=6000,
                                          onpolicy_reward="caps_heading"),
    "paper": Preset(collect_steps=158_400, collect_robots=256, episode_length=600, train_steps=360_000,
                    baseline_steps=360_000, eval_episodes=16, eval_steps=640, cem=(4096, 1024, 4, 128), horizon=12,
                    labelled_fraction=0.002, segmenter_steps=5000, save_every=10_000, mirror=True),
}

RC_CAR = {"collision": 1.0, "heading_angle": 0.1, "action": 0.01}
GATED = ("heading_angle", "door")
# The paper's door weight 0.05 on a door fraction of ~0.04 is worth ~0.002 per step, too little to move the
# car (door share +3 % over the heading reward on the 'val' split).  Chosen on 'val' (8 loops, never 'eval';
# door weight: door share, route, no crash): 0 4.3 %, 63 %, 25 %; 0.05 4.4 %, 78 %, 62 %; 0.2 7.3 %, 73 %,
# 38 %; 0.4 7.8 %, 48 %, 12 %; 1.0 8.2 %, 58 %, 25 %: 0.2 raises the door share most for the least route.
# Re-checked with the current model on 16 'val' loops: no door term 4.0 %, 94 %, 81 %; 0.05 3.9 %, 97 %,
# 94 %; 0.1 3.9 %, 93 %, 81 %; 0.2 5.2 % (+31 %), 98 %, 94 %: 0.2 stays.
# On an AVX-512 host with the small_onpolicy model (16 'val' loops; door share vs no door term, no crash):
# 0.05 +7 %, 14/16; 0.1 +13 %, 16/16; 0.2 +65 %, 14/16 (none: 15/16): 0.2 stays (docs/indoor.md).
DOOR_WEIGHT = 0.2
# On an AVX-512 host door 0.2 crashes more (2026-12-06, the small_onpolicy model, 32 'val' loops: 24 of 32
# without a crash).  Chosen there on 'val' with the rule set before the run (at least 26 of 32 without a crash
# and the door share at least +17 % over collision + heading): 0.15 gave 29 of 32 and +54 % [+44, +67]
# (docs/indoor.md).  Hosts differ, so both weights are evaluated.
DOOR_WEIGHT_LOW = 0.15
# The paper's heading weight 0.1 is worth at most 0.1 per step between the commanded corridor and the
# opposite one, less than the collision model's doubts about a turn it cannot yet see round: on the
# clockwise loop the `small_onpolicy` car often took the open dead end on the left instead of the
# commanded right turn.  Chosen on 'val' (16 loops, the small_onpolicy model, a host without AVX-512;
# heading weight: no crash, route): 0.1 7/16, 56 %; 0.3 15/16, 97 %; 1.0 13/16, 87 %.  With the door
# weight DOOR_WEIGHT on top (caps_heading_x3_door_x4): 14/16, 96 %, door share 4.4 % vs 3.7 % (+17 %);
# at the paper's heading weight the same door weight gave 4/16, 49 %, 5.3 %.
HEADING_WEIGHT = 0.3

EXPERIMENT = pipeline.Experiment(
    name="indoor",
    env_name="indoor",
    env_overrides={},
    cues=(cues.COLLISION, cues.HEADING, cues.DOOR_FRAC),
    learned_cues=("door_frac",),
    baseline_config=baselines.BaselineConfig.halls,
    methods=(
        Method("caps_collision", "caps", {"collision": 1.0}, description="CAPs, reward: no collision"),
        Method("caps_heading", "caps", RC_CAR, gated=GATED, description="CAPs, reward: collision + heading"),
        Method("caps_heading_x3", "caps", dict(RC_CAR, heading_angle=HEADING_WEIGHT), gated=GATED,
               description=f"CAPs, reward: collision + heading with the heading weight {HEADING_WEIGHT} (3x the "
                           "paper's), chosen on the val split"),
        Method("caps_heading_door", "caps", dict(RC_CAR, door=0.05), gated=GATED,
               description="CAPs, the paper's RC-car reward: collision + heading + door"),
        Method("caps_heading_door_x4", "caps", dict(RC_CAR, door=DOOR_WEIGHT), gated=GATED,
               description=f"CAPs, the paper's RC-car reward with the door weight {DOOR_WEIGHT} (4x the paper's), "
                           "chosen on the val split"),
        Method("caps_heading_door_x3", "caps", dict(RC_CAR, door=DOOR_WEIGHT_LOW), gated=GATED,
               description=f"CAPs, the paper's RC-car reward with the door weight {DOOR_WEIGHT_LOW} (3x the paper's), "
                           "chosen on an AVX-512 host's val split, where the door weight "
                           f"{DOOR_WEIGHT} crashes more"),
        Method("caps_heading_x3_door_x4", "caps", dict(RC_CAR, heading_angle=HEADING_WEIGHT, door=DOOR_WEIGHT),
               gated=GATED, description=f"CAPs, the paper's RC-car reward with the heading weight {HEADING_WEIGHT} and "
                                        f"the door weight {DOOR_WEIGHT}: compare its door share with caps_heading_x3"),
        Method("dql", "dql", {"collision": 1.0}, description="DQL trained on collision only"),
        Method("gc_dql", "gc_dql", dict(RC_CAR, door=0.05), gated=GATED, goal_speed=0.5,
               description="goal-conditioned Q on collision + heading + door"),
        Method("caps_avoid_doors", "caps", dict(RC_CAR, door=-DOOR_WEIGHT), gated=GATED, novel=True,
               description="novel reward (Q1): the same model told to look away from doors"),
    ),
    episode_metrics=None,
    columns=(("route_fraction", "route traversed", "rate"), ("no_crash_rate", "no crash", "rate"),
             ("turn_success_rate", "successful turns", "rate"), ("door_seen_mean", "door seen (% of image)", "pct")),
    paper={"caps_heading_door": {"route_fraction": 0.98, "no_crash_rate": 0.80, "turn_success_rate": 0.80,
                                 "door_seen_mean": 8.1},
           "caps_heading": {"door_seen_mean": 6.9}},
    primary_metric="route_fraction",
    notes=("Paper numbers: the real RC car in Cory Hall (caps-algorithm.md section 10).",),
    segmenter=lambda env: labeller_experiment.segmenter_config("indoor", env),
)


def episode_metrics(traj, env) -> dict:
    turns, total = pipeline.final(traj, "turns"), pipeline.final(traj, "turns_total")
    return {
        "route_fraction": pipeline.final(traj, "route_fraction"),
        "no_crash_rate": (pipeline.final(traj, "crash") < 0.5).astype(np.float32),
        # Episodes that reached no intersection have no turn to score (NaN, left out of the mean).
        "turn_success_rate": np.where(total > 0, turns / np.maximum(total, 1), np.nan),
        "door_seen_mean": 100.0 * pipeline.final(traj, "door_fraction"),
    }


EXPERIMENT = pipeline.dataclasses.replace(EXPERIMENT, episode_metrics=episode_metrics)


def main(cfg: pipeline.RunConfig) -> dict:
    return pipeline.run(EXPERIMENT, PRESETS, cfg)


if __name__ == "__main__":
    pipeline.cli(main, __doc__)
