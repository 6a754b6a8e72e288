"""The paper's Q-learning baselines on the CAPs trunk: DQL, GC-DQL and GC-DQL-sep (caps-algorithm.md section 7).

The Q-network *is* a ``CAPsModel`` with horizon 1 whose "cues" are Q heads, so the CNN, the vector MLP,
the action embedding, the MI-LSTM step and the dense heads are the same code as CAPs, trained with the
same optimiser (``training.make_optimizer``) and batch size.  Goal-conditioned variants append the goal
(goal speed, goal heading x, y) to every frame of the vector observation: the model's vector box
normalises the goal speed by ``goal_speed_scale`` (the authors' speed / 30).

* **DQL**: one Q head on a fixed reward (collision plus speed); no goal input; gamma 0.99.  Used as a
  data-collection policy too (``baseline_policy`` with ``small_cem``, inside ``collect.exploration_policy``).
* **GC-DQL**: one Q head on the combined reward ``collision_reward`` on a crash, else
  ``sum_k w_k * phi_k`` over ``reward_terms``; goals are inputs; hindsight goals in training.  DQL and
  GC-DQL learn Q of that reward times ``reward_scaling`` (the forest and CARLA variants: one over the crash
  penalty; the greedy action is unchanged): at the paper's scale the Q-network died within 1,000 steps.
* **GC-DQL-sep**: one head per sub-reward: ``collision`` (sigmoid, cross-entropy on the bootstrapped
  probability ``c' + gamma (1 - d) Q'_coll``, which stays in [0, 1] because a crash is terminal) and one
  linear head per term of ``reward_terms`` (0.5 squared error).  At action selection the heads are
  combined with the task's ``RewardSpec`` weights, term by term:
  ``w_collision * (1 - Q_collision) + sum_k w_k * Q_k``; ``w_collision`` multiplies the ``collision``
  term (1 - c) exactly as in CAPs, so one ``RewardSpec`` drives CAPs and GC-DQL-sep alike.

Sub-rewards are the reward library's own terms (``reward.TERMS``: ``speed``, ``speed_sq``,
``heading_cos``, ``heading_angle``, ``lane``, ``door``, ``steer``, ``action``) evaluated on the recorded
signals of observation t+1 and the goals, so a baseline's reward and CAPs' are one definition.

Targets (double-Q style, both variants): 100 uniform actions at s_{t+1} from the plan box (random
shooting through ``planner.cem_search``), the argmax under the method's selection value with the online
network, evaluated by the target network; ``y = r + gamma (1 - d_{t+1}) Q_target``.  The goal at t is
reused at t+1.  The target network is a hard copy every ``target_every`` loop steps: gradient steps
offline, env steps online (the paper: 5k env steps = 20k gradient steps).

**Where the authors' code differs from the paper, and what we follow** (section 7):
* GC-DQL-sep's combination: the code uses ``100 (1 - Q_coll) + Q_speed + 5 Q_lane + 5 Q_head``; the paper
  says "the same coefficients as GC-DQL".  We follow the paper (and the issue): the task's weights.
* GC-DQL-sep's speed head: the code does not bootstrap it and its error is not normalised
  (``(1 - d) gamma (-(v_g - v)^2)``); the paper describes one Q-function per sub-reward.  We follow the
  paper (every head bootstraps, the speed term is the library's); ``no_bootstrap=('speed_sq',)``
  reproduces the missing bootstrap (not the extra ``gamma (1 - d)`` factor).
* The RC-car GC-DQL reward's ``(1 - door_frac)`` rewards *not* seeing doors (probably a typo); the
  ``halls`` preset rewards doors (``+door``), as CAPs' RC-car reward does.
* Hindsight goals are used offline, as in the authors' code (they trained GC-DQL offline); online
  training uses the goal the robot acted on (the final position is unknown while the episode runs).
* ``d`` is the dataset's terminal flag (crash or end of episode), as the authors'; online, only a
  crash stops the bootstrap, a time limit does not.
"""
from capsjax.baselines.agent import (GOAL_KEYS, KINDS, SIGNAL_CUES, SUB_REWARDS, BaselineAgent, BaselineConfig,
                                     BaselineState, Transition, baseline_policy, checkpointer, compute_targets,
                                     double_q_values, fit_offline, head_rewards, hindsight_heading, init_state,
                                     make_offline_train, make_train_step, q_loss, selection_cem, small_cem,
                                     sync_target, td_targets, transitions_from_batch)
from capsjax.baselines.online import OnlineState, OnlineTrainer, make_online_train

__all__ = [
    "GOAL_KEYS", "KINDS", "SIGNAL_CUES", "SUB_REWARDS", "BaselineAgent", "BaselineConfig", "BaselineState",
    "OnlineState", "OnlineTrainer", "Transition", "baseline_policy", "checkpointer", "compute_targets",
    "double_q_values", "fit_offline", "head_rewards", "hindsight_heading", "init_state", "make_offline_train",
    "make_online_train", "make_train_step", "q_loss", "selection_cem", "small_cem", "sync_target", "td_targets",
    "transitions_from_batch",
]
