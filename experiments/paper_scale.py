"""The ``paper`` presets, ready for the accelerator they were written for.

``python experiments/paper_scale.py check`` compiles and runs one iteration of every algorithm at each env's
``paper`` preset (1 seed, one gradient step of each kind, so a CPU gets through it; a step's memory does not depend on
how many steps an iteration takes) and prints, per program, the config's memory estimate (``jaxdeconf.memory``: its
buffers, parameters and working set) beside XLA's own account of the compiled chunk (arguments, outputs and temporary
buffers), both scaled to the preset's seeds, against an 80 GB H100: a program fits when the estimate is at least XLA's
account and under the 75% of the H100's memory that JAX's allocator may use by default.

``python experiments/paper_scale.py time`` (on a GPU) trains the MDP study at paper scale, the three MDP parts of
``python -m jaxdeconf.reproduce --scale paper``, part by part, and prints each part's wall time.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

# What the CLI's memory check reads on an H100 (80 GB, 79.6 GiB usable): the allocator's limit, JAX's default 75%.
H100_LIMIT = 0.75 * 79.6 * 2**30
ENVS = ("bandit", "lunar_lander", "half_cheetah", "ant_goal")
MDPS = ("lunar_lander", "half_cheetah", "ant_goal")
ONE_ITERATION = {"train.iterations": 1, "train.warmup": 0, "train.chunk": 1, "train.policy_steps": 1,
                 "train.encoder_steps": 1}


def one_iteration(env: str, algo: str, seeds: int) -> dict[str, float]:
    """Compile and run one iteration of ``algo`` at ``env``'s paper preset on 1 seed: seconds and bytes."""
    import jax
    from jaxdeconf.envs import make

    from jaxdeconf.memory import estimate
    from jaxdeconf.resolve import build
    from jaxdeconf.train import build_algorithm, compiled_chunk, seed_keys

    config = build(env, "paper", (algo,), 1, ONE_ITERATION)
    algo_obj = build_algorithm(config, algo)
    t0 = time.perf_counter()
    states = jax.block_until_ready(jax.jit(jax.vmap(algo_obj.init))(seed_keys(config)))
    compiled = compiled_chunk(algo_obj, 1).lower(states).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(states))
    memory = compiled.memory_analysis()
    xla = memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes
    env_obj, params = make(config.env, **config.env_params)
    est = estimate(config, algo, env_obj, params)
    return {"compile_s": compile_s, "run_s": time.perf_counter() - t0, "estimate": est.total * seeds,
            "buffers": est.buffers * seeds, "xla": xla * seeds}


def check(seeds: int, envs: list[str], algos: list[str]) -> int:
    """Every algorithm at every paper preset: one iteration each, with memory against an H100; exit 1 when one fails
    or does not fit."""
    print(f"## paper presets, one iteration at 1 seed; memory scaled to {seeds} seeds against an 80 GB H100's "
          f"{H100_LIMIT / 1e9:.1f} GB (JAX's default 75%)")
    print("| env | algo | compile s | iteration s | estimate GB (buffers) | XLA chunk GB | fits |")
    print("|---|---|---|---|---|---|---|")
    failed = 0
    for env in envs:
        for algo in algos:
            try:
                r = one_iteration(env, algo, seeds)
            except Exception as err:  # A failure is a finding: report it and go on with the others.
                print(f"| {env} | {algo} | failed: {str(err).splitlines()[0][:120]} | | | | |", flush=True)
                failed += 1
                continue
            fits = ("no: estimate below XLA's" if r["estimate"] < r["xla"]
                    else "yes" if r["estimate"] < H100_LIMIT else "no")
            failed += fits != "yes"
            print(f"| {env} | {algo} | {r['compile_s']:.1f} | {r['run_s']:.1f} | {r['estimate'] / 1e9:.2f} "
                  f"({r['buffers'] / 1e9:.2f}) | {r['xla'] / 1e9:.2f} | {fits} |", flush=True)
    return 1 if failed else 0


def time_study(out: str) -> int:
    """The MDP study at paper scale, one reproduce part after another, each part's wall time printed."""
    for part in MDPS:
        t0 = time.perf_counter()
        code = subprocess.call([sys.executable, "-m", "jaxdeconf.reproduce", "--scale", "paper", "--out", out,
                                "--only", part])
        print(f"{part}: wall {time.perf_counter() - t0:.0f} s, exit {code}", flush=True)
        if code:
            return code
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse the mode and run it."""
    from jaxdeconf.algos import names

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=("check", "time"), help="check: compile every paper preset on this machine; "
                        "time: train the MDP study at paper scale (a GPU)")
    parser.add_argument("--seeds", type=int, default=5, help="check: seeds the memory is scaled to (default: 5)")
    parser.add_argument("--algo", default="all", help="check: comma-separated algorithms (default: all)")
    parser.add_argument("--env", default=",".join(ENVS), help="check: comma-separated envs (default: all four)")
    parser.add_argument("--out", default="report-paper", help="time: the report folder (default: report-paper)")
    args = parser.parse_args(argv)
    if args.seeds < 1:
        parser.exit(2, f"error: --seeds={args.seeds} is not allowed: need a positive integer\n")
    algos = list(names()) if args.algo == "all" else args.algo.split(",")
    unknown = [a for a in algos if a not in names()]
    if unknown:
        parser.exit(2, f"error: unknown algorithm {unknown[0]!r}; allowed: {', '.join(names())}\n")
    envs = args.env.split(",")
    if any(e not in ENVS for e in envs):
        parser.exit(2, f"error: unknown env {next(e for e in envs if e not in ENVS)!r}; allowed: {', '.join(ENVS)}\n")
    return check(args.seeds, envs, algos) if args.mode == "check" else time_study(args.out)


if __name__ == "__main__":
    sys.exit(main())
