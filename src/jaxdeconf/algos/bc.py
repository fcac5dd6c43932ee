"""Naive recurrent BC on the imitator's view, and the oracle: the same network that also sees θ."""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from jaxdeconf import losses
from jaxdeconf.actors import MarkovActor, RecurrentActor
from jaxdeconf.algos.base import Algorithm, Learner, TrainState
from jaxdeconf.data import Trajectory
from jaxdeconf.models import LatentPolicy, RecurrentPolicy, action_features, head_size


@dataclasses.dataclass(frozen=True)
class BehaviourCloning(Algorithm):
    """Naive recurrent BC on the imitator's view; with ``view="oracle"`` the oracle that also sees θ."""

    view: str = "imitator"

    @property
    def recurrent(self) -> bool:
        """Whether the network is the recurrent policy (``model.bc_memory=gru``) or a Markov one."""
        return self.config.model.bc_memory == "gru"

    @property
    def network(self) -> RecurrentPolicy | LatentPolicy:
        """The recurrent policy, or (``model.bc_memory=none``) dil's Markov policy network with an empty latent."""
        m = self.config.model
        if not self.recurrent:
            return LatentPolicy(m.width, head_size(self.space))
        return RecurrentPolicy(m.width, m.action_embed, m.bc_gru, head_size(self.space))

    def init(self, key: jax.Array) -> TrainState:
        """Fresh policy and an expert buffer."""
        key, k_init = jax.random.split(key)
        size = getattr(self.env.obs_sizes(self.env_params), self.view)
        second = jnp.zeros((1, self.space.feature_size if self.recurrent else 0))
        params = self.network.init(k_init, jnp.zeros((1, size)), second)
        return TrainState(
            policy=Learner(params, self.policy_tx.init(params)),
            encoder=None,
            expert_buffer=self._empty_buffer(),
            explore_buffer=None,
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )

    def actor(self) -> RecurrentActor | MarkovActor:
        """The policy acting on its view."""
        return RecurrentActor(self.network, self.view) if self.recurrent else MarkovActor(self.network, self.view)

    def actor_params(self, state: TrainState) -> Any:
        """Policy parameters."""
        return state.policy.params

    def policy_outputs(
        self, policy_params: Any, state: TrainState, traj: Trajectory, context: jax.Array | None = None
    ) -> jax.Array:
        """GRU over the view and the previous expert actions (or the Markov head on each step's view)."""
        del state, context  # Unused.
        obs = getattr(traj.obs, self.view)[: traj.horizon]
        if not self.recurrent:
            return self.network.apply(policy_params, obs, jnp.zeros((*obs.shape[:-1], 0)))
        prev = losses.prev_actions(action_features(self.space, traj.action))
        return losses.recurrent_policy_scan(self.network, policy_params, obs, prev)
