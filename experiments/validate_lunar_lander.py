"""Our JAX LunarLander against gymnasium's LunarLander-v3 (Box2D) under the same controller.

``python experiments/validate_lunar_lander.py [--episodes 500] [--out results/lunar_lander-validation]``

Both envs are driven by gymnasium's own heuristic controller (``gymnasium.envs.box2d.lunar_lander.heuristic``; ours is
a line-for-line JAX port, tested equal), with no action noise, the identity permutation and the same 500-step limit.
The table compares landing rate (terminated at rest, +100), crash rate (hull contact or out of view, -100), return and
episode length. They are different engines with different random terrains, so the comparison is distributional.
Writes ``validation.md`` and ``validation.json`` to ``--out`` (an existing folder's files are replaced only with
``--overwrite``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxdeconf.envs import make
from jaxdeconf.envs.lunar_lander import heuristic

from jaxdeconf.platform import available_cores, pin_to_core

HORIZON = 500


def run_jax(episodes: int, seed: int, random_actions: bool = False) -> dict[str, np.ndarray]:
    """Returns, lengths and outcomes of ``episodes`` episodes of our env (noise 0, identity) under the heuristic, or
    under uniformly random actions."""
    env, params = make("lunar_lander", noise=0.0, horizon=HORIZON)

    def one(key: jax.Array):
        k_reset, k_run = jax.random.split(key)
        state, obs = env.reset(k_reset, params)
        state = state.replace(theta=jnp.zeros((), jnp.int32))

        def body(carry, k):
            state, s, ret, alive, length = carry
            k_act, k_step = jax.random.split(k)
            action = jax.random.randint(k_act, (), 0, 4) if random_actions else heuristic(s)
            state, res = env.step(k_step, state, action, params)
            return (state, res.obs.imitator, ret + res.reward, alive & ~res.done, length + alive), (
                res.extras["landed"], res.extras["crashed"])

        init = (state, obs.imitator, jnp.zeros(()), jnp.ones((), jnp.bool_), jnp.zeros((), jnp.int32))
        (_, _, ret, _, length), (landed, crashed) = jax.lax.scan(body, init, jax.random.split(k_run, HORIZON))
        return ret, length, landed.sum(), crashed.sum()

    ret, length, landed, crashed = jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(seed), episodes))
    return {"return": np.asarray(ret), "length": np.asarray(length), "landed": np.asarray(landed) > 0,
            "crashed": np.asarray(crashed) > 0}


def run_gymnasium(episodes: int, seed: int, random_actions: bool = False) -> dict[str, np.ndarray]:
    """The same statistics for gymnasium's LunarLander-v3 under its heuristic (or random actions)."""
    import gymnasium as gym
    from gymnasium.envs.box2d.lunar_lander import heuristic as gym_heuristic

    env = gym.make("LunarLander-v3", max_episode_steps=HORIZON)
    rng = np.random.default_rng(seed)
    out = {"return": [], "length": [], "landed": [], "crashed": []}
    for episode in range(episodes):
        s, _ = env.reset(seed=seed + episode)
        total, steps = 0.0, 0
        while True:
            action = int(rng.integers(4)) if random_actions else gym_heuristic(env, s)
            s, r, terminated, truncated, _ = env.step(action)
            total += float(r)
            steps += 1
            if terminated or truncated:
                break
        out["return"].append(total)
        out["length"].append(steps)
        out["landed"].append(terminated and r == 100)
        out["crashed"].append(terminated and r == -100)
    return {k: np.asarray(v) for k, v in out.items()}


def summarize(stats: dict[str, np.ndarray]) -> dict[str, float | None]:
    """Rates, return mean/std/quantiles and mean length (of the landed episodes: None when none landed, which JSON
    writes as null)."""
    ret = stats["return"]
    return {
        "episodes": int(ret.size),
        "landing_rate": float(stats["landed"].mean()),
        "crash_rate": float(stats["crashed"].mean()),
        "timeout_rate": float(1 - stats["landed"].mean() - stats["crashed"].mean()),
        "return_mean": float(ret.mean()),
        "return_std": float(ret.std()),
        "return_q05": float(np.quantile(ret, 0.05)),
        "return_median": float(np.median(ret)),
        "return_q95": float(np.quantile(ret, 0.95)),
        "length_mean": float(stats["length"].mean()),
        "length_landed_mean": float(stats["length"][stats["landed"]].mean()) if stats["landed"].any() else None,
    }


def table(rows: dict[str, dict[str, float | None]]) -> str:
    """Markdown table of the summaries."""
    lines = ["| env | episodes | landed | crashed | timed out | return mean ± std | return 5% / 50% / 95% "
             "| mean length | mean length (landed) |", "|---|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(
            f"| {name} | {r['episodes']} | {r['landing_rate']:.3f} | {r['crash_rate']:.3f} | {r['timeout_rate']:.3f} "
            f"| {r['return_mean']:.1f} ± {r['return_std']:.1f} | {r['return_q05']:.0f} / {r['return_median']:.0f} / "
            f"{r['return_q95']:.0f} | {r['length_mean']:.1f} | {_length(r['length_landed_mean'])} |")
    return "\n".join(lines)


def _length(value: float | None) -> str:
    """A mean length for the table; None when no episode landed."""
    return "none landed" if value is None else f"{value:.1f}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("results/lunar_lander-validation"))
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.episodes < 1:
        print(f"error: --episodes={args.episodes} is not allowed: need a positive integer", file=sys.stderr)
        return 2
    if (args.out / "validation.json").exists() and not args.overwrite:
        print(f"error: {args.out / 'validation.json'} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    pin_to_core(available_cores()[0])  # See jaxdeconf.platform.pin_to_core.
    rows = {}
    for controller, random_actions in (("heuristic", False), ("random actions", True)):
        rows[f"ours (JAX), {controller}"] = summarize(run_jax(args.episodes, args.seed, random_actions))
        rows[f"gymnasium LunarLander-v3 (Box2D), {controller}"] = summarize(
            run_gymnasium(args.episodes, args.seed, random_actions))
    text = (f"Same controller in both (gymnasium's heuristic, or uniformly random actions), no action noise, identity "
            f"permutation, {HORIZON}-step limit; measured by experiments/validate_lunar_lander.py.\n\n"
            + table(rows) + "\n")
    print(text)
    data = json.dumps(rows, indent=2, allow_nan=False) + "\n"  # Before writing anything: it refuses NaN.
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "validation.md").write_text(text)
    (args.out / "validation.json").write_text(data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
