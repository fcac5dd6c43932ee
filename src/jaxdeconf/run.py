"""Command line: ``python -m jaxdeconf.run --env bandit --algo bc,dil --seeds 10 [--preset cpu] [--set k=v ...]``."""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time
from typing import Any

from jaxdeconf import config as cfg
from jaxdeconf.config import ConfigError


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """Command-line flags."""
    p = argparse.ArgumentParser(prog="python -m jaxdeconf.run", description=__doc__)
    p.add_argument("--env", default="bandit", help="environment name (default: bandit)")
    p.add_argument("--algo", default="bc,dil", help=f"comma-separated algorithms from {', '.join(cfg.ALGOS)}")
    p.add_argument("--seeds", type=int, default=10, help="number of seeds, trained together in one program")
    p.add_argument("--preset", default="cpu", help="preset of the environment (cpu, paper)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a config field, e.g. train.iterations=100, model.gru=256, env.p=0.7")
    p.add_argument("--out", default=None, help="results folder (default: results/<env>-<preset>)")
    p.add_argument("--overwrite", action="store_true", help="delete an existing results folder and start over")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--jobs", type=int, default=0,
                   help="algorithms trained at once, each in its own process pinned to its own CPU core "
                        "(default: one per algorithm, at most one per available core)")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # Internal: train one algorithm of --out.
    p.add_argument("--core", type=int, default=None, help=argparse.SUPPRESS)  # Internal: the worker's core.
    p.add_argument("--position", type=int, default=0, help=argparse.SUPPRESS)  # Internal: its progress-bar row.
    return p.parse_args(argv)


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``FIELD=VALUE`` strings to a dict."""
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ConfigError(f"--set {item!r} is not of the form FIELD=VALUE")
        out[name.strip()] = value.strip()
    return out


def prepare_folder(folder: pathlib.Path, config: cfg.Config, overwrite: bool) -> None:
    """Create the results folder, or check an existing one holds the same config (never clobber results)."""
    config_path = folder / "config.json"
    if folder.exists() and overwrite:
        shutil.rmtree(folder)
    if config_path.exists():
        old = config_path.read_text()
        if old.strip() != cfg.dumps(config).strip():
            old_cfg = json.loads(old)
            diff = _first_difference(old_cfg, config.to_dict())
            raise ConfigError(
                f"results folder {folder} holds a different config ({diff}); use another --out, or --overwrite"
            )
    elif folder.exists() and any(folder.iterdir()):
        raise ConfigError(f"results folder {folder} is not empty and has no config.json; use another --out")
    folder.mkdir(parents=True, exist_ok=True)
    config_path.write_text(cfg.dumps(config) + "\n")


def _first_difference(old: Any, new: Any, path: str = "") -> str:
    """Describe the first differing field of two nested dicts."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            if old.get(key) != new.get(key):
                return _first_difference(old.get(key), new.get(key), f"{path}.{key}" if path else key)
    return f"{path}: {old!r} there, {new!r} now"


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (2 for bad input)."""
    args = parse_args(argv)
    if args.worker is not None:
        return _worker(args)
    try:
        if args.jobs < 0:
            raise ConfigError(f"--jobs={args.jobs} is not allowed: need 0 (automatic) or a positive integer")
        algos = tuple(a.strip() for a in args.algo.split(",") if a.strip())
        config = cfg.build(args.env, args.preset, algos, args.seeds, parse_overrides(args.set))
        from jaxdeconf.envs import make

        try:
            make(config.env, **config.env_params)
        except ValueError as err:
            raise ConfigError(str(err)) from None
        folder = pathlib.Path(args.out or f"results/{config.env.rpartition(':')[2]}-{args.preset}")
        prepare_folder(folder, config, args.overwrite)
        return _run(config, folder, quiet=args.quiet, jobs=args.jobs)
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


def pin_to_core(core: int) -> None:
    """Run this process on one CPU core (Linux; elsewhere a no-op). Must happen before JAX starts its backend.

    XLA's CPU runtime (jaxlib 0.10.2) deadlocked here, intermittently, running the seed-vmapped programs with its
    threads spread over both cores of a 2-core machine; every run pinned to one core finished. The programs are
    small-matrix and sequential (scans over time), so one core per algorithm loses little, and the CLI uses the
    other cores by training the algorithms side by side.
    """
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {core})


# The cores this process was allowed when it started (before any pinning of its own).
_CORES = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [0]


def available_cores() -> list[int]:
    """Cores this process was started with (a user's ``taskset`` is respected)."""
    return list(_CORES)


def _worker(args: argparse.Namespace) -> int:
    """Internal entry point: train one algorithm of an already prepared results folder."""
    if args.core is not None:
        pin_to_core(args.core)
    import logging

    from jaxdeconf.train import train_algorithm

    # Orbax logs each damaged file through absl before raising; the one-line error below says it for the user.
    logging.getLogger("absl").setLevel(logging.CRITICAL)

    folder = pathlib.Path(args.out)
    config = cfg.from_dict(json.loads((folder / "config.json").read_text()))
    try:
        timing = train_algorithm(config, args.worker, folder / args.worker, progress=not args.quiet,
                                 position=args.position)
    except ConfigError as err:  # E.g. an unreadable checkpoint: one line, and the parent adds none.
        print(f"error: {err}", file=sys.stderr, flush=True)
        return 2
    print(f"[{args.worker}] compile {timing['compile_s']:.1f} s, run {timing['run_s']:.1f} s", flush=True)
    return 0


def _train_workers(folder: pathlib.Path, queue: list[str], cores: list[int], jobs: int, quiet: bool) -> dict[str, int]:
    """Train the queued algorithms in worker processes, ``jobs`` at a time, each pinned to its slot's core; a freed
    slot takes the next algorithm at once. Returns each algorithm's exit code."""
    codes: dict[str, int] = {}
    running: dict[int, tuple[str, subprocess.Popen]] = {}  # Slot (a core and a progress-bar row) -> worker.
    queue = list(queue)
    while queue or running:
        for slot in range(jobs):
            if slot not in running and queue:
                algo = queue.pop(0)
                cmd = [sys.executable, "-m", "jaxdeconf.run", "--worker", algo, "--out", str(folder),
                       "--core", str(cores[slot % len(cores)]), "--position", str(slot)]
                running[slot] = (algo, subprocess.Popen([*cmd, "--quiet"] if quiet else cmd))
        finished = [slot for slot, (_, proc) in running.items() if proc.poll() is not None]
        if not finished:
            time.sleep(0.5)
        for slot in finished:
            algo, proc = running.pop(slot)
            codes[algo] = proc.returncode
    return codes


def _run(config: cfg.Config, folder: pathlib.Path, quiet: bool, jobs: int = 0) -> int:
    """Train every algorithm not yet finished (side by side, one core each), then write references, summary and
    figures."""
    from jaxdeconf import results

    cores = available_cores()
    pin_to_core(cores[0])  # The exact references below run here, in this process.
    refs = _references(config, folder)
    queue = []
    for algo in config.algos:
        if (folder / algo / "DONE").exists():
            print(f"[{algo}] already finished in {folder}; kept as is (use --overwrite to retrain)")
        else:
            queue.append(algo)
    codes = _train_workers(folder, queue, cores, jobs or len(cores), quiet)
    if 2 in codes.values():
        return 2  # A worker already printed its one-line error.
    failed = [f"{algo} (exit {code})" for algo, code in codes.items() if code != 0]
    if failed:
        print(f"error: training failed for {', '.join(failed)}; its checkpoints are kept, so running the same "
              "command again resumes it", file=sys.stderr)
        return 1
    table = results.summarize(folder, config, refs)
    print(results.write_summary(folder, table, refs))
    for path in results.plot(folder, config, refs):
        print(f"wrote {path}")
    return 0


def _references(config: cfg.Config, folder: pathlib.Path) -> dict[str, Any] | None:
    """Exact bandit references (computed once per folder and cached in references.json)."""
    if config.env != "bandit":
        return None
    import numpy as np

    path = folder / "references.json"
    if path.exists():
        return {k: np.asarray(v) for k, v in json.loads(path.read_text()).items()}
    import jax

    from jaxdeconf.envs import make
    from jaxdeconf.references import reference_curves

    _, params = make(config.env, **config.env_params)
    refs = jax.jit(reference_curves, static_argnums=(1, 2))(jax.random.key(12345), params, 20000)
    refs = {k: np.asarray(v) for k, v in refs.items()}
    path.write_text(json.dumps({k: v.tolist() for k, v in refs.items()}) + "\n")
    return refs


if __name__ == "__main__":
    sys.exit(main())
