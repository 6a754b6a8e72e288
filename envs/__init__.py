"""capsjax worlds: the env API (``envs.base``), the registry ``envs.make(name, **overrides)``.

``SCENES`` are the MJX worlds (forest, city, indoor halls); ``ALL_ENVS`` adds ``fast``, the tiny analytic
world for tests.  ``make`` returns the bare single-robot env; wrap it with ``envs.base.VmapWrapper``,
``EpisodeWrapper`` and ``AutoResetWrapper`` as needed.  Overrides replace fields of the env's typed
default config (``envs.default_config(name)``), e.g. ``envs.make("forest", arena_half=25.0)``.
Modules are imported on first use, so importing ``envs`` stays cheap.
"""
from __future__ import annotations

import dataclasses
import importlib

from envs.base import Env, EnvSpec, EnvState, Observation  # noqa: F401

# name -> (module, env class, config class)
_REGISTRY = {
    "forest": ("envs.scenes.forest", "ForestEnv", "ForestConfig"),
    "city": ("envs.scenes.city", "CityEnv", "CityConfig"),
    "indoor": ("envs.scenes.indoor", "IndoorEnv", "IndoorConfig"),
    "fast": ("envs.fast", "FastEnv", "FastConfig"),
}
SCENES = ("forest", "city", "indoor")
ALL_ENVS = SCENES + ("fast",)


def _lookup(name: str):
    if name not in _REGISTRY:
        raise ValueError(f"unknown env {name!r}; valid names: {', '.join(ALL_ENVS)}")
    module, env_cls, cfg_cls = _REGISTRY[name]
    mod = importlib.import_module(module)
    return getattr(mod, env_cls), getattr(mod, cfg_cls)


def default_config(name: str):
    """The typed default config of env ``name`` (a frozen dataclass)."""
    return _lookup(name)[1]()


def make(name: str, **overrides) -> Env:
    """The env ``name`` with its default config, fields replaced by ``overrides``."""
    env_cls, cfg_cls = _lookup(name)
    fields = {f.name for f in dataclasses.fields(cfg_cls)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"unknown config field(s) {unknown} for env {name!r}; valid: {', '.join(sorted(fields))}")
    return env_cls(dataclasses.replace(cfg_cls(), **overrides))
