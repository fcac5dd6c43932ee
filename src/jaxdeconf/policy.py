"""A trained imitator from a results folder as a callable policy with its recurrent state.

    policy = load_policy("results/bandit-cpu", "dil", seed=0)
    state = policy.initial_state(seed=1, num_envs=1)
    action, state = policy(obs, state)          # obs: the env's ``policy.view`` [d] or [num_envs, d]

The policy reads the raw view a ``jaxdeconf.gym`` wrapper returns and standardises it itself where the algorithm
learnt on standardised views. ``initial_state(seed=s)`` draws the action keys ``jaxdeconf.data.rollout`` draws from
``jax.random.key(s)``, so with an env reset with the same seed the pair reproduces the compiled rollout.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxdeconf import config as cfg
from jaxdeconf import resolve
from jaxdeconf.actors import ExpertActor
from jaxdeconf.checkpoint import Checkpoints
from jaxdeconf.envs.base import NormalizedViews, Observation
from jaxdeconf.errors import ConfigError
from jaxdeconf.gym import GymEnv, GymVectorEnv, step_key
from jaxdeconf.models import action_features, sample


@struct.dataclass
class PolicyState:
    """The actor's recurrent carry, the previous action's features and the key schedule, batched over envs."""

    carry: Any
    prev: jax.Array  # float32 [N, A]: features of the previous action (zero at an episode's start).
    step: jax.Array  # int32 []: steps taken, picks the action key.
    key_steps: jax.Array  # Typed key the per-step action keys derive from.


class Policy:
    """An algorithm's actor with fixed parameters, acting on one view of the env."""

    def __init__(self, algorithm: Any, actor_params: Any) -> None:
        self.algorithm = algorithm
        self.env, self.env_params = algorithm.env, algorithm.env_params
        self.actor = algorithm.actor()
        self.params = actor_params
        self.space = self.env.action_space(self.env_params)
        self.view = "expert" if isinstance(self.actor, ExpertActor) else getattr(self.actor, "view", "imitator")
        self.horizon = self.env.horizon(self.env_params)
        self._act = jax.jit(self._act_impl)

    @property
    def raw_env(self) -> Any:
        """The environment the policy acts in, without the algorithm's view standardisation."""
        return self.env.env if isinstance(self.env, NormalizedViews) else self.env

    def gym_env(self, num_envs: int | None = None) -> Any:
        """The env it was trained on, with the same parameters and view, as a ``gymnasium.Env`` (or, with
        ``num_envs``, a ``gymnasium.vector.VectorEnv``)."""
        if num_envs is None:
            return GymEnv(self.raw_env, self.env_params, view=self.view)
        return GymVectorEnv(self.raw_env, num_envs, self.env_params, view=self.view)

    def initial_state(self, seed: int = 0, num_envs: int = 1) -> PolicyState:
        """The state at the start of an episode of each of ``num_envs`` envs; ``seed`` fixes the sampled actions."""
        _, key_steps = jax.random.split(jax.random.key(seed))
        return PolicyState(carry=self.actor.init_carry(num_envs),
                           prev=jnp.zeros((num_envs, self.space.feature_size), jnp.float32),
                           step=jnp.zeros((), jnp.int32), key_steps=key_steps)

    def reset(self, state: PolicyState, mask: Any) -> PolicyState:
        """Start a new episode in the envs where ``mask`` [N] is true (after a vector env's autoreset)."""
        fresh = self.actor.init_carry(state.prev.shape[0])
        mask = jnp.asarray(mask, jnp.bool_)

        def pick(new: jax.Array, old: jax.Array) -> jax.Array:
            return jnp.where(mask.reshape((-1,) + (1,) * (old.ndim - 1)), new, old)

        return state.replace(carry=jax.tree.map(pick, fresh, state.carry),
                             prev=pick(jnp.zeros_like(state.prev), state.prev))

    def _observation(self, view: jax.Array) -> Observation:
        """An Observation holding ``view`` in the policy's view, standardised as the algorithm trained on it."""
        sizes = self.env.obs_sizes(self.env_params)
        batch = view.shape[0]
        obs = Observation(**{name: jnp.zeros((batch, getattr(sizes, name)), jnp.float32)
                             for name in ("expert", "imitator", "oracle")})
        obs = obs.replace(**{self.view: view})
        return self.env.normalize(obs) if isinstance(self.env, NormalizedViews) else obs

    def _act_impl(self, params: Any, view: jax.Array, state: PolicyState) -> tuple[jax.Array, jax.Array, PolicyState]:
        """Head output, sampled action and new state for a batch of views [N, d]."""
        carry, out = self.actor(params, state.carry, self._observation(view), state.prev)
        key_act, _ = jax.random.split(step_key(state.key_steps, state.step, self.horizon))
        action = sample(self.space, key_act, out)
        state = state.replace(carry=carry, prev=action_features(self.space, action), step=state.step + 1)
        return out, action, state

    def __call__(self, obs: Any, state: PolicyState) -> tuple[np.ndarray, PolicyState]:
        """Sample an action for ``obs`` ([d] for one env, [N, d] for N) and advance the state."""
        view = jnp.asarray(obs, jnp.float32)
        single = view.ndim == 1
        _, action, state = self._act(self.params, view[None] if single else view, state)
        action = np.asarray(action)
        return (action[0] if single else action), state

    def head(self, obs: Any, state: PolicyState) -> tuple[np.ndarray, PolicyState]:
        """The policy head's output (logits, or mean and log-std) for ``obs`` [N, d], and the advanced state."""
        out, _, state = self._act(self.params, jnp.asarray(obs, jnp.float32), state)
        return np.asarray(out), state


def load_config(folder: str | pathlib.Path) -> cfg.Config:
    """The config a results folder was trained with."""
    path = pathlib.Path(folder) / "config.json"
    if not path.exists():
        raise ConfigError(f"{folder} is not a results folder (no config.json)")
    return resolve.from_dict(json.loads(path.read_text()))


def load_state(folder: str | pathlib.Path, algo: str) -> tuple[Any, Any, cfg.Config]:
    """(algorithm, seed-batched TrainState of its newest checkpoint, config) of ``algo`` in ``folder``."""
    from jaxdeconf.train import build_algorithm, seed_keys

    folder = pathlib.Path(folder)
    config = load_config(folder)
    if algo not in config.algos:
        raise ConfigError(f"{folder} holds no {algo!r} run; it has {', '.join(config.algos)}")
    algorithm = build_algorithm(config, algo)
    ckpt = Checkpoints(folder / algo / "checkpoints")
    step = ckpt.latest_step()
    if step is None:
        ckpt.close()
        raise ConfigError(f"{folder / algo} has no checkpoint yet")
    states = ckpt.restore(step, jax.jit(jax.vmap(algorithm.init))(seed_keys(config)))
    ckpt.close()
    return algorithm, states, config


@dataclasses.dataclass(frozen=True)
class ExpertAlgorithm:
    """The env's own θ-aware expert in the shape of an algorithm (``env``, ``env_params``, ``actor()``)."""

    env: Any
    env_params: Any

    def actor(self) -> ExpertActor:
        """The expert acting on the expert's view."""
        return ExpertActor(self.env, self.env_params)


def expert_policy(folder: str | pathlib.Path) -> Policy:
    """The expert of the env a results folder was trained on, as a Policy (it needs no checkpoint)."""
    from jaxdeconf.envs import make

    config = load_config(folder)
    env, params = make(config.env, **config.env_params)
    return Policy(ExpertAlgorithm(env, params), None)


def load_policy(folder: str | pathlib.Path, algo: str, seed: int = 0) -> Policy:
    """The imitator ``algo`` trained with ``seed`` in results ``folder``, at its newest checkpoint."""
    algorithm, states, config = load_state(folder, algo)
    index = seed - config.seed_start
    if not 0 <= index < config.seeds:
        raise ConfigError(f"seed {seed} was not trained in {folder}: seeds are {config.seed_start}.."
                              f"{config.seed_start + config.seeds - 1}")
    state = jax.tree.map(lambda x: x[index], states)
    return Policy(algorithm, algorithm.actor_params(state))
