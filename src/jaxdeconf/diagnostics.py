"""What an evaluation says beyond the return: how much of θ an imitator's belief carries, step by step, and how
each imitator does across θ.

``theta_probe`` is a linear probe of θ from the posterior mean q_phi(. | tau_{:t}), fitted per step on one half of
the evaluation's episodes and scored (R²) on the other half. Computed on the imitator's own episodes and on the
expert's, it shows whether the inference model infers θ where it matters (online) and not only on the data the policy
was cloned on. ``episode_theta`` reads each episode's θ from its first oracle observation (the oracle's view is the
imitator's plus θ, by the env contract) so results can be binned by θ.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

RIDGE = 1e-3  # Keeps the per-step least-squares fit well-posed when the belief is (nearly) constant.
MIN_EPISODES = 8  # Fewer valid episodes in either half gives NaN for that step.


def spd_solve(a: jax.Array, b: jax.Array) -> jax.Array:
    """x with a x = b, for a symmetric positive-definite a [n, n] and b [n, k], by Cholesky and two substitutions.

    Written out (n steps of masked vector operations) because ``jnp.linalg.solve`` calls LAPACK, whose batched CPU
    kernels (jaxlib 0.10.2) split the batch over XLA's intra-op thread pool and, inside the seed-vmapped training
    program, were seen to deadlock with every thread idle.
    """
    n = a.shape[0]
    idx = jnp.arange(n)

    def column(j: jax.Array, chol: jax.Array) -> jax.Array:  # chol holds columns < j of the factor L.
        v = a[:, j] - chol @ chol[j]
        col = jnp.where(idx >= j, v / jnp.sqrt(v[j]), 0.0)
        return jnp.where(idx[None, :] == j, col[:, None], chol)

    chol = jax.lax.fori_loop(0, n, column, jnp.zeros_like(a))

    def forward(i: jax.Array, y: jax.Array) -> jax.Array:  # L y = b, row i from rows < i.
        return jnp.where(idx[:, None] == i, (b[i] - chol[i] @ y) / chol[i, i], y)

    def backward(k: jax.Array, x: jax.Array) -> jax.Array:  # L^T x = y, row i = n - 1 - k from rows > i.
        i = n - 1 - k
        return jnp.where(idx[:, None] == i, (y[i] - chol[:, i] @ x) / chol[i, i], x)

    y = jax.lax.fori_loop(0, n, forward, jnp.zeros_like(b))
    return jax.lax.fori_loop(0, n, backward, jnp.zeros_like(b))


def _r2(z: jax.Array, theta: jax.Array, valid: jax.Array) -> jax.Array:
    """Held-out R² of a ridge-regularised linear map z [B, L] -> θ [B, D], fitted on the first half of the valid
    episodes and scored on the second (averaged over θ's dimensions); NaN when a half has too few."""
    half = z.shape[0] // 2
    x = jnp.concatenate([z, jnp.ones_like(z[:, :1])], axis=-1)
    w_fit = (jnp.arange(z.shape[0]) < half) & valid
    w_test = (jnp.arange(z.shape[0]) >= half) & valid
    xw = x * w_fit[:, None]
    coef = spd_solve(xw.T @ x + RIDGE * jnp.eye(x.shape[1]), xw.T @ theta)
    resid = jnp.sum(((x @ coef - theta) ** 2) * w_test[:, None], axis=0)
    n_test = jnp.maximum(jnp.sum(w_test), 1)
    mean = jnp.sum(theta * w_test[:, None], axis=0) / n_test
    total = jnp.sum(((theta - mean) ** 2) * w_test[:, None], axis=0)
    r2 = jnp.mean(1.0 - resid / jnp.maximum(total, 1e-12))
    enough = (jnp.sum(w_fit) >= MIN_EPISODES) & (jnp.sum(w_test) >= MIN_EPISODES)
    return jnp.where(enough, r2, jnp.nan)


def theta_probe(belief: jax.Array, theta: jax.Array, valid: jax.Array) -> jax.Array:
    """Per-step held-out R² [T] of θ [B, D] from the belief [T, B, L] over episodes still running (valid [T, B])."""
    return jax.vmap(_r2, in_axes=(0, None, 0))(belief, theta, valid)


def episode_theta(env: Any, env_params: Any, oracle_obs: jax.Array) -> jax.Array:
    """Each episode's θ [B, D] from the first oracle observation [B, d] (the trailing entries past the imitator's view),
    in the env's own units when the views are standardised (``NormalizedViews``)."""
    size = env.obs_sizes(env_params).imitator
    theta = oracle_obs[:, size:]
    stats = getattr(env, "stats", None)
    if stats is not None and "oracle" in stats:
        mean, std = stats["oracle"]
        theta = theta * jnp.asarray(std)[size:] + jnp.asarray(mean)[size:]
    return theta


def theta_scalar(theta: jax.Array) -> jax.Array:
    """One number per episode to bin by: θ itself when it is scalar, else its norm (e.g. a goal's distance)."""
    return theta[:, 0] if theta.shape[-1] == 1 else jnp.linalg.norm(theta, axis=-1)
