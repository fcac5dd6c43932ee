"""Does XLA's CPU runtime hang on the default job when a training process may use every core?

Runs the CPU default's two trainings (``bc`` and ``dil`` on the bandit, 10 seeds) side by side, each in its own process
with no core pinning, ``--runs`` times in a row, each under a watchdog. XLA flags come from ``--flags`` (default: none,
XLA's own defaults). A run that outlives ``--timeout`` counts as a hang: every thread's native stack is written with
gdb (when installed) to ``<out>/hang-<run>-<algo>.txt`` before the process is killed.

    python experiments/deadlock_repro.py --runs 20 --set train.iterations=50 --out /tmp/deadlock

Prints one line per run (wall seconds per training, or HANG) and a tally; exit code 1 if any run hung.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

CHILD = """
import pathlib, sys
from jaxdeconf.config import build
from jaxdeconf.train import train_algorithm
algo, seeds, out, *overrides = sys.argv[1:]
config = build("bandit", "cpu", (algo,), int(seeds), dict(o.split("=", 1) for o in overrides))
timing = train_algorithm(config, algo, pathlib.Path(out), progress=False)
print(f"{timing['compile_s']:.1f} {timing['run_s']:.1f}")
"""


def parse_args() -> argparse.Namespace:
    """Flags."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--algos", default="bc,dil")
    p.add_argument("--flags", default="", help="XLA_FLAGS of the training processes (default: none)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE", help="config override")
    p.add_argument("--timeout", type=float, default=900.0, help="seconds before a run counts as hung")
    p.add_argument("--out", default=None, help="folder for stack dumps of hung runs (default: a temporary one)")
    return p.parse_args()


def dump_stacks(pid: int, path: pathlib.Path) -> None:
    """Every thread's native backtrace of ``pid`` into ``path`` (gdb), if gdb is installed."""
    if shutil.which("gdb") is None:
        path.write_text("gdb not installed\n")
        return
    out = subprocess.run(["gdb", "-p", str(pid), "-batch", "-ex", "thread apply all bt 30"],
                         capture_output=True, text=True, timeout=300, check=False)
    path.write_text(out.stdout + out.stderr)


def one_run(args: argparse.Namespace, run: int, out: pathlib.Path) -> dict[str, str]:
    """Start every training unpinned, wait for all under the watchdog; 'compile run' seconds per algo, or HANG."""
    env = {**os.environ, "XLA_FLAGS": args.flags}
    procs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for algo in args.algos.split(","):
            cmd = [sys.executable, "-c", CHILD, algo, str(args.seeds), f"{tmp}/{algo}", *args.set]
            procs[algo] = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        deadline = time.monotonic() + args.timeout
        result = {}
        for algo, proc in procs.items():
            try:
                stdout, _ = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
                result[algo] = stdout.strip() if proc.returncode == 0 else f"exit {proc.returncode}"
            except subprocess.TimeoutExpired:
                dump_stacks(proc.pid, out / f"hang-{run}-{algo}.txt")
                proc.kill()
                proc.communicate()
                result[algo] = "HANG"
    return result


def main() -> int:
    """Run, tally, exit 1 on any hang."""
    args = parse_args()
    out = pathlib.Path(args.out or tempfile.mkdtemp(prefix="deadlock-"))
    out.mkdir(parents=True, exist_ok=True)
    print(f"XLA_FLAGS={args.flags!r}; {args.seeds} seeds; overrides {args.set}; unpinned on "
          f"{len(os.sched_getaffinity(0))} cores; stack dumps in {out}", flush=True)
    hangs = 0
    for run in range(1, args.runs + 1):
        t0 = time.perf_counter()
        result = one_run(args, run, out)
        hangs += any(v == "HANG" for v in result.values())
        shown = ", ".join(f"{a}: {v}" for a, v in result.items())
        print(f"run {run:2d}: {time.perf_counter() - t0:6.1f} s wall ({shown}; compile/run s)", flush=True)
    print(f"{hangs} of {args.runs} runs hung")
    return 1 if hangs else 0


if __name__ == "__main__":
    sys.exit(main())
