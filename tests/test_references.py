"""Exact bandit references against direct Bayes and against brute-force enumeration on a short horizon."""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxdeconf.envs import make

from jaxdeconf.references import belief_update, policy_probs, reference_curves


def _direct_belief(kind, actions, outcomes, p, q, arms):
    """Posterior over θ by multiplying every likelihood factor from scratch (no recursion)."""
    post = np.ones(arms) / arms
    for a, s in zip(actions, outcomes, strict=True):
        for th in range(arms):
            ps = q if a == th else 1 - q
            post[th] *= ps if s else 1 - ps
            if kind == "conditional":
                post[th] *= p if a == th else (1 - p) / (arms - 1)
    return post / post.sum()


@pytest.mark.parametrize("kind", ["interventional", "conditional"])
def test_recursion_equals_direct_bayes(kind):
    _, params = make("bandit", p=0.7, q=0.8, arms=4)
    rng = np.random.default_rng(0)
    for _ in range(20):
        n = rng.integers(1, 12)
        actions, outcomes = rng.integers(0, 4, n), rng.integers(0, 2, n)
        logb = jnp.full(4, -jnp.log(4.0))
        for a, s in zip(actions, outcomes, strict=True):
            logb = belief_update(kind, logb, jnp.int32(a), jnp.float32(s), params)
        np.testing.assert_allclose(np.exp(logb), _direct_belief(kind, actions, outcomes, 0.7, 0.8, 4), atol=1e-5)


def _enumerate(kind, p, q, arms, T):
    """Exact E[P(best arm) at step t] online (the policy acting) and on expert data, by enumerating histories."""
    online, expert = np.zeros(T), np.zeros(T)

    def pi_ref(actions, outcomes):
        b = _direct_belief(kind, actions, outcomes, p, q, arms)
        return p * b + (1 - p) / (arms - 1) * (1 - b)

    pi_exp = lambda th: np.where(np.arange(arms) == th, p, (1 - p) / (arms - 1))  # noqa: E731
    for th in range(arms):
        for actions in itertools.product(range(arms), repeat=T):
            for outcomes in itertools.product((0, 1), repeat=T):
                w_on, w_ex = 1.0 / arms, 1.0 / arms
                for t in range(T):
                    probs = pi_ref(actions[:t], outcomes[:t])
                    online[t] += w_on * probs[th]  # Expected P(best) given the history so far.
                    expert[t] += w_ex * probs[th]
                    ps = q if actions[t] == th else 1 - q
                    lik = ps if outcomes[t] else 1 - ps
                    w_on *= probs[actions[t]] * lik
                    w_ex *= pi_exp(th)[actions[t]] * lik
    # Each prefix was counted once per completion of the remaining steps: divide by those counts.
    for t in range(T):
        online[t] /= (2 * arms) ** (T - t)
        expert[t] /= (2 * arms) ** (T - t)
    return online, expert


def test_monte_carlo_references_match_enumeration():
    _, params = make("bandit", p=0.7, q=0.8, arms=3, horizon=4)
    n = 40000  # P(best) lies in [0, 1], so each mean's standard error is at most 0.5 / sqrt(n) = 0.0025.
    mc = jax.jit(reference_curves, static_argnums=(1, 2))(jax.random.key(1), params, n)
    for kind in ("interventional", "conditional"):
        online, expert = _enumerate(kind, 0.7, 0.8, 3, 4)
        np.testing.assert_allclose(mc[f"{kind}_online"], online, atol=0.01)
        np.testing.assert_allclose(mc[f"{kind}_expert"], expert, atol=0.01)
    np.testing.assert_allclose(mc["expert_online"], 0.7, atol=0.01)


def test_paper_bandit_counts():
    """The paper reports interventional ≈ 54.1 and conditional ≈ 32.4 best-arm pulls per 100 steps; expert 60."""
    _, params = make("bandit")
    refs = jax.jit(reference_curves, static_argnums=(1, 2))(jax.random.key(0), params, 20000)
    assert float(refs["expert_count"]) == pytest.approx(60.0, abs=0.5)
    assert float(refs["interventional_count"]) == pytest.approx(54.1, abs=0.3)
    assert float(refs["conditional_count"]) == pytest.approx(32.4, abs=0.8)
    assert float(refs["interventional_online"][-1]) == pytest.approx(0.60, abs=0.02)
    assert float(refs["conditional_online"][-1]) == pytest.approx(0.33, abs=0.03)


def test_policy_probs_sum_to_one():
    _, params = make("bandit")
    logb = jax.nn.log_softmax(jax.random.normal(jax.random.key(0), (7, 5)))
    np.testing.assert_allclose(policy_probs(logb, params).sum(-1), 1.0, atol=1e-6)
