"""Whether dil's policy reads θ-hat at the wrong scale: re-clone it on θ-hat raw and standardised.

    python experiments/latent_scale.py results/half_cheetah-cpu [--seed 0]

Restores one seed's last ``dil`` checkpoint and clones fresh copies of its policy for 35 policy updates on the
expert buffer with the frozen final encoder's posterior mean after each whole episode, (1) as it is, (2) standardised
per dimension by its moments over the buffer's final latents, (3) standardised by the moments of every step's belief.
Each is rolled out from the same starts (48 episodes) with θ-hat held at the expert's final belief for the same θ and
start, and online (Algorithm 2, the current belief through the same standardisation).
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
from latent_input import clone

from jaxdeconf.actors import DeconfoundedActor, ExpertActor, FixedLatentActor
from jaxdeconf.algos.dil import latent_moments, training_latents
from jaxdeconf.data import rollout
from jaxdeconf.models import standardise
from jaxdeconf.policy import load_state


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    folder, seed = args.folder, args.seed
    alg, states, config = load_state(folder, "dil")
    state = jax.tree.map(lambda x: x[seed - config.seed_start], states)
    enc, _, policy = alg.networks
    data = state.expert_buffer.data
    allz = alg.posterior_means(state, data)
    zf = training_latents(allz, data.valid, "final")
    stats = {"raw": (jnp.zeros(zf.shape[-1]), jnp.ones(zf.shape[-1])),
             "std by final latents": latent_moments(zf, data.valid),
             "std by every step's belief": latent_moments(allz, data.valid)}

    def run(params, st, key):
        expert, _ = rollout(alg.env, alg.env_params, ExpertActor(alg.env, alg.env_params), None, key, 48)
        z = standardise(alg.posterior_means(state, expert)[-1], st)
        fixed, _ = rollout(alg.env, alg.env_params, FixedLatentActor(policy), {"policy": params, "z": z}, key, 48)
        actor = DeconfoundedActor(enc, policy, alg.encoder_scale, True)
        actor_params = {"encoder": state.encoder.params["encoder"], "policy": params, "latent_stats": st}
        online, _ = rollout(alg.env, alg.env_params, actor, actor_params, key, 48)
        return jnp.mean(jnp.sum(fixed.reward, axis=0)), jnp.mean(jnp.sum(online.reward, axis=0))
    for name, st in stats.items():
        print(name, "std range", float(st[1].min()), float(st[1].max()), flush=True)
        cloned = jax.jit(lambda z, k: clone(alg, state, z, k, 35))
        params, loss = cloned(standardise(zf[0], st), jax.random.key(seed + 1))
        f, o = jax.jit(lambda p, k, st=st: run(p, st, k))(params, jax.random.key(seed + 1000))
        print(name, "fixed", float(f), "online", float(o), "loss", float(loss), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
