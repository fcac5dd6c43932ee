"""DAgger's mixture and labels, GAIL's losses, absorbing state and recurrent PPO, on hand values and tiny bandit
runs."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from conftest import assert_rows_close
from jaxdeconf.envs.base import ActionSpace, Observation

from jaxdeconf.actors import ExpertActor
from jaxdeconf.algos.dagger import MixtureActor, mixture_beta
from jaxdeconf.algos.gail import (
    absorbing,
    absorbing_gae_inputs,
    discriminator_batch_loss,
    discriminator_features,
    discriminator_loss,
    discriminator_rewards,
    episode_steps,
    gail_reward,
    next_step_values,
)
from jaxdeconf.data import Trajectory, rollout
from jaxdeconf.errors import ConfigError
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
    # An episode that does not go on after step 1: step 1 no longer bootstraps. delta_1 = -1, A_1 = -1,
    # A_0 = 1.0 + 0.25 * (-1) = 0.75.
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


def _episodes(valid, imitator):
    """A hand-built Trajectory [T, B] from its valid mask [T, B] and imitator view [T + 1, B, d]."""
    valid = jnp.asarray(valid, bool)
    imitator = jnp.asarray(imitator, jnp.float32)
    zeros = jnp.zeros(valid.shape, jnp.float32)
    return Trajectory(obs=Observation(expert=imitator, imitator=imitator, oracle=imitator),
                      action=jnp.zeros(valid.shape, jnp.int32), reward=zeros, valid=valid,
                      best_action=jnp.full(valid.shape, -1, jnp.int32), extras={})


def _three_episodes(stop=2):
    """T = 5, B = 3: episode 0 terminates at step ``stop`` (valid up to and including it; the env then freezes its
    observation), episode 1 runs to the horizon, slot 2 is an empty buffer slot (all zeros, never valid)."""
    t = np.arange(6, dtype=np.float32)
    ep0 = np.stack([np.minimum(t, stop + 1), np.ones(6)], -1)  # s_0 .. s_{stop+1}, then s_{stop+1} frozen.
    ep1 = np.stack([10 + t, -np.ones(6)], -1)
    obs = np.stack([ep0, ep1, np.zeros((6, 2))], 1)  # [T + 1, B, 2]
    valid = np.stack([np.arange(5) <= stop, np.ones(5, bool), np.zeros(5, bool)], 1)
    return _episodes(valid, obs)


def _indicator_disc(w, x):
    """A linear discriminator on the features [..., 3]: logit = x . w."""
    return x @ w


def test_absorbing_features_masks_and_rewards_hand_values():
    """After termination an episode is in the absorbing state (0, 0 | 1); before it the discriminator reads s' with
    indicator 0, the terminating step reading the env's terminal observation. Every step of a stored episode is in
    the discriminator's and the generator's mask, none of an empty slot."""
    traj = _three_episodes()
    np.testing.assert_array_equal(absorbing(traj.valid), [[0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0], [1, 0, 0]])
    np.testing.assert_array_equal(episode_steps(traj.valid), [[1, 1, 0]] * 5)
    features = discriminator_features(traj)
    np.testing.assert_array_equal(features[:, 0], [[1, 1, 0], [2, 1, 0], [3, 1, 0], [0, 0, 1], [0, 0, 1]])
    np.testing.assert_array_equal(features[:, 1], [[11, -1, 0], [12, -1, 0], [13, -1, 0], [14, -1, 0], [15, -1, 0]])
    np.testing.assert_array_equal(features[:, 2], np.zeros((5, 3)))
    # logit = log 3 x indicator: 0 (D = 1/2, reward log 2) at live steps, log 3 (D = 3/4, reward log 4) absorbed.
    logits = _indicator_disc(jnp.array([0.0, 0.0, np.log(3.0)]), features)
    l2, l4 = np.log(2.0), np.log(4.0)
    np.testing.assert_allclose(discriminator_rewards(logits, traj.valid),
                               [[l2, l2, 0], [l2, l2, 0], [l2, l2, 0], [l4, l2, 0], [l4, l2, 0]], rtol=1e-6)


def test_discriminator_loss_with_absorbing_steps_hand_values():
    """Both sides' absorbing steps count in the BCE, each side averaged over every step of its stored episodes.
    With logit = log 3 x indicator: a live step costs log 2 on either side; an absorbing step costs the expert
    -log(3/4) = log(4/3) and the generator -log(1 - 3/4) = log 4.
    Expert: episode 0 absorbed at step 4 only (9 live steps, 1 absorbing): (9 log 2 + log(4/3)) / 10.
    Generator: absorbed at steps 3 and 4 (8 live, 2 absorbing): (8 log 2 + 2 log 4) / 10 = 1.2 log 2.
    The empty slot counts for neither (with it, each mean would be over 15 steps)."""
    w = jnp.array([0.0, 0.0, np.log(3.0)])
    expert, gen = _three_episodes(stop=3), _three_episodes(stop=2)
    expected = (9 * np.log(2.0) + np.log(4 / 3)) / 10 + 1.2 * np.log(2.0)
    np.testing.assert_allclose(discriminator_batch_loss(_indicator_disc, w, expert, gen), expected, rtol=1e-6)


def test_absorbing_gae_hand_values():
    """gamma = lambda = 0.5. Episode 0 terminates at step 2; its absorbing steps 3 and 4 earn the absorbing reward
    0.8 each, and their values are exact, whatever the critic said (9): V_4 = 0.8, V_3 = 0.8 + 0.5 x 0.8 = 1.2, so
    their deltas and advantages are 0.
    delta_2 = 2 + 0.5 x 1.2 - 0.2 = 2.4             A_2 = 2.4  (target 2.6; ending at termination would give 1.8)
    delta_1 = 0 + 0.5 x 0.2 - 1 = -0.9              A_1 = -0.9 + 0.25 x 2.4 = -0.3
    delta_0 = 1 + 0.5 x 1 - 0.5 = 1                 A_0 = 1 + 0.25 x (-0.3) = 0.925
    Episode 1 runs to the horizon with reward 1 and value 0: delta = 1, A_4 = 1, A_t = 1 + 0.25 A_{t+1}."""
    rewards = jnp.array([[1.0, 1.0], [0.0, 1.0], [2.0, 1.0], [0.8, 1.0], [0.8, 1.0]])
    critic = jnp.array([[0.5, 0.0], [1.0, 0.0], [0.2, 0.0], [9.0, 0.0], [9.0, 0.0]])
    valid = jnp.array([[1, 1], [1, 1], [1, 1], [0, 1], [0, 1]], bool)
    values, next_values, continues = absorbing_gae_inputs(critic, rewards, valid, 0.5)
    np.testing.assert_allclose(values[:, 0], [0.5, 1.0, 0.2, 1.2, 0.8], rtol=1e-6)
    np.testing.assert_array_equal(values[:, 1], critic[:, 1])
    np.testing.assert_array_equal(continues, [[1, 1]] * 4 + [[0, 0]])
    adv = gae(rewards, values, next_values, continues, 0.5, 0.5)
    np.testing.assert_allclose(adv[:, 0], [0.925, -0.3, 2.4, 0.0, 0.0], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(adv[:, 1], [1.33203125, 1.328125, 1.3125, 1.25, 1.0], rtol=1e-6)


@pytest.mark.timeout(300)
def test_gail_advantages_continue_through_absorbing_state(tiny_config):
    """GAIL's own ``advantages`` on a bandit episode cut short after step 3 of 10: the absorbing steps earn the
    discriminator's reward of s_a = (0 | 1), have advantage 0, and the terminating step's target is its reward plus
    the discounted absorbing rewards to the horizon, sum_{j=0}^{5} gamma^(j+1) r(s_a)."""
    algo = build_algorithm(tiny_config(), "gail")
    state = jax.jit(algo.init)(jax.random.key(0))
    example = algo.example_episode()
    T = example.horizon
    obs = jax.random.normal(jax.random.key(1), example.obs.imitator.shape)
    traj = example.replace(obs=example.obs.replace(imitator=obs), valid=jnp.arange(T)[:, None] <= 3)
    rewards = np.asarray(jax.jit(algo.rewards)(state, traj))[:, 0]
    adv, target = (np.asarray(x)[:, 0] for x in jax.jit(algo.advantages)(state, traj))
    s_a = jnp.zeros(obs.shape[-1] + 1).at[-1].set(1.0)
    r_a = float(gail_reward(algo.networks[2].apply(state.encoder.params, s_a)))
    assert r_a > 0.1
    np.testing.assert_allclose(rewards[4:], r_a, rtol=1e-6)
    np.testing.assert_allclose(adv[4:], 0.0, atol=1e-5)
    gamma = algo.config.gail.gamma
    absorbed_value = sum(gamma ** (j + 1) * r_a for j in range(T - 4))
    np.testing.assert_allclose(target[3], rewards[3] + absorbed_value, rtol=1e-5)


@pytest.mark.timeout(300)
def test_discriminator_gradient_is_clipped(tiny_config):
    """The discriminator's Adam sees the gradient clipped to global norm ``gail.disc_clip`` (100 by default): a
    gradient (3e6, 4e6, 0) of norm 5e6 reaches Adam's first moment, (1 - beta_1) g = 0.1 g, as 0.1 x (60, 80, 0); with
    disc_clip = 5, as 0.1 x (3, 4, 0); one under the clip passes unchanged."""
    params = {"w": jnp.zeros(3)}

    def first_moment(algo, grad):
        tx = algo.disc_tx
        _, opt_state = tx.update({"w": jnp.asarray(grad)}, tx.init(params), params)
        return np.asarray(optax.tree_utils.tree_get(opt_state, "mu")["w"])

    algo = build_algorithm(tiny_config(), "gail")
    assert algo.config.gail.disc_clip == 100.0
    np.testing.assert_allclose(first_moment(algo, [3e6, 4e6, 0.0]), [6.0, 8.0, 0.0], rtol=1e-5)
    np.testing.assert_allclose(first_moment(algo, [3.0, 4.0, 0.0]), [0.3, 0.4, 0.0], rtol=1e-5)
    small = build_algorithm(tiny_config(**{"gail.disc_clip": "5"}), "gail")
    np.testing.assert_allclose(first_moment(small, [3e6, 4e6, 0.0]), [0.3, 0.4, 0.0], rtol=1e-5)
    with pytest.raises(ConfigError, match=r"gail\.disc_clip=0"):
        tiny_config(**{"gail.disc_clip": "0"})


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


