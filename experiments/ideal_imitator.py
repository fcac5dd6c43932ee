"""How far any imitator that infers the cheetah's target online could get: the oracle acting on the ideal observer's
belief in place of θ.

    python experiments/ideal_imitator.py results/half_cheetah-cpu [--seed 0] [--episodes 64] [--horizon 200]

The folder must hold a finished ``bc`` and ``oracle``. The trained oracle policy (it reads θ beside the imitator's
view) is rolled out with θ replaced by the exact posterior mean of θ given the speeds and cues seen so far (the grid
filter of ``bayes_filter.py``), by the prior mean, and by θ itself, next to ``bc`` from the same starts. The first is
what an imitator gets whose inference model is exact and whose policy is the oracle's: the share of the bc → oracle
gap it closes is a ceiling for dil at that episode length, short of one that explores to learn θ sooner. ``--horizon``
rolls the same policies out for longer episodes (the policies were trained on the folder's own), to see how the
ceiling grows with the episode's length, as the paper's 1000-step cheetah has it.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from bayes_filter import GRID, SPEED_INDEX, raw_imitator_view
from jax.scipy.stats import norm
from jaxdeconf.envs.base import Observation

from jaxdeconf.actors import ExpertActor
from jaxdeconf.config import ConfigError
from jaxdeconf.data import rollout
from jaxdeconf.diagnostics import episode_theta
from jaxdeconf.models import standardise
from jaxdeconf.policy import load_state


@dataclasses.dataclass(frozen=True)
class IdealObserver:
    """A belief over θ from the speeds and cues alone: the exact grid posterior's mean (``mode="ideal"``) or the prior
    mean throughout (``mode="prior"``); ``inner`` acts on it (``init_carry``; ``act(params, carry, obs, prev, θ̂)``)."""

    inner: Any
    env: Any  # NormalizedViews: the views' (mean, std) are in env.stats.
    params: Any
    mode: str
    boundary: float = 0.1

    @property
    def grid(self) -> jax.Array:
        return jnp.linspace(float(self.params.target_low), float(self.params.target_high), GRID)

    def init_carry(self, batch: int) -> Any:
        return self.inner.init_carry(batch), jnp.zeros((batch, GRID), jnp.float32)

    def __call__(self, params: Any, carry: Any, obs: Observation, prev_action: jax.Array):
        inner, log_post = carry
        view = raw_imitator_view(self.env, obs.imitator)
        p_up = norm.cdf((view[:, SPEED_INDEX, None] - self.grid) / self.boundary)
        p_cue = jnp.where(view[:, -1:] > 0, p_up, 1.0 - p_up)
        flip = float(self.params.flip_prob)
        log_post = log_post + jnp.log(flip + (1.0 - 2.0 * flip) * p_cue)
        if self.mode == "ideal":
            theta_hat = jax.nn.softmax(log_post, axis=-1) @ self.grid
        else:
            theta_hat = jnp.full((view.shape[0],), self.grid.mean())
        inner, out = self.inner.act(params, inner, obs, prev_action, theta_hat)
        return (inner, log_post), out


@dataclasses.dataclass(frozen=True)
class OracleOn:
    """The trained oracle with θ̂ in place of θ in its view."""

    oracle: Any  # The oracle's RecurrentActor or MarkovActor.
    env: Any

    def init_carry(self, batch: int) -> Any:
        return self.oracle.init_carry(batch)

    def act(self, params: Any, carry: Any, obs: Observation, prev_action: jax.Array, theta_hat: jax.Array):
        mean, std = self.env.stats["oracle"]
        view = (jnp.concatenate([raw_imitator_view(self.env, obs.imitator), theta_hat[:, None]], -1) - mean) / std
        return self.oracle(params, carry, dataclasses.replace(obs, oracle=view), prev_action)


@dataclasses.dataclass(frozen=True)
class DilPolicyOn:
    """dil's π_η(a | s, z) with z = E[q_φ's final posterior mean | θ] at θ̂: ``coef`` [4, L] of a cubic in θ fitted
    on expert episodes, so the policy gets the code it was cloned on for that θ."""

    policy: Any
    coef: jax.Array

    def init_carry(self, batch: int) -> Any:
        return jnp.zeros((batch, 0), jnp.float32)

    def act(self, params: Any, carry: Any, obs: Observation, prev_action: jax.Array, theta_hat: jax.Array):
        return carry, self.policy.apply(params, obs.imitator, cubic(theta_hat) @ self.coef)


def cubic(theta: jax.Array) -> jax.Array:
    return jnp.stack([jnp.ones_like(theta), theta, theta**2, theta**3], axis=-1)


def latent_map(dil: Any, state: Any, key: jax.Array, episodes: int = 512) -> jax.Array:
    """Least-squares cubic [4, L] from θ to q_φ's posterior mean after the expert's whole episode, as the policy reads
    it (standardised with ``model.latent_norm=expert``)."""
    expert, _ = jax.jit(lambda k: rollout(dil.env, dil.env_params, ExpertActor(dil.env, dil.env_params), None, k,
                                          episodes))(key)
    z = dil.posterior_means(state, expert)[-1]
    if dil.standardises:
        z = standardise(z, state.latent_stats)
    theta = episode_theta(dil.env, dil.env_params, expert.obs.oracle[0])[:, 0]
    return jnp.linalg.lstsq(cubic(theta), z)[0]


def evaluate(alg: Any, actor: Any, actor_params: Any, key: jax.Array, episodes: int, horizon: int) -> dict[str, float]:
    """Mean return and mean |v − θ| per step over ``episodes`` episodes of ``horizon`` steps."""
    params = dataclasses.replace(alg.env_params, horizon=horizon)
    traj, _ = jax.jit(lambda k: rollout(alg.env, params, actor, actor_params, k, episodes))(key)
    error = np.asarray(traj.extras["abs_speed_error"])
    quarter = horizon // 4
    return {"return": float(np.asarray(traj.reward).sum(0).mean()), "error": float(error.mean()),
            "error_first_quarter": float(error[:quarter].mean()), "error_rest": float(error[quarter:].mean())}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--horizon", type=int, default=0, help="episode length (default: the folder's)")
    p.add_argument("--dil", default="", help="a results folder with a finished dil (same env settings and seeds)")
    args = p.parse_args(argv)
    try:
        bc, bc_state, config = seed_state(args.folder, "bc", args.seed)
        oracle, oracle_state, _ = seed_state(args.folder, "oracle", args.seed)
        dil = seed_state(args.dil, "dil", args.seed) if args.dil else None
        if config.env != "half_cheetah":
            raise ConfigError(f"{args.folder} is a {config.env} run; this diagnostic is for half_cheetah")
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    horizon = args.horizon or oracle.env_params.horizon
    key = jax.random.key(args.seed + 3000)
    o_actor, o_params = OracleOn(oracle.actor(), oracle.env), oracle.actor_params(oracle_state)
    runs = {
        "bc": (bc, bc.actor(), bc.actor_params(bc_state)),
        "oracle (θ)": (oracle, oracle.actor(), o_params),
        "oracle on the ideal observer's belief": (oracle, IdealObserver(o_actor, oracle.env, oracle.env_params,
                                                                        "ideal"), o_params),
        "oracle on the prior mean": (oracle, IdealObserver(o_actor, oracle.env, oracle.env_params, "prior"), o_params),
    }
    if dil is not None:
        alg, state, _ = dil
        coef = latent_map(alg, state, jax.random.key(args.seed + 4000))
        policy = DilPolicyOn(alg.networks[2], coef)
        runs["dil as deployed (Algorithm 2)"] = (alg, alg.actor(), alg.actor_params(state))
        runs["dil's π_η on the ideal observer's belief"] = (
            alg, IdealObserver(policy, alg.env, alg.env_params, "ideal"), state.policy.params)
        runs["dil's π_η on z(θ), the true θ"] = (alg, TrueTheta(policy, alg.env, alg.env_params), state.policy.params)
    rows = {name: evaluate(a, actor, params, key, args.episodes, horizon) for name, (a, actor, params) in runs.items()}
    low, high = rows["bc"]["return"], rows["oracle (θ)"]["return"]
    print(f"seed {args.seed}, {args.episodes} episodes of {horizon} steps")
    for name, r in rows.items():
        gap = (r["return"] - low) / (high - low)
        print(f"  {name:45s} return {r['return']:8.1f}  gap {gap:5.0%}  |v − θ| {r['error']:.3f} "
              f"(first quarter {r['error_first_quarter']:.3f}, rest {r['error_rest']:.3f})")
    return 0


@dataclasses.dataclass(frozen=True)
class TrueTheta:
    """``inner`` acting on θ itself, read off the oracle's view."""

    inner: Any
    env: Any
    params: Any

    def init_carry(self, batch: int) -> Any:
        return self.inner.init_carry(batch)

    def __call__(self, params: Any, carry: Any, obs: Observation, prev_action: jax.Array):
        theta = episode_theta(self.env, self.params, obs.oracle)[:, 0]
        return self.inner.act(params, carry, obs, prev_action, theta)


def seed_state(folder: str, algo: str, seed: int) -> tuple[Any, Any, Any]:
    """(algorithm, one seed's TrainState, config) of ``algo`` in ``folder``."""
    alg, states, config = load_state(folder, algo)
    if not config.seed_start <= seed < config.seed_start + config.seeds:
        raise ConfigError(f"--seed {seed} is not in {folder}; it holds seeds {config.seed_start} to "
                          f"{config.seed_start + config.seeds - 1}")
    return alg, jax.tree.map(lambda x: x[seed - config.seed_start], states), config


if __name__ == "__main__":
    sys.exit(main())
