"""θ-conditioned experts for the Brax locomotion envs, trained with Brax's own PPO (``brax.training.agents.ppo``).

Brax's trainer needs a ``brax.envs.Env``; ``ExpertView`` presents one of our confounded envs through the expert's
view (state + θ). Brax's stock auto-reset returns every finished episode to the *same* first state, which would fix
θ per env slot for the whole of training; ``wrap_resampling`` instead draws a fresh reset (a new θ) whenever an
episode ends. The shipped expert is Brax's tanh-Gaussian policy with its observation normaliser; ``PolicyExpert``
rebuilds it from the metadata and acts with the distribution's mode.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
from brax import envs as brax_envs
from brax.envs.wrappers import training as brax_wrappers
from brax.training.acme import running_statistics, specs
from brax.training.agents.ppo import networks as ppo_networks


def _restore_device_put_replicated() -> None:
    """brax 0.14.2's trainer calls ``jax.device_put_replicated``, which jax 0.10 removed from its public namespace
    (the function itself remains in ``jax._src.api``); put it back so ``brax.training.agents.ppo.train`` runs."""
    if "device_put_replicated" not in vars(jax):
        from jax._src import api

        jax.device_put_replicated = api.device_put_replicated


_restore_device_put_replicated()


class ExpertView(brax_envs.Env):
    """One of our envs as a single-instance Brax env on the expert's view; the reward is ``reward_fn``'s."""

    def __init__(self, env: Any, params: Any, reward_fn: Any = None):
        self.env, self.params = env, params
        self.reward_fn = reward_fn

    @property
    def observation_size(self) -> int:
        return int(self.env.obs_sizes(self.params).expert)  # Abstract: never Brax's eager reset.

    @property
    def action_size(self) -> int:
        return int(self.env.action_space(self.params).n)

    @property
    def backend(self) -> str:
        return str(self.params.backend)

    def reset(self, rng: jax.Array) -> brax_envs.State:
        k_reset, k_next = jax.random.split(rng)
        state, obs = self.env.reset(k_reset, self.params)
        zero = jnp.zeros(())
        return brax_envs.State(pipeline_state=state, obs=obs.expert, reward=zero, done=zero,
                               metrics={"task_reward": zero}, info={"rng": k_next})

    def step(self, state: brax_envs.State, action: jax.Array) -> brax_envs.State:
        rng, k_step = jax.random.split(state.info["rng"])
        new, result = self.env.step(k_step, state.pipeline_state, action, self.params)
        reward = result.reward if self.reward_fn is None else self.reward_fn(state.pipeline_state, new, action)
        state.info.update(rng=rng)
        state.metrics.update(task_reward=result.reward)
        return state.replace(pipeline_state=new, obs=result.obs.expert, reward=reward,
                             done=result.done.astype(jnp.float32))


class ResamplingAutoReset(brax_wrappers.Wrapper):
    """Like Brax's AutoResetWrapper, but a finished episode restarts from a fresh reset (a new θ)."""

    def reset(self, rng: jax.Array) -> brax_envs.State:
        state = self.env.reset(rng)
        state.info["reset_rng"] = jax.vmap(lambda k: jax.random.fold_in(k, 1))(rng)
        return state

    def step(self, state: brax_envs.State, action: jax.Array) -> brax_envs.State:
        steps = jnp.where(state.done, jnp.zeros_like(state.info["steps"]), state.info["steps"])
        state.info.update(steps=steps)
        state = self.env.step(state.replace(done=jnp.zeros_like(state.done)), action)
        keys = jax.vmap(jax.random.split)(state.info["reset_rng"])
        fresh = self.env.reset(keys[:, 0])

        def where_done(x, y):
            done = jnp.reshape(state.done, (x.shape[0],) + (1,) * (x.ndim - 1))
            return jnp.where(done, x, y)

        state.info.update(reset_rng=keys[:, 1])
        return state.replace(pipeline_state=jax.tree.map(where_done, fresh.pipeline_state, state.pipeline_state),
                             obs=where_done(fresh.obs, state.obs))


def wrap_resampling(env: brax_envs.Env, episode_length: int = 1000, action_repeat: int = 1,
                    randomization_fn: Any = None) -> brax_envs.Env:
    """Brax's training wrappers (vmap, episode) with the resampling auto-reset; for ``ppo.train(wrap_env_fn=...)``."""
    del randomization_fn  # Unused: θ is the only randomisation.
    env = brax_wrappers.VmapWrapper(env)
    env = brax_wrappers.EpisodeWrapper(env, episode_length, action_repeat)
    return ResamplingAutoReset(env)


def make_networks(obs_size: int, action_size: int, policy_layers: tuple[int, ...],
                  value_layers: tuple[int, ...]) -> ppo_networks.PPONetworks:
    """Brax's PPO networks with its running observation normaliser."""
    return ppo_networks.make_ppo_networks(
        obs_size, action_size, preprocess_observations_fn=running_statistics.normalize,
        policy_hidden_layer_sizes=tuple(policy_layers), value_hidden_layer_sizes=tuple(value_layers))


def network_factory(policy_layers: tuple[int, ...], value_layers: tuple[int, ...]) -> Any:
    """``ppo.train``'s ``network_factory`` for the given layer sizes."""

    def factory(obs_size, action_size, preprocess_observations_fn=running_statistics.normalize):
        return ppo_networks.make_ppo_networks(
            obs_size, action_size, preprocess_observations_fn=preprocess_observations_fn,
            policy_hidden_layer_sizes=tuple(policy_layers), value_hidden_layer_sizes=tuple(value_layers))

    return factory


def policy_template(meta: dict[str, Any], value: bool = False) -> dict[str, Any]:
    """Freshly initialised {normalizer, policy(, value)} parameters of the shape ``meta`` describes (to
    deserialise into)."""
    nets = make_networks(int(meta["obs_size"]), int(meta["action_size"]), meta["policy_layers"],
                         meta["value_layers"])
    normalizer = running_statistics.init_state(specs.Array((int(meta["obs_size"]),), jnp.dtype("float32")))
    template = {"normalizer": normalizer, "policy": nets.policy_network.init(jax.random.key(0))}
    if value:
        template["value"] = nets.value_network.init(jax.random.key(0))
    return template


@dataclasses.dataclass(frozen=True)
class PolicyExpert:
    """A loaded Brax PPO expert acting with its tanh-Gaussian's mode."""

    params: dict[str, Any]
    meta: dict[str, Any]

    @functools.cached_property
    def _policy(self) -> Any:
        nets = make_networks(int(self.meta["obs_size"]), int(self.meta["action_size"]), self.meta["policy_layers"],
                             self.meta["value_layers"])
        return ppo_networks.make_inference_fn(nets)((self.params["normalizer"], self.params["policy"]),
                                                    deterministic=True)

    def act(self, obs: jax.Array) -> jax.Array:
        """Deterministic action in [-1, 1] for expert-view observations [..., obs]."""
        action, _ = self._policy(obs, jax.random.key(0))
        return action
