"""capsjax: Composable Action-Conditioned Predictors in JAX.

The public API in one place::

    model = capsjax.CAPsModel(capsjax.ModelConfig.from_env_spec(env.spec))
    params = model.init(key)
    spec = capsjax.RewardSpec.from_terms(model, collision=500, heading_cos=1, goal_heading=(1, 0))
    cfg = capsjax.CEMConfig(env.spec.plan_low, env.spec.plan_high)
    action, plan_state, info = capsjax.plan(model, params, obs, spec, capsjax.init_plan_state(cfg), key, cfg=cfg)
"""
from capsjax import baselines, checkpoint, collect, cues, data, labellers, mpc, sharding
from capsjax.cues import Cue
from capsjax.ensemble import Ensemble
from capsjax.losses import Batch, total_loss
from capsjax.model import CAPsModel, Carry, ModelConfig
from capsjax.planner import CEMConfig, PlanState, init_plan_state, plan_batch
from capsjax.planner import jit_plan as plan
from capsjax.planner import jit_plan_batch
from capsjax.reward import RewardSpec
from capsjax.training import TrainConfig, TrainState, init_train_state, make_train, make_train_step

__all__ = [
    "Batch", "CAPsModel", "Ensemble", "baselines", "checkpoint", "collect", "data", "labellers", "mpc", "sharding", "CEMConfig", "Carry", "Cue", "ModelConfig", "PlanState", "RewardSpec",
    "TrainConfig", "TrainState", "cues", "init_plan_state", "init_train_state", "jit_plan_batch",
    "make_train", "make_train_step", "plan", "plan_batch", "total_loss",
]
