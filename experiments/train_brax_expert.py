"""Train and ship a θ-aware locomotion expert with Brax's PPO (``experiments/train_brax_expert.py --env ant_goal``).

Brax's trainer (``brax.training.agents.ppo.train``) runs on the expert's view of the confounded env (state + θ), with
a fresh θ at every episode (``jaxdeconf.brax_experts.wrap_resampling``). Rewards while training:
- ``half_cheetah``: the task's own, -|v - target| - 0.05·‖a‖².
- ``ant_goal`` (``--reward progress``, the default): progress toward the goal per second plus Brax's ant healthy bonus
  and control cost. The progress terms telescope to (d_0 - d_T)/dt, so the shaping optimises the final distance the
  expert is judged by; ``--reward task`` trains on -distance itself.
Every ``--evals``-th of the way the parameters are written to ``--work`` (default ``results/experts/<env>``); a run
started again with ``--resume`` continues from the latest snapshot. At the end the expert is evaluated over 100
episodes of the env (deterministic actions) and written to ``envs/experts/<env>.msgpack`` and ``.json``, with the
command, the PPO config, the train time and the evaluation; an existing expert is kept unless ``--overwrite``.
``--evaluate`` only re-evaluates the shipped expert.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np
from jaxdeconf.envs import make

from jaxdeconf.brax_experts import ExpertView, PolicyExpert, network_factory, policy_template, wrap_resampling
from jaxdeconf.experts import expert_paths, load_expert, save_expert
from jaxdeconf.platform import available_cores, pin_to_core

ENVS = ("half_cheetah", "ant_goal")


def ant_progress_reward(env, params, ctrl_cost: float = 0.5, healthy: float = 1.0):
    """Progress toward the goal per second + healthy bonus - control cost (Brax's ant terms, goal-directed)."""
    dt = env.brax_env(params).dt

    def reward(before, after, action):
        progress = (env.distance(before.brax, before.theta, params) - env.distance(after.brax, after.theta, params))
        z = after.brax.pipeline_state.x.pos[0, 2]
        alive = ((z >= 0.2) & (z <= 1.0)).astype(jnp.float32)
        return progress / dt + healthy * alive - ctrl_cost * jnp.sum(jnp.clip(action, -1, 1) ** 2)

    return reward


def make_evaluator(env, params, meta: dict, episodes: int = 100):
    """One compiled program: ``fn(key, policy_params)`` runs ``episodes`` episodes of the expert network ``meta``
    describes, acting deterministically on the expert's view; returns per-episode return, per-step extras [episodes,
    T] and θ."""
    horizon = env.horizon(params)

    def one(key, policy_params):
        k_reset, k_run = jax.random.split(key)
        state, obs = env.reset(k_reset, params)

        def body(carry, k):
            state, obs = carry
            action = PolicyExpert(policy_params, meta).act(obs.expert)
            state, res = env.step(k, state, action, params)
            return (state, res.obs), (res.reward, res.extras)

        _, (rewards, extras) = jax.lax.scan(body, (state, obs), jax.random.split(k_run, horizon))
        return rewards.sum(), extras, state.theta

    batched = jax.jit(jax.vmap(one, in_axes=(0, None)))
    return lambda key, policy_params: batched(jax.random.split(key, episodes), policy_params)


def evaluate(env, params, policy_params, meta) -> dict:
    """100 episodes with a fixed key: returns and the issue's quality measure, printed and returned."""
    ret, extras, theta = make_evaluator(env, params, meta)(jax.random.key(2024), policy_params)
    ret, theta = np.asarray(ret), np.asarray(theta)
    row = {"episodes": int(ret.shape[0]), "mean_return": float(ret.mean()), "std_return": float(ret.std())}
    if env.name == "half_cheetah":
        err = np.asarray(extras["abs_speed_error"])
        second = err[:, err.shape[1] // 2:].mean(1)
        row["mean_abs_speed_error_second_half"] = float(second.mean())
        edges = np.linspace(0, 3, 7)
        row["by_target"] = {f"{lo:.1f}-{hi:.1f}": float(second[(theta >= lo) & (theta < hi)].mean())
                            for lo, hi in itertools.pairwise(edges) if ((theta >= lo) & (theta < hi)).any()}
        print(f"eval: return {row['mean_return']:.1f} ± {row['std_return']:.1f}; mean |v - target| over the second "
              f"half {row['mean_abs_speed_error_second_half']:.3f} m/s; by target {row['by_target']}", flush=True)
    else:
        dist = np.asarray(extras["distance"])
        row["median_final_distance"] = float(np.median(dist[:, -1]))
        row["mean_final_distance"] = float(dist[:, -1].mean())
        row["mean_initial_goal_distance"] = float(np.linalg.norm(theta, axis=-1).mean())
        row["unhealthy_step_fraction"] = float(np.asarray(extras["unhealthy"]).mean())
        print(f"eval: return {row['mean_return']:.1f} ± {row['std_return']:.1f}; final distance median "
              f"{row['median_final_distance']:.2f} mean {row['mean_final_distance']:.2f} (goals at "
              f"{row['mean_initial_goal_distance']:.2f} on average); unhealthy steps "
              f"{row['unhealthy_step_fraction']:.3f}", flush=True)
    return row


def evaluate_shipped(name: str) -> int:
    """Re-evaluate the shipped expert."""
    env, params = make(name)
    expert = load_expert(env.name)
    evaluate(env, params, expert.params, expert.meta)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="ant_goal", choices=ENVS)
    parser.add_argument("--steps", type=float, default=2e7, help="environment steps")
    parser.add_argument("--reward", default="progress", choices=("progress", "task"),
                        help="ant_goal's training reward (half_cheetah always trains on its task reward)")
    parser.add_argument("--num-envs", type=int, default=128)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--minibatches", type=int, default=8)
    parser.add_argument("--updates-per-batch", type=int, default=4)
    parser.add_argument("--unroll", type=int, default=10)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--entropy", type=float, default=1e-2)
    parser.add_argument("--discount", type=float, default=0.97)
    parser.add_argument("--reward-scaling", type=float, default=1.0)
    parser.add_argument("--policy-layers", default="64,64")
    parser.add_argument("--value-layers", default="128,128")
    parser.add_argument("--evals", type=int, default=20, help="progress reports / snapshots during training")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=None, help="snapshot folder (default results/experts/<env>)")
    parser.add_argument("--resume", action="store_true", help="continue from the latest snapshot in --work")
    parser.add_argument("--out", type=Path, default=None, help="folder for the expert files (default envs/experts)")
    parser.add_argument("--overwrite", action="store_true")
    parser.add_argument("--evaluate", action="store_true", help="only re-evaluate the shipped expert")
    args = parser.parse_args(argv)
    pin_to_core(available_cores()[0])  # One core per process; see jaxdeconf.platform.pin_to_core.
    if args.evaluate:
        return evaluate_shipped(args.env)
    weights, _ = expert_paths(args.env, args.out)
    if weights.exists() and not args.overwrite:
        print(f"error: expert {weights} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    from brax.training.agents.ppo import train as ppo  # After jaxdeconf.brax_experts (its jax shim).

    env, params = make(args.env)
    reward_fn = ant_progress_reward(env, params) if args.env == "ant_goal" and args.reward == "progress" else None
    view = ExpertView(env, params, reward_fn)
    policy_layers = tuple(int(x) for x in args.policy_layers.split(","))
    value_layers = tuple(int(x) for x in args.value_layers.split(","))
    meta = {"kind": "brax_ppo", "env": env.name, "obs_size": view.observation_size, "action_size": view.action_size,
            "policy_layers": list(policy_layers), "value_layers": list(value_layers)}
    work = args.work or Path("results/experts") / env.name
    work.mkdir(parents=True, exist_ok=True)
    snapshot = work / "snapshot.msgpack"
    restore = None
    if args.resume and snapshot.exists():
        full = json.loads((work / "snapshot.json").read_text())
        restore = flax.serialization.from_bytes(policy_template(meta, value=True), snapshot.read_bytes())
        print(f"resuming from {snapshot} ({full['steps']:,} steps done)", flush=True)
    ppo_config = {"num_timesteps": int(args.steps), "num_envs": args.num_envs, "batch_size": args.batch_size,
                  "num_minibatches": args.minibatches, "num_updates_per_batch": args.updates_per_batch,
                  "unroll_length": args.unroll, "learning_rate": args.lr, "entropy_cost": args.entropy,
                  "discounting": args.discount, "reward_scaling": args.reward_scaling,
                  "episode_length": env.horizon(params), "normalize_observations": True,
                  "num_evals": args.evals, "num_eval_envs": 32, "seed": args.seed}
    start = time.time()

    def progress(step: int, metrics: dict) -> None:
        seconds = time.time() - start
        done = max(step / args.steps, 1e-9)
        print(f"steps {step:>11,}  eval reward {float(metrics.get('eval/episode_reward', np.nan)):10.1f}  "
              f"task return {float(metrics.get('eval/episode_task_reward', np.nan)):10.1f}  "
              f"{seconds:6.0f}s  eta {seconds / done * (1 - done) if step else float('nan'):6.0f}s", flush=True)

    def keep(step: int, make_policy, p) -> None:
        del make_policy  # Unused.
        snapshot.write_bytes(flax.serialization.to_bytes({"normalizer": p[0], "policy": p[1], "value": p[2]}))
        (work / "snapshot.json").write_text(json.dumps({"steps": int(step), "seconds": time.time() - start}))

    _, trained, _ = ppo.train(
        environment=view, wrap_env_fn=wrap_resampling, progress_fn=progress, policy_params_fn=keep,
        network_factory=network_factory(policy_layers, value_layers),
        restore_params=None if restore is None else (restore["normalizer"], restore["policy"], restore["value"]),
        **ppo_config)
    train_seconds = time.time() - start
    policy_params = {"normalizer": trained[0], "policy": trained[1]}
    evaluation = evaluate(env, params, policy_params, meta)
    meta.update({
        "env_params": {"backend": params.backend, "horizon": env.horizon(params)},
        "training_reward": "task" if reward_fn is None else "progress + healthy - 0.5·‖a‖² (see module docstring)",
        "ppo": ppo_config,
        "command": "python experiments/train_brax_expert.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "train_seconds": round(train_seconds, 1),
        "resumed": restore is not None,
        "device": str(jax.devices()[0]),
        "evaluation_100_episodes": evaluation,
    })
    save_expert(env.name, policy_params, meta, args.out, overwrite=args.overwrite)
    print(f"wrote {weights}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
