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


@pytest.mark.timeout(300)
def test_dagger_labels_are_the_experts_action_probabilities(tiny_config):
    """Every stored label is the bandit expert's distribution at that state, written out by hand from the episode's
    θ (the env's best arm, not the expert's view): p = 0.6 on θ and (1 - p) / 4 = 0.1 on each other arm, at beta = 1
    and at beta = 1/2 (where the imitator picked some of the executed actions) alike."""
    algo = build_algorithm(tiny_config(**{"dagger.anneal_iterations": "2"}), "dagger")
    collect = jax.jit(algo.collect_expert)
    state = jax.jit(algo.init)(jax.random.key(0))
    state, metrics = collect(state, jax.random.key(1))
    assert float(metrics["beta"]) == 1.0
    state, metrics = collect(state.replace(iteration=jnp.int32(1)), jax.random.key(2))
    assert float(metrics["beta"]) == 0.5
    data = state.expert_buffer.data
    n = int(state.expert_buffer.size)
    assert n == 8  # Both collections' episodes (4 each) are stored.
    theta = np.asarray(data.traj.best_action[:, :n])  # [T, n]: θ at every step.
    assert (theta == theta[:1]).all() and len(np.unique(theta[0])) > 1  # θ fixed per episode, varied across them.
    expected = np.full((*theta.shape, 5), 0.1)
    np.put_along_axis(expected, theta[..., None], 0.6, axis=-1)
    np.testing.assert_allclose(np.asarray(data.tags["label"][:, :n]), expected, rtol=1e-6)


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


@pytest.mark.timeout(300)
def test_recurrent_ppo_replay_equals_rollout(tiny_config):
    """The log-probabilities replayed from a zero GRU state equal those recorded while acting: the first PPO
    minibatch of the first epoch sees a ratio of 1. On those episodes, GAIL's PPO loss is the clipped surrogate of a
    numpy re-computation, and a small step down its gradient on a hand-built advantage, +1 where arm 0 was pulled
    and -1 elsewhere, makes arm 0 more likely at the steps it was pulled and every other pulled arm less likely."""
    algo = build_algorithm(tiny_config(), "gail")
    state = jax.jit(algo.init)(jax.random.key(0))
    state, _ = jax.jit(algo.collect_explore)(state, jax.random.key(1))
    data = state.explore_buffer.data
    out = jax.jit(algo.policy_outputs)(state.policy.params, state, data.traj)
    replayed = np.asarray(log_prob(algo.space, out, data.traj.action))
    recorded = np.asarray(data.tags["log_prob"])
    np.testing.assert_allclose(np.exp(replayed - recorded), 1.0, atol=1e-5)
    assert np.ptp(recorded) > 0.1  # A stochastic policy, so the check has teeth.

    action, valid = np.asarray(data.traj.action), np.asarray(data.traj.valid)
    pulled0 = action == 0
    assert pulled0[valid].any() and (~pulled0)[valid].any()
    adv = np.where(pulled0, 1.0, -1.0).astype(np.float32)
    targets = jnp.zeros(valid.shape, jnp.float32)
    loss_fn = jax.jit(algo.ppo_loss)

    # Old log-probabilities shifted by -0.5, 0, 0.1 and 0.5 (ratios e^0.5, 1, e^-0.1, e^-0.5) across the steps, so
    # both sides of the clip (eps 0.2) are taken; the expected surrogate from numpy, advantages standardised over the
    # valid steps.
    shift = np.resize(np.array([-0.5, 0.0, 0.1, 0.5], np.float32), valid.shape)
    batch = data.replace(tags={"log_prob": jnp.asarray(recorded + shift), "adv": jnp.asarray(adv),
                               "target": targets})
    _, metrics = loss_fn(state.policy.params, batch)
    a = adv[valid].astype(np.float64)
    a = (a - a.mean()) / (a.std() + 1e-8)
    ratio = np.exp(-shift[valid].astype(np.float64))
    eps = algo.config.gail.clip_eps
    expected = -np.mean(np.minimum(ratio * a, np.clip(ratio, 1 - eps, 1 + eps) * a))
    assert float(metrics["policy_loss"]) == pytest.approx(expected, rel=1e-4)
    assert abs(expected - (-np.mean(ratio * a))) > 0.05  # The clip changes the value: the check sees it.

    # A small step down the loss's gradient from the behaviour policy (ratio 1) on the hand-built advantage. (One
    # Adam step moves every weight by the learning rate whatever its gradient, which on this GRU moves log-probs by
    # up to 1.5 nats: no longer a first-order step whose direction the loss's sign decides.) To first order the step
    # raises sum_t A_t log p(a_t); measured at 1e-3: +0.82 mean change where arm 0 was pulled, -1.07 elsewhere.
    batch = data.replace(tags={"log_prob": data.tags["log_prob"], "adv": jnp.asarray(adv), "target": targets})
    grads, metrics = jax.jit(jax.grad(algo.ppo_loss, has_aux=True))(state.policy.params, batch)
    assert float(metrics["policy_loss"]) == pytest.approx(0.0, abs=1e-6)  # Ratio 1, standardised A: mean 0.
    stepped = jax.tree.map(lambda p, g: p - 1e-4 * g, state.policy.params, grads)
    after = np.asarray(log_prob(algo.space, jax.jit(algo.policy_outputs)(stepped, state, data.traj),
                                data.traj.action))
    change = after - replayed
    assert (change * adv)[valid].mean() > 0
    assert change[valid & pulled0].mean() > 0 and change[valid & ~pulled0].mean() < 0, change


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


