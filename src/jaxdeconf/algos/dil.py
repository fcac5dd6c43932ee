"""Deconfounded imitation learning (Algorithm 1): q_phi by the sequential ELBO on the imitator's own episodes, then
a latent-conditional policy cloned on expert episodes with θ-hat inferred by q_phi; Algorithm 2 at test time."""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import optax

from jaxdeconf import losses
from jaxdeconf.actors import DeconfoundedActor
from jaxdeconf.algos.base import (
    Algorithm,
    Learner,
    TrainState,
    apply_gradients,
    make_optimizer,
    observation_delta_scale,
)
from jaxdeconf.config import Config, field
from jaxdeconf.data import Trajectory, buffer_add, buffer_sample, rollout
from jaxdeconf.envs import ObsGroup
from jaxdeconf.models import (
    Decoder,
    Encoder,
    EvidenceEncoder,
    LatentPolicy,
    action_features,
    head_size,
    make_encoder,
)

ENCODERS = ("gru", "evidence", "filter")
WEIGHTINGS = losses.WEIGHTINGS
GROUP_LIKELIHOODS = ("declared", "gaussian")
POLICY_LATENTS = ("current", "matched")
FUSIONS = ("late", "early")


@dataclasses.dataclass(frozen=True)
class DilConfig:
    """How the deconfounded imitator's networks read their inputs. The defaults are the paper's Algorithm 1 with the
    reference code's inputs and decoder weighting; presets never set these (only sizes and budgets differ by env)."""

    # Also feed q_phi the standardised change (s_t - s_{t-1}) / delta_scale that the decoder scores (Gaussian
    # likelihoods only): the evidence about theta is in transitions. Off is the paper's input (s_t, a_{t-1}).
    encoder_deltas: bool = False
    # q_phi's recurrence: "gru" (the paper's), "evidence" (a product of per-step Gaussian factors, whose belief cannot
    # fade once the evidence is in) or "filter" (the same product with each factor read off the step and the belief
    # so far: assumed-density filtering). models.py has the three.
    encoder: str = field("gru", ENCODERS)
    # How the decoder weighs the groups of the imitator's view an env declares (``Environment.obs_groups``: e.g. the
    # body and the cue): "group_mean" averages within each group and adds the groups (the reference code's per-key
    # MSE), "sum" adds every dimension's NLL. One-group envs (bandit, LunarLander) differ only in scale.
    decoder_weighting: str = field("group_mean", WEIGHTINGS)
    # Each group's likelihood: "declared" (the env's: e.g. Bernoulli for a ±1 indicator) or "gaussian" for all.
    group_likelihood: str = field("declared", GROUP_LIKELIHOODS)
    # The θ-hat the policy is cloned on, at every step of an expert episode: "current" (q_phi's posterior mean at
    # that step, the paper's) or "matched" (the posterior mean over the final beliefs of the imitator's own stored
    # episodes, each weighed by the decoder's likelihood of the expert episode: θ coded as q_phi codes it on the
    # imitator's own episodes, where the policy reads it online). Online the policy reads the current posterior mean.
    policy_latent: str = field("current", POLICY_LATENTS)
    # ``matched`` only: how many of the own buffer's slots are codes (evenly spaced, so the codes span the buffer's
    # ages; at most the buffer's capacity); 0 for every slot. Its cost per iteration is expert-buffer capacity x codes
    # x horizon decoder steps.
    match_codes: int = field(0, ">=0")
    # Where the policy reads θ-hat (``models.LatentPolicy``): "late", after the observation's own MLP (the reference
    # code's), or "early", beside the observation at the input, where the oracle's θ sits in its view.
    policy_fusion: str = field("late", FUSIONS)


@dataclasses.dataclass(frozen=True)
class Deconfounded(Algorithm):
    """Algorithm 1: an inference model trained by the sequential ELBO on the imitator's own episodes, and a
    latent-conditional policy cloned on expert episodes with θ-hat = the posterior mean at the current step (or, with
    ``dil.policy_latent=matched``, a code of the imitator's own episodes matched by the decoder's likelihood).

    For Gaussian observation likelihoods the decoder predicts standardised one-step changes of the observation; the
    per-dimension scale is fixed once from expert data (``delta_scale``), as the paper normalises from expert data.
    """

    settings = ("dil", DilConfig)
    #: The section of ``DilConfig`` fields this class reads (a subclass with its own settings may keep reading it).
    method_section: ClassVar[str] = "dil"

    @classmethod
    def stored_episodes(cls, config: Config) -> int:
        """The expert buffer and the buffer of the imitator's own episodes."""
        return 2 * config.train.buffer_episodes

    @classmethod
    def decoded_episodes(cls, config: Config) -> int:
        """The ELBO's batch of exploration episodes."""
        return config.train.batch_size

    def __post_init__(self) -> None:
        object.__setattr__(self, "delta_scale", observation_delta_scale(self.env, self.env_params)
                           if self.env.obs_likelihood == "gaussian" else None)

    @property
    def method(self) -> DilConfig:
        """How the networks read their inputs (the ``method_section`` of the config)."""
        return getattr(self.config, self.method_section)

    @property
    def encoder_scale(self) -> Any:
        """The delta scale when the encoder reads standardised changes (``encoder_deltas``), else None."""
        return self.delta_scale if self.method.encoder_deltas else None

    def encoder_obs(self, obs: jax.Array) -> jax.Array:
        """What q_phi reads along a sequence obs [T, B, d]: obs, or ``losses.transition_inputs``."""
        scale = self.encoder_scale
        return obs if scale is None else losses.transition_inputs(obs, scale)

    @property
    def networks(self) -> tuple[Encoder | EvidenceEncoder, Decoder, LatentPolicy]:
        """Encoder q_phi, decoder p_psi and policy pi_eta."""
        m, method = self.config.model, self.method
        size = self.env.obs_sizes(self.env_params).imitator
        return (
            make_encoder(method.encoder, m.width, m.action_embed, m.gru, m.latent, m.cell),
            Decoder(m.width, m.action_embed, size),
            LatentPolicy(m.width, head_size(self.space), method.policy_fusion),
        )

    @property
    def decoder_groups(self) -> tuple[ObsGroup, ...] | None:
        """The env's groups of the imitator's view, each with its likelihood (``group_likelihood``); None when
        they change nothing (all under the env's likelihood, and summed or each of one dimension), so the decoder's
        loss is the one-family one."""
        groups = self.env.obs_groups(self.env_params)
        if self.method.group_likelihood == "gaussian":
            groups = tuple(dataclasses.replace(g, likelihood="gaussian") for g in groups)
        same_family = all(g.likelihood == self.env.obs_likelihood for g in groups)
        if same_family and (self.method.decoder_weighting == "sum" or all(g.size == 1 for g in groups)):
            return None
        return groups

    @property
    def encoder_tx(self) -> optax.GradientTransformation:
        """Inference-model optimiser."""
        t = self.config.train
        return make_optimizer(t.encoder_lr, t.weight_decay, t.encoder_clip)

    def init(self, key: jax.Array) -> TrainState:
        """Fresh encoder, decoder and policy; expert and exploration buffers."""
        key, k_enc, k_dec, k_pol = jax.random.split(key, 4)
        encoder, decoder, policy = self.networks
        size, latent = self.env.obs_sizes(self.env_params).imitator, self.config.model.latent
        obs, act, z = jnp.zeros((1, size)), jnp.zeros((1, self.space.feature_size)), jnp.zeros((1, latent))
        enc_obs = self.encoder_obs(obs[None])[0]
        enc_params = {"encoder": encoder.init(k_enc, enc_obs, act), "decoder": decoder.init(k_dec, z, obs, act)}
        pol_params = policy.init(k_pol, obs, z)
        return TrainState(
            policy=Learner(pol_params, self.policy_tx.init(pol_params)),
            encoder=Learner(enc_params, self.encoder_tx.init(enc_params)),
            expert_buffer=self._empty_buffer(),
            explore_buffer=self._empty_buffer(),
            key=key,
            iteration=jnp.zeros((), jnp.int32),
        )

    def actor(self) -> DeconfoundedActor:
        """Algorithm 2."""
        encoder, _, policy = self.networks
        return DeconfoundedActor(encoder, policy, self.encoder_scale)

    def actor_params(self, state: TrainState) -> dict[str, Any]:
        """Encoder and policy parameters."""
        return {"encoder": state.encoder.params["encoder"], "policy": state.policy.params}

    def collect_explore(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """The imitator's own episodes: pi_eta on the current posterior mean (Algorithm 2)."""
        n = self.config.train.episodes_per_iter
        traj, _ = rollout(self.env, self.env_params, self.actor(), self.actor_params(state), key, n)
        state = state.replace(explore_buffer=buffer_add(state.explore_buffer, traj))
        return state, {"train_return": jnp.mean(jnp.sum(traj.reward, axis=0))}

    @property
    def elbo_fn(self) -> Any:
        """``losses.elbo_loss`` bound to this algorithm's networks, likelihood, scales and ``train.*`` constants."""
        t = self.config.train
        encoder, decoder, _ = self.networks
        return functools.partial(
            losses.elbo_loss,
            encoder=encoder,
            decoder=decoder,
            beta=t.beta,
            steps=t.prediction_steps,
            encoder_delta_scale=self.encoder_scale,
            **self.decoder_scoring,
        )

    @property
    def decoder_scoring(self) -> dict[str, Any]:
        """How the decoder's predictions are scored (``losses.prediction_nll``'s keywords), shared by the ELBO and
        ``dynamics_nll``."""
        return {"likelihood": self.env.obs_likelihood, "delta_scale": self.delta_scale, "groups": self.decoder_groups,
                "weighting": self.method.decoder_weighting}

    def update_encoder(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """``encoder_steps`` ELBO steps on batches of whole exploration episodes."""
        t = self.config.train
        grad_fn = jax.value_and_grad(self.elbo_fn, has_aux=True)

        def step(learner: Learner, step_key: jax.Array) -> tuple[Learner, dict[str, jax.Array]]:
            k_batch, k_noise = jax.random.split(step_key)
            batch = buffer_sample(state.explore_buffer, k_batch, t.batch_size)
            feats = action_features(self.space, batch.action)
            (loss, metrics), grads = grad_fn(learner.params, batch.obs.imitator, feats, batch.valid, k_noise)
            return apply_gradients(learner, grads, self.encoder_tx), {"elbo_loss": loss, **metrics}

        learner, metrics = jax.lax.scan(step, state.encoder, jax.random.split(key, t.encoder_steps))
        return state.replace(encoder=learner), jax.tree.map(jnp.mean, metrics)

    def posterior_means(self, state: TrainState, traj: Trajectory) -> jax.Array:
        """Posterior means [T, B, L] of q_phi along ``traj``, detached: the policy never trains the encoder."""
        encoder, _, _ = self.networks
        obs = self.encoder_obs(traj.obs.imitator[: traj.horizon])
        prev = losses.prev_actions(action_features(self.space, traj.action))
        mean, _ = losses.encoder_scan(encoder, state.encoder.params["encoder"], obs, prev)
        return jax.lax.stop_gradient(mean)

    def belief(self, state: TrainState, traj: Trajectory) -> jax.Array:
        """q_phi's posterior means along ``traj``."""
        return self.posterior_means(state, traj)

    def policy_context(self, state: TrainState, key: jax.Array) -> jax.Array | None:
        """θ-hat along the whole expert buffer, computed once before the policy steps: the encoder is frozen during
        them, so where the steps would encode at least as many episodes as the buffer holds this is the same latents
        for less work; ``matched`` always encodes the buffer once (it weighs every expert episode against every stored
        own episode, too costly per batch)."""
        del key  # Unused: the latents are posterior means, no draw.
        t = self.config.train
        if self.method.policy_latent == "current" and t.buffer_episodes > t.batch_size * t.policy_steps:
            return None
        return self.training_context(state, state.expert_buffer.data)

    def training_context(self, state: TrainState, traj: Trajectory) -> jax.Array:
        """The θ-hat [T, B, L] the policy is cloned on along expert episodes ``traj`` (``policy_latent``)."""
        if self.method.policy_latent == "matched":
            return self.matched_latents(state, traj)
        return self.posterior_means(state, traj)

    def matched_latents(self, state: TrainState, traj: Trajectory) -> jax.Array:
        """θ-hat [T, B, L] for ``policy_latent=matched``: per expert episode, the posterior mean over the final
        codes of the imitator's own stored episodes (``match_codes`` of its slots) under the decoder's likelihood
        of the expert episode (``decoder_posterior_mean``), so the policy is cloned on codes from where q_phi's online
        beliefs live."""
        own, wanted = state.explore_buffer, self.method.match_codes
        count = min(wanted, own.capacity) if wanted else own.capacity
        slots = jnp.arange(count) * own.capacity // count  # Evenly spaced over the buffer.
        data = jax.tree.map(lambda x: x[:, slots], own.data)
        particles = final_latents(self.posterior_means(state, data), data.valid)
        filled = slots < own.size
        z = decoder_posterior_mean(self.dynamics_nll(state), particles, filled, traj.obs.imitator,
                                   action_features(self.space, traj.action), traj.valid)
        return jnp.broadcast_to(z, (traj.horizon, *z.shape))

    def dynamics_nll(self, state: TrainState) -> Any:
        """(z, obs, action_feats, valid) -> the decoder's one-step NLL per step [T, B], as the ELBO scores it."""
        _, decoder, _ = self.networks
        fn = functools.partial(losses.prediction_nll, decoder, state.encoder.params["decoder"], steps=1,
                               **self.decoder_scoring)
        return lambda z, obs, feats, valid: fn(z, obs, feats, valid)[0]

    def policy_outputs(
        self, policy_params: Any, state: TrainState, traj: Trajectory, context: jax.Array | None = None
    ) -> jax.Array:
        """pi_eta(a_t | s_t, θ-hat) with θ-hat from the frozen (detached) encoder (``training_context``)."""
        _, _, policy = self.networks
        if context is None:
            context = self.training_context(state, traj)
        return policy.apply(policy_params, traj.obs.imitator[: traj.horizon], context)


def final_latents(mean: jax.Array, valid: jax.Array) -> jax.Array:
    """Each episode's posterior mean [B, L] at its last valid step, from means [T, B, L] and mask [T, B]."""
    last = jnp.maximum(jnp.sum(valid, axis=0) - 1, 0)
    return jnp.take_along_axis(mean, last[None, :, None], axis=0)[0]


def decoder_posterior_mean(
    nll: Any, particles: jax.Array, filled: jax.Array, obs: jax.Array, feats: jax.Array, valid: jax.Array
) -> jax.Array:
    """Posterior means [B, L] of θ-hat for episodes obs [T+1, B, d], action features [T, B, A], valid [T, B] when the
    prior is uniform over the codes ``particles`` [P, L] (where ``filled`` [P] holds) and the likelihood of an episode
    given a code is the decoder's, ``exp(-sum_t nll(z, ...))`` over its valid steps. ``nll`` maps (z, obs, feats,
    valid) with batch axis P to the NLL per step [T, P]. One episode at a time (``lax.map``), so memory is T x P.
    At least one code must be filled (else NaN). Summed over a whole episode, the weights are close to one-hot."""
    P = particles.shape[0]

    def one(episode: tuple[jax.Array, jax.Array, jax.Array]) -> jax.Array:
        tiled = jax.tree.map(lambda x: jnp.broadcast_to(x[:, None], (x.shape[0], P, *x.shape[1:])), episode)
        z = jnp.broadcast_to(particles, (tiled[2].shape[0], *particles.shape))
        log_lik = -jnp.sum(nll(z, *tiled) * tiled[2], axis=0)
        weights = jax.nn.softmax(jnp.where(filled, log_lik, -jnp.inf))
        return weights @ particles

    return jax.lax.map(one, jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), (obs, feats, valid)))
