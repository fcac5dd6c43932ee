"""Shipped experts: parameter files under ``envs/experts/`` with the command, config and evaluation that made them.

Each expert is two files: ``<env>.msgpack`` (Flax-serialised network parameters) and ``<env>.json`` (the network and
PPO config, the exact training command, and its evaluation numbers). ``load_expert`` rebuilds the network from the
JSON and restores the parameters; ``save_expert`` writes both without touching an existing pair unless asked.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
from pathlib import Path
from typing import Any

import flax.serialization
import jax
import jax.numpy as jnp

from jaxdeconf.ppo import ExpertNetwork

# Found without importing ``jaxdeconf.envs`` (whose envs import this module): the envs package's folder on disk.
EXPERT_DIR = Path(importlib.util.find_spec("jaxdeconf.envs").submodule_search_locations[0]).resolve() / "experts"


@dataclasses.dataclass(frozen=True)
class Expert:
    """A loaded expert: its network, parameters and metadata."""

    network: ExpertNetwork
    params: Any
    meta: dict[str, Any]

    def probs(self, obs: jax.Array) -> jax.Array:
        """Action probabilities for expert-view observations [..., obs]."""
        logits, _ = self.network.apply(self.params, obs)
        return jax.nn.softmax(logits, axis=-1)


def expert_paths(name: str, folder: Path | None = None) -> tuple[Path, Path]:
    """Parameter and metadata file of env ``name``'s expert."""
    folder = EXPERT_DIR if folder is None else Path(folder)
    return folder / f"{name}.msgpack", folder / f"{name}.json"


def save_expert(name: str, params: Any, meta: dict[str, Any], folder: Path | None = None,
                overwrite: bool = False) -> tuple[Path, Path]:
    """Write the expert's two files; refuse to replace an existing expert unless ``overwrite``."""
    weights, info = expert_paths(name, folder)
    if weights.exists() and not overwrite:
        raise FileExistsError(f"expert {weights} exists; pass overwrite to replace it")
    weights.parent.mkdir(parents=True, exist_ok=True)
    weights.write_bytes(flax.serialization.to_bytes(params))
    info.write_text(json.dumps(meta, indent=2) + "\n")
    return weights, info


def load_expert(name: str, folder: Path | None = None) -> Any:
    """Load env ``name``'s expert (an ``Expert``, or a ``brax_experts.PolicyExpert`` for the locomotion envs); a
    missing or corrupt file is a one-line ValueError."""
    weights, info = expert_paths(name, folder)
    if not weights.exists() or not info.exists():
        raise ValueError(f"no expert for env {name!r}: expected {weights} and {info}")
    try:
        meta = json.loads(info.read_text())
        if meta.get("kind") == "brax_ppo":  # Locomotion experts: Brax's tanh-Gaussian PPO policy.
            from jaxdeconf.brax_experts import PolicyExpert, policy_template

            return PolicyExpert(flax.serialization.from_bytes(policy_template(meta), weights.read_bytes()), meta)
        net = ExpertNetwork(int(meta["actions"]), int(meta["width"]), int(meta["depth"]))
        template = net.init(jax.random.key(0), jnp.zeros((int(meta["obs_size"]),)))
        params = flax.serialization.from_bytes(template, weights.read_bytes())
    except Exception as err:
        raise ValueError(f"expert files {weights} / {info} are corrupt ({type(err).__name__})") from None
    return Expert(net, params, meta)
