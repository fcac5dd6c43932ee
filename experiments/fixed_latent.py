"""Whether dil's shortfall is its belief or its policy: the cloned policy online with the best θ-hat there is.

    python experiments/fixed_latent.py results/half_cheetah-cpu [--seed 0] [--episodes 48]

Restores one seed's last ``dil`` checkpoint from a results folder and rolls out, from the same starts and θ, (1) the
expert, (2) the cloned policy π_η(a | s, θ-hat) with θ-hat held fixed at the posterior mean after the expert's own
episode (the belief the policy could at best have), and (3) the imitator as deployed, reading its own online belief
(Algorithm 2). Prints each one's mean return, its sum over each quarter of the episode, the env's per-step
extras averaged over the episodes at a few steps, and how far (3)'s belief sits from the expert's final one on the same
θ (``code_distance``). When (2) is no better than (3), better inference cannot close the gap: the policy's cloning is
what falls short; when (2) is far better and the distance is as large as between unrelated θ, q_φ codes θ
differently on the imitator's own episodes.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import jax
import numpy as np

from jaxdeconf.actors import ExpertActor, FixedLatentActor
from jaxdeconf.algos.dil import latent_moments, training_latents
from jaxdeconf.config import ConfigError
from jaxdeconf.data import rollout
from jaxdeconf.diagnostics import episode_theta
from jaxdeconf.models import standardise
from jaxdeconf.policy import load_state

STEPS = (5, 10, 25, 50, 100, 150, 199)


def rollouts(folder: str, seed: int, episodes: int) -> tuple[Any, Any, dict[str, Any]]:
    """(algorithm, the seed's state, the three rollouts' trajectories), from the same key (same starts and θ)."""
    alg, states, config = load_state(folder, "dil")
    state = jax.tree.map(lambda x: x[seed - config.seed_start], states)
    _, _, policy = alg.networks

    @jax.jit
    def run(state: Any, key: jax.Array) -> dict[str, Any]:
        expert, _ = rollout(alg.env, alg.env_params, ExpertActor(alg.env, alg.env_params), None, key, episodes)
        z = alg.as_policy_reads(state, alg.posterior_means(state, expert)[-1])
        fixed, _ = rollout(alg.env, alg.env_params, FixedLatentActor(policy),
                           {"policy": state.policy.params, "z": z}, key, episodes)
        online, _ = rollout(alg.env, alg.env_params, alg.actor(), alg.actor_params(state), key, episodes)
        return {"expert": expert, "policy on the expert's final belief": fixed, "dil online": online}

    return alg, state, run(state, jax.random.key(seed + 1000))


def code_distance(alg: Any, state: Any, result: dict[str, Any]) -> tuple[list[float], float]:
    """Mean per-dimension distance, in units of the spread of the expert buffer's final posterior means, from the
    online belief at steps 25 / 100 / 199 to the expert's final belief on the same θ and start; and the same distance
    between expert episodes of unrelated θ (every pair): how far online θ-hat sits from where π_η was cloned."""
    data = state.expert_buffer.data
    stats = latent_moments(training_latents(alg.posterior_means(state, data), data.valid, "final"), data.valid)
    own = np.asarray(standardise(alg.posterior_means(state, result["dil online"]), stats))
    final = np.asarray(standardise(alg.posterior_means(state, result["expert"]), stats))[-1]
    steps = [t for t in (25, 100, 199) if t < len(own)]
    unrelated = float(np.abs(final[:, None] - final[None]).mean())
    return [float(np.abs(own[t] - final).mean()) for t in steps], unrelated


def cross_probe(alg: Any, state: Any, result: dict[str, Any]) -> tuple[list[float], float]:
    """R² of θ read off the online belief at steps 25 / 100 / 199 by the linear map fitted from the expert buffer's
    final posterior means to their θ (least squares), and that map's R² on the final beliefs of this run's fresh
    expert episodes: whether θ-hat online means what it means where π_η was cloned (a probe fitted on the online
    beliefs themselves, as ``diagnostics.png``'s, finds θ wherever it is coded)."""
    data = state.expert_buffer.data
    kept = np.asarray(data.valid[0])
    fit = np.asarray(training_latents(alg.posterior_means(state, data), data.valid, "final")[0])[kept]
    theta = np.asarray(episode_theta(alg.env, alg.env_params, data.obs.oracle[0]))[kept]
    coef, *_ = np.linalg.lstsq(np.c_[fit, np.ones(len(fit))], theta, rcond=None)

    def r2(z: np.ndarray, traj: Any) -> float:
        target = np.asarray(episode_theta(alg.env, alg.env_params, traj.obs.oracle[0]))
        resid = ((np.c_[z, np.ones(len(z))] @ coef - target) ** 2).sum()
        return float(1.0 - resid / ((target - target.mean(0)) ** 2).sum())

    own = np.asarray(alg.posterior_means(state, result["dil online"]))
    expert = np.asarray(alg.posterior_means(state, result["expert"]))[-1]
    return [r2(own[t], result["dil online"]) for t in (25, 100, 199) if t < len(own)], r2(expert, result["expert"])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=48)
    args = p.parse_args(argv)
    try:
        alg, state, result = rollouts(args.folder, args.seed, args.episodes)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for name, traj in result.items():
        reward = np.asarray(traj.reward)
        quarters = [float(q.sum(0).mean()) for q in np.array_split(reward, 4)]
        line = f"{name}: return {reward.sum(0).mean():.1f} (by quarter " + " ".join(f"{q:.1f}" for q in quarters) + ")"
        for extra, values in traj.extras.items():
            per_step = np.asarray(values).mean(1)
            line += f"; {extra} at steps {STEPS}: " + " ".join(f"{per_step[t]:.2f}" for t in STEPS
                                                               if t < len(per_step))
        print(line)
    online, unrelated = code_distance(alg, state, result)
    print("online belief's distance to the expert's final one, same θ, at steps 25 / 100 / 199: "
          + " / ".join(f"{d:.2f}" for d in online) + f"; between unrelated expert episodes: {unrelated:.2f}")
    online, expert = cross_probe(alg, state, result)
    print("θ read off the online belief at steps 25 / 100 / 199 by the expert buffer's linear map (R²): "
          + " / ".join(f"{r:.2f}" for r in online) + f"; the same map on fresh expert episodes' final beliefs: "
          f"{expert:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
