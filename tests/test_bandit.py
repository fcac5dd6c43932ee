"""The bandit's dynamics and expert checked statistically; the registry's errors; θ absent from the imitator's view."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxdeconf.envs import make
from jaxdeconf.envs.bandit import BanditState

N = 40000


def _within(rate: float, p: float, n: int, sigmas: float = 4.5) -> bool:
    return abs(rate - p) <= sigmas * np.sqrt(p * (1 - p) / n)


@pytest.mark.parametrize(("p", "q"), [(0.6, 0.75), (0.9, 0.55)])
def test_outcome_and_expert_rates(p, q):
    env, params = make("bandit", p=p, q=q)
    k_reset, k_step, k_act = jax.random.split(jax.random.key(0), 3)
    state, obs = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, N), params)
    theta = np.asarray(state.theta)
    assert _within(np.mean(theta == 2), 0.2, N)  # θ uniform over 5 arms.
    action = jax.vmap(env.expert_action, in_axes=(0, 0, None))(jax.random.split(k_act, N), obs, params)
    hit = np.asarray(action) == theta
    assert _within(hit.mean(), p, N)
    # Pull half the arms at θ and half elsewhere to measure both outcome rates.
    pulled = jnp.where(jnp.arange(N) % 2 == 0, state.theta, (state.theta + 1) % 5)
    _, res = jax.vmap(env.step, in_axes=(0, 0, 0, None))(jax.random.split(k_step, N), state, pulled, params)
    outcome = np.asarray(res.obs.imitator[:, 0])
    assert _within(outcome[0::2].mean(), q, N // 2)
    assert _within(outcome[1::2].mean(), 1 - q, N // 2)
    np.testing.assert_array_equal(np.asarray(res.reward), (np.arange(N) % 2 == 0).astype(np.float32))
    np.testing.assert_array_equal(np.asarray(res.extras["outcome"]), outcome)


def test_imitator_view_never_contains_theta():
    env, params = make("bandit")
    for theta in range(5):
        state = BanditState(theta=jnp.int32(theta), outcome=jnp.float32(1.0), t=jnp.int32(3))
        obs = env._observe(state, params)
        np.testing.assert_array_equal(obs.imitator, [1.0])  # Identical for every θ.
        np.testing.assert_array_equal(obs.oracle[1:], np.eye(5)[theta])
        np.testing.assert_array_equal(obs.expert, obs.oracle)


def test_registry_rejects_bad_names_and_values():
    with pytest.raises(ValueError, match="unknown env 'cartpole'"):
        make("cartpole")
    with pytest.raises(ValueError, match="unknown parameter 'r'"):
        make("bandit", r=0.5)
    with pytest.raises(ValueError, match=r"p=1.5 is outside the allowed range \(0, 1\]"):
        make("bandit", p=1.5)
    with pytest.raises(ValueError, match=r"q=0.0 is outside"):
        make("bandit", q=0.0)
    _, params = make("bandit", p=1.0, arms=3, horizon=7)
    assert (params.p, params.arms, params.horizon) == (1.0, 3, 7)
