"""Actors: the expert, the recurrent naive-BC / oracle policy and the deconfounded imitator of Algorithm 2."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from jaxdeconf.envs.base import Environment, Observation
from jaxdeconf.models import LOG_STD_MIN, Encoder, EvidenceEncoder, LatentPolicy, RecurrentPolicy


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
    """Naive BC (view "imitator") or the oracle (view "oracle"): a GRU (or minGRU) over observations and previous
    actions, one ``recur`` step per call."""

    policy: RecurrentPolicy
    view: str

    def init_carry(self, batch: int) -> jax.Array:
        """Zero cell state."""
        return jnp.zeros((batch, self.policy.hidden), jnp.float32)

    def __call__(self, params: Any, carry: jax.Array, obs: Observation, prev_action: jax.Array):
        """One cell step on the chosen view."""
        x = self.policy.apply(params, getattr(obs, self.view), prev_action, method=RecurrentPolicy.embed)
        return self.policy.apply(params, carry, x, method=RecurrentPolicy.recur)


@dataclasses.dataclass(frozen=True)
class DeconfoundedActor:
    """Algorithm 2: update the belief q_phi with (a_{t-1}, s_t), then act with pi_eta on its mean.

    With ``delta_scale`` the encoder also reads the standardised change s_t - s_{t-1} (``losses.transition_inputs``),
    so the carry keeps the previous observation and whether there is one.
    """

    encoder: Encoder | EvidenceEncoder
    policy: LatentPolicy
    delta_scale: Any = None  # [d] array, or None.

    def init_carry(self, batch: int) -> Any:
        """Zero recurrent state of the inference model (and, with deltas, no previous observation yet)."""
        gru = jnp.zeros((batch, self.encoder.hidden), jnp.float32)
        if self.delta_scale is None:
            return gru
        return gru, jnp.zeros((batch, len(self.delta_scale)), jnp.float32), jnp.zeros((batch, 1), jnp.bool_)

    def __call__(self, params: dict[str, Any], carry: Any, obs: Observation, prev_action: jax.Array):
        """params: {"encoder": ..., "policy": ...}."""
        s = obs.imitator
        if self.delta_scale is None:
            gru, enc_obs = carry, s
        else:
            gru, prev_obs, started = carry
            enc_obs = jnp.concatenate([s, jnp.where(started, s - prev_obs, 0.0) / self.delta_scale], axis=-1)
        x = self.encoder.apply(params["encoder"], enc_obs, prev_action, method="embed")
        gru, (mean, _) = self.encoder.apply(params["encoder"], gru, x, method="recur")
        carry = gru if self.delta_scale is None else (gru, s, jnp.ones_like(started))
        return carry, self.policy.apply(params["policy"], s, mean)
