"""Losses as module-level pure functions returning ``(loss, metrics)``; loops over time are ``lax.scan``s, or for a
minGRU cell (``models.parallel_in_time``) one associative scan of its linear recurrence (``linear_scan``).

Arrays are time-major. A trajectory of T steps holds observations ``obs`` [T+1, B, d], actions [T, B(, A)] and a
``valid`` mask [T, B]; step t is valid while the episode has not terminated before t.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp

from jaxdeconf.models import (
    Decoder,
    Encoder,
    EvidenceEncoder,
    LatentPolicy,
    RecurrentPolicy,
    action_features,
    log_prob,
    parallel_in_time,
)

LOG_2PI = jnp.log(2.0 * jnp.pi)


def kl_diag_gaussian(
    mean_q: jax.Array, logvar_q: jax.Array, mean_p: jax.Array, logvar_p: jax.Array
) -> jax.Array:
    """KL(N(mean_q, exp(logvar_q)) || N(mean_p, exp(logvar_p))) summed over the last axis."""
    return 0.5 * jnp.sum(
        logvar_p - logvar_q + (jnp.exp(logvar_q) + (mean_q - mean_p) ** 2) * jnp.exp(-logvar_p) - 1.0, axis=-1
    )


def gaussian_nll(x: jax.Array, mean: jax.Array) -> jax.Array:
    """-log N(x; mean, I), summed over the last axis."""
    return jnp.sum(0.5 * (x - mean) ** 2 + 0.5 * LOG_2PI, axis=-1)


def bernoulli_nll(x: jax.Array, logits: jax.Array) -> jax.Array:
    """-log Bernoulli(x; sigmoid(logits)), summed over the last axis."""
    return jnp.sum(jnp.logaddexp(0.0, logits) - x * logits, axis=-1)


def obs_nll(likelihood: str, x: jax.Array, out: jax.Array) -> jax.Array:
    """Observation negative log-likelihood under the decoder's likelihood family."""
    if likelihood == "bernoulli":
        return bernoulli_nll(x, out)
    return gaussian_nll(x, out)


WEIGHTINGS = ("sum", "group_mean")


def grouped_nll(
    groups: tuple[Any, ...], weighting: str, cur: jax.Array, nxt: jax.Array, out: jax.Array,
    delta_scale: jax.Array | None,
) -> jax.Array:
    """The decoder's NLL of the next observation ``nxt`` [..., d] from its outputs ``out``, group by group.

    ``groups`` (``envs.ObsGroup``) split the last axis in order. A Gaussian group scores the standardised change
    (nxt - cur) / delta_scale (or ``nxt`` when ``delta_scale`` is None) under unit variance; a Bernoulli group scores
    whether each next value is positive, from logits. ``weighting="sum"`` adds every dimension's NLL; ``"group_mean"``
    averages within each group and adds the groups (the reference code's per-key MSE), so a one-dimensional cue
    weighs as much as a whole body.
    """
    total, start = jnp.zeros(out.shape[:-1], out.dtype), 0
    for group in groups:
        part = slice(start, start + group.size)
        start += group.size
        if group.likelihood == "bernoulli":
            nll = bernoulli_nll((nxt[..., part] > 0).astype(out.dtype), out[..., part])
        else:
            target = nxt[..., part] if delta_scale is None else (nxt - cur)[..., part] / delta_scale[part]
            nll = gaussian_nll(target, out[..., part])
        total = total + (nll / group.size if weighting == "group_mean" else nll)
    return total


def masked_mean(x: jax.Array, mask: jax.Array) -> jax.Array:
    """Mean of ``x`` over entries where ``mask`` holds (0 if none)."""
    mask = mask.astype(x.dtype)
    return jnp.sum(x * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def prev_actions(action_feats: jax.Array) -> jax.Array:
    """Shift action features [T, B, A] one step later, zeros at t = 0: the input a_{t-1} of step t."""
    return jnp.concatenate([jnp.zeros_like(action_feats[:1]), action_feats[:-1]], axis=0)


def transition_inputs(obs: jax.Array, delta_scale: jax.Array) -> jax.Array:
    """[s_t, (s_t - s_{t-1}) / delta_scale] along a sequence obs [T, B, d] -> [T, B, 2d], the change zero at t = 0."""
    prev = jnp.concatenate([obs[:1], obs[:-1]], axis=0)
    return jnp.concatenate([obs, (obs - prev) / delta_scale], axis=-1)


def linear_scan(a: jax.Array, b: jax.Array) -> jax.Array:
    """h_t = a_t * h_{t-1} + b_t along axis 0 from h_{-1} = 0, for a, b [T, ...]: one associative scan of the pairs
    (a_t, b_t) under (a1, b1) then (a2, b2) -> (a1 a2, a2 b1 + b2), the composition of the two affine maps."""

    def compose(first: tuple[jax.Array, jax.Array], then: tuple[jax.Array, jax.Array]) -> tuple[jax.Array, jax.Array]:
        return first[0] * then[0], then[0] * first[1] + then[1]

    _, h = jax.lax.associative_scan(compose, (a, b))
    return h


def cell_states(
    network: Encoder | RecurrentPolicy, params: Any, inputs: jax.Array, read: jax.Array | None = None
) -> jax.Array:
    """A minGRU network's cell states [T, B, hidden] over cell inputs [T, B, width], from a zero state, with every
    step's input projection computed at once. Where ``read`` [T, B] is false the step is skipped (a = 1, b = 0): the
    state is carried unchanged."""
    a, b = network.apply(params, inputs, method="coefficients")
    if read is not None:
        a, b = jnp.where(read[..., None], a, 1.0), jnp.where(read[..., None], b, 0.0)
    return linear_scan(a, b)


def encoder_scan(
    encoder: Encoder | EvidenceEncoder, params: Any, obs: jax.Array, prev_action: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """Posterior means and log-variances [T, B, L] of q_phi over a sequence (obs and prev_action [T, B, ...])."""
    inputs = encoder.apply(params, obs, prev_action, method="embed")
    if parallel_in_time(encoder):
        return encoder.apply(params, cell_states(encoder, params, inputs), method="readout")
    carry = jnp.zeros((*obs.shape[1:-1], encoder.hidden), jnp.float32)

    def body(carry: jax.Array, x: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        return encoder.apply(params, carry, x, method="recur")

    _, (mean, logvar) = jax.lax.scan(body, carry, inputs)
    return mean, logvar


def recurrent_policy_scan(policy: RecurrentPolicy, params: Any, obs: jax.Array, prev_action: jax.Array) -> jax.Array:
    """Head outputs [T, B, out] of a recurrent policy over a sequence."""
    inputs = policy.apply(params, obs, prev_action, method=RecurrentPolicy.embed)
    if parallel_in_time(policy):
        return policy.apply(params, cell_states(policy, params, inputs), method=RecurrentPolicy.readout)
    carry = jnp.zeros((*obs.shape[1:-1], policy.hidden), jnp.float32)

    def body(carry: jax.Array, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        return policy.apply(params, carry, x, method=RecurrentPolicy.recur)

    _, out = jax.lax.scan(body, carry, inputs)
    return out


def sequential_kl(mean: jax.Array, logvar: jax.Array) -> jax.Array:
    """KL(q_t || q_{t-1}) per step [T, B], with q_{-1} = N(0, I) (eq. 11's prior)."""
    prior_mean = jnp.concatenate([jnp.zeros_like(mean[:1]), mean[:-1]], axis=0)
    prior_logvar = jnp.concatenate([jnp.zeros_like(logvar[:1]), logvar[:-1]], axis=0)
    return kl_diag_gaussian(mean, logvar, prior_mean, prior_logvar)


def shift_ahead(x: jax.Array, k: int) -> jax.Array:
    """x[t + k] at position t along axis 0, zero-padded past the end."""
    if k == 0:
        return x
    return jnp.concatenate([x[k:], jnp.zeros((k, *x.shape[1:]), x.dtype)], axis=0)


def prediction_nll(
    decoder: Decoder,
    params: Any,
    z: jax.Array,
    obs: jax.Array,
    action_feats: jax.Array,
    valid: jax.Array,
    steps: int,
    likelihood: str,
    delta_scale: jax.Array | None = None,
    groups: tuple[Any, ...] | None = None,
    weighting: str = "sum",
) -> tuple[jax.Array, jax.Array]:
    """K-step teacher-forced prediction NLL summed over k, and its mask count, per step [T, B].

    From z_t the decoder predicts s_{t+k+1} given the true s_{t+k} and a_{t+k}, for k < K and t + k < T with step
    t + k valid. obs is [T+1, B, d]; z, action_feats and valid are [T, ...]. With ``delta_scale`` [d] (Gaussian
    likelihood only) the target is the standardised change (s_{t+k+1} - s_{t+k}) / delta_scale, so that small but
    informative changes (an engine's kick) are not drowned by a unit variance. With ``groups`` the NLL is
    ``grouped_nll``'s (each group's own family, weighted by ``weighting``); without, one ``likelihood`` for all.
    """
    T = valid.shape[0]
    total = jnp.zeros(valid.shape, jnp.float32)
    count = jnp.zeros(valid.shape, jnp.float32)
    for k in range(min(steps, T)):  # K is a small static constant; each k is one batched decoder call.
        cur = shift_ahead(obs[:T], k)
        nxt = shift_ahead(obs[1:], k)
        act = shift_ahead(action_feats, k)
        mask = shift_ahead(valid.astype(jnp.float32), k)
        out = decoder.apply(params, z, cur, act)
        if groups is None:
            target = nxt if delta_scale is None else (nxt - cur) / delta_scale
            nll = obs_nll(likelihood, target, out)
        else:
            nll = grouped_nll(groups, weighting, cur, nxt, out, delta_scale)
        total = total + nll * mask
        count = count + mask
    return total, count


def elbo_loss(
    params: dict[str, Any],
    obs: jax.Array,
    action_feats: jax.Array,
    valid: jax.Array,
    key: jax.Array,
    *,
    encoder: Encoder | EvidenceEncoder,
    decoder: Decoder,
    beta: float,
    steps: int,
    likelihood: str,
    delta_scale: jax.Array | None = None,
    encoder_delta_scale: jax.Array | None = None,
    groups: tuple[Any, ...] | None = None,
    weighting: str = "sum",
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Negative sequential ELBO (eq. 11) per valid step, on exploration data (``delta_scale``: see prediction_nll;
    with ``encoder_delta_scale`` the encoder reads ``transition_inputs`` standardised by it; ``groups`` and
    ``weighting``: see ``grouped_nll``).

    params: {"encoder": ..., "decoder": ...}; obs [T+1, B, d] (imitator view); action_feats [T, B, A]; valid [T, B].
    At step t the posterior q_t = q_phi(. | s_{0:t}, a_{0:t-1}) is sampled by reparameterisation; its prior is q_{t-1}
    (N(0, I) at t = 0); the decoder scores the next K observations from the sample.
    """
    T = valid.shape[0]
    enc_obs = obs[:T] if encoder_delta_scale is None else transition_inputs(obs[:T], encoder_delta_scale)
    mean, logvar = encoder_scan(encoder, params["encoder"], enc_obs, prev_actions(action_feats))
    z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape)
    nll, _ = prediction_nll(decoder, params["decoder"], z, obs, action_feats, valid, steps, likelihood, delta_scale,
                            groups, weighting)
    kl = sequential_kl(mean, logvar)
    loss = masked_mean(nll + beta * kl, valid)
    metrics = {"elbo_nll": masked_mean(nll, valid), "elbo_kl": masked_mean(kl, valid)}
    return loss, metrics


def trajectory_posterior(
    encoder: Encoder | EvidenceEncoder, params: Any, obs: jax.Array, prev_action: jax.Array, read: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """q_off's mean and log-variance [B, L] after reading a whole sequence (obs and prev_action [S, B, ...]).

    Step i is read where ``read`` [S, B] holds; elsewhere the recurrent state and the output are carried unchanged,
    so an episode that ended early is encoded exactly as if its sequence stopped at its last real step.
    """
    inputs = encoder.apply(params, obs, prev_action, method="embed")
    if parallel_in_time(encoder):
        mean, logvar = encoder.apply(params, cell_states(encoder, params, inputs, read)[-1], method="readout")
        seen = jnp.any(read, axis=0)[..., None]  # Nothing read: the zero output, as the scan below carries.
        return jnp.where(seen, mean, 0.0), jnp.where(seen, logvar, 0.0)
    batch, latent = obs.shape[1:-1], encoder.latent
    init = (jnp.zeros((*batch, encoder.hidden), jnp.float32), jnp.zeros((*batch, latent), jnp.float32),
            jnp.zeros((*batch, latent), jnp.float32))

    def body(carry: tuple, xs: tuple[jax.Array, jax.Array]) -> tuple[tuple, None]:
        x, keep = xs
        h, (mean, logvar) = encoder.apply(params, carry[0], x, method="recur")
        new = (h, mean, logvar)
        return jax.tree.map(lambda n, o: jnp.where(keep[:, None], n, o), new, carry), None

    (_, mean, logvar), _ = jax.lax.scan(body, init, (inputs, read))
    return mean, logvar


def episode_posterior(
    encoder: Encoder | EvidenceEncoder,
    params: Any,
    obs: jax.Array,
    feats: jax.Array,
    valid: jax.Array,
    encoder_delta_scale: jax.Array | None = None,
) -> tuple[jax.Array, jax.Array]:
    """q_off's mean and log-variance [B, L] of whole episodes: obs [T+1, B, d] (imitator view), action features
    [T, B, F], valid [T, B]. q_off reads s_0, then (a_{t-1}, s_t) where step t-1 was valid."""
    enc_obs = obs if encoder_delta_scale is None else transition_inputs(obs, encoder_delta_scale)
    enc_prev = jnp.concatenate([jnp.zeros_like(feats[:1]), feats], axis=0)
    read = jnp.concatenate([jnp.ones_like(valid[:1]), valid], axis=0)
    return trajectory_posterior(encoder, params, enc_obs, enc_prev, read)


def offline_elbo_loss(
    params: dict[str, Any],
    obs: jax.Array,
    action: jax.Array,
    valid: jax.Array,
    key: jax.Array,
    *,
    encoder: Encoder | EvidenceEncoder,
    decoder: Decoder,
    policy: LatentPolicy,
    space: Any,
    beta: float,
    likelihood: str,
    delta_scale: jax.Array | None = None,
    encoder_delta_scale: jax.Array | None = None,
    groups: tuple[Any, ...] | None = None,
    weighting: str = "sum",
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Negative offline ELBO (the paper's eq. 12) of whole expert episodes, per episode and divided by T.

    params: {"offline": q_off, "decoder": p_psi, "policy": pi_eta}; obs [T+1, B, d] (imitator view); action [T, B] or
    [T, B, A]; valid [T, B]. q_off reads the whole episode (s_0, then (a_{t-1}, s_t) up to the last real step) and
    gives one θ-tilde per episode, sampled by reparameterisation and shared by every step. Per episode the loss is
    sum over valid t of [-log p_psi(s_{t+1} | s_t, a_t, θ-tilde) - log pi_eta(a_t | s_t, θ-tilde)]
    + beta KL(q_off || N(0, I)); the batch mean of that is divided by the constant T, so that gradient sizes do not
    grow with the horizon. ``likelihood``, ``delta_scale``, ``groups`` and ``weighting`` score p_psi exactly as
    ``elbo_loss`` does (``prediction_nll``), so q_on's ELBO reads the frozen p_psi with the likelihood it was trained
    with; ``encoder_delta_scale``: as in ``elbo_loss``.
    """
    T = valid.shape[0]
    feats = action_features(space, action)
    mean, logvar = episode_posterior(encoder, params["offline"], obs, feats, valid, encoder_delta_scale)
    z = mean + jnp.exp(0.5 * logvar) * jax.random.normal(key, mean.shape)
    z_t = jnp.broadcast_to(z, (T, *z.shape))
    dynamics_nll, _ = prediction_nll(decoder, params["decoder"], z_t, obs, feats, valid, 1, likelihood, delta_scale,
                                     groups, weighting)
    policy_nll = -log_prob(space, policy.apply(params["policy"], obs[:T], z_t), action) * valid
    kl = kl_diag_gaussian(mean, logvar, jnp.zeros_like(mean), jnp.zeros_like(logvar))
    per_episode = jnp.sum(dynamics_nll + policy_nll, axis=0) + beta * kl
    metrics = {"vae_dynamics_nll": masked_mean(dynamics_nll, valid), "vae_policy_nll": masked_mean(policy_nll, valid),
               "vae_kl": jnp.mean(kl)}
    return jnp.mean(per_episode) / T, metrics


def nll_from_outputs(space: Any, out: jax.Array, action: jax.Array, valid: jax.Array) -> jax.Array:
    """Mean negative log-likelihood of actions under head outputs over valid steps (eq. 10's BC loss)."""
    return masked_mean(-log_prob(space, out, action), valid)


def soft_nll(space: Any, out: jax.Array, label: jax.Array, valid: jax.Array) -> jax.Array:
    """Mean over valid steps of the expected negative log-likelihood of the expert's action (DAgger's loss).

    ``label`` is the expert's action distribution [T, B, n] for a discrete space (the cross-entropy
    -sum_a label(a) log pi(a); with a one-hot label it is the NLL of that action), or its action [T, B, A] for a box.
    """
    if not space.discrete:
        return nll_from_outputs(space, out, label, valid)
    cross_entropy = -jnp.sum(label * jax.nn.log_softmax(out, axis=-1), axis=-1)
    return masked_mean(cross_entropy, valid)
