"""capsjax worlds: the env API (``envs.base``), the registry ``envs.make(name, **overrides)``."""
from envs.base import Env, EnvSpec, EnvState, Observation  # noqa: F401
