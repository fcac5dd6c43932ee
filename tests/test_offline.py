"""dil_offline (Algorithm 3): the offline ELBO on hand values and against a plain loop, synthetic rollouts that never
step the environment, the frozen dynamics model under q_on's steps, a short learning check on the bandit, and the
synthetic episodes of the box-action Brax envs (uniform exploration, starts and masks of expert episodes, p_psi's
mean steps)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import CARTPOLE, TINY
from jaxdeconf.envs.bandit import Bandit

from jaxdeconf import losses
from jaxdeconf.algos import make_algorithm
from jaxdeconf.errors import ConfigError
from jaxdeconf.models import Decoder, Encoder, LatentPolicy, log_prob
from jaxdeconf.resolve import build, from_dict
from jaxdeconf.results import load_metrics
from jaxdeconf.train import train_algorithm

HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def _offline_config(**extra):
    return build("bandit", "cpu", ("dil_offline",), 2, {**TINY, **extra})


def _networks(obs_size, latent, actions, enc_obs_size):
    encoder, decoder, policy = Encoder(8, 4, 6, latent), Decoder(8, 4, obs_size), LatentPolicy(8, actions)
    k1, k2, k3 = jax.random.split(jax.random.key(0), 3)
    obs, act, z = jnp.zeros((1, obs_size)), jnp.zeros((1, actions)), jnp.zeros((1, latent))
    params = {"offline": encoder.init(k1, jnp.zeros((1, enc_obs_size)), act), "decoder": decoder.init(k2, z, obs, act),
              "policy": policy.init(k3, obs, z)}
    return encoder, decoder, policy, params


def _with_output_biases(params, mean, logvar, dynamics, logits):
    """All weights zero, so every network outputs the bias of its last layer whatever its input: q_off gives
    (mean, logvar) at every step (a zero GRU stays zero), p_psi ``dynamics`` and pi_eta ``logits``."""
    params = jax.tree.map(jnp.zeros_like, params)
    params["offline"]["params"]["out"]["bias"] = jnp.concatenate([jnp.asarray(mean), jnp.asarray(logvar)])
    params["decoder"]["params"]["Dense_1"]["bias"] = jnp.asarray(dynamics)
    params["policy"]["params"]["Dense_0"]["bias"] = jnp.asarray(logits)
    return params


@pytest.mark.timeout(120)
def test_offline_elbo_hand_values():
    """Two episodes of T = 2 steps, one observation dimension, 2 actions, latent size 2.

    Fixed outputs: q_off = N((1, 0), diag(1, e^-2)); p_psi's mean change 0.5 with delta_scale 2; pi_eta's logits
    (0, log 3), so P(a=0) = 1/4 and P(a=1) = 3/4. Observations (0, 1, 1) and (0, 3, *): changes / 2 = (0.5, 0) and
    (1.5, *), the second episode ending after its first step.
      dynamics:  episode 1: -log N(0.5; 0.5, 1) + -log N(0; 0.5, 1) = HALF_LOG_2PI + (0.125 + HALF_LOG_2PI)
                 episode 2: -log N(1.5; 0.5, 1) = 0.5 + HALF_LOG_2PI
      policy:    actions (1, 0) and (1, -): -log(3/4) - log(1/4) and -log(3/4)
      KL:        0.5 * (1 + 1 - 1 - 0) + 0.5 * (2 + e^-2 - 1) = 0.5 + 0.5 * (1 + e^-2), the same for both episodes
    loss = (episode 1 + episode 2 + 2 * beta * KL) / 2 / T with beta = 0.3.
    """
    encoder, decoder, policy, params = _networks(1, 2, 2, 1)
    params = _with_output_biases(params, [1.0, 0.0], [0.0, -2.0], [0.5], [0.0, math.log(3.0)])
    obs = jnp.array([[[0.0], [0.0]], [[1.0], [3.0]], [[1.0], [7.0]]])  # [T+1=3, B=2, 1]
    action = jnp.array([[1, 1], [0, 0]])
    valid = jnp.array([[True, True], [True, False]])
    loss, metrics = losses.offline_elbo_loss(
        params, obs, action, valid, jax.random.key(0), encoder=encoder, decoder=decoder, policy=policy,
        space=Bandit().action_space(Bandit().default_params().replace(arms=2)), beta=0.3, likelihood="gaussian",
        delta_scale=jnp.array([2.0]))
    dynamics = [2 * HALF_LOG_2PI + 0.125, 0.5 + HALF_LOG_2PI]
    policy_nll = [-math.log(0.75) - math.log(0.25), -math.log(0.75)]
    kl = 0.5 + 0.5 * (1 + math.exp(-2))
    expected = (sum(dynamics) + sum(policy_nll) + 2 * 0.3 * kl) / 2 / 2
    assert float(loss) == pytest.approx(expected, rel=1e-5)
    assert float(metrics["vae_kl"]) == pytest.approx(kl, rel=1e-5)
    assert float(metrics["vae_dynamics_nll"]) == pytest.approx(sum(dynamics) / 3, rel=1e-5)
    assert float(metrics["vae_policy_nll"]) == pytest.approx(sum(policy_nll) / 3, rel=1e-5)


@pytest.mark.timeout(120)
@pytest.mark.parametrize(("likelihood", "deltas"), [("bernoulli", False), ("gaussian", True)])
def test_offline_elbo_scan_matches_plain_loop(likelihood, deltas):
    """The scanned, masked loss equals a loop over t in which q_off reads each episode cut at its own length."""
    T, B, L, n = 6, 3, 2, 5
    scale = jnp.array([0.5, 2.0]) if likelihood == "gaussian" else None
    d = 2 if likelihood == "gaussian" else 1
    encoder, decoder, policy, params = _networks(d, L, n, 2 * d if deltas else d)
    k1, k2, key = jax.random.split(jax.random.key(5), 3)
    obs = (jax.random.normal(k1, (T + 1, B, d)) if likelihood == "gaussian"
           else jax.random.bernoulli(k1, 0.5, (T + 1, B, d)).astype(jnp.float32))
    action = jax.random.randint(k2, (T, B), 0, n)
    lengths = [T, 4, 1]
    valid = jnp.arange(T)[:, None] < jnp.array(lengths)[None, :]
    space = Bandit().action_space(Bandit().default_params())
    loss, _ = losses.offline_elbo_loss(params, obs, action, valid, key, encoder=encoder, decoder=decoder,
                                       policy=policy, space=space, beta=0.7, likelihood=likelihood, delta_scale=scale,
                                       encoder_delta_scale=scale if deltas else None)

    eps = jax.random.normal(key, (B, L))
    feats = jax.nn.one_hot(action, n)
    total = 0.0
    for b, length in enumerate(lengths):
        carry = jnp.zeros((1, encoder.hidden))
        for i in range(length + 1):  # s_0 .. s_length, each with the action that led to it.
            enc_obs = obs[i, b : b + 1]
            if deltas:
                enc_obs = jnp.concatenate([enc_obs, (obs[i, b : b + 1] - obs[max(i - 1, 0), b : b + 1]) / scale], -1)
            prev = feats[i - 1, b : b + 1] if i > 0 else jnp.zeros((1, n))
            x = encoder.apply(params["offline"], enc_obs, prev, method="embed")
            carry, (mean, logvar) = encoder.apply(params["offline"], carry, x, method="recur")
        z = mean + jnp.exp(0.5 * logvar) * eps[b : b + 1]
        episode = 0.7 * losses.kl_diag_gaussian(mean, logvar, jnp.zeros_like(mean), jnp.zeros_like(mean))
        for t in range(length):
            out = decoder.apply(params["decoder"], z, obs[t, b : b + 1], feats[t, b : b + 1])
            if likelihood == "gaussian":
                episode += losses.gaussian_nll((obs[t + 1, b : b + 1] - obs[t, b : b + 1]) / scale, out)
            else:
                episode += losses.bernoulli_nll(obs[t + 1, b : b + 1], out)
            logits = policy.apply(params["policy"], obs[t, b : b + 1], z)
            episode -= log_prob(space, logits, action[t, b : b + 1])
        total += float(episode[0])
    assert float(loss) == pytest.approx(total / B / T, rel=1e-5)


class CountingBandit(Bandit):
    """The bandit, counting how often a program traces its ``step`` (each rollout's scan traces it once)."""

    calls = 0

    def step(self, key, state, action, params):
        """Count, then step."""
        CountingBandit.calls += 1
        return super().step(key, state, action, params)


@pytest.mark.timeout(300)
def test_training_never_steps_the_environment_besides_the_experts_episodes():
    """Synthetic rollouts, q_on's steps and the VAE's steps trace no env step; a whole iteration traces exactly the
    expert collection's steps. q_on's steps leave p_psi, q_off and pi_eta (and their optimiser moments) untouched,
    and the VAE's steps leave q_on untouched."""
    config = _offline_config()
    env = CountingBandit()
    params = env.default_params().replace(horizon=int(TINY["env.horizon"]))
    algo = make_algorithm("dil_offline", env, params, config)
    state = jax.jit(algo.init)(jax.random.key(0))
    CountingBandit.calls = 0
    state, _ = jax.jit(algo.collect_expert)(state, jax.random.key(1))
    expert_calls, CountingBandit.calls = CountingBandit.calls, 0
    assert expert_calls >= 1

    batch = jax.jit(algo.synthetic_rollout)(state, jax.random.key(2))
    online, metrics = jax.jit(algo.update_encoder)(state, jax.random.key(3))
    vae, _ = jax.jit(algo.update_policy)(state, jax.random.key(4))
    assert CountingBandit.calls == 0
    jax.eval_shape(algo.iteration, state)  # Tracing alone calls step as often as compiling would.
    assert CountingBandit.calls == expert_calls

    T, n = params.horizon, config.offline.synthetic_episodes
    assert batch.obs.shape == (T + 1, n, 1) and batch.action.shape == (T, n)
    assert set(np.unique(np.asarray(batch.obs))) <= {0.0, 1.0}  # Bernoulli samples of the outcome.
    assert np.isfinite(float(metrics["elbo_loss"]))
    same = lambda a, b: jax.tree.all(jax.tree.map(lambda x, y: bool(jnp.array_equal(x, y)), a, b))  # noqa: E731
    for part in ("decoder", "offline"):
        assert same(online.encoder.params[part], state.encoder.params[part])
        assert not same(vae.encoder.params[part], state.encoder.params[part])
    assert same(online.encoder.opt_state["model"], state.encoder.opt_state["model"])
    assert same(online.policy, state.policy) and not same(vae.policy.params, state.policy.params)
    assert not same(online.encoder.params["encoder"], state.encoder.params["encoder"])
    assert same(vae.encoder.params["encoder"], state.encoder.params["encoder"])
    assert same(vae.encoder.opt_state["encoder"], state.encoder.opt_state["encoder"])



@pytest.mark.timeout(120)
def test_synthetic_latents_from_the_prior_or_from_q_off():
    """``prior`` draws N(0, I); ``posterior`` samples q_off on the chosen expert episodes: with q_off made to output
    (mean, logvar) whatever it reads, that is mean + exp(logvar / 2) times the prior's draw from the same key."""
    env = Bandit()
    params = env.default_params().replace(horizon=int(TINY["env.horizon"]))
    prior = make_algorithm("dil_offline", env, params, _offline_config(**{"offline.synthetic_latent": "prior"}))
    posterior = make_algorithm("dil_offline", env, params, _offline_config())
    state = jax.jit(prior.init)(jax.random.key(0))
    state, _ = jax.jit(prior.collect_expert)(state, jax.random.key(1))
    latent = prior.config.model.latent
    mean, logvar = np.linspace(-1.0, 1.0, latent), np.linspace(-2.0, 0.5, latent)
    q_off = jax.tree.map(jnp.zeros_like, state.encoder.params["offline"])
    q_off["params"]["out"]["bias"] = jnp.asarray(np.concatenate([mean, logvar]), jnp.float32)
    state = state.replace(encoder=state.encoder.replace(params={**state.encoder.params, "offline": q_off}))
    episodes = jax.tree.map(lambda d: d[:, :3], state.expert_buffer.data)
    key = jax.random.key(5)
    draw = np.asarray(prior.synthetic_latents(state, episodes, key))
    np.testing.assert_array_equal(draw, np.asarray(jax.random.normal(key, (3, latent))))
    np.testing.assert_allclose(np.asarray(posterior.synthetic_latents(state, episodes, key)),
                               mean + np.exp(0.5 * logvar) * draw, rtol=1e-5, atol=1e-6)


@pytest.mark.timeout(300)
def test_offline_elbo_scores_p_psi_as_q_on_elbo_does():
    """p_psi is trained with the likelihood q_on's ELBO reads it with (``decoder_scoring``, one definition for both).
    On the cart-pole (one Gaussian group of 4 dimensions) ``decoder_weighting=group_mean`` averages the group's NLL
    where ``sum`` adds it, so with the same parameters, batch and key the offline ELBO's dynamics NLL is exactly a
    quarter (on a loss that summed every dimension whatever the setting, both would be equal)."""
    out = {}
    for weighting in ("sum", "group_mean"):
        config = build(CARTPOLE, "cpu", ("dil_offline",), 1, {**TINY, "dil.decoder_weighting": weighting})
        algo = make_algorithm("dil_offline", *_cartpole(), config)
        state = algo.init(jax.random.key(0))
        state, _ = algo.collect_expert(state, jax.random.key(1))
        data = state.expert_buffer.data
        params = {**state.encoder.params, "policy": state.policy.params}
        _, metrics = algo.offline_elbo_fn(params, data.obs.imitator, data.action, data.valid, jax.random.key(2))
        out[weighting] = float(metrics["vae_dynamics_nll"])
        scoring = ("likelihood", "delta_scale", "groups", "weighting")
        online, offline = algo.elbo_fn.keywords, algo.offline_elbo_fn.keywords
        assert all(online[k] is offline[k] or online[k] == offline[k] for k in scoring)
    assert out["group_mean"] == pytest.approx(out["sum"] / 4, rel=1e-5)


def _cartpole():
    """The cart-pole example env and its default params."""
    from jaxdeconf.envs import make

    return make(CARTPOLE)


def test_saved_configs_read_back_and_a_removed_setting_is_named():
    """A saved config reads back equal, the algorithm-owned ``offline`` section included; a folder whose config holds
    a setting this version does not have is refused with one line naming it."""
    config = _offline_config()
    saved = config.to_dict()
    assert from_dict(saved) == config
    saved["offline"]["dynamics_noise"] = 0.0
    with pytest.raises(ConfigError, match=r"^offline.dynamics_noise is not a setting of this version"):
        from_dict(saved)


#: The learning check's reduced budget: 30-step episodes, 20 iterations, small step counts; every other setting is the
#: shipped ``cpu`` preset's and dil_offline's defaults (synthetic latents from q_off's posterior included).
SHORT = {"env.horizon": "30", "train.iterations": "20", "train.warmup": "5", "train.chunk": "20",
         "train.eval_episodes": "256", "offline.vae_steps": "40", "offline.online_steps": "40"}
# Seeds 0-5 at this budget ended at 8.71, 9.77, 9.27, 8.33, 9.46, 9.86 best arms of 30 (mean 9.23, standard deviation
# 0.60, so a 2-seed mean has a standard error of 0.43); with a quarter of the gradient steps (vae_steps and
# online_steps 10) seeds 0-5 stayed at chance: 6.10, 6.41, 6.43, 6.08, 6.31, 6.20. 7.8 lies 3.3 standard errors below
# the measured mean and above every seed that did not learn.
BOUND = 7.8


@pytest.mark.slow  # A learning check: about 2 min on one core.
@pytest.mark.timeout(600)
def test_bandit_learns_at_a_reduced_budget(tmp_path):
    """Clearly above chance (6 of 30; the expert pulls the best arm 18 times) after 800 VAE steps, with the shipped
    settings."""
    config = build("bandit", "cpu", ("dil_offline",), 2, SHORT)
    assert config.offline == type(config.offline)(vae_steps=40, online_steps=40)  # Defaults but the step counts.
    train_algorithm(config, "dil_offline", tmp_path / "dil_offline", progress=False)
    returns = [r["eval_return"] for r in load_metrics(tmp_path, "dil_offline") if "eval_return" in r]
    assert np.mean(returns) >= BOUND, returns


def _uniform_box_checks(action: np.ndarray) -> None:
    """``action`` [T, B, A] holds independent draws of U[-1, 1]: every value in the box; per dimension, the mean (0,
    variance 1/3 per draw) and the mean square (1/3, variance 1/5 - 1/9 = 4/45 per draw) within 4.5 standard errors;
    the pooled draws' ten equal-width bins each within 4.5 binomial standard errors of 1/10; the correlation of two
    dimensions, and of one dimension at consecutive steps, within 4.5 / sqrt(N) of 0."""
    T, B, A = action.shape
    n = T * B  # Draws per dimension.
    assert action.min() >= -1.0 and action.max() <= 1.0
    flat = action.reshape(n, A)
    np.testing.assert_array_less(np.abs(flat.mean(0)), 4.5 * np.sqrt(1 / 3 / n))
    np.testing.assert_array_less(np.abs((flat**2).mean(0) - 1 / 3), 4.5 * np.sqrt(4 / 45 / n))
    share = np.histogram(action, bins=10, range=(-1.0, 1.0))[0] / action.size
    np.testing.assert_array_less(np.abs(share - 0.1), 4.5 * np.sqrt(0.1 * 0.9 / action.size))
    across = np.corrcoef(flat, rowvar=False)[~np.eye(A, dtype=bool)]
    along = [np.corrcoef(action[:-1, :, k].ravel(), action[1:, :, k].ravel())[0, 1] for k in range(A)]
    np.testing.assert_array_less(np.abs(across), 4.5 / np.sqrt(n))
    np.testing.assert_array_less(np.abs(along), 4.5 / np.sqrt(n - B))


#: Lengths given to the four stored expert episodes, so a synthetic episode's mask names the episode it started from.
LENGTHS = (20, 13, 7, 1)


# Brax compiles slowly on a CPU (minutes per program), so the box-action envs run in the slow tier.
@pytest.mark.slow
@pytest.mark.timeout(900)
@pytest.mark.parametrize("env", ["half_cheetah", "ant_goal"])
def test_synthetic_episodes_on_box_action_envs(env):
    """On the Brax envs, 256 synthetic episodes of 20 steps: the exploration actions are uniform over the box
    [-1, 1]^n (``_uniform_box_checks``); each episode starts at the s_0 of one of the four stored expert episodes,
    drawn uniformly with replacement, and takes that episode's valid mask (the stored masks are set to distinct
    lengths first); and each step is p_psi's predicted mean change, s_{t+1} = s_t + p_psi(θ-tilde, s_t, a_t) *
    delta_scale, with the episode's recorded θ-tilde (recomputed here by one batched call of the decoder)."""
    from jaxdeconf.train import build_algorithm

    episodes = 256
    config = build(env, "cpu", ("dil_offline",), 1, {**TINY, "env.horizon": "20",
                                                        "offline.synthetic_episodes": str(episodes)})
    algo = build_algorithm(config, "dil_offline")
    T, stored = algo.env.horizon(algo.env_params), config.train.episodes_per_iter
    assert (T, stored) == (LENGTHS[0], len(LENGTHS))
    state = jax.jit(algo.init)(jax.random.key(0))
    state, _ = jax.jit(algo.collect_expert)(state, jax.random.key(1))
    data = state.expert_buffer.data
    assert int(state.expert_buffer.size) == stored
    lengths = jnp.zeros(data.valid.shape[1], jnp.int32).at[:stored].set(jnp.array(LENGTHS))
    data = data.replace(valid=jnp.arange(T)[:, None] < lengths[None, :])
    state = state.replace(expert_buffer=state.expert_buffer.replace(data=data))
    batch = jax.jit(algo.synthetic_rollout)(state, jax.random.key(2))

    _uniform_box_checks(np.asarray(batch.action))

    starts = np.asarray(data.obs.imitator[0])  # [capacity, d]
    match = (np.asarray(batch.obs[0])[:, None] == starts[None]).all(-1)  # [episodes, capacity]
    assert len({tuple(s) for s in starts[:stored]}) == stored  # Distinct starts, so a start names its episode.
    assert (match.sum(1) == 1).all() and not match[:, stored:].any()
    source = match.argmax(1)
    np.testing.assert_array_equal(np.asarray(batch.valid), np.asarray(data.valid)[:, source])
    counts = np.bincount(source, minlength=stored)
    np.testing.assert_array_less(np.abs(counts / episodes - 1 / stored),
                                 4.5 * np.sqrt((1 / stored) * (1 - 1 / stored) / episodes))

    _, decoder, _ = algo.networks
    latent = jnp.broadcast_to(batch.latent, (T, *batch.latent.shape))
    change = decoder.apply(state.encoder.params["decoder"], latent, batch.obs[:-1], batch.action)
    np.testing.assert_allclose(np.asarray(batch.obs[1:]), np.asarray(batch.obs[:-1] + change * algo.delta_scale),
                               rtol=1e-5, atol=1e-5)
