"""Whether dil's policy suffers from cloning on an encoder that keeps changing: re-clone it on the final one.

    python experiments/refit_policy.py results/half_cheetah-cpu [--seeds 0,1] [--updates 35]

Restores each seed's last ``dil`` checkpoint from a results folder and evaluates (1) the imitator as trained, (2) a
freshly initialised policy cloned for ``--updates`` policy updates (each ``train.policy_steps`` steps, as in training)
on the expert buffer with θ-hat from the frozen final encoder, so its latents never move under it, and (3) the trained
policy given the same extra updates. All three act with the same final encoder and are evaluated from the same starts.
When (2) is no better than (1), encoder drift during training is not what holds the policy back; when (3) fits the
expert better (its loss) and returns less, more cloning on the same episodes overfits.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import jax
import numpy as np

from jaxdeconf.config import ConfigError
from jaxdeconf.policy import load_state


def refits(folder: str, seed: int, updates: int) -> dict[str, tuple[float, float, float]]:
    """{variant: (return, held-out expert NLL, last policy loss)} for one seed."""
    alg, states, config = load_state(folder, "dil")
    state = jax.tree.map(lambda x: x[seed - config.seed_start], states)

    @jax.jit
    def clone(state: Any, key: jax.Array) -> tuple[Any, jax.Array]:
        def body(s: Any, k: jax.Array) -> tuple[Any, jax.Array]:
            s, metrics = alg.update_policy(s, k)
            return s, metrics["policy_loss"]

        return jax.lax.scan(body, state, jax.random.split(key, updates))

    evaluate = jax.jit(alg.evaluate)
    fresh = jax.jit(alg.init)(jax.random.key(seed + 99)).policy
    variants = {"as trained": (state, np.nan)}
    for name, start in (("fresh policy, frozen final encoder", state.replace(policy=fresh)),
                        ("trained policy, further updates", state)):
        cloned, loss = clone(start, jax.random.key(seed + 1))
        variants[name] = (cloned, float(loss[-1]))
    out = {}
    for name, (s, loss) in variants.items():
        metrics = evaluate(s, jax.random.key(seed + 1000))
        out[name] = (float(metrics["eval_return"]), float(metrics["eval_expert_nll"]), loss)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder")
    p.add_argument("--seeds", default="0")
    p.add_argument("--updates", type=int, default=35)
    args = p.parse_args(argv)
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        print(f"error: --seeds {args.seeds!r} is not a comma-separated list of integers", file=sys.stderr)
        return 2
    try:
        for seed in seeds:
            for name, (ret, nll, loss) in refits(args.folder, seed, args.updates).items():
                print(f"seed {seed}, {name}: return {ret:.1f}, held-out expert NLL {nll:.2f}, policy loss {loss:.2f}")
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
