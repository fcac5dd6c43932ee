"""Naive recurrent BC on the imitator's view, and the oracle: the same network that also sees θ."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from jaxdeconf import losses
from jaxdeconf.actors import RecurrentActor
from jaxdeconf.algos.base import Algorithm, Learner, TrainState
from jaxdeconf.data import Trajectory
from jaxdeconf.models import RecurrentPolicy, action_features, head_size


@dataclasses.dataclass(frozen=True)
class BehaviourCloning(Algorithm):
    """Naive recurrent BC on the imitator's view; with ``view="oracle"`` the oracle that also sees θ."""

    view: str = "imitator"

    @property
    def network(self) -> RecurrentPolicy:
        """The recurrent policy over the view and the previous action."""
        m = self.config.model
        return RecurrentPolicy(m.width, m.action_embed, m.bc_gru, head_size(self.space), m.cell)

    def init(self, key: jax.Array) -> TrainState:
        """Fresh policy and an expert buffer."""
        key, k_init = jax.random.split(key)
        size = getattr(self.env.obs_sizes(self.env_params), self.view)
        params = self.network.init(k_init, jnp.zeros((1, size)), jnp.zeros((1, self.space.feature_size)))
        return TrainState(
            policy=Learner(params, self.policy_tx.init(params)),
            encoder=None,
            expert_buffer=self._empty_buffer(),
            explore_buffer=None,
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )

    def actor(self) -> RecurrentActor:
        """The policy acting on its view."""
        return RecurrentActor(self.network, self.view)

    def actor_params(self, state: TrainState) -> Any:
        """Policy parameters."""
        return state.policy.params

    def policy_outputs(
        self, policy_params: Any, state: TrainState, traj: Trajectory, context: jax.Array | None = None
    ) -> jax.Array:
        """GRU over the view and the previous expert actions."""
        del state, context  # Unused.
        obs = getattr(traj.obs, self.view)[: traj.horizon]
        prev = losses.prev_actions(action_features(self.space, traj.action))
        return losses.recurrent_policy_scan(self.network, policy_params, obs, prev)
