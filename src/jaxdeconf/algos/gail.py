"""GAIL (Ho and Ermon, 2016) with a recurrent PPO generator, and DAC's absorbing state (Kostrikov et al., 2019).

The generator is a GRU actor and a GRU critic, each on the imitator's view and the previous action (bc's network).
Each iteration it rolls out ``gail.rollout_factor`` times the other algorithms' episodes; the discriminator (an MLP on
s', the reference code's input) takes ``gail.disc_steps`` BCE steps separating expert from generator transitions,
behind a global-norm gradient clip of ``gail.disc_clip``; the generator's reward is -log(1 - D) = softplus(logit);
then PPO (clipped surrogate, GAE, normalised advantages) runs ``gail.epochs`` epochs over minibatches of whole
episodes. Recurrent PPO replays each episode from its first step with a zero GRU state, exactly as it was rolled out,
so before the first update the probability ratio is 1.

Early termination (``absorbing``, ``discriminator_features``, ``absorbing_gae_inputs``). Episodes have a fixed horizon
T and an episode that terminates at step k < T - 1 (``valid`` holds up to and including k) would otherwise collect
the positive reward -log(1 - D) only while alive: a survival bonus. As in DAC, the episode instead enters an
absorbing state s_a after its terminal state and stays there to the horizon. The discriminator reads s' with an
indicator appended: (s_{t+1}, 0) at the valid steps, so the terminating step k reads the env's terminal observation
s_{k+1}, which plays DAC's terminal state s_T; the absorbing steps k+1 .. T-1, DAC's transition (s_T, ., s_a) and
then (s_a, ., s_a), read their s' = s_a = (0, 1). The discriminator trains on every step of every stored episode,
absorbing ones included, for expert and generator alike, so D(s_a) is learned from how often each of them is
absorbed; the generator is rewarded softplus(D(s_a)) at each absorbing step, and GAE runs through the absorbing steps
to the horizon instead of stopping at termination, so ending early is worth what s_a is worth. The absorbing state's
reward is the same at every step and nothing the generator does there changes it, so its value at absorbing step t is
exact, the discounted sum of its rewards to the horizon, and stands in for the critic's there: absorbing steps then
have advantage 0, and the terminating step's target bootstraps from that exact value. Absorbing steps stay out of the
policy's and the critic's losses (their actions change nothing). Empty buffer slots (step 0 not valid) count as no
episode at all.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import optax

from jaxdeconf import losses
from jaxdeconf.actors import RecurrentActor
from jaxdeconf.algos.base import Algorithm, Learner, TrainState, apply_gradients
from jaxdeconf.config import Config, field
from jaxdeconf.data import Tagged, Trajectory, buffer_add, buffer_sample, rollout_with_outputs
from jaxdeconf.errors import ConfigError
from jaxdeconf.models import Discriminator, RecurrentPolicy, action_features, entropy, head_size, log_prob
from jaxdeconf.ppo import clipped_surrogate, gae, normalize_advantages, squared_value_error

GAIL_REWARDS = ("discriminator", "env")


@dataclasses.dataclass(frozen=True)
class GailConfig:
    """GAIL: the recurrent PPO generator and the discriminator (defaults: the reference code's constants)."""

    rollout_factor: int = field(4, ">=1")  # Generator episodes per iteration, in units of train.episodes_per_iter.
    disc_steps: int = field(20, ">=1")  # Discriminator gradient steps per iteration.
    disc_lr: float = field(3e-4, ">0")  # Discriminator Adam learning rate.
    disc_clip: float = field(100.0, ">0")  # Global-norm gradient clip of the discriminator (the paper's table).
    # The generator's reward: "discriminator" (-log(1 - D)) or "env" (the env's own reward: a check that the same PPO
    # learns the task at this budget, separating a weak generator from a weak discriminator).
    reward: str = field("discriminator", GAIL_REWARDS)
    lr: float = field(3e-4, ">0")  # Generator (actor and critic) Adam learning rate.
    epochs: int = field(10, ">=1")  # PPO epochs over each iteration's rollouts.
    minibatches: int = field(4, ">=1")  # Minibatches per epoch, each of whole episodes.
    clip_eps: float = field(0.2, ">0")  # PPO's probability-ratio clip.
    gamma: float = field(0.99, ">=0")  # Discount (at most 1).
    gae_lambda: float = field(0.95, ">=0")  # GAE's lambda (at most 1).
    max_grad_norm: float = field(0.5, ">0")  # Global-norm gradient clip of the generator.
    value_coef: float = field(0.5, ">=0")  # Weight of the critic's squared error in the generator's loss.
    entropy_coef: float = field(0.0, ">=0")  # Weight of the policy's entropy bonus.

    def check(self, config: Config) -> None:
        """Raise ConfigError for relations no single field's range states."""
        for name in ("gamma", "gae_lambda"):
            if getattr(self, name) > 1:
                raise ConfigError(f"gail.{name}={getattr(self, name)} is not allowed: need a number in [0, 1]")
        episodes = config.train.episodes_per_iter * self.rollout_factor
        if episodes % self.minibatches:
            raise ConfigError(f"gail.minibatches={self.minibatches} must divide the generator's {episodes} episodes "
                              "per iteration (train.episodes_per_iter x gail.rollout_factor)")


def absorbing(valid: jax.Array) -> jax.Array:
    """The absorbing steps [T, B] bool: those after a stored episode's termination (an empty buffer slot, whose step 0
    is not valid, has none)."""
    return valid[:1] & ~valid


def episode_steps(valid: jax.Array) -> jax.Array:
    """Every step of a stored episode [T, B] bool, valid or absorbing (none of an empty buffer slot): the steps the
    discriminator trains on and the generator is rewarded at."""
    return jnp.broadcast_to(valid[:1], valid.shape)


def discriminator_features(traj: Trajectory) -> jax.Array:
    """What the discriminator reads at each step [T, B, d + 1]: the next observation s' and an absorbing indicator,
    (s_{t+1}, 0) at valid steps and the absorbing state (0, 1) after termination."""
    next_obs = traj.obs.imitator[1:]
    absorbed = absorbing(traj.valid)[..., None]
    return jnp.concatenate([jnp.where(absorbed, 0.0, next_obs), absorbed.astype(next_obs.dtype)], axis=-1)


def discriminator_loss(
    expert_logits: jax.Array, expert_mask: jax.Array, gen_logits: jax.Array, gen_mask: jax.Array
) -> jax.Array:
    """Binary cross-entropy, expert = 1 and generator = 0, each the mean over its masked steps:
    mean(-log D(expert)) + mean(-log(1 - D(generator))) with D = sigmoid(logit)."""
    return losses.masked_mean(jax.nn.softplus(-expert_logits), expert_mask) + losses.masked_mean(
        jax.nn.softplus(gen_logits), gen_mask)


def discriminator_batch_loss(
    disc_apply: Callable[[Any, jax.Array], jax.Array], params: Any, expert: Trajectory, gen: Trajectory
) -> jax.Array:
    """``discriminator_loss`` of ``disc_apply(params, features)`` on batches of expert and generator episodes, over
    every step of each stored episode, absorbing steps included."""
    return discriminator_loss(disc_apply(params, discriminator_features(expert)), episode_steps(expert.valid),
                              disc_apply(params, discriminator_features(gen)), episode_steps(gen.valid))


def gail_reward(logits: jax.Array) -> jax.Array:
    """The generator's reward -log(1 - D) = softplus(logit)."""
    return jax.nn.softplus(logits)


def discriminator_rewards(logits: jax.Array, valid: jax.Array) -> jax.Array:
    """The generator's reward per step [T, B] from the discriminator's logits on ``discriminator_features``:
    softplus(logit) at every step of a stored episode, the absorbing state's reward at absorbing steps."""
    return gail_reward(logits) * episode_steps(valid)


def next_step_values(values: jax.Array, goes_on: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(V of the state after step t, whether the episode goes on after step t) for fixed-horizon episodes [T, B]:
    an episode goes on while its next step is in ``goes_on``, and ends at the horizon."""
    next_values = jnp.concatenate([values[1:], jnp.zeros_like(values[:1])], axis=0)
    continues = jnp.concatenate([goes_on[1:], jnp.zeros_like(goes_on[:1])], axis=0).astype(jnp.float32)
    return next_values, continues


def discounted_returns(rewards: jax.Array, gamma: float) -> jax.Array:
    """sum_{j >= t} gamma^(j - t) r_j to the horizon, per step [T, ...]."""

    def body(ret: jax.Array, reward: jax.Array) -> tuple[jax.Array, jax.Array]:
        ret = reward + gamma * ret
        return ret, ret

    _, returns = jax.lax.scan(body, jnp.zeros_like(rewards[0]), rewards, reverse=True)
    return returns


def absorbing_gae_inputs(
    values: jax.Array, rewards: jax.Array, valid: jax.Array, gamma: float
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """GAE's (values, next values, continues) [T, B] with the absorbing state going on to the horizon: each absorbing
    step's value is the exact discounted sum of the rewards from there to the horizon (all of them the absorbing
    state's), in place of the critic's, and every step of a stored episode but the last continues."""
    values = jnp.where(absorbing(valid), discounted_returns(rewards, gamma), values)
    next_values, continues = next_step_values(values, episode_steps(valid))
    return values, next_values, continues


@dataclasses.dataclass(frozen=True)
class GAIL(Algorithm):
    """Adversarial imitation: the generator never sees the expert's actions, only the discriminator's reward."""

    settings = ("gail", GailConfig)

    @classmethod
    def stored_episodes(cls, config: Config) -> int:
        """The expert buffer and one iteration of generator rollouts."""
        return config.train.buffer_episodes + config.gail.rollout_factor * config.train.episodes_per_iter

    @classmethod
    def episodes_in_flight(cls, config: Config) -> int:
        """The generator's rollouts are the largest batch."""
        return max(super().episodes_in_flight(config), config.gail.rollout_factor * config.train.episodes_per_iter)

    @property
    def networks(self) -> tuple[RecurrentPolicy, RecurrentPolicy, Discriminator]:
        """Actor, critic and discriminator."""
        m = self.config.model
        return (RecurrentPolicy(m.width, m.action_embed, m.bc_gru, head_size(self.space), m.cell),
                RecurrentPolicy(m.width, m.action_embed, m.bc_gru, 1, m.cell), Discriminator(m.width))

    @property
    def policy_tx(self) -> optax.GradientTransformation:
        """Generator optimiser: Adam behind a global-norm clip."""
        g = self.config.gail
        return optax.chain(optax.clip_by_global_norm(g.max_grad_norm), optax.adam(g.lr))

    @property
    def disc_tx(self) -> optax.GradientTransformation:
        """Discriminator optimiser: Adam behind a global-norm clip."""
        g = self.config.gail
        return optax.chain(optax.clip_by_global_norm(g.disc_clip), optax.adam(g.disc_lr))

    @property
    def generator_episodes(self) -> int:
        """Generator episodes per iteration."""
        return self.config.gail.rollout_factor * self.config.train.episodes_per_iter

    def init(self, key: jax.Array) -> TrainState:
        """Fresh actor, critic and discriminator; the expert buffer and a buffer for one iteration's rollouts."""
        key, k_actor, k_critic, k_disc = jax.random.split(key, 4)
        actor, critic, disc = self.networks
        size = self.env.obs_sizes(self.env_params).imitator
        obs, act = jnp.zeros((1, size)), jnp.zeros((1, self.space.feature_size))
        gen = {"actor": actor.init(k_actor, obs, act), "critic": critic.init(k_critic, obs, act)}
        example = self.example_episode()
        disc_params = disc.init(k_disc, discriminator_features(example)[0])
        tagged = Tagged(traj=example, tags={"log_prob": jnp.zeros(example.valid.shape, jnp.float32)})
        return TrainState(
            policy=Learner(gen, self.policy_tx.init(gen)),
            encoder=Learner(disc_params, self.disc_tx.init(disc_params)),
            expert_buffer=self._empty_buffer(),
            explore_buffer=self._empty_buffer(tagged, self.generator_episodes),
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )

    def actor(self) -> RecurrentActor:
        """The GRU actor on the imitator's view."""
        return RecurrentActor(self.networks[0], "imitator")

    def actor_params(self, state: TrainState) -> Any:
        """The actor's parameters."""
        return state.policy.params["actor"]

    def policy_outputs(
        self, policy_params: Any, state: TrainState, traj: Trajectory, context: jax.Array | None = None
    ) -> jax.Array:
        """The actor's head outputs [T, B, ...] replayed along ``traj`` from a zero GRU state."""
        del state, context  # Unused.
        return self._scan(self.networks[0], policy_params["actor"], traj)

    def values(self, gen_params: Any, traj: Trajectory) -> jax.Array:
        """The critic's values [T, B] replayed along ``traj``."""
        return self._scan(self.networks[1], gen_params["critic"], traj)[..., 0]

    def _scan(self, network: RecurrentPolicy, params: Any, traj: Trajectory) -> jax.Array:
        """A recurrent network over the imitator's view and the previous actions of ``traj``."""
        prev = losses.prev_actions(action_features(self.space, traj.action))
        return losses.recurrent_policy_scan(network, params, traj.obs.imitator[: traj.horizon], prev)

    def collect_explore(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """Generator rollouts, with the log-probability of each action as it was taken."""
        traj, _, out = rollout_with_outputs(
            self.env, self.env_params, self.actor(), self.actor_params(state), key, self.generator_episodes)
        tagged = Tagged(traj=traj, tags={"log_prob": log_prob(self.space, out, traj.action)})
        state = state.replace(explore_buffer=buffer_add(state.explore_buffer, tagged))
        return state, {"train_return": jnp.mean(jnp.sum(traj.reward, axis=0))}

    def update_encoder(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """``gail.disc_steps`` discriminator steps on batches of expert and generator episodes."""
        grad_fn = jax.value_and_grad(self._disc_loss)

        def step(learner: Learner, step_key: jax.Array) -> tuple[Learner, jax.Array]:
            k_expert, k_gen = jax.random.split(step_key)
            expert = buffer_sample(state.expert_buffer, k_expert, self.config.train.batch_size)
            gen = buffer_sample(state.explore_buffer, k_gen, self.config.train.batch_size).traj
            loss, grads = grad_fn(learner.params, expert, gen)
            return apply_gradients(learner, grads, self.disc_tx), loss

        keys = jax.random.split(key, self.config.gail.disc_steps)
        learner, loss = jax.lax.scan(step, state.encoder, keys)
        return state.replace(encoder=learner), {"disc_loss": jnp.mean(loss)}

    def _disc_loss(self, params: Any, expert: Trajectory, gen: Trajectory) -> jax.Array:
        """``discriminator_batch_loss`` on two batches."""
        return discriminator_batch_loss(self.networks[2].apply, params, expert, gen)

    def rewards(self, state: TrainState, traj: Trajectory) -> jax.Array:
        """The generator's reward per step [T, B]: the discriminator's (absorbing steps included), or the env's with
        ``gail.reward=env`` (zero after termination)."""
        if self.config.gail.reward == "env":
            return traj.reward
        logits = self.networks[2].apply(state.encoder.params, discriminator_features(traj))
        return discriminator_rewards(logits, traj.valid)

    def advantages(self, state: TrainState, traj: Trajectory) -> tuple[jax.Array, jax.Array]:
        """GAE advantages and value targets [T, B] of the generator's rollouts under the current critic, the absorbing
        state going on to the horizon (``absorbing_gae_inputs``)."""
        g = self.config.gail
        rewards = self.rewards(state, traj)
        values, next_values, continues = absorbing_gae_inputs(
            self.values(state.policy.params, traj), rewards, traj.valid, g.gamma)
        adv = gae(rewards, values, next_values, continues, g.gamma, g.gae_lambda)
        return adv, adv + values

    def ppo_loss(self, gen_params: Any, batch: Tagged) -> tuple[jax.Array, dict[str, jax.Array]]:
        """Clipped surrogate + value_coef x critic error - entropy_coef x entropy, over valid steps."""
        g, traj = self.config.gail, batch.traj
        out = self.policy_outputs(gen_params, None, traj)
        adv = normalize_advantages(batch.tags["adv"], traj.valid)
        surrogate = clipped_surrogate(log_prob(self.space, out, traj.action), batch.tags["log_prob"], adv,
                                      g.clip_eps, traj.valid)
        value_loss = squared_value_error(self.values(gen_params, traj), batch.tags["target"], traj.valid)
        ent = losses.masked_mean(entropy(self.space, out), traj.valid)
        total = surrogate + g.value_coef * value_loss - g.entropy_coef * ent
        return total, {"policy_loss": surrogate, "value_loss": value_loss, "entropy": ent}

    def update_policy(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """PPO: ``gail.epochs`` passes over this iteration's rollouts in minibatches of whole episodes."""
        g = self.config.gail
        data = state.explore_buffer.data
        adv, target = self.advantages(state, data.traj)
        data = data.replace(tags={**data.tags, "adv": adv, "target": target})
        grad_fn = jax.value_and_grad(self.ppo_loss, has_aux=True)

        def minibatch(learner: Learner, idx: jax.Array) -> tuple[Learner, dict[str, jax.Array]]:
            (_, metrics), grads = grad_fn(learner.params, jax.tree.map(lambda d: d[:, idx], data))
            return apply_gradients(learner, grads, self.policy_tx), metrics

        def epoch(learner: Learner, epoch_key: jax.Array) -> tuple[Learner, dict[str, jax.Array]]:
            order = jax.random.permutation(epoch_key, self.generator_episodes).reshape(g.minibatches, -1)
            return jax.lax.scan(minibatch, learner, order)

        learner, metrics = jax.lax.scan(epoch, state.policy, jax.random.split(key, g.epochs))
        return state.replace(policy=learner), jax.tree.map(jnp.mean, metrics)
