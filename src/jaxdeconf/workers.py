"""The processes that train: one worker process per algorithm (``python -m jaxdeconf.run --worker ALGO``), started by
a scheduler that keeps ``jobs`` of them running, each dying with its parent; and a process of a run spread over
several processes (hosts), which joins the others and trains every algorithm in turn. Stopping them cleanly is
processes.py's."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import pathlib
import signal
import subprocess
import sys
import time
from typing import Any

from jaxdeconf import config as cfg
from jaxdeconf import resolve
from jaxdeconf.errors import ConfigError
from jaxdeconf.files import FolderLock, command_line, writable
from jaxdeconf.folders import finished
from jaxdeconf.platform import worker_cores
from jaxdeconf.processes import stop_processes


def run_worker(args: argparse.Namespace) -> int:
    """Internal entry point: train one algorithm of an already prepared results folder."""
    _die_with_parent()
    from jaxdeconf.platform import pin_to_cores, set_host_devices

    if args.cores:
        pin_to_cores([int(c) for c in args.cores.split(",")])
    set_host_devices(args.host_devices)
    import logging

    from jaxdeconf.train import train_algorithm

    # Orbax logs each damaged file through absl before raising; the one-line error below says it for the user.
    logging.getLogger("absl").setLevel(logging.CRITICAL)
    # SIGTERM from the parent (or Ctrl-C, which the terminal sends to every process of the run): leave quietly; the
    # parent prints the one line. Files are written atomically, so stopping at any point is safe.
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda n, _: sys.exit(128 + n))

    folder = pathlib.Path(args.out)
    config = resolve.from_dict(json.loads((folder / "config.json").read_text()))  # Checked by the parent.
    try:
        with writable(folder / args.worker):
            (folder / args.worker).mkdir(exist_ok=True)
            lock = FolderLock(folder / args.worker, command_line())  # Even an orphaned worker never trains twice.
            timing = train_algorithm(config, args.worker, folder / args.worker, progress=not args.quiet,
                                     position=args.position)
            lock.release()
    except ConfigError as err:  # E.g. an unreadable checkpoint: one line, and the parent adds none.
        print(f"error: {err}", file=sys.stderr, flush=True)
        sys.stdout.flush()
        # Leave at once: a damaged checkpoint can leave orbax's reads in flight, whose callbacks, run against the
        # closed event loop while Python shuts down, print a traceback each. Nothing is left to write; the OS
        # releases the folder's lock.
        os._exit(2)
    print(f"[{args.worker}] compile {timing['compile_s']:.1f} s, run {timing['run_s']:.1f} s", flush=True)
    return 0


def _die_with_parent() -> None:
    """Have Linux send this worker SIGTERM when its parent dies (even by SIGKILL), so no worker outlives its run."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG.
    if os.getppid() == 1:  # The parent died before the call above.
        sys.exit(128 + signal.SIGTERM)


def train_workers(folder: pathlib.Path, queue: list[str], jobs: int, quiet: bool,
                  host_devices: int, pin: bool = False) -> dict[str, int]:
    """Train the queued algorithms in worker processes, ``jobs`` at a time, each slot pinned to its own cores when
    ``pin`` and they fit (``platform.worker_cores``); a freed slot takes the next algorithm at once. Returns each
    algorithm's exit code."""
    codes: dict[str, int] = {}
    running: dict[int, tuple[str, subprocess.Popen]] = {}  # Slot (a progress-bar row) -> worker.
    queue = list(queue)
    try:
        _schedule(folder, queue, jobs, quiet, host_devices, pin, running, codes)
    finally:  # Normally nothing is left; on SIGTERM or Ctrl-C, the workers stop with the run.
        stop_processes(proc for _, proc in running.values())
    return codes


def _schedule(folder: pathlib.Path, queue: list[str], jobs: int, quiet: bool, host_devices: int, pin: bool,
              running: dict[int, tuple[str, subprocess.Popen]], codes: dict[str, int]) -> None:
    """Start a worker in each free slot until the queue is empty, collecting exit codes."""
    while queue or running:
        for slot in range(jobs):
            if slot not in running and queue:
                algo = queue.pop(0)
                cmd = [sys.executable, "-m", "jaxdeconf.run", "--worker", algo, "--out", str(folder),
                       "--position", str(slot), "--host-devices", str(host_devices)]
                cores = worker_cores(slot, jobs, host_devices) if pin else None
                cmd += ["--cores", ",".join(map(str, cores))] if cores else []
                running[slot] = (algo, subprocess.Popen([*cmd, "--quiet"] if quiet else cmd))
        finished_slots = [slot for slot, (_, proc) in running.items() if proc.poll() is not None]
        if not finished_slots:
            time.sleep(0.5)
        for slot in finished_slots:
            algo, proc = running.pop(slot)
            codes[algo] = proc.returncode


def join_processes(host_devices: int, set_up: dict[str, Any]) -> None:
    """Make this process one of a run over several processes (hosts): its CPU devices, then joining the others
    (blocks until all have joined); only process 0 prints (errors still reach stderr), the C++ libraries' lines
    too."""
    from jaxdeconf.platform import join, set_host_devices

    set_host_devices(host_devices)  # Before anything starts JAX's backend (importing train does).
    join(set_up)
    from jaxdeconf.sharding import is_primary

    if not is_primary():
        sys.stdout.flush()
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def train_in_turn(config: cfg.Config, folder: pathlib.Path, quiet: bool) -> None:
    """Train every algorithm not yet finished in ``folder``, one after another, in this process (on its devices' share
    of the seeds, in a run over several processes)."""
    from jaxdeconf.train import train_algorithm

    for algo in config.algos:
        if not finished(config, folder, algo):
            train_algorithm(config, algo, folder / algo, progress=not quiet)
