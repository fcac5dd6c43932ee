"""Naive BC, the oracle and deconfounded IL (Algorithm 1) as pure functions of a TrainState.

``init -> iteration -> train_chunk``: a chunk is a ``lax.scan`` over iterations followed by one evaluation, and the
caller vmaps it over seeds, so collection, updates and evaluation of all seeds run in one compiled program.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from jaxdeconf import losses
from jaxdeconf.actors import DeconfoundedActor, ExpertActor, RecurrentActor
from jaxdeconf.config import Config
from jaxdeconf.data import (
    Buffer,
    Trajectory,
    best_action_prob,
    buffer_add,
    buffer_indices,
    buffer_init,
    buffer_sample,
    replay,
    rollout,
)
from jaxdeconf.envs.base import Environment, NormalizedViews
from jaxdeconf.models import (
    Decoder,
    Encoder,
    EvidenceEncoder,
    LatentPolicy,
    RecurrentPolicy,
    action_features,
    head_size,
)


@struct.dataclass
class Learner:
    """Parameters and optimiser state of one set of networks."""

    params: Any
    opt_state: Any


@struct.dataclass
class TrainState:
    """Everything one seed's run carries between iterations (checkpointed whole, so resuming is exact)."""

    policy: Learner
    encoder: Learner | None  # Inference model and decoder (dil only).
    expert_buffer: Buffer
    explore_buffer: Buffer | None  # The imitator's own episodes (dil only).
    key: jax.Array
    iteration: jax.Array  # int32: iterations done.


def make_optimizer(lr: float, weight_decay: float, clip: float) -> optax.GradientTransformation:
    """AdamW behind a global-norm clip."""
    return optax.chain(optax.clip_by_global_norm(clip), optax.adamw(lr, weight_decay=weight_decay))


def apply_gradients(learner: Learner, grads: Any, tx: optax.GradientTransformation) -> Learner:
    """One optimiser step."""
    updates, opt_state = tx.update(grads, learner.opt_state, learner.params)
    return Learner(params=optax.apply_updates(learner.params, updates), opt_state=opt_state)


def observation_delta_scale(env: Environment, env_params: Any, episodes: int = 64) -> jax.Array:
    """Per-dimension standard deviation of the imitator's one-step observation changes on expert episodes (fixed
    key, so every seed and run uses the same scale), floored at 1e-3."""
    traj, _ = jax.jit(lambda k: rollout(env, env_params, ExpertActor(env, env_params), None, k, episodes))(
        jax.random.key(0))
    obs = traj.obs.imitator
    delta = obs[1:] - obs[:-1]
    mask = traj.valid[..., None].astype(jnp.float32)
    count = jnp.maximum(mask.sum((0, 1)), 1.0)
    mean = (delta * mask).sum((0, 1)) / count
    var = (((delta - mean) ** 2) * mask).sum((0, 1)) / count
    return jax.device_get(jnp.maximum(jnp.sqrt(var), 1e-3))


def fit_view_normalizer(env: Environment, env_params: Any, episodes: int = 64) -> NormalizedViews:
    """``env`` with its imitator and oracle views standardised by the per-dimension mean and standard deviation
    (floored at 1e-3) over ``episodes`` expert episodes drawn with a fixed key, identical for every seed and run."""
    traj, _ = jax.jit(lambda k: rollout(env, env_params, ExpertActor(env, env_params), None, k, episodes))(
        jax.random.key(1))
    mask = traj.valid.astype(jnp.float32)[..., None]
    mask = jnp.concatenate([jnp.ones_like(mask[:1]), mask])  # obs has T + 1 steps; the first is always real.
    stats = {}
    for view in ("imitator", "oracle"):
        obs = getattr(traj.obs, view)
        count = mask.sum((0, 1))
        mean = (obs * mask).sum((0, 1)) / count
        std = jnp.sqrt((((obs - mean) ** 2) * mask).sum((0, 1)) / count)
        stats[view] = (np.asarray(mean), np.asarray(jnp.maximum(std, 1e-3)))
    return NormalizedViews(env, stats)


@dataclasses.dataclass(frozen=True)
class Algorithm:
    """What all algorithms share: expert data collection, the policy's BC updates, evaluation and the chunk loop."""

    env: Environment
    env_params: Any
    config: Config

    @property
    def space(self) -> Any:
        """The env's action space."""
        return self.env.action_space(self.env_params)

    @property
    def policy_tx(self) -> optax.GradientTransformation:
        """Policy optimiser."""
        t = self.config.train
        return make_optimizer(t.policy_lr, t.weight_decay, t.policy_clip)

    def _empty_buffer(self) -> Buffer:
        """An empty episode buffer shaped like this env's trajectories."""
        shape = jax.eval_shape(
            lambda k: rollout(self.env, self.env_params, ExpertActor(self.env, self.env_params), None, k, 1)[0],
            jax.random.key(0),
        )
        example = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shape)
        return buffer_init(example, self.config.train.buffer_episodes)

    # To be provided by each algorithm.
    def init(self, key: jax.Array) -> TrainState:
        """Fresh networks, optimisers and empty buffers for one seed."""
        raise NotImplementedError

    def actor(self) -> Any:
        """The imitator as an Actor (Algorithm 2 for dil)."""
        raise NotImplementedError

    def actor_params(self, state: TrainState) -> Any:
        """Parameters the actor needs."""
        raise NotImplementedError

    def policy_outputs(
        self, policy_params: Any, state: TrainState, traj: Trajectory, context: jax.Array | None = None
    ) -> jax.Array:
        """Policy head outputs [T, B, ...] along ``traj`` (teacher-forced), differentiable in ``policy_params``.

        ``context`` is this batch's slice of ``policy_context`` when one was precomputed.
        """
        raise NotImplementedError

    def policy_context(self, state: TrainState) -> jax.Array | None:
        """Per-episode inputs [T, capacity, ...] computed once for the whole expert buffer before the policy steps
        (what stays fixed while the policy trains), or None."""
        del state  # Unused.
        return None

    def update_encoder(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """Inference-model updates (none by default)."""
        del key  # Unused.
        return state, {}

    def collect_explore(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """Exploration data (none by default)."""
        del key  # Unused.
        return state, {}

    # Shared.
    def collect_expert(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """Roll out the expert and store its episodes."""
        actor = ExpertActor(self.env, self.env_params)
        traj, _ = rollout(self.env, self.env_params, actor, None, key, self.config.train.episodes_per_iter)
        state = state.replace(expert_buffer=buffer_add(state.expert_buffer, traj))
        return state, {"expert_return": jnp.mean(jnp.sum(traj.reward, axis=0))}

    def policy_loss(
        self, policy_params: Any, state: TrainState, batch: Trajectory, context: jax.Array | None
    ) -> jax.Array:
        """BC negative log-likelihood of the expert's actions (eq. 10)."""
        out = self.policy_outputs(policy_params, state, batch, context)
        return losses.nll_from_outputs(self.space, out, batch.action, batch.valid)

    def update_policy(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """``policy_steps`` BC steps on batches of whole expert episodes."""
        grad_fn = jax.value_and_grad(self.policy_loss)
        context = self.policy_context(state)

        def step(learner: Learner, step_key: jax.Array) -> tuple[Learner, jax.Array]:
            idx = buffer_indices(state.expert_buffer, step_key, self.config.train.batch_size)
            batch = jax.tree.map(lambda d: d[:, idx], state.expert_buffer.data)
            ctx = None if context is None else context[:, idx]
            loss, grads = grad_fn(learner.params, state, batch, ctx)
            return apply_gradients(learner, grads, self.policy_tx), loss

        keys = jax.random.split(key, self.config.train.policy_steps)
        learner, loss = jax.lax.scan(step, state.policy, keys)
        return state.replace(policy=learner), {"policy_loss": jnp.mean(loss)}

    def iteration(self, state: TrainState, _: Any = None) -> tuple[TrainState, dict[str, jax.Array]]:
        """Collect, update the inference model, then (after warm-up) the policy."""
        key, k_expert, k_explore, k_enc, k_pol = jax.random.split(state.key, 5)
        state, m_expert = self.collect_expert(state.replace(key=key), k_expert)
        state, m_explore = self.collect_explore(state, k_explore)
        state, m_enc = self.update_encoder(state, k_enc)
        updated, m_pol = self.update_policy(state, k_pol)
        warm = state.iteration >= self.config.train.warmup
        state = jax.tree.map(lambda new, old: jnp.where(warm, new, old), updated, state)
        m_pol = {name: jnp.where(warm, value, jnp.nan) for name, value in m_pol.items()}
        return state.replace(iteration=state.iteration + 1), {**m_expert, **m_explore, **m_enc, **m_pol}

    def evaluate(self, state: TrainState, key: jax.Array) -> dict[str, jax.Array]:
        """Online returns and per-step P(best action), online and teacher-forced on fresh expert episodes."""
        k_online, k_expert = jax.random.split(key)
        n = self.config.train.eval_episodes
        traj, p_online = rollout(self.env, self.env_params, self.actor(), self.actor_params(state), k_online, n)
        expert_traj, _ = rollout(self.env, self.env_params, ExpertActor(self.env, self.env_params), None, k_expert, n)
        out = replay(self.actor(), self.actor_params(state), expert_traj, self.space)
        metrics = {
            "eval_return": jnp.mean(jnp.sum(traj.reward, axis=0)),
            "eval_expert_nll": losses.nll_from_outputs(self.space, out, expert_traj.action, expert_traj.valid),
            "p_best_online": jnp.mean(p_online, axis=1),
            "p_best_expert": jnp.mean(best_action_prob(out, expert_traj.best_action), axis=1)
            if self.space.discrete
            else jnp.full((expert_traj.horizon,), jnp.nan),
        }
        for name, value in traj.extras.items():
            metrics[f"eval_{name}"] = jnp.mean(jnp.sum(value, axis=0))
        return metrics

    def train_chunk(self, state: TrainState, length: int) -> tuple[TrainState, dict[str, Any], dict[str, Any]]:
        """``length`` iterations then one evaluation: (state, per-iteration metrics [length], eval metrics)."""
        state, per_iter = jax.lax.scan(self.iteration, state, None, length=length)
        key, k_eval = jax.random.split(state.key)
        return state.replace(key=key), per_iter, self.evaluate(state, k_eval)


@dataclasses.dataclass(frozen=True)
class BehaviourCloning(Algorithm):
    """Naive recurrent BC on the imitator's view; with ``view="oracle"`` the oracle that also sees θ."""

    view: str = "imitator"

    @property
    def network(self) -> RecurrentPolicy:
        """The recurrent policy."""
        m = self.config.model
        return RecurrentPolicy(m.width, m.action_embed, m.bc_gru, head_size(self.space))

    def init(self, key: jax.Array) -> TrainState:
        """Fresh GRU policy and an expert buffer."""
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
        """The GRU policy acting on its view."""
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


@dataclasses.dataclass(frozen=True)
class Deconfounded(Algorithm):
    """Algorithm 1: an inference model trained by the sequential ELBO on the imitator's own episodes, and a
    latent-conditional policy cloned on expert episodes with θ-hat = the posterior mean at the current step.

    For Gaussian observation likelihoods the decoder predicts standardised one-step changes of the observation; the
    per-dimension scale is fixed once from expert data (``delta_scale``), as the paper normalises from expert data.
    """

    def __post_init__(self) -> None:
        object.__setattr__(self, "delta_scale", observation_delta_scale(self.env, self.env_params)
                           if self.env.obs_likelihood == "gaussian" else None)

    @property
    def encoder_scale(self) -> Any:
        """The delta scale when the encoder reads standardised changes (``model.encoder_deltas``), else None."""
        return self.delta_scale if self.config.model.encoder_deltas else None

    def encoder_obs(self, obs: jax.Array) -> jax.Array:
        """What q_phi reads along a sequence obs [T, B, d]: obs, or ``losses.transition_inputs``."""
        scale = self.encoder_scale
        return obs if scale is None else losses.transition_inputs(obs, scale)

    @property
    def networks(self) -> tuple[Encoder | EvidenceEncoder, Decoder, LatentPolicy]:
        """Encoder q_phi, decoder p_psi and policy pi_eta."""
        m = self.config.model
        size = self.env.obs_sizes(self.env_params).imitator
        return (
            Encoder(m.width, m.action_embed, m.gru, m.latent) if m.encoder == "gru"
            else EvidenceEncoder(m.width, m.action_embed, m.latent),
            Decoder(m.width, m.action_embed, size),
            LatentPolicy(m.width, head_size(self.space)),
        )

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
        """The imitator's own episodes (the exploration policy is pi_eta on the current posterior mean)."""
        n = self.config.train.episodes_per_iter
        traj, _ = rollout(self.env, self.env_params, self.actor(), self.actor_params(state), key, n)
        state = state.replace(explore_buffer=buffer_add(state.explore_buffer, traj))
        return state, {"train_return": jnp.mean(jnp.sum(traj.reward, axis=0))}

    def update_encoder(self, state: TrainState, key: jax.Array) -> tuple[TrainState, dict[str, jax.Array]]:
        """``encoder_steps`` ELBO steps on batches of whole exploration episodes."""
        t = self.config.train
        encoder, decoder, _ = self.networks
        loss_fn = functools.partial(
            losses.elbo_loss,
            encoder=encoder,
            decoder=decoder,
            beta=t.beta,
            steps=t.prediction_steps,
            likelihood=self.env.obs_likelihood,
            delta_scale=self.delta_scale,
            encoder_delta_scale=self.encoder_scale,
        )
        grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

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

    def policy_context(self, state: TrainState) -> jax.Array | None:
        """The encoder is frozen during the policy steps, so when the policy steps would encode at least as many
        episodes as the buffer holds, encoding the whole buffer once gives the same latents for less work."""
        t = self.config.train
        if t.buffer_episodes > t.batch_size * t.policy_steps:
            return None
        return self.posterior_means(state, state.expert_buffer.data)

    def policy_outputs(
        self, policy_params: Any, state: TrainState, traj: Trajectory, context: jax.Array | None = None
    ) -> jax.Array:
        """pi_eta(a_t | s_t, mean of q_phi(. | tau_{:t})) with the encoder frozen (detached)."""
        _, _, policy = self.networks
        mean = self.posterior_means(state, traj) if context is None else context
        return policy.apply(policy_params, traj.obs.imitator[: traj.horizon], mean)


def make_algorithm(name: str, env: Environment, env_params: Any, config: Config) -> Algorithm:
    """Algorithm by name: bc, oracle or dil; envs that ask for it get their learner views standardised first."""
    if env.normalize_views and not isinstance(env, NormalizedViews):
        env = fit_view_normalizer(env, env_params)
    if name == "bc":
        return BehaviourCloning(env, env_params, config, view="imitator")
    if name == "oracle":
        return BehaviourCloning(env, env_params, config, view="oracle")
    if name == "dil":
        return Deconfounded(env, env_params, config)
    raise ValueError(f"unknown algorithm {name!r}; allowed: bc, oracle, dil")
