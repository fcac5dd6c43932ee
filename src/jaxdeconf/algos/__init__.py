"""The imitation algorithms, one file each, and their registry: the only list of algorithms.

Adding an algorithm is one new file (a subclass of ``base.Algorithm``, with its own settings dataclass if it has
settings) plus one line in ``REGISTRY``. The CLI, the config, the memory estimate, the results code and the tests
read the names, classes and sections from here. Modules are imported when first asked for.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any, NamedTuple

if TYPE_CHECKING:
    from jaxdeconf.algos.base import Algorithm
    from jaxdeconf.config import Config
    from jaxdeconf.envs.base import Environment

class Entry(NamedTuple):
    """Where an algorithm lives and how it is shown."""

    module: str
    cls: str
    kwargs: dict[str, Any]  # Keyword arguments of the class (one class may serve several names).
    color: str | None = None  # Its colour in every plot (None: matplotlib's next).


#: Algorithm name -> its entry.
REGISTRY: dict[str, Entry] = {
    "bc": Entry("jaxdeconf.algos.bc", "BehaviourCloning", {"view": "imitator"}, "tab:red"),
    "oracle": Entry("jaxdeconf.algos.bc", "BehaviourCloning", {"view": "oracle"}, "tab:green"),
    "dil": Entry("jaxdeconf.algos.dil", "Deconfounded", {}, "tab:blue"),
    "dil_plus": Entry("jaxdeconf.algos.dil_plus", "DeconfoundedPlus", {}, "tab:brown"),
    "dil_offline": Entry("jaxdeconf.algos.dil_offline", "DeconfoundedOffline", {}, "tab:cyan"),
    "dagger": Entry("jaxdeconf.algos.dagger", "DAgger", {}, "tab:purple"),
    "gail": Entry("jaxdeconf.algos.gail", "GAIL", {}, "tab:orange"),
}


def names() -> tuple[str, ...]:
    """Every registered algorithm's name, in registry order."""
    return tuple(REGISTRY)


def algorithm_class(name: str) -> type[Algorithm]:
    """The class registered under ``name``; ValueError naming the allowed names for an unknown one."""
    if name not in REGISTRY:
        raise ValueError(f"unknown algorithm {name!r}; allowed: {', '.join(names())}")
    entry = REGISTRY[name]
    return getattr(importlib.import_module(entry.module), entry.cls)


def color(name: str) -> str | None:
    """The plot colour of ``name`` (None for a name not registered: matplotlib picks one)."""
    entry = REGISTRY.get(name)
    return entry.color if entry else None


def settings_sections() -> dict[str, type]:
    """Section name -> settings dataclass of every registered algorithm that declares one, in registry order."""
    out: dict[str, type] = {}
    for name in REGISTRY:
        declared = algorithm_class(name).settings
        if declared is not None:
            out.setdefault(*declared)
    return out


def make_algorithm(name: str, env: Environment, env_params: Any, config: Config) -> Algorithm:
    """Algorithm by name; envs that ask for it get their learner views standardised first."""
    cls = algorithm_class(name)
    from jaxdeconf.algos.base import fit_view_normalizer
    from jaxdeconf.envs.base import NormalizedViews

    if env.normalize_views and not isinstance(env, NormalizedViews):
        env = fit_view_normalizer(env, env_params)
    return cls(env, env_params, config, **REGISTRY[name].kwargs)
