"""``make bench``: the default job's wall time as ``make run`` starts it, whole, in each way its two algorithms can
share the machine (section ``e2e``: pinned side by side, unpinned, in turn over 2 host devices); seconds per
iteration at the reference code's bandit configuration, seed scaling; LunarLander env steps per second against
gymnasium's Box2D; the Brax envs' steps per second and the confounding layer's overhead. Prints a table; numbers are
measured on the machine it runs on.

Also seconds per iteration versus seeds on one device and over 2 host devices, and the GRU's achieved GFLOP/s against
a plain matmul's (``bench_scale.py``), and seconds per iteration of every algorithm at each env's CPU preset (section
``algos``), and milliseconds per part of the default job's iteration (section ``profile``). Sections can be chosen:
``make bench SECTIONS="seeds e2e efficiency profile cells layouts reference batch algos lunar brax"`` (the default
is all eleven; ``cells`` times model.cell=gru against mingru, ``layouts`` the GRU's sequence in three layouts);
``python experiments/bench.py e2e --e2e-iterations 50`` compares the layouts on a shorter run.
"""

from __future__ import annotations

import argparse
import csv
import pathlib
import subprocess
import sys
import tempfile
import time

import bench_scale
import jax

from jaxdeconf.algos import names
from jaxdeconf.platform import available_cores, pin_to_core
from jaxdeconf.resolve import build
from jaxdeconf.train import build_algorithm, compiled_chunk, seed_keys

# The authors' PyTorch code on this same 2-core machine (from the issue): seconds per iteration.
TORCH_S_PER_ITER = {"dil": 17.0, "bc": 165.0}


def time_iterations(
    algo_name: str, preset: str, seeds: int, iters: int, overrides: dict, env: str = "bandit"
) -> tuple[float, float]:
    """(compile seconds, run seconds per iteration) of a chunk of ``iters`` iterations over ``seeds`` seeds."""
    config = build(env, preset, (algo_name,), seeds, {"train.warmup": 0, "train.chunk": iters, **overrides})
    algo = build_algorithm(config, algo_name)
    states = jax.jit(jax.vmap(algo.init))(seed_keys(config))
    jax.block_until_ready(states)
    t0 = time.perf_counter()
    compiled = compiled_chunk(algo, iters).lower(states).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(states))
    return compile_s, (time.perf_counter() - t0) / iters


# How the default job's two algorithms can share the machine: the command-line flags of each layout.
LAYOUTS = {
    "side by side, unpinned (the default)": [],
    "side by side, each pinned to its own core": ["--pin"],
    "one process, the algorithms in turn, seeds over 2 host devices": ["--jobs", "1", "--host-devices", "2"],
}


def default_job(cores: list[int], iterations: int) -> None:
    """The default job as ``make run`` starts it (``python -m jaxdeconf.run --env bandit --algo bc,dil --seeds 10``),
    timed whole (start-up, compiles, training, references, summary and figures) in each layout of ``LAYOUTS``, one
    after another; ``iterations`` > 0 shortens every layout's run alike."""
    extra = ["--set", f"train.iterations={iterations}"] if iterations else []
    print(f"\n## The default job, whole: python -m jaxdeconf.run --env bandit --algo bc,dil --seeds 10 "
          f"{' '.join(extra)}")
    print(f"##  on the {len(cores)} cores available, each layout in turn")
    for name, flags in LAYOUTS.items():
        if "--host-devices" in flags and len(cores) < 2:
            continue
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, "-m", "jaxdeconf.run", "--seeds", "10", "--out", out, "--quiet",
                                   *extra, *flags], capture_output=True, text=True, check=False)
            wall = time.perf_counter() - t0
            summary = pathlib.Path(out, "summary.csv")
            rows = {r["algo"]: r for r in csv.DictReader(summary.read_text().splitlines())} if summary.exists() else {}
        result = ", ".join(f"{a} {float(r['return_mean']):.2f}" for a, r in rows.items())
        print(f"{name}: wall {wall:.1f} s, exit {proc.returncode}; {result}", flush=True)
        for line in proc.stdout.splitlines():
            if "compile" in line and "run" in line:
                print("  " + line)


def main(sections: list[str], e2e_iterations: int = 0) -> None:
    """Run the named measurements (default: all) and print the table."""
    cores = available_cores()
    if "seeds" in sections:  # Subprocesses, before this process pins itself: a 2-device process gets both cores.
        bench_scale.seeds_and_devices()
    if "e2e" in sections:  # Subprocesses too: the CLI gets every core.
        default_job(cores, e2e_iterations)

    pin_to_core(cores[0])  # The in-process sections measure one core.
    print(f"\njax {jax.__version__} on {jax.devices()[0].platform}; {len(cores)} cores available, "
          "in-process timings on one core")

    if "reference" in sections:
        print("\n## Reference code's bandit configuration (batch 32, 100 policy steps, 1 encoder step per iteration;")
        print("##  GRU 500 for dil, 1000 for bc; width 128 / 250), 1 seed")
        for name, over in (("dil", {"model.width": 128}), ("bc", {"model.width": 250})):
            c, s = time_iterations(name, "paper", 1, 2, over)
            print(f"{name:4s}: {s:7.2f} s/iteration (compile {c:.1f} s); PyTorch reference "
                  f"{TORCH_S_PER_ITER[name]:.0f} s on 2 cores -> {TORCH_S_PER_ITER[name] / s:.1f}x faster per seed")

    if "efficiency" in sections:
        bench_scale.efficiency()
    if "profile" in sections:
        bench_scale.profile()
    if "cells" in sections:
        bench_scale.cells()
    if "layouts" in sections:
        bench_scale.layouts()

    if "batch" in sections:
        batch_sizes()

    if "algos" in sections:
        print("\n## Every algorithm at each env's CPU preset: seconds per iteration (after warm-up), 1 seed")
        for env in ("bandit", "lunar_lander", "half_cheetah", "ant_goal"):
            for name in names():
                c, s = time_iterations(name, "cpu", 1, 2, {}, env=env)
                print(f"{env:13s} {name:7s}: {s:7.3f} s/iteration (compile {c:.1f} s)", flush=True)

    if "lunar" in sections:
        lunar_lander_speed()
    if "brax" in sections:
        brax_speed()


def batch_sizes() -> None:
    """Milliseconds per gradient step of bc (policy steps) and dil (ELBO steps) at the bandit CPU preset by batch size,
    10 seeds vmapped, one core: whether a step is bound by its overhead (flat in the batch) or its arithmetic."""
    print("\n## Gradient steps by batch size: bandit CPU preset, 10 seeds vmapped, one core, 8 steps per iteration")
    for batch in (32, 128, 256, 512):
        over = {"train.batch_size": batch, "train.buffer_episodes": batch, "train.episodes_per_iter": batch,
                "train.policy_steps": 8, "train.encoder_steps": 8, "train.eval_episodes": 16}
        cells = []
        for name in ("bc", "dil"):
            _, s = time_iterations(name, "cpu", 10, 2, over)
            per_episode = s * 1e6 / (10 * 8 * batch)  # Per seed, step and episode of the batch.
            cells.append(f"{name} {s * 1e3:7.1f} ms/iteration, {per_episode:5.0f} us per seed, step and episode")
        print(f"batch {batch:3d}: " + "; ".join(cells), flush=True)


def lunar_lander_speed() -> None:
    """Env steps per second of our JAX LunarLander against gymnasium's vectorised Box2D one, random actions."""
    import os

    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    import gymnasium as gym
    import numpy as np
    from jaxdeconf.envs import make

    print("\n## lunar_lander: env steps per second, uniformly random actions, one core")
    print("##  ours: jit(scan(vmap(step))) over 500 steps (terminated episodes stay frozen but are still stepped);")
    print("##  gymnasium: LunarLander-v3 vectorised with make_vec(vectorization_mode='sync'), autoreset")
    env, params = make("lunar_lander")
    steps = 500

    def run(key, n):
        state, _ = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, n), params)

        def body(state, k):
            k_a, k_s = jax.random.split(k)
            action = jax.random.randint(k_a, (n,), 0, 4)
            state, res = jax.vmap(env.step, in_axes=(0, 0, 0, None))(jax.random.split(k_s, n), state, action, params)
            return state, res.reward

        return jax.lax.scan(body, state, jax.random.split(key, steps))[1].sum()

    for n in (16, 128, 1024):
        t0 = time.perf_counter()
        fn = jax.jit(run, static_argnums=1).lower(jax.random.key(0), n).compile()
        compile_s = time.perf_counter() - t0
        jax.block_until_ready(fn(jax.random.key(1)))
        t0 = time.perf_counter()
        jax.block_until_ready(fn(jax.random.key(2)))
        ours = n * steps / (time.perf_counter() - t0)
        vec = gym.make_vec("LunarLander-v3", num_envs=n, vectorization_mode="sync")
        vec.reset(seed=0)
        rng = np.random.default_rng(0)
        calls = max(20, 20000 // n)
        t0 = time.perf_counter()
        for _ in range(calls):
            vec.step(rng.integers(0, 4, size=n))
        theirs = n * calls / (time.perf_counter() - t0)
        vec.close()
        print(f"batch {n:5d}: ours {ours:10,.0f} steps/s (compile {compile_s:.1f} s); gymnasium {theirs:9,.0f} steps/s "
              f"-> {ours / theirs:.1f}x")


def brax_speed() -> None:
    """half_cheetah and ant_goal: env steps/s at batch 16, 128, 1024, compile time, and the confounding layer's
    overhead over the raw Brax step; each measurement in its own process with a time limit (XLA on this CPU was seen
    to hang stepping MJX at batch 1024)."""
    print("\n## Brax/MJX envs: env steps per second, uniformly random actions in [-1, 1], one core, 100 steps")
    print("##  ours = the confounded env's step (θ, cue, reward, three views); raw = the same Brax env's own step")
    for name in ("half_cheetah", "ant_goal"):
        for n in (16, 128, 1024):
            try:
                proc = subprocess.run([sys.executable, __file__, "_brax_one", name, str(n)], capture_output=True,
                                      text=True, timeout=900, check=False)
                lines = [line for line in proc.stdout.splitlines() if line.startswith(name)]
                print(lines[-1] if lines else f"{name} batch {n}: failed (exit {proc.returncode}) "
                      f"{proc.stderr.strip().splitlines()[-1:]}", flush=True)
            except subprocess.TimeoutExpired:
                print(f"{name} batch {n:5d}: no result within 900 s (XLA hang at this batch on this CPU)", flush=True)


def _brax_one(name: str, n: int) -> None:
    """One row of ``brax_speed``: compile and time ours and the raw Brax step at batch ``n``."""
    from jaxdeconf.envs import make

    pin_to_core(available_cores()[0])
    env, params = make(name)
    raw = env.brax_env(params)
    size, steps = env.action_space(params).n, 100

    def ours(key):
        state, _ = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, n), params)

        def body(state, k):
            k_a, k_s = jax.random.split(k)
            action = jax.random.uniform(k_a, (n, size), minval=-1.0, maxval=1.0)
            state, res = jax.vmap(env.step, in_axes=(0, 0, 0, None))(jax.random.split(k_s, n), state, action, params)
            return state, res.reward

        return jax.lax.scan(body, state, jax.random.split(key, steps))[1].sum()

    def brax_only(key):
        state = jax.vmap(raw.reset)(jax.random.split(key, n))

        def body(state, k):
            k_a, _ = jax.random.split(k)
            action = jax.random.uniform(k_a, (n, size), minval=-1.0, maxval=1.0)
            state = jax.vmap(raw.step)(state, action)
            return state, state.reward

        return jax.lax.scan(body, state, jax.random.split(key, steps))[1].sum()

    programs, compiles, best = {}, {}, {}
    for label, fn in (("ours", ours), ("raw", brax_only)):
        t0 = time.perf_counter()
        programs[label] = jax.jit(fn).lower(jax.random.key(0)).compile()
        compiles[label] = time.perf_counter() - t0
        jax.block_until_ready(programs[label](jax.random.key(1)))
        best[label] = float("inf")
    for rep in range(5):  # Alternate the two programs, keep each one's best: drift on a shared machine cancels.
        for label, compiled in programs.items():
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(jax.random.key(2 + rep)))
            best[label] = min(best[label], time.perf_counter() - t0)
    rates = {label: n * steps / seconds for label, seconds in best.items()}
    print(f"{name} batch {n:5d}: ours {rates['ours']:9,.0f} steps/s (compile {compiles['ours']:.0f} s); raw Brax "
          f"{rates['raw']:9,.0f} steps/s (compile {compiles['raw']:.0f} s); confounding overhead "
          f"{100 * (rates['raw'] / rates['ours'] - 1):+.1f}%", flush=True)


SECTIONS = ("seeds", "e2e", "efficiency", "profile", "cells", "layouts", "reference", "batch", "algos", "lunar",
            "brax")

def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The sections to run (all when none is named) and the e2e length; exit code 2 with one line for bad input."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "),
                                     epilog=f"sections: {', '.join(SECTIONS)}")
    parser.add_argument("sections", nargs="*", help="sections to run (default: all)")
    parser.add_argument("--e2e-iterations", type=int, default=0,
                        help="e2e: train every layout this many iterations (default: the preset's 300)")
    args = parser.parse_args(argv)
    args.sections = args.sections or list(SECTIONS)
    unknown = [name for name in args.sections if name not in SECTIONS]
    if unknown:
        parser.exit(2, f"error: unknown bench section {unknown[0]!r}; allowed: {', '.join(SECTIONS)}\n")
    if args.e2e_iterations < 0:
        parser.exit(2, f"error: --e2e-iterations={args.e2e_iterations} is not allowed: need 0 (the preset's) or "
                       "a positive integer\n")
    return args


if __name__ == "__main__":
    if sys.argv[1:2] == ["_brax_one"]:  # One Brax env's measurement in a fresh process (see ``brax``).
        _brax_one(sys.argv[2], int(sys.argv[3]))
        sys.exit(0)
    args = parse_args()
    main(args.sections, args.e2e_iterations)
