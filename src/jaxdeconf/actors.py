"""Actors: the expert, the recurrent naive-BC / oracle policy, and the deconfounded imitator of Algorithm 2."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from jaxdeconf.envs.base import Environment, Observation
from jaxdeconf.models import LOG_STD_MIN, Encoder, LatentPolicy, RecurrentPolicy


@dataclasses.dataclass(frozen=True)
class ExpertActor:
    """The env's expert acting on its own view; no memory."""

    env: Environment
    env_params: Any

    def init_carry(self, batch: int) -> jax.Array:
        """No recurrent state."""
        return jnp.zeros((batch, 0), jnp.float32)

    def __call__(self, params: Any, carry: jax.Array, obs: Observation, prev_action: jax.Array):
        """Expert logits (log-probabilities); for box actions a Gaussian head centred on the expert's deterministic
        action with the smallest standard deviation a head can express (exp(LOG_STD_MIN) = 0.0067)."""
        del params, prev_action  # Unused.
        if self.env.action_space(self.env_params).discrete:
            return carry, jnp.log(self.env.expert_probs(obs, self.env_params))
        mean = self.env.expert_action(jax.random.key(0), obs, self.env_params)
        return carry, jnp.concatenate([mean, jnp.full_like(mean, LOG_STD_MIN)], axis=-1)


@dataclasses.dataclass(frozen=True)
class RecurrentActor:
    """Naive BC (view "imitator") or the oracle (view "oracle"): a GRU over observations and previous actions."""

    policy: RecurrentPolicy
    view: str

    def init_carry(self, batch: int) -> jax.Array:
        """Zero GRU state."""
        return jnp.zeros((batch, self.policy.hidden), jnp.float32)

    def __call__(self, params: Any, carry: jax.Array, obs: Observation, prev_action: jax.Array):
        """One GRU step on the chosen view."""
        x = self.policy.apply(params, getattr(obs, self.view), prev_action, method=RecurrentPolicy.embed)
        return self.policy.apply(params, carry, x, method=RecurrentPolicy.recur)


@dataclasses.dataclass(frozen=True)
class DeconfoundedActor:
    """Algorithm 2: update the belief q_phi with (a_{t-1}, s_t), then act with pi_eta on its mean."""

    encoder: Encoder
    policy: LatentPolicy

    def init_carry(self, batch: int) -> jax.Array:
        """Zero GRU state of the inference model."""
        return jnp.zeros((batch, self.encoder.hidden), jnp.float32)

    def __call__(self, params: dict[str, Any], carry: jax.Array, obs: Observation, prev_action: jax.Array):
        """params: {"encoder": ..., "policy": ...}."""
        x = self.encoder.apply(params["encoder"], obs.imitator, prev_action, method=Encoder.embed)
        carry, (mean, _) = self.encoder.apply(params["encoder"], carry, x, method=Encoder.recur)
        return carry, self.policy.apply(params["policy"], obs.imitator, mean)
