"""Confounded environments and their registry; installed as ``jaxdeconf.envs`` from the top-level ``envs/`` folder."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from jaxdeconf.envs.base import ActionSpace, Environment, Observation, StepResult

__all__ = ["REGISTRY", "ActionSpace", "Environment", "Observation", "StepResult", "make"]


def _bandit() -> Environment:
    from jaxdeconf.envs.bandit import Bandit

    return Bandit()


def _lunar_lander() -> Environment:
    from jaxdeconf.envs.lunar_lander import LunarLander

    return LunarLander()


def _half_cheetah() -> Environment:
    from jaxdeconf.envs.locomotion import HalfCheetah

    return HalfCheetah()


def _ant_goal() -> Environment:
    from jaxdeconf.envs.locomotion import AntGoal

    return AntGoal()


#: Environment name -> constructor. Heavy environments (Brax) import their modules lazily here.
REGISTRY: dict[str, Callable[[], Environment]] = {
    "bandit": _bandit,
    "lunar_lander": _lunar_lander,
    "half_cheetah": _half_cheetah,
    "ant_goal": _ant_goal,
}


def parse_bool(value: Any) -> bool:
    """A boolean from a bool or the strings true/false, yes/no, 1/0 (any case); ValueError for anything else
    (``bool("false")`` is True, so command-line strings cannot go through ``bool``)."""
    if isinstance(value, bool):
        return value
    text = str(value).strip().lower()
    if text in ("1", "true", "yes"):
        return True
    if text in ("0", "false", "no"):
        return False
    raise ValueError(f"{value!r} is not a boolean (allowed: true, false)")


def make(name: str, **overrides: Any) -> tuple[Environment, Any]:
    """Build environment ``name`` and its params with ``overrides``; raise ValueError on unknown names or values."""
    if name not in REGISTRY:
        raise ValueError(f"unknown env {name!r}; allowed: {', '.join(sorted(REGISTRY))}")
    env = REGISTRY[name]()
    params = env.default_params()
    fields = {f.name: f for f in dataclasses.fields(params)}
    for key, value in overrides.items():
        if key not in fields:
            raise ValueError(f"unknown parameter {key!r} for env {name!r}; allowed: {', '.join(fields)}")
        default = getattr(params, key)
        kind = "boolean (allowed: true, false)" if isinstance(default, bool) else type(default).__name__
        try:
            value = parse_bool(value) if isinstance(default, bool) else type(default)(value)
        except (TypeError, ValueError):
            raise ValueError(f"env {name} parameter {key}={value!r} is not a {kind}") from None
        params = params.replace(**{key: value})
    env.validate(params)
    return env, params
