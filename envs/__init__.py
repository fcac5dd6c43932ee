"""Confounded environments and their registry; installed as ``jaxdeconf.envs`` from the top-level ``envs/`` folder."""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import os
import pathlib
import sys
from collections.abc import Callable
from typing import Any

from jaxdeconf.envs.base import ActionSpace, Environment, Observation, ObsGroup, StepResult
from jaxdeconf.envs.check import EnvCheckError, check_env

__all__ = [
    "REGISTRY",
    "ActionSpace",
    "EnvCheckError",
    "Environment",
    "ObsGroup",
    "Observation",
    "StepResult",
    "check_env",
    "make",
    "register",
    "resolve",
]


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


def register(name: str, constructor: Callable[[], Environment]) -> None:
    """Add an environment under ``name`` (for this process; the CLI's workers load ``module:Class`` names instead)."""
    REGISTRY[name] = constructor


def _import_module(spec: str) -> Any:
    """Import a dotted module name, or a ``.py`` file by path; the current directory is searched too."""
    if spec.endswith(".py") or "/" in spec:
        path = pathlib.Path(spec).resolve()
        if not path.exists():
            raise ValueError(f"env module file {spec!r} does not exist")
        name = f"_jaxdeconf_user_{path.stem}"
        if name not in sys.modules:
            module_spec = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(module_spec)
            sys.modules[name] = module  # Before exec: flax.struct dataclasses look their module up by name.
            module_spec.loader.exec_module(module)
        return sys.modules[name]
    if os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.append(os.getcwd())  # ``jaxdeconf`` (the console script) does not put it there; ``python -m`` does.
    try:
        return importlib.import_module(spec)
    except ModuleNotFoundError as err:
        raise ValueError(f"cannot import env module {spec!r} ({err})") from None


def resolve(name: str) -> Callable[[], Environment]:
    """The constructor of a registered env, or of ``module:Class`` / ``path/to/file.py:Class`` from the user's code."""
    if name in REGISTRY:
        return REGISTRY[name]
    module_name, sep, attr = name.rpartition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"unknown env {name!r}; allowed: {', '.join(sorted(REGISTRY))}, or module:Class")
    module = _import_module(module_name)
    constructor = getattr(module, attr, None)
    if constructor is None:
        raise ValueError(f"env module {module_name!r} has no attribute {attr!r}")
    if not callable(constructor):
        raise ValueError(f"env {name!r} is not a class or function returning an Environment")
    return constructor


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
    env = resolve(name)()
    if not isinstance(env, Environment):
        raise ValueError(f"env {name!r} built a {type(env).__name__}, not a jaxdeconf.envs.Environment")
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
