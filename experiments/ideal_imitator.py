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

from jaxdeconf.config import ConfigError
from jaxdeconf.data import rollout
from jaxdeconf.policy import load_state


@dataclasses.dataclass(frozen=True)
class BeliefOracle:
    """The oracle's actor with θ in its view replaced by a belief: the ideal observer's posterior mean
    (``mode="ideal"``) or the prior mean (``mode="prior"``)."""

    oracle: Any  # The oracle's RecurrentActor or MarkovActor.
    env: Any  # NormalizedViews: the views' (mean, std) are in env.stats.
    params: Any
    mode: str
    boundary: float = 0.1

    @property
    def grid(self) -> jax.Array:
        return jnp.linspace(float(self.params.target_low), float(self.params.target_high), GRID)

    def init_carry(self, batch: int) -> Any:
        return self.oracle.init_carry(batch), jnp.zeros((batch, GRID), jnp.float32)

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
        mean, std = self.env.stats["oracle"]
        oracle_view = (jnp.concatenate([view, theta_hat[:, None]], axis=-1) - mean) / std
        inner, out = self.oracle(params, inner, dataclasses.replace(obs, oracle=oracle_view), prev_action)
        return (inner, log_post), out


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
    args = p.parse_args(argv)
    try:
        bc, bc_states, config = load_state(args.folder, "bc")
        oracle, oracle_states, _ = load_state(args.folder, "oracle")
        if config.env != "half_cheetah":
            raise ConfigError(f"{args.folder} is a {config.env} run; this diagnostic is for half_cheetah")
        if not config.seed_start <= args.seed < config.seed_start + config.seeds:
            raise ConfigError(f"--seed {args.seed} is not in {args.folder}; it holds seeds {config.seed_start} to "
                              f"{config.seed_start + config.seeds - 1}")
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    pick = args.seed - config.seed_start
    bc_params = bc.actor_params(jax.tree.map(lambda x: x[pick], bc_states))
    oracle_params = oracle.actor_params(jax.tree.map(lambda x: x[pick], oracle_states))
    horizon = args.horizon or oracle.env_params.horizon
    key = jax.random.key(args.seed + 3000)
    rows = {
        "bc": evaluate(bc, bc.actor(), bc_params, key, args.episodes, horizon),
        "oracle (θ)": evaluate(oracle, oracle.actor(), oracle_params, key, args.episodes, horizon),
        "oracle on the ideal observer's belief": evaluate(
            oracle, BeliefOracle(oracle.actor(), oracle.env, oracle.env_params, "ideal"), oracle_params, key,
            args.episodes, horizon),
        "oracle on the prior mean": evaluate(
            oracle, BeliefOracle(oracle.actor(), oracle.env, oracle.env_params, "prior"), oracle_params, key,
            args.episodes, horizon),
    }
    low, high = rows["bc"]["return"], rows["oracle (θ)"]["return"]
    print(f"seed {args.seed}, {args.episodes} episodes of {horizon} steps")
    for name, r in rows.items():
        gap = (r["return"] - low) / (high - low)
        print(f"  {name:40s} return {r['return']:8.1f}  gap {gap:5.0%}  |v − θ| {r['error']:.3f} "
              f"(first quarter {r['error_first_quarter']:.3f}, rest {r['error_rest']:.3f})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
