"""How much of θ a trained inference model's posterior mean carries: a linear probe, per step, on fresh episodes.

    python experiments/probe_latent.py results/lunar_lander-cpu [--steps 5,10,25,50,100,200,300] [--episodes 256]

Restores each seed's last ``dil`` checkpoint from a results folder, rolls out the expert and the imitator itself
(Algorithm 2), and at each listed step fits a least-squares map from the posterior mean q_phi(. | tau_{:t}) to θ on
half of the episodes still running, scoring it on the other half. θ is read from the last ``--theta-dims`` entries of
the expert's view (the confounded envs append it there). Prints the held-out accuracy for a two-valued θ
(LunarLander's swap) and R² otherwise, with the fraction of episodes still running.

It also prints how much the cloned policy relies on what q_phi says about *this* episode: its negative
log-likelihood of the expert's actions on the expert episodes with z as inferred, and with each episode's z sequence
swapped for another episode's (a fixed permutation). A policy that reads θ from z loses likelihood when z is swapped;
one that has learnt to read the expert's state instead (where the state itself reveals θ, as a half_cheetah's speed
does once it has reached the target) barely notices.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import jax
import numpy as np

from jaxdeconf import losses
from jaxdeconf.actors import ExpertActor
from jaxdeconf.checkpoint import Checkpoints
from jaxdeconf.config import from_dict
from jaxdeconf.data import rollout
from jaxdeconf.train import build_algorithm, seed_keys


def probe(z: np.ndarray, theta: np.ndarray) -> float:
    """Held-out accuracy (θ in {0, 1}) or R² of a linear map z -> θ; first half fits, second half scores."""
    half = len(z) // 2
    x = np.c_[z, np.ones(len(z))]
    binary = set(np.unique(theta)) <= {0.0, 1.0}
    target = 2.0 * theta - 1.0 if binary else theta
    w, *_ = np.linalg.lstsq(x[:half], target[:half], rcond=None)
    pred = x[half:] @ w
    if binary:
        return float(np.mean((pred[:, 0] > 0) == (theta[half:, 0] > 0.5)))
    resid = np.sum((pred - theta[half:]) ** 2)
    return float(1.0 - resid / np.sum((theta[half:] - theta[half:].mean(0)) ** 2))


def main(argv: list[str] | None = None) -> int:
    """Print one line per (seed, data source)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=pathlib.Path)
    parser.add_argument("--steps", default="5,10,25,50,100,200,300")
    parser.add_argument("--episodes", type=int, default=256)
    parser.add_argument("--theta-dims", type=int, default=1)
    args = parser.parse_args(argv)
    config_path = args.folder / "config.json"
    ckpt_dir = args.folder / "dil" / "checkpoints"
    if not config_path.exists() or not ckpt_dir.exists():
        print(f"error: {args.folder} holds no dil run (need config.json and dil/checkpoints)", file=sys.stderr)
        return 2
    config = from_dict(json.loads(config_path.read_text()))
    algo = build_algorithm(config, "dil")
    states = jax.jit(jax.vmap(algo.init))(seed_keys(config))
    checkpoints = Checkpoints(ckpt_dir)
    states = checkpoints.restore(checkpoints.latest_step(), states)
    horizon = algo.env.horizon(algo.env_params)
    steps = [t for t in (int(s) for s in args.steps.split(",")) if t < horizon]
    # Compiled once each, outside the seed loop (a Brax rollout takes minutes to compile on a CPU).
    actors = {"expert": ExpertActor(algo.env, algo.env_params), "imitator": algo.actor()}
    roll = {name: jax.jit(lambda p, k, a=actor: rollout(algo.env, algo.env_params, a, p, k, args.episodes)[0])
            for name, actor in actors.items()}
    posterior_means = jax.jit(algo.posterior_means)

    @jax.jit
    def expert_nll(state, traj, z):
        out = algo.policy_outputs(state.policy.params, state, traj, z)
        return losses.nll_from_outputs(algo.space, out, traj.action, traj.valid)

    reliance = []
    print(f"{'seed':>4} {'episodes':>9}  " + "  ".join(f"t={t:<4}" for t in steps) + "   (alive fraction below)")
    for seed in range(config.seeds):
        state = jax.tree.map(lambda x, i=seed: x[i], states)
        for name, params in (("expert", None), ("imitator", algo.actor_params(state))):
            traj = roll[name](params, jax.random.key(1000 + seed))
            theta = np.asarray(traj.obs.expert[0, :, -args.theta_dims:])
            z = np.asarray(posterior_means(state, traj))
            valid = np.asarray(traj.valid)
            scores = [probe(z[t][valid[t]], theta[valid[t]]) if valid[t].sum() >= 8 else float("nan") for t in steps]
            alive = [valid[t].mean() for t in steps]
            print(f"{config.seed_start + seed:>4} {name:>9}  " + "  ".join(f"{v:6.2f}" for v in scores))
            print(f"{'':>4} {'':>9}  " + "  ".join(f"({a:4.2f})" for a in alive))
            if name == "expert":
                swapped = z[:, np.random.default_rng(0).permutation(z.shape[1])]
                reliance.append((config.seed_start + seed, float(expert_nll(state, traj, z)),
                                 float(expert_nll(state, traj, swapped))))
    print("\npolicy NLL of the expert's actions on expert episodes: z as inferred -> z swapped between episodes")
    for seed, own, swapped in reliance:
        print(f"{seed:>4}  {own:9.3f} -> {swapped:9.3f}  (+{swapped - own:.3f})")
    checkpoints.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
