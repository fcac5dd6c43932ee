"""DAgger's mixture and labels, GAIL's losses and recurrent PPO, on hand values and tiny bandit runs."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import assert_rows_close
from jaxdeconf.envs.base import ActionSpace

from jaxdeconf.actors import ExpertActor
from jaxdeconf.algos.dagger import MixtureActor, mixture_beta
from jaxdeconf.algos.gail import discriminator_loss, gail_reward, next_step_values
from jaxdeconf.data import rollout
from jaxdeconf.losses import soft_nll
from jaxdeconf.models import log_prob
from jaxdeconf.ppo import clipped_surrogate, gae, normalize_advantages, squared_value_error
from jaxdeconf.train import build_algorithm, train_algorithm


def _rows(folder):
    return [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()]


def _mixture_rollout(algo, state, beta, key, coin_key, episodes=64):
    actor = MixtureActor(algo.actor(), ExpertActor(algo.env, algo.env_params))
    params = {"policy": state.policy.params, "key": coin_key, "beta": jnp.float32(beta)}
    return rollout(algo.env, algo.env_params, actor, params, key, episodes)[0]


def test_mixture_at_beta_one_and_zero_is_exactly_expert_and_imitator(tiny_config):
    algo = build_algorithm(tiny_config(), "dagger")
    state = jax.jit(algo.init)(jax.random.key(0))
    key, coin = jax.random.key(1), jax.random.key(2)
    expert = rollout(algo.env, algo.env_params, ExpertActor(algo.env, algo.env_params), None, key, 64)[0]
    imitator = rollout(algo.env, algo.env_params, algo.actor(), state.policy.params, key, 64)[0]
    np.testing.assert_array_equal(_mixture_rollout(algo, state, 1.0, key, coin).action, expert.action)
    np.testing.assert_array_equal(_mixture_rollout(algo, state, 0.0, key, coin).action, imitator.action)
    assert not np.array_equal(expert.action, imitator.action)  # Otherwise the two checks above say nothing.


def test_mixture_coin_per_slot_and_step():
    """At beta = 0.3 a step executes the expert's head in 30% of slots, independently across slots and steps."""
    batch, steps = 4096, 6
    expert_out = jnp.tile(jnp.array([[0.0, 1.0]]), (batch, 1))

    class Imitator:  # A memoryless stand-in whose head differs from the expert's.
        def init_carry(self, batch):
            return jnp.zeros((batch, 0))

        def __call__(self, params, carry, obs, prev):
            return carry, jnp.tile(jnp.array([[1.0, 0.0]]), (batch, 1))

    class Expert(Imitator):
        def __call__(self, params, carry, obs, prev):
            return carry, expert_out

    actor = MixtureActor(Imitator(), Expert())
    params = {"policy": None, "key": jax.random.key(3), "beta": jnp.float32(0.3)}
    carry, picks = actor.init_carry(batch), []
    for _ in range(steps):
        carry, out = actor(params, carry, None, None)
        picks.append(np.asarray(out[:, 1] == 1.0))
    picks = np.stack(picks).astype(float)  # [steps, batch]
    se = np.sqrt(0.3 * 0.7 / picks.size)
    assert abs(picks.mean() - 0.3) < 5 * se
    assert abs(np.corrcoef(picks[0], picks[1])[0, 1]) < 5 / np.sqrt(batch)  # Fresh coins every step.
    assert np.ptp(picks.mean(axis=1)) > 0  # Not one coin shared by all slots.


def test_beta_schedule():
    np.testing.assert_allclose([float(mixture_beta(jnp.int32(i), 4)) for i in (0, 1, 2, 4, 9)],
                               [1.0, 0.75, 0.5, 0.0, 0.0])
    assert float(mixture_beta(jnp.int32(0), 0)) == 0.0


def test_dagger_labels_are_the_experts_action_probabilities(tiny_config):
    algo = build_algorithm(tiny_config(**{"dagger.anneal_iterations": "2"}), "dagger")
    state = jax.jit(algo.init)(jax.random.key(0))
    state, metrics = jax.jit(algo.collect_expert)(state, jax.random.key(1))
    assert float(metrics["beta"]) == 1.0
    data = state.expert_buffer.data
    n = int(state.expert_buffer.size)
    obs = jax.tree.map(lambda x: x[:-1, :n], data.traj.obs)
    expected = algo.env.expert_probs(obs, algo.env_params)  # [T, n, arms]: p on θ, (1 - p)/4 elsewhere.
    np.testing.assert_allclose(data.tags["label"][:, :n], expected, rtol=1e-6)
    np.testing.assert_allclose(np.sort(np.asarray(expected[0, 0])), [0.1, 0.1, 0.1, 0.1, 0.6], rtol=1e-6)


def test_soft_nll_hand_values():
    space = ActionSpace("discrete", 5)
    # logits (0, 0, 0, 0, log 2): probabilities (1, 1, 1, 1, 2) / 6. A uniform label gives
    # -(4 log(1/6) + log(2/6)) / 5 = log 6 - log(2) / 5.
    out = jnp.array([[[0.0, 0.0, 0.0, 0.0, np.log(2.0)]]])
    label = jnp.full((1, 1, 5), 0.2)
    valid = jnp.ones((1, 1), bool)
    np.testing.assert_allclose(soft_nll(space, out, label, valid), np.log(6) - np.log(2) / 5, rtol=1e-6)
    # A one-hot label is the plain NLL: -log(2/6).
    onehot = jax.nn.one_hot(jnp.array([[4]]), 5)
    np.testing.assert_allclose(soft_nll(space, out, onehot, valid), np.log(3), rtol=1e-6)


def test_gae_hand_values():
    # gamma = 0.5, lambda = 0.5, one episode of 3 steps that ends after the last one.
    # delta_2 = 2 - 0.2 = 1.8                      A_2 = 1.8
    # delta_1 = 0 + 0.5 * 0.2 - 1 = -0.9           A_1 = -0.9 + 0.25 * 1.8 = -0.45
    # delta_0 = 1 + 0.5 * 1 - 0.5 = 1.0            A_0 = 1.0 + 0.25 * (-0.45) = 0.8875
    rewards = jnp.array([1.0, 0.0, 2.0])
    values = jnp.array([0.5, 1.0, 0.2])
    next_values, continues = next_step_values(values, jnp.array([True, True, True]))
    np.testing.assert_array_equal(continues, [1, 1, 0])
    np.testing.assert_allclose(gae(rewards, values, next_values, continues, 0.5, 0.5), [0.8875, -0.45, 1.8],
                               rtol=1e-6)
    # Terminated after step 1 (step 2 invalid): step 1 no longer bootstraps. delta_1 = -1, A_1 = -1,
    # A_0 = 1.0 + 0.25 * (-1) = 0.75 (step 2's advantage is masked out of every loss).
    next_values, continues = next_step_values(values, jnp.array([True, True, False]))
    np.testing.assert_allclose(gae(rewards * jnp.array([1, 1, 0]), values, next_values, continues, 0.5, 0.5)[:2],
                               [0.75, -1.0], rtol=1e-6)


def test_clipped_surrogate_and_value_loss_hand_values():
    # ratios e^0.5 = 1.6487 (clipped to 1.2) with A = 1, and e^-0.5 = 0.6065 (clipped to 0.8) with A = -2:
    # min(1.6487, 1.2) = 1.2 and min(-1.2131, -1.6) = -1.6, so the loss is -(1.2 - 1.6) / 2 = 0.2.
    logp, old = jnp.array([0.5, -0.5]), jnp.zeros(2)
    np.testing.assert_allclose(clipped_surrogate(logp, old, jnp.array([1.0, -2.0]), 0.2), 0.2, rtol=1e-6)
    # Unclipped side: ratio e^0.1 = 1.10517 with A = 1 is inside the clip, loss -1.10517.
    np.testing.assert_allclose(clipped_surrogate(jnp.array([0.1]), jnp.zeros(1), jnp.ones(1), 0.2),
                               -np.exp(0.1), rtol=1e-6)
    # The mask drops the second step: only -1.2 remains.
    np.testing.assert_allclose(
        clipped_surrogate(logp, old, jnp.array([1.0, -2.0]), 0.2, jnp.array([True, False])), -1.2, rtol=1e-6)
    np.testing.assert_allclose(squared_value_error(jnp.array([1.0, 3.0]), jnp.array([0.0, 0.0])), 2.5)
    adv = normalize_advantages(jnp.array([1.0, 3.0, 100.0]), jnp.array([True, True, False]))
    np.testing.assert_allclose(adv[:2], [-1.0, 1.0], rtol=1e-6)


def test_discriminator_loss_and_reward_hand_values():
    # D = sigmoid(0) = 1/2 everywhere: -log(1/2) for each side, 2 log 2 in all.
    zeros, valid = jnp.zeros((3, 2)), jnp.ones((3, 2), bool)
    np.testing.assert_allclose(discriminator_loss(zeros, valid, zeros, valid), 2 * np.log(2), rtol=1e-6)
    # Expert logit log 3 (D = 3/4): -log(3/4); generator logit -log 3 (D = 1/4): -log(3/4). Masked steps ignored.
    e = jnp.array([np.log(3.0), 50.0])
    g = jnp.array([-np.log(3.0), 50.0])
    mask = jnp.array([True, False])
    np.testing.assert_allclose(discriminator_loss(e, mask, g, mask), -2 * np.log(0.75), rtol=1e-6)
    # Reward -log(1 - D): D = 3/4 gives log 4.
    np.testing.assert_allclose(gail_reward(jnp.array(np.log(3.0))), np.log(4.0), rtol=1e-6)


def test_recurrent_ppo_replay_equals_rollout(tiny_config):
    """The log-probabilities replayed from a zero GRU state equal those recorded while acting: the first PPO
    minibatch of the first epoch sees a ratio of 1."""
    algo = build_algorithm(tiny_config(), "gail")
    state = jax.jit(algo.init)(jax.random.key(0))
    state, _ = jax.jit(algo.collect_explore)(state, jax.random.key(1))
    data = state.explore_buffer.data
    out = jax.jit(algo.policy_outputs)(state.policy.params, state, data.traj)
    replayed = log_prob(algo.space, out, data.traj.action)
    ratio = np.exp(np.asarray(replayed) - np.asarray(data.tags["log_prob"]))
    np.testing.assert_allclose(ratio, 1.0, atol=1e-5)
    assert np.ptp(np.asarray(data.tags["log_prob"])) > 0.1  # A stochastic policy, so the check has teeth.
    _, metrics = jax.jit(algo.update_policy)(state, jax.random.key(2))
    assert np.isfinite(float(metrics["policy_loss"]))


# gail's two programs take about two minutes to compile; dagger keeps the check in the default tier.
@pytest.mark.parametrize("algo", ["dagger", pytest.param("gail", marks=pytest.mark.slow)])
def test_seed_of_sweep_equals_single_run(tmp_path, tiny_config, algo):
    sweep = tiny_config(seeds=2)
    single = dataclasses.replace(tiny_config(seeds=1), seed_start=1)
    train_algorithm(sweep, algo, tmp_path / "sweep", progress=False)
    train_algorithm(single, algo, tmp_path / "single", progress=False)
    a = [r for r in _rows(tmp_path / "sweep") if r["seed"] == 1]
    b = _rows(tmp_path / "single")
    assert len(a) == len(b) == 4 and "eval_return" in a[-1]
    assert_rows_close(a, b)


