"""Whether dil's shortfall is its belief or its policy: the cloned policy online with the best θ-hat there is.

    python experiments/fixed_latent.py results/half_cheetah-cpu [--seed 0] [--episodes 48]

Restores one seed's last ``dil`` checkpoint from a results folder and rolls out, from the same starts and θ, (1) the
expert, (2) the cloned policy π_η(a | s, θ-hat) with θ-hat held fixed at the posterior mean after the expert's own
episode (the belief the policy could at best have), and (3) the imitator as deployed, reading its own online belief
(Algorithm 2). Prints each one's mean return, its sum over each quarter of the episode, the env's per-step
extras averaged over the episodes at a few steps, and how far (3)'s belief sits from the expert's final one on the same
θ (``code_distance``), and how well the expert buffer's linear map from final beliefs to θ reads θ off (3)'s belief
(``cross_probe``). When (2) is no better than (3), better inference cannot close the gap: the policy's cloning is
what falls short; when (2) is far better, the distance is as large as between unrelated θ and the expert's map reads
little of θ online, q_φ codes θ differently on the imitator's own episodes.
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


def beliefs(alg: Any, state: Any, result: dict[str, Any]) -> dict[str, Any]:
    """q_φ's posterior means, encoded once for both measures below: the expert buffer's final ones as the policy was
    cloned on them ([T, B, L], with the buffer), the online ones along (3) [T, B, L], the expert's final ones [B, L]."""
    data = state.expert_buffer.data
    return {"data": data, "buffer": training_latents(alg.posterior_means(state, data), data.valid, "final"),
            "own": alg.posterior_means(state, result["dil online"]),
            "expert": alg.posterior_means(state, result["expert"])[-1]}


def code_distance(b: dict[str, Any]) -> tuple[list[float], float]:
    """Mean per-dimension distance, in units of the spread of the expert buffer's final posterior means, from the
    online belief at steps 25 / 100 / 199 to the expert's final belief on the same θ and start; and the same distance
    between expert episodes of unrelated θ (every pair): how far online θ-hat sits from where π_η was cloned."""
    stats = latent_moments(b["buffer"], b["data"].valid)
    own, final = np.asarray(standardise(b["own"], stats)), np.asarray(standardise(b["expert"], stats))
    steps = [t for t in (25, 100, 199) if t < len(own)]
    unrelated = float(np.abs(final[:, None] - final[None]).mean())
    return [float(np.abs(own[t] - final).mean()) for t in steps], unrelated


def cross_probe(alg: Any, b: dict[str, Any], result: dict[str, Any]) -> tuple[list[float], float]:
    """R² of θ read off the online belief at steps 25 / 100 / 199 by the linear map fitted from the expert buffer's
    final posterior means to their θ (least squares), and that map's R² on the final beliefs of this run's fresh
    expert episodes: whether θ-hat online means what it means where π_η was cloned (a probe fitted on the online
    beliefs themselves, as ``diagnostics.png``'s, finds θ wherever it is coded)."""
    theta_of = lambda traj: np.asarray(episode_theta(alg.env, alg.env_params, traj.obs.oracle[0]))  # noqa: E731
    kept = np.asarray(b["data"].valid[0])
    fit = np.asarray(b["buffer"][0])[kept]
    coef, *_ = np.linalg.lstsq(np.c_[fit, np.ones(len(fit))], theta_of(b["data"])[kept], rcond=None)

    def r2(z: np.ndarray, target: np.ndarray) -> float:
        resid = ((np.c_[z, np.ones(len(z))] @ coef - target) ** 2).sum()
        return float(1.0 - resid / ((target - target.mean(0)) ** 2).sum())

    own, online_theta = np.asarray(b["own"]), theta_of(result["dil online"])
    steps = [t for t in (25, 100, 199) if t < len(own)]
    return [r2(own[t], online_theta) for t in steps], r2(np.asarray(b["expert"]), theta_of(result["expert"]))


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
    b = beliefs(alg, state, result)
    online, unrelated = code_distance(b)
    print("online belief's distance to the expert's final one, same θ, at steps 25 / 100 / 199: "
          + " / ".join(f"{d:.2f}" for d in online) + f"; between unrelated expert episodes: {unrelated:.2f}")
    online, expert = cross_probe(alg, b, result)
    print("θ read off the online belief at steps 25 / 100 / 199 by the expert buffer's linear map (R²): "
          + " / ".join(f"{r:.2f}" for r in online) + f"; the same map on fresh expert episodes' final beliefs: "
          f"{expert:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
