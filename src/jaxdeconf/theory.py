"""Theorem 1 (eq. 5): the interventional policy estimated by counting on each expert demonstration.

Per demonstration i, counts give the dynamics p̂_i(s' | s, a) and the expert's policy π̂_i(a | s). A new trajectory's
belief over the demonstrations follows from the transition likelihoods alone,

    p̂(i | s_1, a_1, ..., s_t) ∝ Π_t p̂_i(s_{t+1} | s_t, a_t),

and the policy is the belief-weighted mixture Σ_i p̂(i | τ) π̂_i(a_t | s_t). The policy's own actions are never
evidence about i, which is what makes it interventional. Theorem 1: with infinitely many infinitely long demonstrations
of an MDP that is recurrent under the expert, this is the exact interventional policy (eq. 3).

Counts are smoothed with a Dirichlet pseudo-count ``alpha`` per cell (``estimate``; default ``ALPHA`` = 0.1): an
(s, a) a demonstration never visited gets the uniform p̂_i(· | s, a), which neither supports nor rules out that
demonstration, and an unseen transition lowers a demonstration's likelihood instead of ruling it out for good. With the
plain maximum-likelihood counts (``alpha = 0``) one unseen transition gives p̂_i = 0 and removes demonstration i from
the belief forever; a large pseudo-count (Laplace's 1) pulls a short demonstration's p̂_i towards 1/2 and so weakens
the evidence that tells the demonstrations apart. 0.1 sits between the two (measured in docs/theory.md).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from jaxdeconf.actors import ExpertActor
from jaxdeconf.data import rollout
from jaxdeconf.envs.bandit import Bandit, BanditParams
from jaxdeconf.envs.base import Observation
from jaxdeconf.references import safe_log

ALPHA = 0.1  # Default pseudo-count per cell of the count tables.


@struct.dataclass
class TabularModel:
    """The per-demonstration estimates of eq. 5."""

    log_dynamics: jax.Array  # float32 [N, S, A, S]: log p̂_i(s' | s, a).
    log_policy: jax.Array  # float32 [N, S, A]: log π̂_i(a | s).

    @property
    def demos(self) -> int:
        """N, the number of demonstrations."""
        return self.log_policy.shape[0]


def demo_counts(states: jax.Array, actions: jax.Array, num_states: int, num_actions: int) -> jax.Array:
    """Transition counts n(s, a, s') [S, A, S] of one demonstration: ``states`` int [H+1], ``actions`` int [H]."""
    s = jax.nn.one_hot(states[:-1], num_states, dtype=jnp.float32)
    a = jax.nn.one_hot(actions, num_actions, dtype=jnp.float32)
    s_next = jax.nn.one_hot(states[1:], num_states, dtype=jnp.float32)
    return jnp.einsum("ts,ta,tu->sau", s, a, s_next)


def _normalise(counts: jax.Array, alpha: float) -> jax.Array:
    """(n + α) / Σ(n + α) over the last axis; uniform where a row has no counts and α = 0 (instead of 0 / 0)."""
    smoothed = counts + alpha
    total = jnp.sum(smoothed, axis=-1, keepdims=True)
    uniform = jnp.full_like(smoothed, 1.0 / smoothed.shape[-1])
    return jnp.where(total > 0, smoothed / jnp.where(total > 0, total, 1.0), uniform)


def estimate(counts: jax.Array, alpha: float) -> tuple[jax.Array, jax.Array]:
    """log p̂(s' | s, a) [S, A, S] and log π̂(a | s) [S, A] of one demonstration's counts [S, A, S]."""
    return safe_log(_normalise(counts, alpha)), safe_log(_normalise(jnp.sum(counts, axis=-1), alpha))


def fit(states: jax.Array, actions: jax.Array, num_states: int, num_actions: int, alpha: float) -> TabularModel:
    """Eq. 5's tables from N demonstrations, time-major: ``states`` int [H+1, N], ``actions`` int [H, N]."""

    def one(s: jax.Array, a: jax.Array) -> tuple[jax.Array, jax.Array]:
        return estimate(demo_counts(s, a, num_states, num_actions), alpha)

    log_dynamics, log_policy = jax.vmap(one, in_axes=(1, 1))(states, actions)
    return TabularModel(log_dynamics=log_dynamics, log_policy=log_policy)


def transition_log_likelihood(log_dynamics: jax.Array, s: jax.Array, a: jax.Array, s_next: jax.Array) -> jax.Array:
    """log p̂_i(s_next | s, a) [B] under one demonstration's table [S, A, S], for a batch of int transitions [B]."""
    return log_dynamics[s, a, s_next]


def belief_update(
    model: TabularModel, log_belief: jax.Array, s: jax.Array, a: jax.Array, s_next: jax.Array
) -> jax.Array:
    """Fold the transitions (s, a, s_next) [B] into the log-belief over demonstrations [B, N]."""
    evidence = jax.vmap(transition_log_likelihood, in_axes=(0, None, None, None), out_axes=1)(
        model.log_dynamics, s, a, s_next
    )
    new = log_belief + evidence
    norm = jax.nn.logsumexp(new, axis=-1, keepdims=True)
    # Only with alpha = 0 can every demonstration be ruled out; then keep the belief (the step carries no evidence).
    return jnp.where(jnp.isfinite(norm), new - norm, log_belief)


def mixture_policy(model: TabularModel, log_belief: jax.Array, s: jax.Array) -> jax.Array:
    """Eq. 5: Σ_i p̂(i | τ) π̂_i(a | s) [B, A] for a log-belief [B, N] and states int [B]."""
    n, num_states, num_actions = model.log_policy.shape
    # One [B, N] x [N, S·A] product for every state, then pick s: no [N, B, A] gather.
    mixed = jax.nn.softmax(log_belief, axis=-1) @ jnp.exp(model.log_policy).reshape(n, num_states * num_actions)
    mixed = mixed.reshape(-1, num_states, num_actions)
    return jnp.take_along_axis(mixed, s[:, None, None], axis=1)[:, 0]


def bandit_state(obs: Observation) -> jax.Array:
    """The bandit's discrete state index (the last outcome, 0 or 1) [...] from the imitator's view [..., 1]."""
    return (obs.imitator[..., 0] > 0.5).astype(jnp.int32)


@dataclasses.dataclass(frozen=True)
class TabularActor:
    """Eq. 5 as an actor on the imitator's view of the bandit; its params are a TabularModel."""

    demos: int  # N (static: it fixes the belief's shape).

    def init_carry(self, batch: int) -> tuple[jax.Array, jax.Array]:
        """Uniform log-belief over demonstrations [batch, N] and the previous state [batch] (none yet)."""
        return jnp.full((batch, self.demos), -jnp.log(self.demos), jnp.float32), jnp.zeros((batch,), jnp.int32)

    def __call__(self, params: TabularModel, carry: tuple, obs: Observation, prev_action: jax.Array):
        """Fold in (s_{t-1}, a_{t-1}, s_t) when there was a previous action, then return log action probabilities."""
        log_belief, prev_state = carry
        s = bandit_state(obs)
        has_prev = jnp.sum(prev_action, axis=-1) > 0
        updated = belief_update(params, log_belief, prev_state, jnp.argmax(prev_action, -1), s)
        log_belief = jnp.where(has_prev[:, None], updated, log_belief)
        return (log_belief, s), safe_log(mixture_policy(params, log_belief, s))


def fit_bandit(key: jax.Array, params: BanditParams, demos: int, length: int, alpha: float) -> TabularModel:
    """Eq. 5's tables from ``demos`` expert demonstrations of ``length`` steps on the bandit ``params``."""
    env = Bandit()
    demo_params = params.replace(horizon=length)
    traj, _ = rollout(env, demo_params, ExpertActor(env, demo_params), None, key, demos)
    return fit(bandit_state(traj.obs), traj.action, 2, params.arms, alpha)


def estimator_curves(
    key: jax.Array, params: BanditParams, demos: int, length: int, episodes: int, alpha: float = ALPHA
) -> dict[str, jax.Array]:
    """Fit eq. 5 on N = ``demos`` demonstrations of H = ``length`` steps, then act online for ``episodes`` episodes.

    Returns the per-step P(best arm) [T] (the policy's probability of θ, averaged over episodes), the expected
    best-arm count per episode and its standard error. Jit with ``demos``, ``length`` and ``episodes`` static.
    """
    key_fit, key_act = jax.random.split(key)
    model = fit_bandit(key_fit, params, demos, length, alpha)
    _, p_best = rollout(Bandit(), params, TabularActor(demos), model, key_act, episodes)
    counts = jnp.sum(p_best, axis=0)
    return {
        "online": jnp.mean(p_best, axis=1),
        "count": jnp.mean(counts),
        "count_se": jnp.std(counts) / jnp.sqrt(episodes),
    }


def exact_model(params: BanditParams) -> TabularModel:
    """The tables Theorem 1's counts converge to: one demonstration per arm θ, p̂ and π̂ exact (no state dependence)."""
    arms = params.arms
    hit = jnp.eye(arms, dtype=bool)[:, None, :]  # [θ, s, a]: a == θ.
    p_one = jnp.where(hit, params.q, 1.0 - params.q)
    dynamics = jnp.stack([1.0 - p_one, p_one], axis=-1)  # [θ, 1, A, 2] -> broadcast over s below.
    policy = jnp.where(hit, params.p, (1.0 - params.p) / (arms - 1))
    return TabularModel(
        log_dynamics=safe_log(jnp.broadcast_to(dynamics, (arms, 2, arms, 2))),
        log_policy=safe_log(jnp.broadcast_to(policy, (arms, 2, arms))),
    )

