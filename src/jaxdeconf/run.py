"""Command line: ``python -m jaxdeconf.run --env bandit --algo bc,dil --seeds 10 [--preset cpu] [--set k=v ...]``.

The entry point, wiring the pieces: the flags (cli.py), the results folder's rules (folders.py), the processes that
train (workers.py) and the process set-up (platform.py); then the summary and figures (results.py).
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Any

from jaxdeconf import algos, resolve
from jaxdeconf import config as cfg
from jaxdeconf.cli import parse_args, parse_overrides
from jaxdeconf.errors import ConfigError
from jaxdeconf.files import writable
from jaxdeconf.folders import cached_references, check_writable, finished, prepare_folder, typed_env_params
from jaxdeconf.processes import Stopped, signals_raise
from jaxdeconf.workers import join_processes, run_worker, train_in_turn, train_workers


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (2 for bad input, 128 + the signal number when stopped by one)."""
    from jaxdeconf import platform

    platform.share_accelerator()
    try:
        args = parse_args(argv)
        if args.worker is not None:
            return run_worker(args)

        set_up = platform.distributed_args(args.coordinator, args.num_processes, args.process_id)
        if set_up is not None:
            return _distributed(args, set_up)
        with signals_raise():
            config, folder, jobs = _setup(args)
            lock = prepare_folder(folder, config, args.overwrite)
            try:
                return _run(config, folder, quiet=args.quiet, jobs=jobs, host_devices=args.host_devices, pin=args.pin)
            finally:
                lock.release()
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except Stopped as stop:
        print(f"error: stopped by {stop.name}; finished chunks are checkpointed: run the same command again to "
              "resume", file=sys.stderr)
        return 128 + stop.signum


def _setup(args: argparse.Namespace) -> tuple[cfg.Config, pathlib.Path, int]:
    """Validate every input (flags, config, env parameters, memory) before anything is written or compiled; the
    config, the results folder and how many algorithms train side by side (``--jobs``, or as many as the cores
    allow and the memory holds)."""
    if args.jobs < 0:
        raise ConfigError(f"--jobs={args.jobs} is not allowed: need 0 (automatic) or a positive integer")
    from jaxdeconf.platform import available_cores, check_host_devices

    check_host_devices(args.host_devices)
    if args.out is not None and not args.out.strip():
        raise ConfigError("--out is empty; give a folder, or leave --out out for results/<env>-<preset>")
    names = algos.names() if args.algo.strip() == "all" else tuple(a.strip() for a in args.algo.split(",") if a.strip())
    config = typed_env_params(resolve.build(args.env, args.preset, names, args.seeds, parse_overrides(args.set)))
    from jaxdeconf.envs import make
    from jaxdeconf.memory import check_fits

    env, params = make(config.env, **config.env_params)
    jobs = check_fits(config, env, params, args.jobs or min(len(config.algos), len(available_cores())),
                      automatic=not args.jobs)
    return config, pathlib.Path(args.out or f"results/{config.env.rpartition(':')[2]}-{args.preset}"), jobs


def _run(config: cfg.Config, folder: pathlib.Path, quiet: bool, jobs: int, host_devices: int = 1,
         pin: bool = False) -> int:
    """Train every algorithm not yet finished (side by side, a process each), then write references, summary and
    figures."""
    check_writable(folder, config.algos)
    queue = [algo for algo in config.algos if not finished(config, folder, algo)]  # Damaged files: before any work.
    refs = cached_references(config, folder)
    codes = train_workers(folder, queue, jobs, quiet, host_devices, pin)
    if 2 in codes.values():
        return 2  # A worker already printed its one-line error.
    failed = [f"{algo} (exit {code})" for algo, code in codes.items() if code != 0]
    if failed:
        print(f"error: training failed for {', '.join(failed)}; its checkpoints are kept, so running the same "
              "command again resumes it", file=sys.stderr)
        return 1
    _report(config, folder, refs)
    return 0


def _distributed(args: argparse.Namespace, set_up: dict[str, Any]) -> int:
    """A run over several processes (hosts): every process joins, validates the same flags and trains every
    algorithm in turn on its devices' share of the seeds; process 0 alone prints and writes the results (the
    results folder must be on a file system all hosts share)."""
    join_processes(args.host_devices, set_up)
    from jaxdeconf.sharding import is_primary, sync

    with signals_raise():
        args.jobs = 1  # One algorithm at a time, over every process's devices: the memory check's count too.
        config, folder, _ = _setup(args)
        lock = prepare_folder(folder, config, args.overwrite) if is_primary() else None
        try:
            sync("prepared")
            refs = cached_references(config, folder) if is_primary() else None
            train_in_turn(config, folder, quiet=args.quiet)
            if is_primary():
                _report(config, folder, refs)
            return 0
        finally:
            if lock is not None:
                lock.release()


def _report(config: cfg.Config, folder: pathlib.Path, refs: dict[str, Any] | None) -> None:
    """Summary table and figures of a trained folder."""
    from jaxdeconf import results

    with writable(folder):
        table = results.summarize(folder, config, refs)
        print(results.write_summary(folder, table, refs))
        for path in results.plot(folder, config, refs):
            print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
