"""Whether dil's policy is held back by what θ-hat is, or by how the policy reads it: clone on θ itself.

    python experiments/latent_input.py results/half_cheetah-cpu [--seed 0] [--updates 35] [--episodes 48]

Restores one seed's last ``dil`` checkpoint and clones fresh copies of its policy network π_η(a | s, z) on the
final expert buffer (``--updates`` policy updates of ``train.policy_steps`` steps each, as in training) with z per
expert episode being (1) θ-hat, the frozen final encoder's posterior mean after the whole episode, or (2) the
episode's true θ (the oracle's standardised θ, zero-padded to the latent size). Each is rolled out from the same
starts and θ with z held fixed for the episode (θ-hat from the expert's own episode with that θ and start, or θ).
When (2) returns like the oracle and (1) does not, what θ-hat carries besides θ is what the policy fails on; when both
fall short, it is how this network reads its latent.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import jax
import jax.numpy as jnp

from jaxdeconf.actors import ExpertActor, FixedLatentActor
from jaxdeconf.algos.base import apply_gradients
from jaxdeconf.algos.dil import training_latents
from jaxdeconf.config import ConfigError
from jaxdeconf.data import buffer_indices, rollout
from jaxdeconf.policy import load_state


def true_latents(alg: Any, traj: Any) -> jax.Array:
    """The standardised θ of each episode [B, L] (the oracle view's trailing entries), zero-padded to the latent."""
    size = alg.env.obs_sizes(alg.env_params).imitator
    theta = traj.obs.oracle[0][:, size:]
    return jnp.pad(theta, ((0, 0), (0, alg.config.model.latent - theta.shape[-1])))


def clone(alg: Any, state: Any, latents: jax.Array, key: jax.Array, updates: int) -> tuple[Any, jax.Array]:
    """A fresh policy cloned on the expert buffer with a fixed z [capacity, L] per episode: (params, last loss)."""
    t = alg.config.train
    buffer = state.expert_buffer
    context = jnp.broadcast_to(latents[None], (buffer.data.action.shape[0], *latents.shape))
    params = jax.jit(alg.init)(jax.random.fold_in(key, 7)).policy

    def step(learner: Any, k: jax.Array) -> tuple[Any, jax.Array]:
        idx = buffer_indices(buffer, k, t.batch_size)
        batch = jax.tree.map(lambda d: d[:, idx], buffer.data)
        loss, grads = jax.value_and_grad(alg.policy_loss)(learner.params, state, batch, context[:, idx])
        return apply_gradients(learner, grads, alg.policy_tx), loss

    learner, loss = jax.lax.scan(step, params, jax.random.split(key, updates * t.policy_steps))
    return learner.params, loss[-t.policy_steps:].mean()


def compare(folder: str, seed: int, updates: int, episodes: int) -> dict[str, tuple[float, float]]:
    """{z: (return with z held fixed, last policy loss)} for one seed."""
    alg, states, config = load_state(folder, "dil")
    state = jax.tree.map(lambda x: x[seed - config.seed_start], states)
    _, _, policy = alg.networks
    data = state.expert_buffer.data
    train_z = {"θ-hat (final posterior mean)": training_latents(alg.posterior_means(state, data), data.valid,
                                                                 "final")[0],
               "θ (the oracle's)": true_latents(alg, data)}

    def run(params: Any, use_theta: bool, key: jax.Array) -> jax.Array:
        expert, _ = rollout(alg.env, alg.env_params, ExpertActor(alg.env, alg.env_params), None, key, episodes)
        z = true_latents(alg, expert) if use_theta else alg.posterior_means(state, expert)[-1]
        traj, _ = rollout(alg.env, alg.env_params, FixedLatentActor(policy), {"policy": params, "z": z}, key,
                          episodes)
        return jnp.mean(jnp.sum(traj.reward, axis=0))

    out = {}
    for i, (name, z) in enumerate(train_z.items()):
        params, loss = jax.jit(lambda z, k: clone(alg, state, z, k, updates))(z, jax.random.key(seed + 1))
        ret = jax.jit(lambda p, k, i=i: run(p, i == 1, k))(params, jax.random.key(seed + 1000))
        out[name] = (float(ret), float(loss))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--updates", type=int, default=35)
    p.add_argument("--episodes", type=int, default=48)
    args = p.parse_args(argv)
    try:
        result = compare(args.folder, args.seed, args.updates, args.episodes)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for name, (ret, loss) in result.items():
        print(f"seed {args.seed}, policy cloned on {name}: return {ret:.1f} (z fixed per episode), loss {loss:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
