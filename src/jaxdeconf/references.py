"""Exact reference policies of the confounded bandit (paper appendix, eqs. 13 and 14, for any p, q and arms).

Both keep a log-belief over θ. After pulling arm a and seeing outcome s', the *interventional* belief adds the
dynamics evidence log P(s' | a, θ) (q for θ = a, 1 - q otherwise); the *conditional* belief also adds the expert's
action likelihood log π_exp(a | θ), treating the imitator's own actions as evidence (the causal delusion). Each
policy plays the expert's action distribution averaged over its belief (Thompson sampling of the expert).
The edges p = 1 (deterministic expert) and q = 1 (deterministic environment) are allowed: a zero probability is a
log-evidence of -inf (``safe_log``), and ``belief_update`` says what happens to a history of probability zero.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from jaxdeconf.actors import ExpertActor
from jaxdeconf.data import best_action_prob, replay, rollout
from jaxdeconf.envs.bandit import Bandit, BanditParams

KINDS = ("interventional", "conditional")


def belief_update(kind: str, log_belief: jax.Array, action: jax.Array, outcome: jax.Array, params: BanditParams):
    """One Bayes step of the log-belief [..., arms] after ``action`` [...] produced ``outcome`` [...] in {0, 1}."""
    hit = jnp.arange(params.arms) == action[..., None]
    success = outcome[..., None] > 0.5
    p_success = jnp.where(hit, params.q, 1.0 - params.q)
    evidence = safe_log(jnp.where(success, p_success, 1.0 - p_success))
    if kind == "conditional":
        evidence = evidence + safe_log(jnp.where(hit, params.p, (1.0 - params.p) / (params.arms - 1)))
    new = log_belief + evidence
    norm = jax.nn.logsumexp(new, axis=-1, keepdims=True)
    # At p = 1 and q = 1 a miss (outcome 0) has probability 0 under every θ of the conditional model (the expert never
    # misses): the history is impossible and Bayes is undefined (-inf - -inf). Keep the belief, which is the limit of
    # (1 - p) / (arms - 1) = 1 - q = ε -> 0, where that step multiplies every θ by the same ε. Histories the real
    # environment produces never rule out the true θ under the interventional model, so it never takes this branch.
    return jnp.where(jnp.isfinite(norm), new - norm, log_belief)


def safe_log(x: jax.Array) -> jax.Array:
    """log x with log 0 = -inf and no NaN gradient (the log's input is guarded where x = 0, as at p = 1 or q = 1)."""
    positive = x > 0
    return jnp.where(positive, jnp.log(jnp.where(positive, x, 1.0)), -jnp.inf)


def policy_probs(log_belief: jax.Array, params: BanditParams) -> jax.Array:
    """The expert's action distribution averaged over the belief: p·b(a) + (1 - p)/(arms - 1)·(1 - b(a))."""
    belief = jnp.exp(log_belief)
    return params.p * belief + (1.0 - params.p) / (params.arms - 1) * (1.0 - belief)


@dataclasses.dataclass(frozen=True)
class ReferenceActor:
    """The exact interventional or conditional policy as an actor on the imitator's view."""

    kind: str
    params: BanditParams

    def init_carry(self, batch: int) -> jax.Array:
        """Uniform prior log-belief [batch, arms]."""
        return jnp.full((batch, self.params.arms), -jnp.log(self.params.arms), jnp.float32)

    def __call__(self, params: Any, carry: jax.Array, obs: Any, prev_action: jax.Array):
        """Fold in (a_{t-1}, s_t) when there was a previous action, then return log action probabilities."""
        del params  # Unused: the references have no learned parameters.
        has_prev = jnp.sum(prev_action, axis=-1) > 0
        updated = belief_update(self.kind, carry, jnp.argmax(prev_action, -1), obs.imitator[..., 0], self.params)
        carry = jnp.where(has_prev[:, None], updated, carry)
        return carry, safe_log(policy_probs(carry, self.params))


def reference_curves(key: jax.Array, params: BanditParams, episodes: int) -> dict[str, jax.Array]:
    """Per-step P(best arm) [T] online and on expert trajectories, and expected best-arm counts, for both kinds.

    P(best arm) is the policy's probability of θ at each step (Rao-Blackwellised), averaged over episodes; the count
    is its sum over the episode, the expected number of best-arm pulls.
    """
    env = Bandit()
    key_expert, key_int, key_cond = jax.random.split(key, 3)
    expert_traj, expert_p = rollout(env, params, ExpertActor(env, params), None, key_expert, episodes)
    space = env.action_space(params)
    out: dict[str, jax.Array] = {"expert_online": jnp.mean(expert_p, axis=1)}
    for kind, k in zip(KINDS, (key_int, key_cond), strict=True):
        actor = ReferenceActor(kind, params)
        _, p_online = rollout(env, params, actor, None, k, episodes)
        p_expert = best_action_prob(replay(actor, None, expert_traj, space), expert_traj.best_action)
        out[f"{kind}_online"] = jnp.mean(p_online, axis=1)
        out[f"{kind}_expert"] = jnp.mean(p_expert, axis=1)
        out[f"{kind}_count"] = jnp.sum(jnp.mean(p_online, axis=1))
        out[f"{kind}_count_se"] = jnp.std(jnp.sum(p_online, axis=0)) / jnp.sqrt(episodes)
    out["expert_count"] = jnp.sum(out["expert_online"])
    return out
