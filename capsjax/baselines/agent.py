"""Config, Q-network, targets, losses, offline training, the policy and checkpoints of the baselines
(see the package docstring)."""
from __future__ import annotations

import dataclasses
import functools
import logging
import types
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from capsjax import checkpoint as checkpoint_lib
from capsjax import cues as cues_lib
from capsjax import losses, mpc, planner, training
from capsjax import reward as reward_lib
from capsjax.model import CAPsModel, ModelConfig

log = logging.getLogger(__name__)

KINDS = ("dql", "gc_dql", "gc_dql_sep")
GOAL_KEYS = ("goal_speed", "goal_heading_x", "goal_heading_y")
# The baselines' goals are a speed and a heading (GOAL_KEYS): a term scored against a goal path would need
# the path in their input, so "path" is no sub-reward of theirs.
SUB_REWARDS = tuple(n for n in reward_lib.TERM_NAMES if n not in ("collision", "path"))
# Signals the sub-reward terms read, by the cue names the reward library expects.
SIGNAL_CUES = ("collision", "speed", "heading", "lane_seen", "lane_diff", "door_frac")


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
    """A baseline as data: its kind, discount, target-network schedule and training reward."""

    kind: str = "gc_dql"
    gamma: float = 0.95
    target_every: int = 5000  # loop steps between hard target copies (gradient steps offline, env steps online)
    target_samples: int = 100  # uniform actions for the target's max
    collision_reward: float = -1000.0  # reward of a crash step (DQL / GC-DQL); -w_collision for GC-DQL-sep training
    reward_terms: tuple[tuple[str, float], ...] = (("speed", 1.0), ("lane", 10.0), ("heading_angle", 5.0))
    goal_speed: float = 7.0  # DQL's fixed goal speed, and the training goal when the data records none
    goal_speed_scale: float = 30.0  # the goal-speed input is goal_speed / goal_speed_scale
    hindsight: bool = True  # offline: goal heading from the window's pose to the episode's final position
    no_bootstrap: tuple[str, ...] = ()  # GC-DQL-sep heads trained on the immediate sub-reward only
    # DQL / GC-DQL learn Q of ``reward_scaling`` x the reward.  A positive factor leaves the greedy action
    # unchanged; at the paper's scale (-500 or -1000 on a crash) the squared TD error of the first steps
    # killed every unit of the Q-network within 1,000 steps (Q constant over actions and observations,
    # README "Baselines"), so the forest and CARLA variants learn in units of the crash penalty.
    reward_scaling: float = 1.0

    def __post_init__(self):
        object.__setattr__(self, "reward_terms", tuple((str(n), float(w)) for n, w in self.reward_terms))
        object.__setattr__(self, "no_bootstrap", tuple(self.no_bootstrap))
        if self.kind not in KINDS:
            raise ValueError(f"BaselineConfig.kind must be one of {KINDS}, got {self.kind!r}")
        if not 0.0 <= self.gamma < 1.0:
            raise ValueError(f"BaselineConfig.gamma must be in [0, 1), got {self.gamma}")
        for name in ("target_every", "target_samples"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v <= 0:
                raise ValueError(f"BaselineConfig.{name} must be a positive int, got {v!r}")
        names = [n for n, _ in self.reward_terms]
        bad = sorted(set(names) - set(SUB_REWARDS))
        if bad or len(set(names)) != len(names):
            raise ValueError(f"BaselineConfig.reward_terms: names must be distinct sub-rewards of {SUB_REWARDS}, got {names}")
        if not all(np.isfinite([w for _, w in self.reward_terms] + [self.collision_reward, self.goal_speed])):
            raise ValueError("BaselineConfig.reward_terms weights, collision_reward and goal_speed must be finite")
        if not (np.isfinite(self.reward_scaling) and self.reward_scaling > 0):
            raise ValueError(f"BaselineConfig.reward_scaling must be a positive finite number, got {self.reward_scaling!r}")
        if self.kind == "gc_dql_sep" and self.reward_scaling != 1.0:
            raise ValueError("BaselineConfig.reward_scaling must be 1.0 for gc_dql_sep: its heads (a crash probability "
                             f"and each sub-reward) are combined at selection in their own units, got {self.reward_scaling}")
        if not self.goal_speed_scale > 0:
            raise ValueError(f"BaselineConfig.goal_speed_scale must be positive, got {self.goal_speed_scale}")
        unknown = sorted(set(self.no_bootstrap) - set(self.head_names))
        if unknown:
            raise ValueError(f"BaselineConfig.no_bootstrap names {unknown}, not heads of {self.kind}: {self.head_names}")

    @property
    def goal_conditioned(self) -> bool:
        return self.kind != "dql"

    @property
    def sub_rewards(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.reward_terms)

    @property
    def head_names(self) -> tuple[str, ...]:
        return ("collision",) + self.sub_rewards if self.kind == "gc_dql_sep" else ("q",)

    # The paper's variants (caps-algorithm.md section 7) as data.
    @classmethod
    def carla(cls, kind: str) -> "BaselineConfig":
        scaling = {} if kind == "gc_dql_sep" else {"reward_scaling": 1e-3}  # Q in units of the crash penalty
        if kind == "dql":
            return cls(kind, gamma=0.99, collision_reward=-1000.0, reward_terms=(("speed", 1.0),), goal_speed=7.0,
                       **scaling)
        return cls(kind, gamma=0.95, collision_reward=-1000.0,
                   reward_terms=(("speed", 1.0), ("lane", 10.0), ("heading_angle", 5.0)), goal_speed=7.0, **scaling)

    @classmethod
    def forest(cls, kind: str) -> "BaselineConfig":
        scaling = {} if kind == "gc_dql_sep" else {"reward_scaling": 1.0 / 500.0}  # Q in units of the crash penalty
        if kind == "dql":
            return cls(kind, gamma=0.99, collision_reward=-500.0, reward_terms=(("speed_sq", 1.0),), goal_speed=2.0,
                       **scaling)
        return cls(kind, gamma=0.95, collision_reward=-500.0,
                   reward_terms=(("heading_cos", 1.0), ("speed_sq", 1.0)), goal_speed=2.0, **scaling)

    @classmethod
    def halls(cls, kind: str) -> "BaselineConfig":
        """RC car in the halls: speed is fixed, so no speed term; DQL is collision-only."""
        if kind == "dql":
            return cls(kind, gamma=0.99, collision_reward=-1.0, reward_terms=(), goal_speed=0.5)
        return cls(kind, gamma=0.95, collision_reward=-1.0,
                   reward_terms=(("heading_angle", 1.0), ("door", 1.0)), goal_speed=0.5)


def small_cem(plan_low, plan_high) -> planner.CEMConfig:
    """The authors' data-collection CEM for DQL: H = 1, 1024 uniform + 3 x 256 Gaussian, 32 elites."""
    return planner.CEMConfig(plan_low, plan_high, horizon=1, init_samples=1024, samples=256, elites=32, centred=False)


def selection_cem(plan_low, plan_high) -> planner.CEMConfig:
    """GC-DQL(-sep) action selection: the CAPs CEM of section 5.1 with H = 1."""
    return planner.CEMConfig.paper(plan_low, plan_high, horizon=1)


def _head_cue(name: str) -> cues_lib.Cue:
    if name == "collision":
        return cues_lib.Cue("collision", kind="binary", activation="sigmoid")
    return cues_lib.Cue(name, kind="scalar", activation="linear")


@dataclasses.dataclass(frozen=True)
class BaselineAgent:
    """Static, hashable: the Q-network definition, the baseline's config and the plan box."""

    model: CAPsModel
    config: BaselineConfig
    plan_low: tuple[float, ...]
    plan_high: tuple[float, ...]

    @classmethod
    def create(cls, trunk: ModelConfig, config: BaselineConfig, plan_low, plan_high) -> "BaselineAgent":
        """The Q-network from a CAPs ``ModelConfig`` (same layer sizes), with Q heads and horizon 1."""
        keys, low, high = trunk.vector_keys, trunk.vector_low, trunk.vector_high
        if config.goal_conditioned:
            s = config.goal_speed_scale
            keys, low, high = keys + GOAL_KEYS, low + (-s, -1.0, -1.0), high + (s, 1.0, 1.0)
        q_config = dataclasses.replace(trunk, vector_keys=keys, vector_low=low, vector_high=high, horizon=1,
                                       cues=tuple(_head_cue(n) for n in config.head_names))
        plan_low, plan_high = tuple(float(x) for x in plan_low), tuple(float(x) for x in plan_high)
        if len(plan_low) != trunk.action_dim or len(plan_high) != trunk.action_dim:
            raise ValueError(f"plan_low/plan_high must have {trunk.action_dim} entries (one per action), "
                             f"got {plan_low} / {plan_high}")
        return cls(CAPsModel(q_config), config, plan_low, plan_high)

    @property
    def target_cem(self) -> planner.CEMConfig:
        """The target's max: ``target_samples`` uniform actions, best taken (random shooting)."""
        n = self.config.target_samples
        return planner.CEMConfig(self.plan_low, self.plan_high, horizon=1, init_samples=n, samples=n,
                                 iterations=1, elites=1, optimizer="random", candidate_chunk=n)

    def with_goals(self, obs, goal_speed, goal_heading):
        """Goal features appended to every frame of the vector history (unchanged for DQL)."""
        if not self.config.goal_conditioned:
            return obs
        goal = jnp.concatenate([jnp.reshape(goal_speed, (1,)), jnp.reshape(goal_heading, (2,))]).astype(jnp.float32)
        vector = jnp.asarray(obs.vector, jnp.float32)
        return obs.replace(vector=jnp.concatenate([vector, jnp.broadcast_to(goal, vector.shape[:-1] + (3,))], -1))

    def q_values(self, params, carry, actions) -> dict:
        """``{head: f32[M]}`` for one-step candidates ``f32[M, 1, A]`` sharing one encoded observation."""
        return {k: v[..., 0] for k, v in self.model.rollout(params, carry, actions).items()}

    def selection_value(self, q: dict, weights) -> jax.Array:
        """The method's score of candidates: Q itself, or GC-DQL-sep's heads combined by term weights.

        ``weights`` is ``f32[K]`` over ``reward.TERM_NAMES`` (a ``RewardSpec``'s ``weights``)."""
        if self.config.kind != "gc_dql_sep":
            return q["q"]
        w = {name: weights[..., i] for i, name in enumerate(reward_lib.TERM_NAMES)}
        value = w["collision"] * (1.0 - q["collision"])
        for name in self.config.sub_rewards:
            value = value + w[name] * q[name]
        return value

    def training_spec(self) -> reward_lib.RewardSpec:
        """The training reward's weights as a ``RewardSpec`` (GC-DQL-sep's selection in its targets)."""
        signals = types.SimpleNamespace(cue_names=SIGNAL_CUES, action_low=self.model.action_low,
                                        action_high=self.model.action_high)
        return reward_lib.RewardSpec.from_terms(signals, goal_speed=self.config.goal_speed,
                                                collision=-self.config.collision_reward,
                                                **dict(self.config.reward_terms))


@struct.dataclass
class Transition:
    """B one-step transitions as the baselines train on them (leading batch axis)."""

    obs: Any  # Observation history ending at t
    action: jax.Array  # f32[B, A]
    next_obs: Any  # Observation history ending at t+1
    signals: dict  # name -> f32[B], of observation t+1
    done: jax.Array  # bool[B]: no bootstrap from t+1
    valid: jax.Array  # bool[B]: the transition exists (loss mask)
    goal_speed: jax.Array  # f32[B]
    goal_heading: jax.Array  # f32[B, 2]


def hindsight_heading(pose: jax.Array, final_xy: jax.Array) -> jax.Array:
    """Unit vector ``f32[..., 2]`` from the pose's (x, y) to the episode's final position (0 if there)."""
    delta = final_xy - pose[..., :2]
    norm = jnp.linalg.norm(delta, axis=-1, keepdims=True)
    return jnp.where(norm > 1e-3, delta / jnp.maximum(norm, 1e-3), 0.0)


def transitions_from_batch(agent: BaselineAgent, batch: losses.Batch) -> Transition:
    """The first step of each window of a ``losses.Batch`` (needs ``done`` and ``next_obs``; hindsight
    needs ``context['pose']`` and ``context['final_xy']``, otherwise ``context['goal_heading']``)."""
    cfg = agent.config
    for field in ("done", "next_obs"):
        if getattr(batch, field) is None:
            raise ValueError(f"batch.{field} is None; Q-learning needs it (use capsjax.data's window sampler)")
    context = batch.context or {}
    size = batch.actions.shape[0]
    goal_speed = jnp.broadcast_to(jnp.asarray(context.get("goal_speed", cfg.goal_speed), jnp.float32), (size,))
    if not cfg.goal_conditioned:
        goal_heading = jnp.zeros((size, 2), jnp.float32)
    elif cfg.hindsight:
        missing = [k for k in ("pose", "final_xy") if k not in context]
        if missing:
            raise ValueError(f"batch.context lacks {missing} (needed for hindsight goals); it has {sorted(context)}")
        goal_heading = hindsight_heading(context["pose"], context["final_xy"])
    elif "goal_heading" in context:
        goal_heading = jnp.asarray(context["goal_heading"], jnp.float32)
    else:
        raise ValueError(f"batch.context lacks 'goal_heading' (hindsight=False); it has {sorted(context)}")
    return Transition(obs=batch.obs, action=batch.actions[:, 0], next_obs=batch.next_obs,
                      signals={k: v[:, 0] for k, v in batch.signals.items()}, done=batch.done[:, 0],
                      valid=batch.valid[:, 0], goal_speed=goal_speed, goal_heading=goal_heading)


def _signals_as_preds(signals: dict) -> dict:
    """Recorded signals ``f32[B]`` in the reward library's prediction layout (``[B, 1]``, heading (cos, sin))."""
    preds = {k: v[:, None] for k, v in signals.items() if k in SIGNAL_CUES and k != "heading"}
    if "heading" in signals:
        preds["heading"] = jnp.stack([jnp.cos(signals["heading"]), jnp.sin(signals["heading"])], -1)[:, None]
    return preds


def head_rewards(agent: BaselineAgent, tr: Transition) -> dict:
    """Immediate reward of each Q head ``{head: f32[B]}`` from the signals at t+1, the action and goals."""
    cfg = agent.config
    if "collision" not in tr.signals:
        raise ValueError(f"transition signals lack 'collision'; they have {sorted(tr.signals)}")
    preds = _signals_as_preds(tr.signals)
    for name in cfg.sub_rewards:
        need = [c for c in next(t for t in reward_lib.TERMS if t.name == name).needs if c not in preds]
        if need:
            raise ValueError(f"sub-reward {name!r} needs signal(s) {need}; the data has {sorted(tr.signals)}")
    spec = agent.training_spec().replace(goal_speed=tr.goal_speed, goal_heading=tr.goal_heading)
    terms = reward_lib.term_values(preds, tr.action[:, None, :], spec)[..., 0]  # [B, K]
    sub = {name: terms[:, reward_lib.TERM_NAMES.index(name)] for name in cfg.sub_rewards}
    crash = (tr.signals["collision"] > 0.5).astype(jnp.float32)
    if cfg.kind == "gc_dql_sep":
        return {"collision": crash, **sub}
    shaped = sum((w * sub[n] for n, w in cfg.reward_terms), jnp.zeros_like(crash))
    return {"q": cfg.reward_scaling * (crash * cfg.collision_reward + (1.0 - crash) * shaped)}


def td_targets(rewards: dict, next_values: dict, done: jax.Array, gamma: float, no_bootstrap=()) -> dict:
    """``y_h = r_h + gamma (1 - d) Q'_h`` per head (``y_h = r_h`` for heads in ``no_bootstrap``)."""
    keep = gamma * (1.0 - done.astype(jnp.float32))
    return {h: r if h in no_bootstrap else r + keep * next_values[h] for h, r in rewards.items()}


def double_q_values(agent: BaselineAgent, q_online: Callable, q_target: Callable, next_obs, weights, key) -> dict:
    """Target-network values at the online network's best of ``target_samples`` uniform actions.

    ``q_online(obs, actions f32[M, 1, A]) -> {head: f32[M]}`` (likewise ``q_target``) for one observation;
    ``next_obs`` and ``weights`` (``f32[B, K]``, the selection weights) carry a leading batch axis."""
    cem = agent.target_cem

    def one(obs, w, k):
        best, _ = planner.cem_search(lambda seqs: agent.selection_value(q_online(obs, seqs), w), k,
                                     planner.init_plan_state(cem), cfg=cem)
        return {h: v[0] for h, v in q_target(obs, best[None]).items()}

    keys = jax.random.split(key, jax.tree.leaves(next_obs)[0].shape[0])
    return jax.vmap(one)(next_obs, weights, keys)


def compute_targets(agent: BaselineAgent, q_online: Callable, q_target: Callable, tr: Transition, key) -> dict:
    """Bootstrapped targets ``{head: f32[B]}`` of a batch of transitions (goals already on ``tr``)."""
    spec = agent.training_spec()
    next_obs = jax.vmap(agent.with_goals)(tr.next_obs, tr.goal_speed, tr.goal_heading)
    weights = jnp.broadcast_to(spec.weights, (tr.action.shape[0],) + spec.weights.shape)
    next_values = double_q_values(agent, q_online, q_target, next_obs, weights, key)
    return td_targets(head_rewards(agent, tr), next_values, tr.done, agent.config.gamma, agent.config.no_bootstrap)


def _q_fn(agent: BaselineAgent, params) -> Callable:
    return lambda obs, seqs: agent.q_values(params, agent.model.encode(params, obs), seqs)


def q_loss(agent: BaselineAgent, params, tr: Transition, targets: dict, l2_coeff: float):
    """Per-head losses (cross-entropy for collision, 0.5 squared error otherwise), masked means, plus L2."""
    model = agent.model
    obs = jax.vmap(agent.with_goals)(tr.obs, tr.goal_speed, tr.goal_heading)
    raw = jax.vmap(lambda o, a: model.rollout_raw(params, model.encode(params, o), a[None]))(obs, tr.action)
    mask = tr.valid.astype(jnp.float32)
    slices = model.config.head_slices()
    metrics, loss = {}, 0.0
    for cue in model.cues:
        target = jax.lax.stop_gradient(targets[cue.name])[:, None, None]
        per = cue.loss(raw[..., slices[cue.name]], target, jnp.zeros((cue.dim,)))[:, 0]
        metrics[f"loss/{cue.name}"] = head_loss = jnp.sum(per * mask) / jnp.maximum(jnp.sum(mask), 1.0)
        loss = loss + head_loss
    if l2_coeff:
        metrics["loss/l2"] = losses.l2_penalty(params, l2_coeff)
        loss = loss + metrics["loss/l2"]
    metrics["loss"] = loss
    return loss, metrics


@struct.dataclass
class BaselineState:
    params: dict
    target_params: dict
    opt_state: optax.OptState
    step: jax.Array  # i32[]: gradient steps attempted
    key: jax.Array
    bad_steps: jax.Array  # i32[]: non-finite steps skipped


def init_state(agent: BaselineAgent, train_cfg: training.TrainConfig, key) -> BaselineState:
    init_key, key = jax.random.split(key)
    params = agent.model.init(init_key)
    return BaselineState(params=params, target_params=params, opt_state=training.make_optimizer(train_cfg).init(params),
                         step=jnp.zeros((), jnp.int32), key=key, bad_steps=jnp.zeros((), jnp.int32))


def sync_target(state: BaselineState, before, after, every: int) -> BaselineState:
    """Hard-copy the online params into the target when the loop counter passes a multiple of ``every``."""
    copy = (after // every) > (before // every)
    target = jax.tree.map(lambda p, t: jnp.where(copy, p, t), state.params, state.target_params)
    return state.replace(target_params=target)


def make_train_step(agent: BaselineAgent, train_cfg: training.TrainConfig) -> Callable:
    """``step(state, transitions, key) -> (state, metrics)``: one gradient step (no target copy; the
    caller owns the loop counter).  A non-finite step is skipped, as in ``training.make_train_step``."""
    optimizer = training.make_optimizer(train_cfg)

    def step(state: BaselineState, tr: Transition, key):
        targets = compute_targets(agent, _q_fn(agent, state.params), _q_fn(agent, state.target_params), tr, key)
        grad_fn = jax.value_and_grad(lambda p: q_loss(agent, p, tr, targets, train_cfg.l2_coeff), has_aux=True)
        (loss, metrics), grads = grad_fn(state.params)
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        params = optax.apply_updates(state.params, updates)
        finite = jnp.isfinite(loss) & jnp.all(jnp.stack([jnp.all(jnp.isfinite(g)) for g in jax.tree.leaves(grads)]))
        keep = lambda new, old: jnp.where(finite, new, old)
        metrics["skipped"] = ~finite
        for h, y in targets.items():
            metrics[f"target/{h}"] = jnp.mean(y)
        return state.replace(params=jax.tree.map(keep, params, state.params),
                             opt_state=jax.tree.map(keep, opt_state, state.opt_state), step=state.step + 1,
                             bad_steps=state.bad_steps + (~finite).astype(jnp.int32)), metrics

    return step


def make_offline_train(agent: BaselineAgent, train_cfg: training.TrainConfig, sample_batch: Callable,
                       num_steps: int) -> Callable:
    """``train(state) -> (state, metrics[num_steps])``: jitted gradient steps on stored data
    (``training.repeat_steps``: one scan on accelerators, a host loop of jitted steps on CPU).

    ``sample_batch(key) -> losses.Batch`` (horizon >= 1, with ``done``/``next_obs``/``context``), e.g.
    ``sampler.batches(32)`` of ``capsjax.data.make_sampler`` (a pytree: its buffers reach the compiled
    step as arguments, ``training.ArraySplit``).  The target is copied every ``config.target_every``
    gradient steps."""
    if not isinstance(num_steps, int) or num_steps <= 0:
        raise ValueError(f"num_steps must be a positive int, got {num_steps!r}")
    step_fn = make_train_step(agent, train_cfg)
    arrays, split = training.ArraySplit.of(sample_batch)

    def body(state, arrays):
        key, k_batch, k_target = jax.random.split(state.key, 3)
        tr = transitions_from_batch(agent, split.rebuild(arrays)(k_batch))
        new, metrics = step_fn(state.replace(key=key), tr, k_target)
        return sync_target(new, state.step, new.step, agent.config.target_every), metrics

    return functools.partial(training.repeat_steps(body, num_steps), data=arrays)


def baseline_policy(agent: BaselineAgent, cem_cfg: planner.CEMConfig) -> mpc.Policy:
    """The baseline as an ``mpc.Policy``: CEM (horizon 1) over the Q-network's selection value.

    Goals come from the ``RewardSpec`` (``goal_speed``, ``goal_heading``) and GC-DQL-sep combines its
    heads with ``spec.weights``; both are traced, so a new task never recompiles."""
    if cem_cfg.horizon != 1:
        raise ValueError(f"CEMConfig.horizon must be 1 for a one-step Q-function, got {cem_cfg.horizon}")
    planner.check_compatible(agent.model, cem_cfg)

    def act(params, obs, spec, plan_state, key):
        carry = agent.model.encode(params, agent.with_goals(obs, spec.goal_speed, spec.goal_heading))
        score = lambda seqs: agent.selection_value(agent.q_values(params, carry, seqs), spec.weights)
        chosen, top = planner.cem_search(score, key, plan_state, cfg=cem_cfg)
        q = agent.q_values(params, carry, chosen[None])
        info = {"value": agent.selection_value(q, spec.weights)[0], "actions": chosen,
                "q": {h: v[0] for h, v in q.items()}, "elite_value": jnp.mean(top)}
        return chosen[0], planner.PlanState(previous=chosen, has_previous=jnp.ones((), bool)), info

    return mpc.Policy(act=act, init_state=functools.partial(planner.init_plan_state, cem_cfg))


# ------------------------------------------------------------------------------------------ checkpoints


def checkpointer(agent: BaselineAgent, train_cfg: training.TrainConfig, directory, *, metadata: dict | None = None,
                 **kwargs) -> checkpoint_lib.Checkpointer:
    """The CAPs orbax helper with this baseline's configs (and ``metadata``, as ``training.fit``'s) saved
    beside every step and checked on restore."""
    config = checkpoint_lib.training_config(agent.model, train_cfg, {
        "BaselineConfig": agent.config, "plan_low": agent.plan_low, "plan_high": agent.plan_high, **(metadata or {})})
    defaults = checkpoint_lib.training_defaults(agent.model, train_cfg,
                                                {"BaselineConfig": agent.config, **(metadata or {})})
    return checkpoint_lib.Checkpointer(directory, config=config, defaults=defaults, **kwargs)


def fit_offline(agent: BaselineAgent, train_cfg: training.TrainConfig, sample_batch: Callable, num_steps: int, *,
                key=None, state: BaselineState | None = None, ckpt_dir=None, save_every: int = 1000, keep: int = 3,
                metadata: dict | None = None, progress: bool | str = False):
    """Offline training to ``num_steps`` gradient steps in jitted chunks of up to ``save_every``, saved
    with orbax after each chunk and resumed from the latest checkpoint in ``ckpt_dir`` up to ``num_steps``
    (refused if it was written with other configs or ``metadata``, or trained past ``num_steps`` without
    that step saved: ``Checkpointer.resume``, as in ``training.fit``).  ``progress``: a tqdm bar of the steps,
    labelled when it is a string (``training.progress_bar``)."""
    for name, value in (("num_steps", num_steps), ("save_every", save_every)):
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise ValueError(f"fit_offline: {name} must be a positive int, got {value!r}")
    if state is None:
        state = init_state(agent, train_cfg, key if key is not None else jax.random.key(0))
    manager = (checkpointer(agent, train_cfg, ckpt_dir, metadata=metadata, save_every=save_every, keep=keep)
               if ckpt_dir else None)
    trains, metrics, bar = {}, {}, None
    try:
        if manager is not None:
            state, restored = manager.resume(state, num_steps, who="fit_offline")
            if restored is not None:
                log.info("resumed baseline from step %d in %s", restored, ckpt_dir)
        bar = training.progress_bar(progress, num_steps, int(state.step))
        while int(state.step) < num_steps:
            done = int(state.step)
            length = min(save_every - done % save_every, num_steps - done)
            if length not in trains:
                trains[length] = make_offline_train(agent, train_cfg, sample_batch, length)
            state, metrics = trains[length](state)
            if manager is not None:
                manager.save(int(state.step), state, force=int(state.step) == num_steps)
            if bar is not None:
                bar.update(length)
                bar.set_postfix(loss=float(metrics["loss"][-1]))
    finally:
        if bar is not None:
            bar.close()
        if manager is not None:
            manager.close()
    return state, metrics
