"""How much of the cheetah's target an ideal observer could know, step by step, against what q_phi knows.

    python experiments/bayes_filter.py results/half_cheetah-cpu [--seed 0] [--episodes 128]

The cheetah's cue is sign(v - θ) flipped with probability ``flip_prob``, so the exact posterior over θ after t steps
follows from the speeds and cues alone: on a grid over θ's range (uniform prior), each step multiplies in
``flip + (1 - 2 flip) · P(sign(v - θ) = cue)``, with v the forward velocity in the imitator's view (Brax's root
velocity, which differs a little from the step-averaged speed the cue is computed from, hence a soft boundary of
``--boundary`` m/s). Its posterior mean's R² against θ per step is what any inference model could reach on those
episodes; q_phi's is the held-out linear probe of its posterior mean (the evaluation's ``theta_probe``).

Both are computed on the expert's episodes and, when the folder holds a finished ``dil``, on dil's own online
episodes (Algorithm 2) from the same starts and θ. If the ideal observer's R² is high where q_phi's is low, the
inference model is the bottleneck; if both are low, the episodes themselves carry little of θ yet (the imitator has
not moved its speed across the target), and only exploration or longer episodes can help.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.stats import norm

from jaxdeconf.actors import ExpertActor
from jaxdeconf.config import ConfigError
from jaxdeconf.data import rollout
from jaxdeconf.diagnostics import episode_theta, theta_probe
from jaxdeconf.policy import load_config, load_state
from jaxdeconf.train import build_algorithm

STEPS = (1, 5, 10, 25, 50, 100, 150, 199)
SPEED_INDEX = 8  # Brax halfcheetah's observation: q[1:] (8 entries), then qd, whose first entry is the root's x speed.
GRID = 301


def raw_imitator_view(env: Any, obs: jax.Array) -> jax.Array:
    """The imitator's view in the env's own units (undoing the learners' standardisation, if any)."""
    stats = getattr(env, "stats", None)
    if stats is None:
        return obs
    mean, std = stats["imitator"]
    return obs * jnp.asarray(std) + jnp.asarray(mean)


def bayes_means(speed: jax.Array, cue: jax.Array, low: float, high: float, flip: float, boundary: float) -> jax.Array:
    """Exact posterior means [T, B] of θ after each step's (speed, cue) [T, B], uniform prior on [low, high]."""
    grid = jnp.linspace(low, high, GRID)
    p_up = norm.cdf((speed[..., None] - grid) / boundary)  # P(v >= θ) per grid point, [T, B, G].
    p_cue = jnp.where(cue[..., None] > 0, p_up, 1.0 - p_up)
    log_lik = jnp.cumsum(jnp.log(flip + (1.0 - 2.0 * flip) * p_cue), axis=0)
    weights = jax.nn.softmax(log_lik, axis=-1)
    return weights @ grid


def r2(estimate: np.ndarray, theta: np.ndarray) -> float:
    """1 - mean squared error / variance of θ."""
    return float(1.0 - np.mean((estimate - theta) ** 2) / np.var(theta))


def report(name: str, env: Any, params: Any, traj: Any, belief: jax.Array | None, boundary: float) -> None:
    """Print the ideal observer's and q_phi's R² per step on one set of episodes, and the mean speed error."""
    view = raw_imitator_view(env, traj.obs.imitator)
    theta = np.asarray(episode_theta(env, params, traj.obs.oracle[0]))[:, 0]
    ideal = np.asarray(bayes_means(view[..., SPEED_INDEX], view[..., -1], float(params.target_low),
                                   float(params.target_high), float(params.flip_prob), boundary))
    probe = None if belief is None else np.asarray(theta_probe(belief, theta[:, None], traj.valid))
    speed_error = np.asarray(traj.extras["abs_speed_error"]).mean(1)
    print(f"{name}: return {float(np.asarray(traj.reward).sum(0).mean()):.1f}")
    for t in STEPS:
        line = f"  t={t:3d}  ideal R² {r2(ideal[t], theta):.2f}"
        if probe is not None:
            line += f"  q_phi probe R² {probe[t]:.2f}"
        print(line + f"  |v - θ| {speed_error[t]:.2f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=128)
    p.add_argument("--boundary", type=float, default=0.1, help="soft boundary of the cue's sign, m/s")
    args = p.parse_args(argv)
    try:
        config = load_config(args.folder)
        if config.env != "half_cheetah":
            raise ConfigError(f"{args.folder} is a {config.env} run; this diagnostic is for half_cheetah")
        has_dil = "dil" in config.algos and (pathlib.Path(args.folder) / "dil" / "DONE").exists()
        if not config.seed_start <= args.seed < config.seed_start + config.seeds:
            raise ConfigError(f"--seed {args.seed} is not in {args.folder}; it holds seeds {config.seed_start} to "
                              f"{config.seed_start + config.seeds - 1}")
        alg, states, _ = load_state(args.folder, "dil") if has_dil else (build_algorithm(config, "bc"), None, None)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    key = jax.random.key(args.seed + 2000)
    expert, _ = jax.jit(lambda k: rollout(alg.env, alg.env_params, ExpertActor(alg.env, alg.env_params), None, k,
                                          args.episodes))(key)
    if states is None:
        report("expert", alg.env, alg.env_params, expert, None, args.boundary)
        return 0
    state = jax.tree.map(lambda x: x[args.seed - config.seed_start], states)
    online, _ = jax.jit(lambda k: rollout(alg.env, alg.env_params, alg.actor(), alg.actor_params(state), k,
                                          args.episodes))(key)
    report("expert", alg.env, alg.env_params, expert, alg.posterior_means(state, expert), args.boundary)
    report("dil online", alg.env, alg.env_params, online, alg.posterior_means(state, online), args.boundary)
    return 0


if __name__ == "__main__":
    sys.exit(main())
