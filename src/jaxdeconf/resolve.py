"""From names to a validated Config: an env's preset, the algorithms' own sections from the registry, then the user's
dotted overrides. The one module that knows the config schema, the algorithm registry and the environments at once."""

from __future__ import annotations

from typing import Any

from jaxdeconf import algos
from jaxdeconf import config as cfg
from jaxdeconf.errors import ConfigError

#: Short names the CLI accepts (the paper calls AntGoal "ant").
ENV_ALIASES = {"ant": "ant_goal", "cheetah": "half_cheetah"}


def env_presets(env: str) -> dict[str, dict[str, Any]]:
    """The presets an env declares (``Environment.presets``); ConfigError for an unknown env or one with none."""
    from jaxdeconf.envs import resolve

    try:
        presets = getattr(resolve(env)(), "presets", {})
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if not presets:
        raise ConfigError(f"env {env!r} declares no presets; give its class a `presets` dict, e.g. "
                          "{'cpu': {'train.iterations': 40}} (see examples/cartpole.py)")
    return presets


def default_config(env: str, algorithms: tuple[str, ...], seeds: int) -> cfg.Config:
    """The dataclass defaults for ``env``, with a section for every registered algorithm that declares one."""
    settings = {name: section() for name, section in algos.settings_sections().items()}
    return cfg.Config(env=env, algos=algorithms, seeds=seeds, settings=settings)


def check_algos(algorithms: tuple[str, ...]) -> None:
    """ConfigError unless ``algorithms`` are registered names, each given once."""
    allowed = ", ".join(algos.names())
    if not algorithms:
        raise ConfigError("no algorithm given; allowed: " + allowed)
    for i, name in enumerate(algorithms):
        if name not in algos.REGISTRY:
            raise ConfigError(f"unknown algorithm {name!r}; allowed: {allowed}")
        if name in algorithms[:i]:
            raise ConfigError(f"algorithm {name!r} is given twice; name each algorithm once")


def build(env: str, preset: str, algorithms: tuple[str, ...], seeds: int, overrides: dict[str, Any]) -> cfg.Config:
    """Resolve a preset plus overrides into a validated Config."""
    env = ENV_ALIASES.get(env, env)
    check_algos(algorithms)
    presets = env_presets(env)
    if preset not in presets:
        raise ConfigError(f"unknown preset {preset!r} for env {env!r}; allowed: {', '.join(presets)}")
    config = cfg.apply_overrides(default_config(env, algorithms, seeds), presets[preset])
    config = cfg.apply_overrides(config, overrides)
    if "train.chunk" not in overrides and config.train.chunk > config.train.iterations:
        # A shorter run than the preset's: its chunk follows (a chunk the user sets stays theirs to get right).
        config = cfg.apply_overrides(config, {"train.chunk": config.train.iterations})
    cfg.validate(config)
    return config


def from_dict(data: dict[str, Any]) -> cfg.Config:
    """A saved ``Config.to_dict`` back into a Config, with every registered algorithm's section."""
    return cfg.from_dict(data, algos.settings_sections())
