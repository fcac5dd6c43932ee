"""The minGRU cell (``model.cell=mingru``): its associative scan against a numpy step loop, the training path's
sequences against the actors' per-step ``recur``, the read-masked posterior, and tiny bc and dil runs."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxdeconf.envs.base import Observation

from jaxdeconf import losses
from jaxdeconf.actors import RecurrentActor
from jaxdeconf.models import Encoder, MinGRUCell, RecurrentPolicy
from jaxdeconf.train import build_algorithm, train_algorithm

T, B = 7, 3


def _inputs(width: int, seed: int = 0) -> tuple[jax.Array, jax.Array]:
    """Observations [T, B, 2] and previous-action features [T, B, width] drawn from a fixed key."""
    k_obs, k_act = jax.random.split(jax.random.key(seed))
    return jax.random.normal(k_obs, (T, B, 2)), jax.random.normal(k_act, (T, B, width))


def _sigmoid(x: np.ndarray) -> np.ndarray:
    """The logistic function in numpy."""
    return 1.0 / (1.0 + np.exp(-x))


@pytest.mark.timeout(120)
def test_associative_scan_equals_numpy_step_loop():
    # Hand-chosen weights of a 2-input, 2-unit minGRU and inputs over 4 steps of 2 sequences.
    wz, bz = np.array([[0.5, -1.0], [2.0, 0.25]]), np.array([0.1, -0.3])
    wh, bh = np.array([[1.5, 0.0], [-0.5, 1.0]]), np.array([0.0, 0.2])
    x = np.array([[[1.0, 0.0], [0.0, 1.0]], [[-1.0, 2.0], [0.5, 0.5]], [[0.3, -0.7], [2.0, -1.0]],
                  [[0.0, 0.0], [-1.5, 0.25]]])
    params = {"params": {"gate": {"kernel": wz, "bias": bz}, "candidate": {"kernel": wh, "bias": bh}}}
    a, b = MinGRUCell(2).apply(params, jnp.asarray(x, jnp.float32), method="coefficients")
    got = np.asarray(losses.linear_scan(a, b))

    h, want = np.zeros((2, 2)), []
    for t in range(x.shape[0]):
        z, candidate = _sigmoid(x[t] @ wz + bz), x[t] @ wh + bh
        h = (1.0 - z) * h + z * candidate
        want.append(h)
    np.testing.assert_allclose(got, np.stack(want), rtol=1e-5, atol=1e-6)


def _mingru_encoder(seed: int) -> tuple[Encoder, dict, jax.Array, jax.Array]:
    """A minGRU q_phi (width 8, hidden 6, latent 3), its parameters and a batch of inputs, from ``seed``."""
    encoder = Encoder(8, 4, 6, 3, "mingru")
    obs, prev = _inputs(5, seed)
    return encoder, encoder.init(jax.random.key(seed + 1), obs[0], prev[0]), obs, prev


def _recur_loop(encoder: Encoder, params: dict, obs: jax.Array, prev: jax.Array, read: jax.Array) -> tuple:
    """(mean, logvar) [T, B, L] after each step, as the actors compute them: ``embed`` and ``recur`` one step at a
    time from a zero state; where ``read`` [T, B] is false the state and the output are carried unchanged."""
    carry, mean, logvar, means, logvars = jnp.zeros((B, encoder.hidden)), np.zeros((B, 3)), np.zeros((B, 3)), [], []
    for t in range(T):
        x = encoder.apply(params, obs[t], prev[t], method="embed")
        new, (m, lv) = encoder.apply(params, carry, x, method="recur")
        keep = np.asarray(read[t])[:, None]
        carry, mean, logvar = jnp.where(keep, new, carry), np.where(keep, m, mean), np.where(keep, lv, logvar)
        means.append(mean)
        logvars.append(logvar)
    return np.stack(means), np.stack(logvars)


@pytest.mark.timeout(120)
def test_encoder_sequence_equals_per_step_recur():
    encoder, params, obs, prev = _mingru_encoder(0)
    mean, logvar = losses.encoder_scan(encoder, params, obs, prev)
    want_mean, want_logvar = _recur_loop(encoder, params, obs, prev, jnp.ones((T, B), bool))
    np.testing.assert_allclose(mean, want_mean, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(logvar, want_logvar, rtol=1e-5, atol=1e-6)


@pytest.mark.timeout(120)
def test_recurrent_policy_sequence_equals_actor_steps():
    policy = RecurrentPolicy(8, 4, 6, 5, "mingru")
    obs, prev = _inputs(5, seed=2)
    params = policy.init(jax.random.key(3), obs[0], prev[0])
    out = losses.recurrent_policy_scan(policy, params, obs, prev)

    actor = RecurrentActor(policy, "imitator")
    carry = actor.init_carry(B)
    for t in range(T):
        view = Observation(expert=obs[t], imitator=obs[t], oracle=obs[t])
        carry, step = actor(params, carry, view, prev[t])
        assert carry.shape == (B, policy.hidden)
        np.testing.assert_allclose(out[t], step, rtol=1e-5, atol=1e-6)


@pytest.mark.timeout(120)
def test_read_masked_posterior_equals_step_loop():
    encoder, params, obs, prev = _mingru_encoder(4)
    # Sequence 0 reads every step, 1 reads steps 0, 2 and 3 (a gap, then it stops), 2 reads nothing (zero output).
    read = jnp.array([[1, 1, 0], [1, 0, 0], [1, 1, 0], [1, 1, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0]], bool)
    mean, logvar = losses.trajectory_posterior(encoder, params, obs, prev, read)
    want_mean, want_logvar = _recur_loop(encoder, params, obs, prev, read)
    np.testing.assert_allclose(mean, want_mean[-1], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(logvar, want_logvar[-1], rtol=1e-5, atol=1e-6)
    assert not np.allclose(mean[0], mean[1])  # The unread steps change what sequence 1 ends on.


def _paths(tree) -> set[str]:
    """Every parameter of a tree as its '/'-joined path."""
    return {"/".join(str(k.key) for k in path) for path, _ in jax.tree_util.tree_flatten_with_path(tree)[0]}


@pytest.mark.timeout(600)
@pytest.mark.parametrize("algo", ["bc", "dil"])
def test_tiny_mingru_run_trains_without_recurrent_kernel(tmp_path, tiny_config, algo):
    config = tiny_config(**{"model.cell": "mingru"})
    state = build_algorithm(config, algo).init(jax.random.key(0))
    gru_state = build_algorithm(tiny_config(), algo).init(jax.random.key(0))
    learner = (lambda s: s.encoder.params["encoder"]) if algo == "dil" else (lambda s: s.policy.params)
    paths, gru_paths = _paths(learner(state)), _paths(learner(gru_state))
    assert any("cell/gate" in p for p in paths) and any("cell/candidate" in p for p in paths)
    assert not any(p.split("/")[-2] in ("hr", "hz", "hn") for p in paths)  # No recurrent kernel.
    assert any(p.split("/")[-2] == "hn" for p in gru_paths) and paths != gru_paths

    train_algorithm(config, algo, tmp_path, progress=False)
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    keys = ("policy_loss", "elbo_loss") if algo == "dil" else ("policy_loss",)
    for key in keys:
        values = [r[key] for r in rows if r.get(key) is not None]
        assert values and np.all(np.isfinite(values)), key
