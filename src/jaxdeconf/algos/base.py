"""What every algorithm shares: the TrainState, optimisers, expert collection, the policy's BC steps, evaluation
and the chunk loop.

``init -> iteration -> train_chunk``: a chunk is a ``lax.scan`` over iterations followed by one evaluation, and the
caller vmaps it over seeds, so collection, updates and evaluation of all seeds run in one compiled program. An
algorithm subclasses ``Algorithm`` in a file of its own and fills in the hooks (``init``, ``actor``, ``actor_params``,
``policy_outputs``, and where it needs them ``collect_explore``, ``update_encoder``, ``update_policy``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from jaxdeconf import diagnostics, losses
from jaxdeconf.actors import ExpertActor
from jaxdeconf.config import Config
from jaxdeconf.data import (
    Buffer,
    Trajectory,
    best_action_prob,
    buffer_add,
    buffer_indices,
    buffer_init,
    replay,
    rollout,
)
from jaxdeconf.envs.base import Environment, NormalizedViews


@struct.dataclass
class Learner:
    """Parameters and optimiser state of one set of networks."""

    params: Any
    opt_state: Any


@struct.dataclass
class TrainState:
    """Everything one seed's run carries between iterations (checkpointed whole, so resuming is exact)."""

    policy: Learner
    encoder: Learner | None  # A second learner: dil's inference model and decoder, gail's discriminator.
    expert_buffer: Buffer  # Demonstrations (dagger: the mixture's episodes with the expert's labels).
    explore_buffer: Buffer | None  # The imitator's own episodes (dil's exploration data, gail's latest rollouts).
    key: jax.Array
    iteration: jax.Array  # int32: iterations done.


def make_optimizer(lr: float, weight_decay: float, clip: float) -> optax.GradientTransformation:
    """AdamW behind a global-norm clip."""
    return optax.chain(optax.clip_by_global_norm(clip), optax.adamw(lr, weight_decay=weight_decay))


def apply_gradients(learner: Learner, grads: Any, tx: optax.GradientTransformation) -> Learner:
    """One optimiser step."""
    updates, opt_state = tx.update(grads, learner.opt_state, learner.params)
    return Learner(params=optax.apply_updates(learner.params, updates), opt_state=opt_state)


def masked_moments(x: jax.Array, valid: jax.Array, floor: float) -> tuple[jax.Array, jax.Array]:
    """Per-dimension mean and standard deviation [D] (floored at ``floor``) of x [T, B, D] over the valid steps (mask
    [T, B]) of episodes; empty buffer slots, all invalid, count for nothing."""
    weight = valid.astype(x.dtype)[..., None]
    count = jnp.maximum(weight.sum((0, 1)), 1.0)
    mean = (x * weight).sum((0, 1)) / count
    var = (((x - mean) ** 2) * weight).sum((0, 1)) / count
    return mean, jnp.maximum(jnp.sqrt(var), floor)


def observation_delta_scale(env: Environment, env_params: Any, episodes: int = 64) -> jax.Array:
    """Per-dimension standard deviation of the imitator's one-step observation changes on expert episodes (fixed
    key, so every seed and run uses the same scale), floored at 1e-3."""
    traj, _ = jax.jit(lambda k: rollout(env, env_params, ExpertActor(env, env_params), None, k, episodes))(
        jax.random.key(0))
    obs = traj.obs.imitator
    return jax.device_get(masked_moments(obs[1:] - obs[:-1], traj.valid, floor=1e-3)[1])


def fit_view_normalizer(env: Environment, env_params: Any, episodes: int = 64) -> NormalizedViews:
    """``env`` with its imitator and oracle views standardised by the per-dimension mean and standard deviation
    (floored at 1e-3) over ``episodes`` expert episodes drawn with a fixed key, identical for every seed and run."""
    traj, _ = jax.jit(lambda k: rollout(env, env_params, ExpertActor(env, env_params), None, k, episodes))(
        jax.random.key(1))
    valid = jnp.concatenate([jnp.ones_like(traj.valid[:1]), traj.valid])  # obs has T + 1 steps; the first is real.
    stats = {}
    for view in ("imitator", "oracle"):
        mean, std = masked_moments(getattr(traj.obs, view), valid, floor=1e-3)
        stats[view] = (np.asarray(mean), np.asarray(std))
    return NormalizedViews(env, stats)


@dataclasses.dataclass(frozen=True)
class Algorithm:
    """What all algorithms share: expert data collection, the policy's BC updates, evaluation and the chunk loop."""

    env: Environment
    env_params: Any
    config: Config

    #: The config section this algorithm owns (``config.<name>``, overridable as ``<name>.field``) and its dataclass,
    #: or None. Several registry names may share one class and so one section (bc and oracle: none).
    settings: ClassVar[tuple[str, type] | None] = None

    @classmethod
    def stored_episodes(cls, config: Config) -> int:
        """Episodes one seed keeps in its buffers (for ``memory.estimate``): the expert buffer by default."""
        return config.train.buffer_episodes

    @classmethod
    def episodes_in_flight(cls, config: Config) -> int:
        """The largest batch of episodes one seed's step works on (for ``memory.estimate``)."""
        t = config.train
        return max(t.batch_size, t.episodes_per_iter, t.eval_episodes)

    @classmethod
    def decoded_episodes(cls, config: Config) -> int:
        """Episodes one seed's ELBO step decodes K steps ahead (for ``memory.estimate``): none without an ELBO."""
        del config  # Unused.
        return 0

    @property
    def space(self) -> Any:
        """The env's action space."""
        return self.env.action_space(self.env_params)

    @property
    def policy_tx(self) -> optax.GradientTransformation:
        """Policy optimiser."""
        t = self.config.train
        return make_optimizer(t.policy_lr, t.weight_decay, t.policy_clip)

    def example_episode(self) -> Trajectory:
        """One all-zero episode [T, 1, ...] shaped like this env's trajectories."""
        shape = jax.eval_shape(
            lambda k: rollout(self.env, self.env_params, ExpertActor(self.env, self.env_params), None, k, 1)[0],
            jax.random.key(0),
        )
        return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shape)

    def _empty_buffer(self, example: Any = None, capacity: int | None = None) -> Buffer:
        """An empty buffer of ``capacity`` (default ``train.buffer_episodes``) episodes shaped like ``example``
        (default: this env's trajectories)."""
        example = self.example_episode() if example is None else example
        return buffer_init(example, capacity or self.config.train.buffer_episodes)

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

    def policy_context(self, state: TrainState, key: jax.Array) -> jax.Array | None:
        """Per-episode inputs [T, capacity, ...] computed once for the whole expert buffer before the policy steps
        (what stays fixed while the policy trains; ``key`` for any draw it makes), or None."""
        del state, key  # Unused.
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
        context = self.policy_context(state, jax.random.fold_in(key, 1))  # Leaves the steps' keys as they were.

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
        return {**metrics, **self.diagnose(state, traj, expert_traj)}

    def belief(self, state: TrainState, traj: Trajectory) -> jax.Array | None:
        """The imitator's belief about θ along ``traj`` [T, B, L], for algorithms that hold one (default: none)."""
        return None

    def diagnose(self, state: TrainState, traj: Trajectory, expert_traj: Trajectory) -> dict[str, jax.Array]:
        """Per-episode θ, return and extras of the online episodes, and (with a belief) the per-step θ probe online
        and on the expert's episodes (``diagnostics``); NaN curves without a belief."""
        theta = diagnostics.episode_theta(self.env, self.env_params, traj.obs.oracle[0])
        out = {"episode_theta": diagnostics.theta_scalar(theta), "episode_return": jnp.sum(traj.reward, axis=0),
               **{f"episode_{k}": jnp.sum(v, axis=0) for k, v in traj.extras.items()}}
        for where, episodes, th in (("online", traj, theta), ("expert", expert_traj, diagnostics.episode_theta(
                self.env, self.env_params, expert_traj.obs.oracle[0]))):
            belief = self.belief(state, episodes)
            out[f"theta_probe_{where}"] = (jnp.full((episodes.horizon,), jnp.nan) if belief is None
                                           else diagnostics.theta_probe(belief, th, episodes.valid))
        return out

    def train_chunk(self, state: TrainState, length: int) -> tuple[TrainState, dict[str, Any], dict[str, Any]]:
        """``length`` iterations then one evaluation: (state, per-iteration metrics [length], eval metrics)."""
        state, per_iter = jax.lax.scan(self.iteration, state, None, length=length)
        key, k_eval = jax.random.split(state.key)
        return state.replace(key=key), per_iter, self.evaluate(state, k_eval)
