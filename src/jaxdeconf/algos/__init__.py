"""The imitation algorithms, one file each, and their registry.

Adding an algorithm is one new file (a subclass of ``base.Algorithm``) plus one line in ``REGISTRY``. The CLI, the
config validation, the results code and the tests read the names from here. Modules are imported lazily so that
``jaxdeconf.config`` can list the names without loading JAX.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from jaxdeconf.algos.base import Algorithm
    from jaxdeconf.config import Config
    from jaxdeconf.envs.base import Environment

#: Algorithm name -> (module, class, keyword arguments of the class).
REGISTRY: dict[str, tuple[str, str, dict[str, Any]]] = {
    "bc": ("jaxdeconf.algos.bc", "BehaviourCloning", {"view": "imitator"}),
    "oracle": ("jaxdeconf.algos.bc", "BehaviourCloning", {"view": "oracle"}),
    "dil": ("jaxdeconf.algos.dil", "Deconfounded", {}),
    "dil_offline": ("jaxdeconf.algos.dil_offline", "DeconfoundedOffline", {}),
    "dagger": ("jaxdeconf.algos.dagger", "DAgger", {}),
    "gail": ("jaxdeconf.algos.gail", "GAIL", {}),
}

NAMES: tuple[str, ...] = tuple(REGISTRY)


def make_algorithm(name: str, env: Environment, env_params: Any, config: Config) -> Algorithm:
    """Algorithm by name; envs that ask for it get their learner views standardised first."""
    if name not in REGISTRY:
        raise ValueError(f"unknown algorithm {name!r}; allowed: {', '.join(NAMES)}")
    from jaxdeconf.algos.base import fit_view_normalizer
    from jaxdeconf.envs.base import NormalizedViews

    if env.normalize_views and not isinstance(env, NormalizedViews):
        env = fit_view_normalizer(env, env_params)
    module, cls, kwargs = REGISTRY[name]
    return getattr(importlib.import_module(module), cls)(env, env_params, config, **kwargs)
