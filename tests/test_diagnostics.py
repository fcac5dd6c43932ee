"""The θ probe of diagnostics.png: exact on a belief that is θ, near zero on noise, NaN on too few episodes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxdeconf.envs import make
from jaxdeconf.envs.base import NormalizedViews

from jaxdeconf import diagnostics


def test_probe_reads_a_linear_belief_exactly_and_noise_not_at_all():
    k1, k2 = jax.random.split(jax.random.key(0))
    theta = jax.random.uniform(k1, (4000, 1), minval=0.0, maxval=3.0)
    noise = jax.random.normal(k2, (3, 4000, 2))
    # Step 0: a belief that is an affine map of θ (R² = 1); step 1: pure noise (held-out R² about 0, below 0.05);
    # step 2: θ plus noise of θ's variance 0.75 (R² = var θ / (var θ + var noise) = 1 / 2).
    belief = jnp.stack([jnp.concatenate([2.0 * theta - 1.0, jnp.zeros_like(theta)], -1), noise[1],
                        jnp.concatenate([theta + jnp.sqrt(0.75) * noise[2, :, :1], noise[2, :, 1:]], -1)])
    r2 = np.asarray(diagnostics.theta_probe(belief, theta, jnp.ones((3, 4000), bool)))
    assert r2[0] > 0.9999
    assert -0.05 < r2[1] < 0.05
    assert abs(r2[2] - 0.5) < 0.05


def test_probe_needs_enough_valid_episodes_in_each_half():
    theta = jnp.arange(40.0)[:, None]
    valid = jnp.stack([jnp.arange(40) < 40, jnp.arange(40) < 27, jnp.arange(40) < 28])  # Test half: 7, then 8.
    r2 = np.asarray(diagnostics.theta_probe(jnp.stack([theta] * 3), theta, valid))
    assert r2[0] > 0.999 and np.isnan(r2[1]) and r2[2] > 0.999


def test_episode_theta_undoes_the_view_standardisation():
    env, params = make("lunar_lander")
    size = env.obs_sizes(params)
    mean, std = np.arange(size.oracle, dtype=np.float32), np.full(size.oracle, 2.0, np.float32)
    wrapped = NormalizedViews(env, {"oracle": (mean, std)})
    raw = jnp.concatenate([jnp.zeros((2, size.imitator)), jnp.array([[0.0], [1.0]])], -1)
    standardised = (raw - mean) / std
    np.testing.assert_allclose(diagnostics.episode_theta(wrapped, params, standardised), [[0.0], [1.0]], atol=1e-6)
    np.testing.assert_allclose(diagnostics.episode_theta(env, params, raw), [[0.0], [1.0]])


def test_spd_solve_matches_numpy_without_lapack():
    """The probe's Cholesky solve equals numpy's on a random SPD system, also batched, and its jaxpr calls no LAPACK
    routine (whose batched CPU kernels deadlocked inside the training program)."""
    rng = np.random.default_rng(0)
    m = rng.normal(size=(3, 6, 6))
    a = np.einsum("bij,bkj->bik", m, m) + 0.1 * np.eye(6)
    b = rng.normal(size=(3, 6, 2))
    got = jax.jit(jax.vmap(diagnostics.spd_solve))(jnp.asarray(a, jnp.float32), jnp.asarray(b, jnp.float32))
    np.testing.assert_allclose(got, np.linalg.solve(a, b), rtol=2e-3, atol=2e-3)
    hlo = jax.jit(jax.vmap(diagnostics.spd_solve)).lower(jnp.asarray(a, jnp.float32),
                                                       jnp.asarray(b, jnp.float32)).as_text()
    assert "lapack" not in hlo.lower() and "custom_call" not in hlo
