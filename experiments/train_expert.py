"""Train and ship a θ-aware PPO expert: ``python experiments/train_expert.py --env lunar_lander``.

Trains on the expert's view of the confounded env, evaluates the result over 100 episodes of each θ (with and
without action noise) and writes ``envs/experts/<env>.msgpack`` and ``.json`` (config, command, evaluation). An
existing expert is kept unless ``--overwrite``; ``--out`` writes elsewhere.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxdeconf.envs import make

from jaxdeconf.experts import expert_paths, save_expert
from jaxdeconf.platform import available_cores, pin_to_core
from jaxdeconf.ppo import ExpertNetwork, PPOConfig, train_ppo


def make_evaluator(env, net, episodes: int = 100):
    """One compiled program: ``fn(key, net_params, env_params, theta, blind)`` runs ``episodes`` full episodes with θ
    forced to ``theta`` and returns their returns, lengths and summed extras.

    ``blind`` feeds the expert θ = 0 whatever the episode's θ: a controller that ignores the confounder. θ, blind and
    the env params (noise) are traced, so every row of the evaluation tables reuses the same compilation.
    """
    horizon = env.horizon(env.default_params())

    def one(key, net_params, env_params, theta, blind):
        k_reset, k_run = jax.random.split(key)
        state, _ = env.reset(k_reset, env_params)
        state = state.replace(theta=jnp.asarray(theta, jnp.int32))
        obs = env._observe(state)

        def body(carry, k):
            state, obs, ret, alive, length = carry
            k_act, k_step = jax.random.split(k)
            view = jnp.where(blind, obs.expert.at[-1].set(0.0), obs.expert)
            logits, _ = net.apply(net_params, view)
            state, res = env.step(k_step, state, jax.random.categorical(k_act, logits), env_params)
            return (state, res.obs, ret + res.reward, alive & ~res.done, length + alive), res.extras

        init = (state, obs, jnp.zeros(()), jnp.ones((), jnp.bool_), jnp.zeros((), jnp.int32))
        (_, _, ret, _, length), extras = jax.lax.scan(body, init, jax.random.split(k_run, horizon))
        return ret, length, {n: v.sum() for n, v in extras.items()}

    batched = jax.jit(jax.vmap(one, in_axes=(0, None, None, None, None)))
    return lambda key, net_params, env_params, theta, blind: batched(
        jax.random.split(key, episodes), net_params, env_params, theta, blind)


def evaluation_table(env, evaluator, net_params, blind: bool) -> dict[str, dict[str, float]]:
    """100 episodes per θ, without action noise and with the env's default noise; printed and returned."""
    evaluation = {}
    params = env.default_params()
    for noise in (0.0, float(params.noise)):
        for theta in (0, 1):
            ret, length, extras = evaluator(jax.random.key(1000 + theta), net_params, params.replace(noise=noise),
                                            theta, blind)
            row = {"mean_return": float(ret.mean()), "std_return": float(ret.std()),
                   "mean_length": float(length.mean())}
            row.update({f"{k}_rate": float(np.mean(np.asarray(v) > 0)) for k, v in extras.items()
                        if k in ("landed", "crashed")})
            evaluation[f"noise={noise:g},theta={theta}"] = row
            print(f"eval{' θ-blind' if blind else ''} noise={noise:g} theta={theta}: return "
                  f"{row['mean_return']:.1f} ± {row['std_return']:.1f}, length {row['mean_length']:.0f}, "
                  f"landed {row.get('landed_rate', np.nan):.2f}, crashed {row.get('crashed_rate', np.nan):.2f}",
                  flush=True)
    return evaluation


def evaluate_shipped(name: str) -> int:
    """Re-evaluate the shipped expert, and the same network fed θ = 0 always (a θ-blind controller)."""
    from jaxdeconf.experts import load_expert

    env, _ = make(name)
    expert = load_expert(name)
    evaluator = make_evaluator(env, expert.network)
    for blind in (False, True):
        evaluation_table(env, evaluator, expert.params, blind)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="lunar_lander")
    parser.add_argument("--steps", type=float, default=PPOConfig.total_steps)
    parser.add_argument("--noise", type=float, default=None, help="action-noise probability while training")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--num-envs", type=int, default=PPOConfig.num_envs)
    parser.add_argument("--rollout", type=int, default=PPOConfig.rollout)
    parser.add_argument("--minibatches", type=int, default=PPOConfig.minibatches)
    parser.add_argument("--width", type=int, default=PPOConfig.width)
    parser.add_argument("--entropy", type=float, default=PPOConfig.entropy)
    parser.add_argument("--out", type=Path, default=None, help="folder for the expert files (default envs/experts)")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--evaluate", action="store_true",
                        help="only re-evaluate the shipped expert (and a θ-blind copy of it); write nothing")
    args = parser.parse_args(argv)
    pin_to_core(available_cores()[0])  # See jaxdeconf.platform.pin_to_core.
    if args.evaluate:
        return evaluate_shipped(args.env)
    weights, _ = expert_paths(args.env, args.out)
    if weights.exists() and not args.overwrite:
        print(f"error: expert {weights} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    overrides = {} if args.noise is None else {"noise": args.noise}
    try:
        env, params = make(args.env, **overrides)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    config = PPOConfig(total_steps=int(args.steps), num_envs=args.num_envs, rollout=args.rollout,
                       minibatches=args.minibatches, entropy=args.entropy, width=args.width)
    start = time.time()

    def log(row: dict) -> None:
        done = row["iteration"] / config.iterations
        eta = row["seconds"] / done * (1 - done)
        print(f"iter {row['iteration']:5d}/{config.iterations}  steps {row['steps']:>9,}"
              f"  return {row['mean_return']:8.1f}"
              f"  entropy {row['entropy']:.3f}  {row['seconds']:6.0f}s  eta {eta:5.0f}s", flush=True)

    net_params, history = train_ppo(env, params, config, args.seed, log)
    train_seconds = time.time() - start
    net = ExpertNetwork(env.action_space(params).n, config.width, config.depth)
    evaluation = evaluation_table(env, make_evaluator(env, net), net_params, blind=False)
    meta = {
        "env": args.env,
        "env_params": {k: v for k, v in dataclasses.asdict(params).items()},
        "actions": env.action_space(params).n,
        "obs_size": env.obs_sizes(params).expert,
        "width": config.width,
        "depth": config.depth,
        "ppo": dataclasses.asdict(config),
        "seed": args.seed,
        "command": "python experiments/train_expert.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "train_seconds": round(train_seconds, 1),
        "device": str(jax.devices()[0]),
        "final_train_return": history[-1]["mean_return"],
        "evaluation_100_episodes_each": evaluation,
    }
    save_expert(args.env, net_params, meta, args.out, overwrite=args.overwrite)
    print(f"wrote {weights}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
