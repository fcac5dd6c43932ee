"""Deconfounded imitation from expert data alone (the paper's Algorithm 3, Appendix C): an offline VAE over whole
expert episodes learns a dynamics model p_psi and the latent-conditional policy pi_eta; an online inference model q_on
learns the sequential ELBO on synthetic episodes of p_psi; Algorithm 2 with q_on and pi_eta acts at test time.

The imitator never acts in the environment during training: the only env steps are the expert's demonstrations
(collected as every algorithm collects them) and the evaluation. A synthetic episode is a ``lax.scan`` over p_psi
alone: s_0 and the episode's length (its ``valid`` mask) from a stored expert episode, θ-tilde from the prior N(0, I)
(or, ``offline.synthetic_latent=posterior``, from q_off on that expert episode), actions from a θ-independent Markov
policy (``offline.explore``), next observations from p_psi (sampled for Bernoulli observations; the predicted mean
change for Gaussian ones).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from jaxdeconf import losses
from jaxdeconf.algos.base import Learner, TrainState, apply_gradients
from jaxdeconf.algos.dil import Deconfounded
from jaxdeconf.config import Config, field
from jaxdeconf.data import buffer_indices
from jaxdeconf.models import action_features, sample

EXPLORERS = ("uniform", "policy")
SYNTHETIC_LATENTS = ("prior", "posterior")


@dataclasses.dataclass(frozen=True)
class OfflineConfig:
    """dil_offline (the paper's Algorithm 3): an offline VAE over expert episodes, and the online encoder q_on trained
    on synthetic episodes of the VAE's dynamics model. Shared fields: a VAE step takes ``train.batch_size`` expert
    episodes; q_off, p_psi and q_on learn at ``train.encoder_lr``, pi_eta at ``train.policy_lr``; q_on's ELBO uses
    ``train.prediction_steps``; during ``train.warmup`` only the VAE trains."""

    vae_steps: int = field(16, ">=1")  # Offline-ELBO (eq. 12) gradient steps per iteration: q_off, p_psi and pi_eta.
    online_steps: int = field(16, ">=1")  # Online-ELBO (eq. 11) gradient steps of q_on per iteration.
    synthetic_episodes: int = field(16, ">=1")  # Synthetic episodes rolled out through p_psi for each online step.
    # The theta-independent Markov policy that acts in synthetic episodes: "uniform" (uniform over the arms, or over
    # the box [-1, 1]^n) or "policy" (pi_eta on a second latent drawn from the prior, independent of the episode's:
    # states like the imitator's own, where uniform actions would leave the expert's region).
    explore: str = field("uniform", EXPLORERS)
    # Where a synthetic episode's θ-tilde comes from: "posterior" (a sample of q_off on the expert episode that gave
    # s_0: the latents p_psi and pi_eta were trained on) or "prior" (N(0, I), the paper's Algorithm 3, whose draws
    # also land between q_off's clusters; docs/ablations.md).
    synthetic_latent: str = field("posterior", SYNTHETIC_LATENTS)
    beta: float = field(1.0, ">=0")  # KL weight of the offline ELBO (eq. 12), against N(0, I).
    # KL weight of q_on's sequential ELBO (eq. 11) on synthetic episodes: 1 makes q_on the variational posterior under
    # the prior and p_psi.
    online_beta: float = field(1.0, ">=0")


@struct.dataclass
class SyntheticBatch:
    """B synthetic episodes of T steps rolled out through p_psi."""

    obs: jax.Array  # [T+1, B, d]: s_0 (an expert episode's) .. s_T, in the imitator's view.
    action: jax.Array  # [T, B] int32 or [T, B, A] float32.
    valid: jax.Array  # [T, B] bool: the length of the expert episode s_0 came from.
    latent: jax.Array  # [B, L]: the θ-tilde that drove p_psi.


@dataclasses.dataclass(frozen=True)
class DeconfoundedOffline(Deconfounded):
    """Algorithm 3: dil's networks and test-time actor; q_off, p_psi and pi_eta by the offline ELBO (eq. 12) on expert
    episodes, q_on by the sequential ELBO (eq. 11) on synthetic episodes of the frozen p_psi.

    ``state.encoder`` holds params {"encoder": q_on, "decoder": p_psi, "offline": q_off} and opt_state {"encoder":
    q_on's, "model": that of {"decoder", "offline"}}, so that q_on's steps leave the VAE's parameters and moments alone.
    """

    settings = ("offline", OfflineConfig)

    @classmethod
    def stored_episodes(cls, config: Config) -> int:
        """The expert buffer alone: the imitator stores no episodes of its own."""
        return config.train.buffer_episodes

    @classmethod
    def episodes_in_flight(cls, config: Config) -> int:
        """Besides the shared batches, the synthetic episodes rolled out through p_psi."""
        return max(super().episodes_in_flight(config), config.offline.synthetic_episodes)

    @classmethod
    def decoded_episodes(cls, config: Config) -> int:
        """p_psi's batch of expert episodes or q_on's synthetic episodes, whichever is larger."""
        return max(config.train.batch_size, config.offline.synthetic_episodes)

    def init(self, key: jax.Array) -> TrainState:
        """Fresh q_on, q_off, p_psi and pi_eta; an expert buffer and no buffer of own episodes."""
        key, k_on, k_off, k_dec, k_pol = jax.random.split(key, 5)
        encoder, decoder, policy = self.networks
        size, latent = self.env.obs_sizes(self.env_params).imitator, self.config.model.latent
        obs, act, z = jnp.zeros((1, size)), jnp.zeros((1, self.space.feature_size)), jnp.zeros((1, latent))
        enc_obs = self.encoder_obs(obs[None])[0]
        model = {"decoder": decoder.init(k_dec, z, obs, act), "offline": encoder.init(k_off, enc_obs, act)}
        online = encoder.init(k_on, enc_obs, act)
        pol_params = policy.init(k_pol, obs, z)
        return TrainState(
            policy=Learner(pol_params, self.policy_tx.init(pol_params)),
            encoder=Learner({"encoder": online, **model},
                            {"encoder": self.encoder_tx.init(online), "model": self.encoder_tx.init(model)}),
            expert_buffer=self._empty_buffer(),
            explore_buffer=None,
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )

    def collect_explore(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """None: this algorithm never acts in the environment while training."""
        del key  # Unused.
        return state, {}

    def explore_action(self, policy_params: Any, obs: jax.Array, latent: jax.Array, key: jax.Array) -> jax.Array:
        """An action [B] or [B, A] of the synthetic episodes' θ-independent Markov policy at observations [B, d]."""
        batch = obs.shape[0]
        if self.config.offline.explore == "policy":  # ``latent`` is drawn independently of the episode's θ-tilde.
            _, _, policy = self.networks
            return sample(self.space, key, policy.apply(policy_params, obs, latent))
        if self.space.discrete:
            return jax.random.randint(key, (batch,), 0, self.space.n, dtype=jnp.int32)
        return jax.random.uniform(key, (batch, self.space.n), minval=-1.0, maxval=1.0)

    def next_observation(self, obs: jax.Array, out: jax.Array, key: jax.Array) -> jax.Array:
        """s_{t+1} [B, d] from p_psi's output at s_t: a Bernoulli sample, or the predicted (standardised) change."""
        if self.env.obs_likelihood == "bernoulli":
            return jax.random.bernoulli(key, jax.nn.sigmoid(out)).astype(jnp.float32)
        del key  # Unused: the Gaussian dynamics' next observation is the mean.
        return obs + out * self.delta_scale

    def synthetic_rollout(self, state: TrainState, key: jax.Array) -> SyntheticBatch:
        """``offline.synthetic_episodes`` episodes of p_psi under θ-tilde ~ N(0, I): one ``lax.scan`` over the model,
        no env step. Starts and lengths come from expert episodes drawn uniformly with replacement."""
        n, latent = self.config.offline.synthetic_episodes, self.config.model.latent
        _, decoder, _ = self.networks
        k_idx, k_latent, k_explore, k_steps = jax.random.split(key, 4)
        del key  # Split above.
        idx = jax.random.randint(k_idx, (n,), 0, jnp.maximum(state.expert_buffer.size, 1))
        data = state.expert_buffer.data
        theta = self.synthetic_latents(state, jax.tree.map(lambda d: d[:, idx], data), k_latent)
        explore_theta = jax.random.normal(k_explore, (n, latent))
        params = jax.lax.stop_gradient((state.encoder.params["decoder"], state.policy.params))

        def body(obs: jax.Array, step_key: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
            k_act, k_obs = jax.random.split(step_key)
            action = self.explore_action(params[1], obs, explore_theta, k_act)
            out = decoder.apply(params[0], theta, obs, action_features(self.space, action))
            return self.next_observation(obs, out, k_obs), (obs, action)

        last, (obs, action) = jax.lax.scan(body, data.obs.imitator[0, idx], jax.random.split(k_steps, data.horizon))
        obs = jnp.concatenate([obs, last[None]], axis=0)
        return SyntheticBatch(obs=obs, action=action, valid=data.valid[:, idx], latent=theta)

    def synthetic_latents(self, state: TrainState, episodes: Any, key: jax.Array) -> jax.Array:
        """θ-tilde [B, L] of B synthetic episodes: from N(0, I), or (``offline.synthetic_latent=posterior``) sampled
        from q_off on the expert episodes ``episodes`` whose starts the synthetic episodes take."""
        batch, latent = episodes.valid.shape[1], self.config.model.latent
        noise = jax.random.normal(key, (batch, latent))
        if self.config.offline.synthetic_latent == "prior":
            return noise
        encoder, _, _ = self.networks
        feats = action_features(self.space, episodes.action)
        params = jax.lax.stop_gradient(state.encoder.params["offline"])
        mean, logvar = losses.episode_posterior(encoder, params, episodes.obs.imitator, feats, episodes.valid,
                                                self.encoder_scale)
        return mean + jnp.exp(0.5 * logvar) * noise

    def update_encoder(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """``offline.online_steps`` steps of q_on on the sequential ELBO (eq. 11, KL weight ``offline.online_beta``),
        each on fresh synthetic episodes; the decoder is the VAE's p_psi held frozen, so q_on's latent space is the one
        pi_eta was trained in."""
        frozen = jax.lax.stop_gradient(state.encoder.params["decoder"])
        loss_fn = functools.partial(self.elbo_fn, beta=self.config.offline.online_beta)

        def online_loss(params: Any, batch: SyntheticBatch, noise_key: jax.Array) -> tuple[jax.Array, dict]:
            feats = action_features(self.space, batch.action)
            return loss_fn({"encoder": params, "decoder": frozen}, batch.obs, feats, batch.valid, noise_key)

        grad_fn = jax.value_and_grad(online_loss, has_aux=True)

        def step(learner: Learner, step_key: jax.Array) -> tuple[Learner, dict[str, jax.Array]]:
            k_roll, k_noise = jax.random.split(step_key)
            (loss, metrics), grads = grad_fn(learner.params, self.synthetic_rollout(state, k_roll), k_noise)
            return apply_gradients(learner, grads, self.encoder_tx), {"elbo_loss": loss, **metrics}

        online = Learner(state.encoder.params["encoder"], state.encoder.opt_state["encoder"])
        online, metrics = jax.lax.scan(step, online, jax.random.split(key, self.config.offline.online_steps))
        learner = Learner({**state.encoder.params, "encoder": online.params},
                          {**state.encoder.opt_state, "encoder": online.opt_state})
        return state.replace(encoder=learner), jax.tree.map(jnp.mean, metrics)

    @property
    def offline_elbo_fn(self) -> Any:
        """``losses.offline_elbo_loss`` bound to the networks and to ``decoder_scoring``, the scoring q_on's ELBO
        (``elbo_fn``) reads the same p_psi with: one definition for both."""
        encoder, decoder, policy = self.networks
        return functools.partial(losses.offline_elbo_loss, encoder=encoder, decoder=decoder, policy=policy,
                                 space=self.space, beta=self.config.offline.beta,
                                 encoder_delta_scale=self.encoder_scale, **self.decoder_scoring)

    def update_policy(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """``offline.vae_steps`` steps of the offline ELBO (eq. 12) on batches of whole expert episodes, training
        q_off, p_psi and pi_eta together: the policy is the VAE's action decoder."""
        t = self.config.train
        loss_fn = self.offline_elbo_fn

        def vae_loss(model: Any, policy_params: Any, batch: Any, noise_key: jax.Array) -> tuple[jax.Array, dict]:
            return loss_fn({**model, "policy": policy_params}, batch.obs.imitator, batch.action, batch.valid,
                           noise_key)

        grad_fn = jax.value_and_grad(vae_loss, argnums=(0, 1), has_aux=True)

        def step(carry: tuple[Learner, Learner], step_key: jax.Array) -> tuple[tuple[Learner, Learner], dict]:
            model, pol = carry
            k_batch, k_noise = jax.random.split(step_key)
            idx = buffer_indices(state.expert_buffer, k_batch, t.batch_size)
            batch = jax.tree.map(lambda d: d[:, idx], state.expert_buffer.data)
            (loss, metrics), (g_model, g_policy) = grad_fn(model.params, pol.params, batch, k_noise)
            model = apply_gradients(model, g_model, self.encoder_tx)
            return (model, apply_gradients(pol, g_policy, self.policy_tx)), {"vae_loss": loss, **metrics}

        params, opt = state.encoder.params, state.encoder.opt_state
        model = Learner({"decoder": params["decoder"], "offline": params["offline"]}, opt["model"])
        (model, pol), metrics = jax.lax.scan(step, (model, state.policy),
                                             jax.random.split(key, self.config.offline.vae_steps))
        encoder_learner = Learner({**params, **model.params}, {**opt, "model": model.opt_state})
        return state.replace(encoder=encoder_learner, policy=pol), jax.tree.map(jnp.mean, metrics)

    def iteration(self, state: TrainState, _: Any = None) -> tuple[TrainState, dict[str, jax.Array]]:
        """Algorithm 3's loop body after collecting expert data: q_on on synthetic episodes (from ``train.warmup`` on,
        once p_psi has learnt something), then the offline VAE (q_off, p_psi, pi_eta)."""
        key, k_expert, k_online, k_vae = jax.random.split(state.key, 4)
        state, m_expert = self.collect_expert(state.replace(key=key), k_expert)
        trained, m_online = self.update_encoder(state, k_online)
        warm = state.iteration >= self.config.train.warmup
        state = state.replace(encoder=jax.tree.map(lambda new, old: jnp.where(warm, new, old), trained.encoder,
                                                   state.encoder))
        m_online = {name: jnp.where(warm, value, jnp.nan) for name, value in m_online.items()}
        state, m_vae = self.update_policy(state, k_vae)
        return state.replace(iteration=state.iteration + 1), {**m_expert, **m_online, **m_vae}
