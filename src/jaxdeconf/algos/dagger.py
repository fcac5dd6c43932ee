"""DAgger (Ross et al., 2011): the recurrent BC policy trained on the expert's labels of states that a mixture of
expert and imitator visits, aggregated in the replay buffer.

The mixture is per environment slot and per step: at every step of every episode an independent coin executes the
expert's action with probability beta, the imitator's otherwise, and the imitator's GRU reads whichever action was
executed. beta falls linearly from 1 to 0 over ``dagger.anneal_iterations``. The label at every visited state is the
expert's action distribution (its action for a box space), so the loss is bc's NLL in expectation over the expert's
choice; for the bandit's stochastic expert that is exactly the intervention the deconfounded imitator approximates.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from jaxdeconf import losses
from jaxdeconf.actors import ExpertActor, RecurrentActor
from jaxdeconf.algos.base import TrainState
from jaxdeconf.algos.bc import BehaviourCloning
from jaxdeconf.config import field
from jaxdeconf.data import Tagged, buffer_add, replay, rollout
from jaxdeconf.envs.base import Observation


@dataclasses.dataclass(frozen=True)
class DaggerConfig:
    """DAgger's mixture schedule (its policy and BC steps are bc's: ``model.bc_gru``, ``train.policy_*``)."""

    # beta, the probability that a step executes the expert's action, falls linearly from 1 at iteration 0 to 0 at
    # this iteration and stays 0 after; 0 means the imitator acts alone from the start.
    anneal_iterations: int = field(125, ">=0")


@dataclasses.dataclass(frozen=True)
class MixtureActor:
    """DAgger's behaviour policy: per slot and step, the expert's head with probability beta, else the imitator's.

    params: {"policy": the imitator's parameters, "key": this rollout's coin key, "beta": a float}. The coin of step
    t is drawn from ``fold_in(key, t)``, independent of the key that samples the action from the chosen head.
    """

    imitator: RecurrentActor
    expert: ExpertActor

    def init_carry(self, batch: int) -> tuple[jax.Array, jax.Array]:
        """The imitator's GRU state and the step counter."""
        return self.imitator.init_carry(batch), jnp.zeros((), jnp.int32)

    def __call__(self, params: dict[str, Any], carry: tuple, obs: Observation, prev_action: jax.Array):
        """One step: both heads, then one coin per slot picks which is executed."""
        gru, t = carry
        gru, imitator_out = self.imitator(params["policy"], gru, obs, prev_action)
        batch = imitator_out.shape[0]
        _, expert_out = self.expert(None, self.expert.init_carry(batch), obs, prev_action)
        coin = jax.random.uniform(jax.random.fold_in(params["key"], t), (batch,)) < params["beta"]
        return (gru, t + 1), jnp.where(coin[:, None], expert_out, imitator_out)


def mixture_beta(iteration: jax.Array, anneal_iterations: int) -> jax.Array:
    """beta = 1 - iteration / anneal_iterations, clipped to [0, 1] (0 throughout when anneal_iterations is 0)."""
    if anneal_iterations == 0:
        return jnp.zeros((), jnp.float32)
    return jnp.clip(1.0 - iteration.astype(jnp.float32) / anneal_iterations, 0.0, 1.0)


@dataclasses.dataclass(frozen=True)
class DAgger(BehaviourCloning):
    """bc's network and BC steps; the data stream is the expert/imitator mixture with the expert's labels."""

    settings = ("dagger", DaggerConfig)

    def expert_labels(self, traj: Any) -> jax.Array:
        """The expert's action distribution [T, B, n] (or action [T, B, A]) at every state of ``traj``."""
        out = replay(ExpertActor(self.env, self.env_params), None, traj, self.space)
        return jax.nn.softmax(out, axis=-1) if self.space.discrete else out[..., : self.space.n]

    def init(self, key: jax.Array) -> TrainState:
        """bc's initial state with a buffer of labelled episodes."""
        state = super().init(key)
        example = self.example_episode()
        tagged = Tagged(traj=example, tags={"label": self.expert_labels(example)})
        return state.replace(expert_buffer=self._empty_buffer(tagged))

    def collect_expert(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """Roll out the mixture at this iteration's beta, label every visited state, aggregate."""
        k_roll, k_coin = jax.random.split(key)
        beta = mixture_beta(state.iteration, self.config.dagger.anneal_iterations)
        actor = MixtureActor(self.actor(), ExpertActor(self.env, self.env_params))
        params = {"policy": state.policy.params, "key": k_coin, "beta": beta}
        traj, _ = rollout(self.env, self.env_params, actor, params, k_roll, self.config.train.episodes_per_iter)
        tagged = Tagged(traj=traj, tags={"label": self.expert_labels(traj)})
        state = state.replace(expert_buffer=buffer_add(state.expert_buffer, tagged))
        return state, {"train_return": jnp.mean(jnp.sum(traj.reward, axis=0)), "beta": beta}

    def policy_loss(self, policy_params: Any, state: TrainState, batch: Tagged, context: jax.Array | None):
        """Expected NLL of the expert's labels along the executed histories."""
        out = self.policy_outputs(policy_params, state, batch.traj, context)
        return losses.soft_nll(self.space, out, batch.tags["label"], batch.traj.valid)
