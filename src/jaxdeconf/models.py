"""Flax networks: inference model q_phi, decoder p_psi, latent-conditional and recurrent policies, action heads.

Every network is split into per-timestep methods (``embed`` works on any leading shape, ``recur`` does one recurrent
step) so that the loops over time live in ``losses.py`` as ``lax.scan``s that tests can compare against plain loops.
The minGRU cell's recurrence is linear in its state, so its networks also give the coefficients of h_t = a_t h_{t-1}
+ b_t for a whole sequence (``coefficients``) and read a whole sequence of states out (``readout``): ``losses.py``
runs such a sequence as one associative scan.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxdeconf.envs.base import ActionSpace

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0


def orthonormal_columns(z: jax.Array) -> jax.Array:
    """Q [r, c] of z = QR with diag(R) > 0 (r >= c), by Gram–Schmidt applied twice per column ("twice is enough")."""
    idx = jnp.arange(z.shape[1])

    def column(j: jax.Array, q: jax.Array) -> jax.Array:  # Columns >= j of q are still zero.
        v = z[:, j]
        v = v - q @ (q.T @ v)
        v = v - q @ (q.T @ v)
        return jnp.where(idx[None, :] == j, (v / jnp.sqrt(jnp.sum(v * v)))[:, None], q)

    return jax.lax.fori_loop(0, z.shape[1], column, jnp.zeros_like(z))


def orthogonal(scale: float = 1.0) -> nn.initializers.Initializer:
    """flax's ``nn.initializers.orthogonal`` (columns on the last axis; the same normal draw, the same matrix up to
    rounding) without LAPACK: jaxlib 0.10.2's batched CPU QR splits the seed batch over XLA's thread pool and was seen
    to deadlock inside the seed-vmapped programs with every thread idle. Every GRU of the imitators uses this."""

    def init(key: jax.Array, shape: tuple[int, ...], dtype: jnp.dtype = jnp.float32) -> jax.Array:
        rows, cols = math.prod(shape) // shape[-1], shape[-1]
        q = orthonormal_columns(jax.random.normal(key, (max(rows, cols), min(rows, cols)), dtype))
        return (scale * (q.T if rows < cols else q)).reshape(shape).astype(dtype)

    return init


def gru_cell(hidden: int) -> nn.GRUCell:
    """flax's GRU cell with its orthogonal recurrent initialiser replaced by ``orthogonal`` (no LAPACK)."""
    return nn.GRUCell(hidden, recurrent_kernel_init=orthogonal())


class MinGRUCell(nn.Module):
    """minGRU (Feng et al. 2024, "Were RNNs all we needed?"): h_t = (1 - z_t) h_{t-1} + z_t h~_t with
    z_t = sigmoid(Dense(x_t)) and h~_t = Dense(x_t), both of the input alone. The recurrence h_t = a_t h_{t-1} + b_t
    (a = 1 - z, b = z h~) is linear in h, so a whole sequence is one associative scan (``losses.linear_scan``)."""

    features: int

    def setup(self) -> None:
        """The gate's and the candidate's projections of the input; no recurrent kernel."""
        self.gate = nn.Dense(self.features)
        self.candidate = nn.Dense(self.features)

    def coefficients(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(a, b) [..., features] of h_t = a h_{t-1} + b for inputs x [..., E] of any leading shape."""
        z = nn.sigmoid(self.gate(x))
        return 1.0 - z, z * self.candidate(x)

    def __call__(self, carry: jax.Array, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """One step in flax's cell convention: carry [B, features], x [B, E] -> (h_t, h_t)."""
        a, b = self.coefficients(x)
        h = a * carry + b
        return h, h


def recurrent_cell(kind: str, hidden: int) -> nn.GRUCell | MinGRUCell:
    """The cell ``model.cell`` names: "gru" (``gru_cell``) or "mingru" (``MinGRUCell``)."""
    return gru_cell(hidden) if kind == "gru" else MinGRUCell(hidden)


def parallel_in_time(network: nn.Module) -> bool:
    """Whether a recurrent network's sequences run as one associative scan (its cell is a minGRU)."""
    return getattr(network, "cell_kind", "gru") == "mingru"


class MLP(nn.Module):
    """Blocks of Linear -> LayerNorm -> ELU, as in the reference code."""

    features: Sequence[int]

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """Apply the blocks."""
        for size in self.features:
            x = nn.elu(nn.LayerNorm()(nn.Dense(size)(x)))
        return x


class Interaction(nn.Module):
    """Features of two embeddings x [..., X] and a [..., E] with their product: [x, a, Dense_E(x) * a].

    The evidence in a transition is an interaction (which action led to which observation; which latent changes what
    an action does). With a plain concatenation gradient descent found that interaction slowly and erratically (on
    the bandit the ELBO sat on plateaus for 600 to over 1500 steps, depending on the seed); the multiplicative term
    lets the next layer read it directly (near the Bayes-optimal ELBO within 400 to 500 steps on both seeds tried).
    """

    @nn.compact
    def __call__(self, x: jax.Array, a: jax.Array) -> jax.Array:
        """[..., X + 2E] features."""
        return jnp.concatenate([x, a, nn.Dense(a.shape[-1])(x) * a], axis=-1)


def action_features(space: ActionSpace, action: jax.Array) -> jax.Array:
    """Vector encoding of an action: one-hot for discrete spaces, the action itself for boxes."""
    if space.discrete:
        return jax.nn.one_hot(action, space.n, dtype=jnp.float32)
    return action.astype(jnp.float32)


def head_size(space: ActionSpace) -> int:
    """Size of a policy head's output: logits, or mean and log-std."""
    return space.n if space.discrete else 2 * space.n


def log_prob(space: ActionSpace, out: jax.Array, action: jax.Array) -> jax.Array:
    """Log-likelihood of ``action`` under a head output ``out`` (leading axes kept)."""
    if space.discrete:
        logp = jax.nn.log_softmax(out, axis=-1)
        return jnp.take_along_axis(logp, action[..., None].astype(jnp.int32), axis=-1)[..., 0]
    mean, log_std = jnp.split(out, 2, axis=-1)
    log_std = jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)
    z = (action - mean) * jnp.exp(-log_std)
    return jnp.sum(-0.5 * z**2 - log_std - 0.5 * jnp.log(2 * jnp.pi), axis=-1)


def entropy(space: ActionSpace, out: jax.Array) -> jax.Array:
    """Entropy of the action distribution of a head output (leading axes kept)."""
    if space.discrete:
        logp = jax.nn.log_softmax(out, axis=-1)
        return -jnp.sum(jnp.exp(logp) * logp, axis=-1)
    _, log_std = jnp.split(out, 2, axis=-1)
    log_std = jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)
    return jnp.sum(log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e), axis=-1)


def sample(space: ActionSpace, key: jax.Array, out: jax.Array) -> jax.Array:
    """Draw an action from a head output."""
    if space.discrete:
        return jax.random.categorical(key, out, axis=-1).astype(jnp.int32)
    mean, log_std = jnp.split(out, 2, axis=-1)
    log_std = jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)
    return mean + jnp.exp(log_std) * jax.random.normal(key, mean.shape)


class StepInput(nn.Module):
    """The per-step input block the recurrent networks share: MLP(obs) and an embedding of the previous action,
    fused through ``Interaction``. Subclasses call ``super().setup()`` and add their recurrence."""

    width: int
    action_embed: int

    def setup(self) -> None:
        """The fused block's sub-networks."""
        self.obs_net = MLP((self.width, self.width))
        self.action_net = nn.Dense(self.action_embed)
        self.interact = Interaction()
        self.fuse = MLP((self.width,))

    def fused(self, obs: jax.Array, prev_action: jax.Array) -> jax.Array:
        """[..., width] for any leading shape: the observation and the action that led to it, fused."""
        return self.fuse(self.interact(self.obs_net(obs), self.action_net(prev_action)))


class Encoder(StepInput):
    """q_phi(theta-hat | tau_{:t}): MLP(obs) ⊕ embedding(previous action) -> GRU (or minGRU) -> (mean, log-variance).
    """

    hidden: int
    latent: int
    cell_kind: str = "gru"  # ``model.cell``: "gru" or "mingru" (``recurrent_cell``).

    def setup(self) -> None:
        """Sub-networks shared by ``embed`` and ``recur``."""
        super().setup()
        self.cell = recurrent_cell(self.cell_kind, self.hidden)
        self.out = nn.Dense(2 * self.latent)

    def embed(self, obs: jax.Array, prev_action: jax.Array) -> jax.Array:
        """Cell inputs [..., width] for any leading shape."""
        return self.fused(obs, prev_action)

    def coefficients(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """minGRU only: (a, b) [..., hidden] of h_t = a h_{t-1} + b for cell inputs x [..., width]."""
        return self.cell.coefficients(x)

    def readout(self, h: jax.Array) -> tuple[jax.Array, jax.Array]:
        """(mean, logvar) [..., latent] of cell states h [..., hidden] of any leading shape."""
        mean, logvar = jnp.split(self.out(h), 2, axis=-1)
        return mean, logvar

    def recur(self, carry: jax.Array, x: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        """One cell step: carry [B, hidden], x [B, E] -> new carry, (mean, logvar) each [B, latent]."""
        carry, h = self.cell(carry, x)
        return carry, self.readout(h)

    def __call__(self, obs: jax.Array, prev_action: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        """One step from a zero carry (used for initialisation)."""
        carry = jnp.zeros((*obs.shape[:-1], self.hidden), jnp.float32)
        return self.recur(carry, self.embed(obs, prev_action))


class EvidenceEncoder(StepInput):
    """q_phi as a product of Gaussian factors, one per step, with the prior N(0, I) (PEARL's encoder, Rakelly et al.
    2019): each (s_t, a_{t-1}) — with ``dil.encoder_deltas`` also the change s_t - s_{t-1}, so a whole transition —
    gives a factor of mean m_t and precision p_t, and the posterior after t steps has precision 1 + sum p and mean
    sum(p m) / (1 + sum p).

    For a θ fixed per episode and transitions independent given θ (the confounded envs' structure) the exact
    posterior has this form, and evidence once gathered is never forgotten, which a GRU trained on short exploration
    episodes does not guarantee on the expert's longer ones. The carry holds the running sums [B, 2 * latent].
    """

    latent: int

    @property
    def hidden(self) -> int:
        """Carry size: the running sums of p m and p."""
        return 2 * self.latent

    def setup(self) -> None:
        """Sub-networks: the same fused block as the GRU encoder's, then the factor's parameters."""
        super().setup()
        self.out = nn.Dense(2 * self.latent)

    def embed(self, obs: jax.Array, prev_action: jax.Array) -> jax.Array:
        """One factor per step [..., 2 * latent]: (p m, p) with p = softplus(.) > 0."""
        mean, raw = jnp.split(self.out(self.fused(obs, prev_action)), 2, axis=-1)
        precision = nn.softplus(raw)
        return jnp.concatenate([precision * mean, precision], axis=-1)

    def belief(self, carry: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Posterior (mean, log-variance) [B, L] from the running sums [B, 2L] and the prior N(0, I)."""
        weighted, precision = jnp.split(carry, 2, axis=-1)
        precision = 1.0 + precision
        return weighted / precision, -jnp.log(precision)

    def recur(self, carry: jax.Array, x: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        """Add this step's factor: carry [B, 2L], x [B, 2L] -> new carry, (mean, logvar) each [B, L]."""
        carry = carry + x
        return carry, self.belief(carry)

    def __call__(self, obs: jax.Array, prev_action: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        """One step from the prior (used for initialisation)."""
        carry = jnp.zeros((*obs.shape[:-1], self.hidden), jnp.float32)
        return self.recur(carry, self.embed(obs, prev_action))


class FilterEncoder(EvidenceEncoder):
    """q_phi as assumed-density filtering: the evidence encoder's running sums, with each step's factor read off the
    step *and the belief so far* (its mean and log-variance). The factor is given in natural parameters, an increment
    w of sum(p m) and p = softplus(.) >= 0 of sum(p), so the posterior's precision still never falls (no forgetting),
    while its mean can move without a gain in precision.

    A likelihood that is not Gaussian in θ makes this the right family: the half_cheetah's ±1 cue says only whether
    the target lies above or below the speed, a step in θ, whose Gaussian moment-matched update (the ADF site) depends
    on where the current belief lies relative to that speed. A factor of the step alone cannot express it."""

    def setup(self) -> None:
        """Sub-networks: the fused block, then the factor's MLP over [step, belief]."""
        super().setup()
        self.site = MLP((self.width,))

    def embed(self, obs: jax.Array, prev_action: jax.Array) -> jax.Array:
        """The step's fused features [..., width]; the factor needs the belief, so it is formed in ``recur``."""
        return self.fused(obs, prev_action)

    def recur(self, carry: jax.Array, x: jax.Array) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
        """Add the factor of step x [B, width] given the belief in carry [B, 2L] -> new carry, (mean, logvar)."""
        mean, logvar = self.belief(carry)
        w, raw = jnp.split(self.out(self.site(jnp.concatenate([x, mean, logvar], axis=-1))), 2, axis=-1)
        carry = carry + jnp.concatenate([w, nn.softplus(raw)], axis=-1)
        return carry, self.belief(carry)


def make_encoder(
    kind: str, width: int, action_embed: int, gru: int, latent: int, cell: str = "gru"
) -> Encoder | EvidenceEncoder:
    """q_phi by ``dil.encoder``'s name: "gru" (hidden size ``gru``, its cell ``cell``: "gru" or "mingru"),
    "evidence" or "filter"."""
    if kind == "gru":
        return Encoder(width, action_embed, gru, latent, cell)
    return {"evidence": EvidenceEncoder, "filter": FilterEncoder}[kind](width, action_embed, latent)


class Decoder(nn.Module):
    """p_psi(s_{t+k+1} | z_t, s_{t+k}, a_{t+k}): the next observation's mean or logits. z is read with the
    observation and the action through one MLP (the reference code's), so z may change what an action does."""

    width: int
    action_embed: int
    obs_size: int

    @nn.compact
    def __call__(self, z: jax.Array, obs: jax.Array, action: jax.Array) -> jax.Array:
        """Predict the next observation's parameters from the latent, the current observation and action."""
        embedded = nn.Dense(self.action_embed)(action)
        h = jnp.concatenate([MLP((self.width, self.width))(obs), Interaction()(z, embedded)], axis=-1)
        return nn.Dense(self.obs_size)(MLP((self.width, self.width))(h))


class LatentPolicy(nn.Module):
    """pi_eta(a | s, theta-hat): a Markov policy conditioned on the inferred latent."""

    width: int
    out_size: int
    # Where theta-hat joins the observation: "late" (after the observation's own MLP, the reference code's) or "early"
    # (beside the observation at the input, as the oracle's θ is part of its view), so the first layer can form
    # differences such as the speed minus the target or the goal minus the position.
    fusion: str = "late"

    @nn.compact
    def __call__(self, obs: jax.Array, z: jax.Array) -> jax.Array:
        """Head output (logits, or mean and log-std) for any leading shape."""
        if self.fusion == "early":
            h = MLP((self.width, self.width))(jnp.concatenate([obs, z], axis=-1))
        else:
            h = jnp.concatenate([MLP((self.width, self.width))(obs), z], axis=-1)
        return nn.Dense(self.out_size)(MLP((self.width, self.width))(h))


class RecurrentPolicy(StepInput):
    """Naive-BC (or oracle) policy: MLP(obs) ⊕ embedding(previous action) -> GRU (or minGRU) -> MLP -> head."""

    hidden: int
    out_size: int
    cell_kind: str = "gru"  # ``model.cell``: "gru" or "mingru" (``recurrent_cell``).

    def setup(self) -> None:
        """Sub-networks shared by ``embed`` and ``recur``."""
        super().setup()
        self.cell = recurrent_cell(self.cell_kind, self.hidden)
        self.head = MLP((self.width,))
        self.out = nn.Dense(self.out_size)

    def embed(self, obs: jax.Array, prev_action: jax.Array) -> jax.Array:
        """Cell inputs [..., width] for any leading shape (the same fused block as the encoder's, for parity)."""
        return self.fused(obs, prev_action)

    def coefficients(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """minGRU only: (a, b) [..., hidden] of h_t = a h_{t-1} + b for cell inputs x [..., width]."""
        return self.cell.coefficients(x)

    def readout(self, h: jax.Array) -> jax.Array:
        """Head outputs [..., out_size] of cell states h [..., hidden] of any leading shape."""
        return self.out(self.head(h))

    def recur(self, carry: jax.Array, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        """One cell step -> new carry, head output [B, out_size]."""
        carry, h = self.cell(carry, x)
        return carry, self.readout(h)

    def __call__(self, obs: jax.Array, prev_action: jax.Array) -> tuple[jax.Array, jax.Array]:
        """One step from a zero carry (used for initialisation)."""
        carry = jnp.zeros((*obs.shape[:-1], self.hidden), jnp.float32)
        return self.recur(carry, self.embed(obs, prev_action))


class Discriminator(nn.Module):
    """GAIL's discriminator: an MLP from transition features to the logit of "the expert produced this"."""

    width: int

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        """Logits [...] for features [..., f]."""
        return nn.Dense(1)(MLP((self.width, self.width))(x))[..., 0]
