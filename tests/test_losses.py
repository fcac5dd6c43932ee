"""Loss values derived by hand, masking, and scan-versus-loop equivalence of the shipped functions."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxdeconf.envs.base import ActionSpace, Observation, ObsGroup

from jaxdeconf import losses
from jaxdeconf.actors import DeconfoundedActor
from jaxdeconf.models import (
    Decoder,
    Encoder,
    EvidenceEncoder,
    FilterEncoder,
    LatentPolicy,
    RecurrentPolicy,
    log_prob,
    make_encoder,
)

HALF_LOG_2PI = 0.5 * math.log(2 * math.pi)


def test_kl_hand_values():
    # KL(N(1, 1) || N(0, 1)) = 0.5 * (0 - 0 + (1 + 1) / 1 - 1) = 0.5 per dimension.
    kl = losses.kl_diag_gaussian(jnp.ones(3), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3))
    assert float(kl) == pytest.approx(1.5, abs=1e-6)
    # KL(N(0, e^-2) || N(0, 1)) = 0.5 * (0 - (-2) + e^-2 - 1) = 0.5 * (1 + e^-2).
    kl = losses.kl_diag_gaussian(jnp.zeros(1), jnp.full(1, -2.0), jnp.zeros(1), jnp.zeros(1))
    assert float(kl) == pytest.approx(0.5 * (1 + math.exp(-2)), abs=1e-6)
    # KL(N(2, 4) || N(1, 2)) = 0.5 * (log 2 - log 4 + (4 + 1) / 2 - 1) = 0.5 * (1.5 - log 2).
    log = lambda v: jnp.log(jnp.array([v]))  # noqa: E731
    kl = losses.kl_diag_gaussian(jnp.array([2.0]), log(4.0), jnp.array([1.0]), log(2.0))
    assert float(kl) == pytest.approx(0.5 * (1.5 - math.log(2)), abs=1e-6)


def test_observation_nll_hand_values():
    # -log N(1; 0, 1) = 0.5 + 0.5 log 2π; two dimensions add.
    assert float(losses.gaussian_nll(jnp.array([1.0, 0.0]), jnp.zeros(2))) == pytest.approx(0.5 + 2 * HALF_LOG_2PI)
    # Bernoulli: logit 0 gives p = 1/2, so -log p = log 2; logit log 3 gives p = 3/4, so s = 0 costs -log(1/4).
    assert float(losses.bernoulli_nll(jnp.array([1.0]), jnp.array([0.0]))) == pytest.approx(math.log(2), abs=1e-6)
    nll = losses.bernoulli_nll(jnp.array([0.0]), jnp.array([math.log(3)]))
    assert float(nll) == pytest.approx(math.log(4), abs=1e-6)


def test_action_log_prob_hand_values():
    # Categorical: logits (0, log 3) give P(a = 1) = 3/4.
    out = jnp.array([0.0, math.log(3.0)])
    assert float(log_prob(ActionSpace("discrete", 2), out, jnp.array(1))) == pytest.approx(math.log(0.75), abs=1e-6)
    # Diagonal Gaussian: mean 0, log-std log 2, action 2 -> -(0.5 * 1 + log 2 + 0.5 log 2π) per dimension.
    out = jnp.array([0.0, 0.0, math.log(2.0), math.log(2.0)])
    expected = 2 * -(0.5 + math.log(2.0) + HALF_LOG_2PI)
    assert float(log_prob(ActionSpace("box", 2), out, jnp.array([2.0, -2.0]))) == pytest.approx(expected, abs=1e-5)


def test_masked_bc_nll_ignores_invalid_steps():
    space = ActionSpace("discrete", 2)
    out = jnp.array([[[0.0, math.log(3.0)]], [[0.0, math.log(3.0)]], [[100.0, -100.0]]])  # [T=3, B=1, 2]
    action = jnp.array([[1], [0], [1]])
    valid = jnp.array([[True], [True], [False]])  # The last step (cost 200) is masked out.
    expected = (-math.log(0.75) - math.log(0.25)) / 2
    assert float(losses.nll_from_outputs(space, out, action, valid)) == pytest.approx(expected, abs=1e-5)


def test_sequential_kl_prior_is_previous_posterior():
    mean = jnp.array([[[1.0]], [[1.0]], [[3.0]]])  # [T=3, B=1, L=1]
    logvar = jnp.zeros_like(mean)
    kl = losses.sequential_kl(mean, logvar)[:, 0]
    # t=0 against N(0, 1): 0.5; t=1 same as t=0: 0; t=2 shifted by 2: 0.5 * 4 = 2.
    np.testing.assert_allclose(kl, [0.5, 0.0, 2.0], atol=1e-6)


def _tiny_models(enc_obs_size=1, kind="gru"):
    encoder = make_encoder(kind, 8, 4, 6, 3)
    decoder = Decoder(8, 4, 1)
    k1, k2 = jax.random.split(jax.random.key(0))
    obs, act, z = jnp.zeros((1, 1)), jnp.zeros((1, 5)), jnp.zeros((1, 3))
    params = {"encoder": encoder.init(k1, jnp.zeros((1, enc_obs_size)), act), "decoder": decoder.init(k2, z, obs, act)}
    return encoder, decoder, params


def _batch(T=7, B=3, seed=1):
    k1, k2 = jax.random.split(jax.random.key(seed))
    obs = jax.random.bernoulli(k1, 0.5, (T + 1, B, 1)).astype(jnp.float32)
    action = jax.random.randint(k2, (T, B), 0, 5)
    valid = jnp.arange(T)[:, None] < jnp.array([T, T - 2, 3])[None, :]
    return obs, jax.nn.one_hot(action, 5), valid


def _np_kl(mean_q, logvar_q, mean_p, logvar_p):
    """KL(N(mean_q, e^logvar_q) || N(mean_p, e^logvar_p)) of diagonal Gaussians, summed over the last axis."""
    return 0.5 * np.sum(logvar_p - logvar_q + (np.exp(logvar_q) + (mean_q - mean_p) ** 2) / np.exp(logvar_p) - 1.0,
                        axis=-1)


def _np_gaussian_nll(x, mean):
    """-log N(x; mean, I), summed over the last axis."""
    return np.sum(0.5 * (x - mean) ** 2 + 0.5 * np.log(2 * np.pi), axis=-1)


def _np_bernoulli_nll(x, logits):
    """-log Bernoulli(x; sigmoid(logits)), summed over the last axis."""
    return np.sum(np.logaddexp(0.0, logits) - x * logits, axis=-1)


def _posteriors(encoder, params, enc_obs, feats):
    """q_phi's (mean, logvar) [T, B, L] after reading s_0..s_t and a_0..a_{t-1}, one network step at a time."""
    T, B = feats.shape[:2]
    carry, means, logvars = jnp.zeros((B, encoder.hidden)), [], []
    for t in range(T):
        prev_action = feats[t - 1] if t > 0 else jnp.zeros_like(feats[0])
        x = encoder.apply(params, enc_obs[t], prev_action, method="embed")
        carry, (mean, logvar) = encoder.apply(params, carry, x, method="recur")
        means.append(mean)
        logvars.append(logvar)
    return np.asarray(jnp.stack(means), np.float64), np.asarray(jnp.stack(logvars), np.float64)


def _np_sequential_elbo(mean, logvar, eps, decode, obs, valid, beta, steps, step_nll):
    """Eq. 11 in numpy, float64, as a loss per valid step: at each valid t, z_t = mean_t + e^(logvar_t / 2) eps_t,
    beta KL(q_t || q_{t-1}) (q_{-1} = N(0, I)) plus the decoder's NLL of the next ``steps`` observations
    s_{t+k+1} given (z_t, s_{t+k}, a_{t+k}) over the valid t + k; returns (loss, mean NLL, mean KL) over the valid
    t. ``decode(z, k)`` is the decoder's output [B, d] for step k; ``step_nll(k, out)`` its NLL [B]."""
    T = valid.shape[0]
    valid = np.asarray(valid, np.float64)
    total = nll_total = kl_total = 0.0
    for t in range(T):
        prior = (mean[t - 1], logvar[t - 1]) if t > 0 else (np.zeros_like(mean[0]), np.zeros_like(logvar[0]))
        kl = _np_kl(mean[t], logvar[t], *prior)
        z = mean[t] + np.exp(0.5 * logvar[t]) * eps[t]
        nll = sum(step_nll(t + k, decode(z, t + k)) * valid[t + k] for k in range(steps) if t + k < T)
        total += np.sum((nll + beta * kl) * valid[t])
        nll_total += np.sum(nll * valid[t])
        kl_total += np.sum(kl * valid[t])
    count = valid.sum()
    return total / count, nll_total / count, kl_total / count


@pytest.mark.timeout(120)
@pytest.mark.parametrize(("steps", "likelihood", "deltas", "kind"),
                         [(1, "bernoulli", False, "gru"), (3, "bernoulli", False, "gru"),
                          (3, "gaussian", False, "gru"), (3, "gaussian", True, "gru"),
                          (3, "gaussian", True, "evidence"), (3, "gaussian", True, "filter")])
def test_elbo_loss_equals_a_numpy_sequential_elbo(steps, likelihood, deltas, kind):
    """``elbo_loss`` against eq. 11 written out in numpy (KL, likelihoods, the prior chain, the reparameterised
    sample, masking and the k-step decoder sum all independent of ``losses``); the networks' per-step outputs are the
    only shared part."""
    encoder, decoder, params = _tiny_models(enc_obs_size=2 if deltas else 1, kind=kind)
    obs, feats, valid = _batch()
    T, B = valid.shape
    key = jax.random.key(3)
    # The Gaussian case scores standardised one-step changes (the MDPs' decoder target); with ``deltas`` the encoder
    # also reads them.
    scale = jnp.linspace(0.1, 2.0, obs.shape[-1]) if likelihood == "gaussian" else None
    loss, metrics = losses.elbo_loss(params, obs, feats, valid, key, encoder=encoder, decoder=decoder, beta=0.3,
                                     steps=steps, likelihood=likelihood, delta_scale=scale,
                                     encoder_delta_scale=scale if deltas else None)

    o = np.asarray(obs, np.float64)
    enc_obs = obs[:T]
    if deltas:  # [s_t, (s_t - s_{t-1}) / scale], the change zero at t = 0.
        prev = np.concatenate([o[:1], o[:T - 1]])
        enc_obs = jnp.asarray(np.concatenate([o[:T], (o[:T] - prev) / np.asarray(scale)], axis=-1), jnp.float32)
    mean, logvar = _posteriors(encoder, params["encoder"], enc_obs, feats)
    eps = np.asarray(jax.random.normal(key, (T, B, 3)), np.float64)

    def decode(z, j):
        return np.asarray(decoder.apply(params["decoder"], jnp.asarray(z, jnp.float32), obs[j], feats[j]), np.float64)

    def step_nll(j, out):
        if likelihood == "gaussian":
            return _np_gaussian_nll((o[j + 1] - o[j]) / np.asarray(scale), out)
        return _np_bernoulli_nll(o[j + 1], out)

    expected, nll, kl = _np_sequential_elbo(mean, logvar, eps, decode, obs, valid, 0.3, steps, step_nll)
    assert float(loss) == pytest.approx(expected, rel=1e-5)
    assert float(metrics["elbo_nll"]) == pytest.approx(nll, rel=1e-5)
    assert float(metrics["elbo_kl"]) == pytest.approx(kl, rel=1e-5)
    assert kl > 0.01 and nll > 0.1  # Both terms weigh in the check.


def test_recurrent_policy_scan_matches_plain_loop():
    policy = RecurrentPolicy(8, 4, 6, 5)
    obs, feats, _ = _batch()
    params = policy.init(jax.random.key(0), obs[0], feats[0])
    prev = losses.prev_actions(feats)
    out = losses.recurrent_policy_scan(policy, params, obs[:-1], prev)
    carry = jnp.zeros((obs.shape[1], 6))
    for t in range(prev.shape[0]):
        x = policy.apply(params, obs[t], prev[t], method=RecurrentPolicy.embed)
        carry, o = policy.apply(params, carry, x, method=RecurrentPolicy.recur)
        np.testing.assert_allclose(out[t], o, rtol=1e-5, atol=1e-6)


def test_prediction_mask_counts_steps_left():
    _, decoder, params = _tiny_models()
    obs, feats, valid = _batch(T=5, B=1)
    valid = jnp.ones_like(valid)
    _, count = losses.prediction_nll(decoder, params["decoder"], jnp.zeros((5, 1, 3)), obs, feats, valid, 3,
                                     "bernoulli")
    np.testing.assert_array_equal(count[:, 0], [3, 3, 3, 2, 1])


@pytest.mark.parametrize(("deltas", "kind"), [(False, "gru"), (True, "gru"), (True, "evidence"), (True, "filter")])
def test_deconfounded_actor_matches_teacher_forced_posterior(deltas, kind):
    """Algorithm 2 step by step (what acts online) gives the policy outputs that training computes with scans."""
    d, B, T = 3, 4, 6
    encoder = make_encoder(kind, 8, 4, 6, 2)
    policy = LatentPolicy(8, 5)
    scale = jnp.array([0.5, 1.0, 2.0]) if deltas else None
    k1, k2, k3, k4 = jax.random.split(jax.random.key(7), 4)
    obs = jax.random.normal(k1, (T, B, d))
    prev = losses.prev_actions(jax.nn.one_hot(jax.random.randint(k2, (T, B), 0, 5), 5))
    enc_obs = losses.transition_inputs(obs, scale) if deltas else obs
    params = {"encoder": encoder.init(k3, enc_obs[0], prev[0]), "policy": policy.init(k4, obs[0], jnp.zeros((B, 2)))}
    mean, _ = losses.encoder_scan(encoder, params["encoder"], enc_obs, prev)
    expected = policy.apply(params["policy"], obs, mean)
    actor = DeconfoundedActor(encoder, policy, scale)
    carry = actor.init_carry(B)
    for t in range(T):
        carry, out = actor(params, carry, Observation(expert=obs[t], imitator=obs[t], oracle=obs[t]), prev[t])
        np.testing.assert_allclose(out, expected[t], rtol=1e-5, atol=1e-5)


def test_early_fusion_policy_is_the_markov_oracle_network_on_obs_and_theta_hat():
    """``policy_fusion=early`` reads θ-hat beside the observation at the input: with the same parameters it is the
    late network with an empty latent applied to [obs, θ-hat]; "late" is not."""
    obs, z = jax.random.normal(jax.random.key(0), (6, 3)), jax.random.normal(jax.random.key(1), (6, 2))
    early, markov = LatentPolicy(8, 4, "early"), LatentPolicy(8, 4)
    params = early.init(jax.random.key(2), obs, z)
    joined, empty = jnp.concatenate([obs, z], axis=-1), jnp.zeros((6, 0))
    np.testing.assert_allclose(early.apply(params, obs, z), markov.apply(params, joined, empty), rtol=1e-6)
    late_params = LatentPolicy(8, 4).init(jax.random.key(2), obs, z)
    assert late_params["params"]["MLP_0"]["Dense_0"]["kernel"].shape[0] == 3  # Late: the first layer sees obs only.
    assert params["params"]["MLP_0"]["Dense_0"]["kernel"].shape[0] == 5


def test_evidence_encoder_posterior_is_the_product_of_its_factors():
    """Hand-derived: N(0, 1) x N(2, 1/1) x N(-1, 1/2) has precision 4 and mean (0 + 2 - 2) / 4 = 0;
    N(0, 1) x N(1, 1/3) x (a zero-precision factor) has precision 4 and mean 3 / 4."""
    encoder = EvidenceEncoder(8, 4, 2)
    params = encoder.init(jax.random.key(0), jnp.zeros((1, 3)), jnp.zeros((1, 5)))
    factor = lambda m, p: jnp.array([[p[0] * m[0], p[1] * m[1], p[0], p[1]]])  # noqa: E731
    carry = jnp.zeros((1, encoder.hidden))
    carry, _ = encoder.apply(params, carry, factor([2.0, 1.0], [1.0, 3.0]), method="recur")
    _, (mean, logvar) = encoder.apply(params, carry, factor([-1.0, 5.0], [2.0, 0.0]), method="recur")
    np.testing.assert_allclose(mean[0], [0.0, 0.75], atol=1e-6)
    np.testing.assert_allclose(logvar[0], [-np.log(4.0), -np.log(4.0)], atol=1e-6)
    # The network's factors have positive precision, so the posterior variance never grows: no forgetting.
    obs = jax.random.normal(jax.random.key(1), (20, 4, 3))
    prev = jax.nn.one_hot(jax.random.randint(jax.random.key(2), (20, 4), 0, 5), 5)
    _, logvar = losses.encoder_scan(encoder, params, obs, prev)
    assert np.all(np.diff(np.asarray(logvar), axis=0) < 0)


def test_filter_encoder_adds_natural_parameter_sites_read_off_the_belief():
    """With the site layer's kernel zeroed, every step adds the bias's site (w, softplus(r)): after two steps from
    N(0, 1) the precision is 1 + 2 softplus(r) and the mean 2 w / (1 + 2 softplus(r)). With the network's own weights
    the site depends on the belief (the same step from two carries adds different sites), the precision never falls,
    and the mean can move while it does (w is not tied to p)."""
    encoder = FilterEncoder(8, 4, 2)
    params = encoder.init(jax.random.key(0), jnp.zeros((1, 3)), jnp.zeros((1, 5)))
    bias = jnp.array([0.5, -1.0, 0.0, math.log(math.e - 1.0)])  # w = (0.5, -1), p = (log 2, 1).
    out = {"kernel": jnp.zeros_like(params["params"]["out"]["kernel"]), "bias": bias}
    fixed = {"params": {**params["params"], "out": out}}
    x = jax.random.normal(jax.random.key(1), (1, 8))
    carry, _ = encoder.apply(fixed, jnp.zeros((1, 4)), x, method="recur")
    _, (mean, logvar) = encoder.apply(fixed, carry, x, method="recur")
    precision = 1.0 + 2.0 * np.array([math.log(2.0), 1.0])
    np.testing.assert_allclose(mean[0], np.array([1.0, -2.0]) / precision, rtol=1e-6)
    np.testing.assert_allclose(logvar[0], -np.log(precision), rtol=1e-6)
    step = lambda c: encoder.apply(params, c, x, method="recur")[0] - c  # noqa: E731
    assert float(jnp.max(jnp.abs(step(jnp.zeros((1, 4))) - step(jnp.array([[3.0, -3.0, 1.0, 1.0]]))))) > 1e-3
    obs = jax.random.normal(jax.random.key(1), (20, 4, 3))
    prev = jax.nn.one_hot(jax.random.randint(jax.random.key(2), (20, 4), 0, 5), 5)
    mean, logvar = losses.encoder_scan(encoder, params, obs, prev)
    assert np.all(np.diff(np.asarray(logvar), axis=0) < 0)


# --- Observation groups: each group its own likelihood, weighted by sum or per-group mean. ---

GROUPS = (ObsGroup("body", 2), ObsGroup("cue", 1, "bernoulli"))


@pytest.mark.parametrize("weighting", ["sum", "group_mean"])
def test_grouped_nll_hand_values(weighting):
    # Body: standardised changes (1 - 0) / 1 = 1 and (0 - 0) / 2 = 0 under N(0, 1): 0.5 + 2 * 0.5 log 2π.
    # Cue: the next value +1 is positive, logit log 3 gives p = 3/4: -log(3/4). A negative next cue (a standardised
    # -1 at -0.3) costs -log(1/4).
    cur, scale, out = jnp.array([0.0, 0.0, -1.0]), jnp.array([1.0, 2.0, 1.0]), jnp.array([0.0, 0.0, math.log(3)])
    body = 0.5 + 2 * HALF_LOG_2PI
    for next_cue, cue in ((1.0, -math.log(0.75)), (-0.3, math.log(4.0))):
        nxt = jnp.array([1.0, 0.0, next_cue])
        nll = losses.grouped_nll(GROUPS, weighting, cur, nxt, out, scale)
        expected = body + cue if weighting == "sum" else body / 2 + cue
        assert float(nll) == pytest.approx(expected, abs=1e-5)


def test_one_group_is_the_single_likelihood():
    # A one-group env (bandit, LunarLander) scores exactly as without groups, under either weighting's "sum".
    cur, nxt, out = jnp.array([[0.0, 1.0]]), jnp.array([[1.0, 0.0]]), jnp.array([[0.3, -2.0]])
    one = (ObsGroup("all", 2, "bernoulli"),)
    assert float(losses.grouped_nll(one, "sum", cur, nxt, out, None)[0]) == float(
        losses.obs_nll("bernoulli", nxt, out)[0])
    scale = jnp.array([0.5, 2.0])
    one = (ObsGroup("all", 2),)
    assert float(losses.grouped_nll(one, "sum", cur, nxt, out, scale)[0]) == pytest.approx(
        float(losses.gaussian_nll((nxt - cur) / scale, out)[0]), rel=1e-6)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("weighting", ["sum", "group_mean"])
def test_grouped_elbo_equals_a_numpy_sequential_elbo(weighting):
    """The grouped ELBO against the numpy eq. 11: the body's standardised changes under N(0, 1), the cue's sign under
    a Bernoulli, added (``sum``) or each group averaged over its dimensions first (``group_mean``)."""
    encoder, decoder = Encoder(8, 4, 6, 3), Decoder(8, 4, 3)
    k1, k2, k3, k4 = jax.random.split(jax.random.key(5), 4)
    T, B, steps = 6, 2, 3
    body = jax.random.normal(k3, (T + 1, B, 2))
    cue = jnp.where(jax.random.bernoulli(k4, 0.5, (T + 1, B, 1)), 1.0, -1.0)
    obs = jnp.concatenate([body, cue], axis=-1)
    feats = jax.nn.one_hot(jnp.arange(T * B).reshape(T, B) % 5, 5)
    valid = jnp.arange(T)[:, None] < jnp.array([T, 4])[None, :]
    params = {"encoder": encoder.init(k1, jnp.zeros((1, 3)), jnp.zeros((1, 5))),
              "decoder": decoder.init(k2, jnp.zeros((1, 3)), jnp.zeros((1, 3)), jnp.zeros((1, 5)))}
    scale = jnp.array([0.5, 2.0, 1.0])
    key = jax.random.key(6)
    loss, _ = losses.elbo_loss(params, obs, feats, valid, key, encoder=encoder, decoder=decoder, beta=0.3,
                               steps=steps, likelihood="gaussian", delta_scale=scale, groups=GROUPS,
                               weighting=weighting)
    o = np.asarray(obs, np.float64)
    mean, logvar = _posteriors(encoder, params["encoder"], obs[:T], feats)
    eps = np.asarray(jax.random.normal(key, (T, B, 3)), np.float64)

    def decode(z, j):
        return np.asarray(decoder.apply(params["decoder"], jnp.asarray(z, jnp.float32), obs[j], feats[j]), np.float64)

    def step_nll(j, out):
        body_nll = _np_gaussian_nll((o[j + 1, :, :2] - o[j, :, :2]) / np.array([0.5, 2.0]), out[:, :2])
        cue_nll = _np_bernoulli_nll((o[j + 1, :, 2:] > 0).astype(np.float64), out[:, 2:])
        return body_nll / 2 + cue_nll if weighting == "group_mean" else body_nll + cue_nll

    expected, _, _ = _np_sequential_elbo(mean, logvar, eps, decode, obs, valid, 0.3, steps, step_nll)
    assert float(loss) == pytest.approx(expected, rel=1e-5)
