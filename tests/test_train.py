"""Determinism, seed i of a sweep equal to a lone run of seed i, exact resume, buffers, the latent cache."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import assert_rows_close

from jaxdeconf.algos import names
from jaxdeconf.algos.dil import Deconfounded, decoder_posterior_mean, final_latents
from jaxdeconf.data import buffer_add, buffer_sample
from jaxdeconf.models import action_features
from jaxdeconf.train import build_algorithm, compiled_chunk, over_seeds, seed_keys, train_algorithm


def _rows(folder):
    return [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("algo", [pytest.param("bc", marks=pytest.mark.slow), "dil"])  # dil holds bc's path too.
def test_same_seed_same_metrics(tmp_path, tiny_config, algo):
    config = tiny_config()
    train_algorithm(config, algo, tmp_path / "a", progress=False)
    train_algorithm(config, algo, tmp_path / "b", progress=False)
    assert _rows(tmp_path / "a") == _rows(tmp_path / "b")
    assert any("eval_return" in r for r in _rows(tmp_path / "a"))


@pytest.mark.slow  # The default tier checks the same seed-vmapped loop with dagger (test_baselines.py; gail is slow).
def test_seed_of_sweep_equals_single_run(tmp_path, tiny_config):
    sweep = tiny_config(seeds=3)
    single = dataclasses.replace(tiny_config(seeds=1), seed_start=2)
    train_algorithm(sweep, "dil", tmp_path / "sweep", progress=False)
    train_algorithm(single, "dil", tmp_path / "single", progress=False)
    a = [r for r in _rows(tmp_path / "sweep") if r["seed"] == 2]
    b = _rows(tmp_path / "single")
    assert len(a) == len(b) == 4
    assert_rows_close(a, b)


def test_buffer_is_circular_and_samples_distinct_episodes(tiny_config):
    algo = build_algorithm(tiny_config(), "bc")
    state = algo.init(jax.random.key(0))
    buf = state.expert_buffer
    assert buf.capacity == 8
    for i in range(3):  # 3 inserts of 4 episodes into 8 slots: the first 4 are overwritten.
        traj = jax.tree.map(lambda x, i=i: jnp.full((x.shape[0], 4, *x.shape[2:]), i, x.dtype), buf.data)
        buf = buffer_add(buf, traj)
    assert int(buf.size) == 8 and int(buf.pos) == 4
    np.testing.assert_array_equal(buf.data.reward[0], [2, 2, 2, 2, 1, 1, 1, 1])
    batch = buffer_sample(buf, jax.random.key(1), 8)
    np.testing.assert_array_equal(np.sort(np.asarray(batch.reward[0])), [1, 1, 1, 1, 2, 2, 2, 2])


def test_cached_latents_equal_per_batch_encoding(tiny_config):
    algo = build_algorithm(tiny_config(), "dil")
    assert isinstance(algo, Deconfounded)
    state = algo.init(jax.random.key(0))
    state, _ = algo.collect_expert(state, jax.random.key(1))
    state = state.replace(expert_buffer=buffer_add(state.expert_buffer, state.expert_buffer.data))
    context = algo.policy_context(state, jax.random.key(2))
    assert context is not None  # 8 episodes <= batch 4 x 2 steps: the cache is used.
    idx = jnp.array([5, 0, 3, 1])
    batch = jax.tree.map(lambda d: d[:, idx], state.expert_buffer.data)
    cached = algo.policy_outputs(state.policy.params, state, batch, context[:, idx])
    direct = algo.policy_outputs(state.policy.params, state, batch)
    np.testing.assert_allclose(cached, direct, rtol=1e-5, atol=1e-6)


def test_final_latents_take_each_episodes_last_valid_step():
    """Hand values: episode 0 is valid for 2 of 3 steps, so its code is step 1's mean; episode 1 for all 3, step 2's;
    an empty slot (no valid step) falls back to step 0."""
    mean = jnp.arange(3 * 3 * 1, dtype=jnp.float32).reshape(3, 3, 1)  # mean[t, b] = 3 t + b.
    valid = jnp.array([[True, True, False], [True, True, False], [False, True, False]])
    np.testing.assert_array_equal(final_latents(mean, valid)[:, 0], [3.0, 7.0, 2.0])


def test_decoder_posterior_mean_hand_values():
    """Codes 0, 1 and 5 (5 not yet filled) and a unit-Gaussian toy decoder nll = (obs_t - z)^2 / 2: an episode at
    1, 1 (a third step at 100, invalid) has log-likelihood -1 under code 0 and 0 under code 1, so its posterior mean
    is e / (1 + e); one at 0, 0 has 0 and -1, so 1 / (1 + e)."""
    particles = jnp.array([[0.0], [1.0], [5.0]])
    filled = jnp.array([True, True, False])

    def nll(z, obs, feats, valid):
        return 0.5 * (obs[:-1, :, 0] - z[..., 0]) ** 2

    obs = jnp.array([[1.0, 0.0], [1.0, 0.0], [100.0, 100.0], [0.0, 0.0]])[..., None]  # [T+1=4, B=2, 1]
    feats = jnp.zeros((3, 2, 1))
    valid = jnp.array([[True, True], [True, True], [False, False]])
    got = decoder_posterior_mean(nll, particles, filled, obs, feats, valid)
    e = np.e
    np.testing.assert_allclose(got[:, 0], [e / (1 + e), 1 / (1 + e)], rtol=1e-6)


def test_matched_latents_equal_a_loop_over_codes_and_episodes(tiny_config):
    """``policy_latent=matched``: the θ-hat of each expert episode is the mean of the own buffer's final codes
    weighed by exp(-summed decoder NLL) of the episode under each code, here recomputed one (code, episode) pair at
    a time; every step of an episode gets the same θ-hat, and it differs across episodes. ``match_codes`` keeps that
    many evenly spaced slots as codes, of which only filled ones count."""
    algo = build_algorithm(tiny_config(**{"dil.policy_latent": "matched"}), "dil")
    state = algo.init(jax.random.key(0))
    state, _ = algo.collect_expert(state, jax.random.key(1))
    state, _ = algo.collect_explore(state, jax.random.key(2))
    data, own = state.expert_buffer.data, state.explore_buffer
    got = np.asarray(algo.training_context(state, data))
    assert np.all(got == got[:1]) and not np.allclose(got[0, 0], got[0, 1])
    codes = np.asarray(final_latents(algo.posterior_means(state, own.data), own.data.valid))
    nll = algo.dynamics_nll(state)
    feats = action_features(algo.space, data.action)
    for b in range(data.valid.shape[1]):
        log_lik = np.array([-float(jnp.sum(nll(jnp.asarray(codes[p])[None, None].repeat(data.horizon, 0),
                                                 data.obs.imitator[:, b:b + 1], feats[:, b:b + 1],
                                                 data.valid[:, b:b + 1]) * data.valid[:, b:b + 1]))
                            for p in range(int(own.size))])
        w = np.exp(log_lik - log_lik.max())
        np.testing.assert_allclose(got[0, b], (w / w.sum()) @ codes[: int(own.size)], rtol=1e-4, atol=1e-5)
    assert algo.policy_context(state, jax.random.key(3)) is not None  # Encoded once per iteration.
    two = build_algorithm(tiny_config(**{"dil.policy_latent": "matched", "dil.match_codes": "2"}), "dil")
    only = np.asarray(two.training_context(state, data))  # Slots 0 and 4 of 8; 4 episodes stored: slot 0 alone.
    np.testing.assert_allclose(only, np.broadcast_to(codes[0], only.shape), rtol=1e-5, atol=1e-6)


def test_seed_keys_follow_seed_start(tiny_config):
    config = dataclasses.replace(tiny_config(seeds=2), seed_start=5)
    np.testing.assert_array_equal(jax.random.key_data(seed_keys(config)[1]), jax.random.key_data(jax.random.key(6)))


@pytest.mark.parametrize("algo", names())
def test_programs_call_no_lapack(tiny_config, algo):
    """The seed-vmapped init and chunk programs contain no LAPACK call: jaxlib 0.10.2's batched CPU LAPACK kernels
    split the seed batch over XLA's thread pool and deadlocked there (gdb: every thread idle, a LAPACK kernel
    waiting for its batch), so the probe's solve and the GRUs' orthogonal initialiser are written without it."""
    config = tiny_config()
    built = build_algorithm(config, algo)
    keys = jax.random.key_data(seed_keys(config))
    init = over_seeds(lambda k: built.init(jax.random.wrap_key_data(k)), config)
    states = jax.eval_shape(init, keys)
    texts = [init.lower(keys).as_text(), compiled_chunk(built, 1).lower(states).as_text()]
    assert not [t for t in texts if "lapack" in t.lower()]
