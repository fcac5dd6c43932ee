"""Stopping a tree of processes cleanly: SIGTERM and SIGINT (Ctrl-C) become an exception in the parent, which then
stops its children before it exits, so no training outlives the command that started it."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import time
from collections.abc import Iterable, Iterator
from typing import Any


class Stopped(Exception):  # noqa: N818  (a signal, not an error)
    """SIGTERM or SIGINT arrived."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum
        self.name = signal.Signals(signum).name


@contextlib.contextmanager
def signals_raise() -> Iterator[None]:
    """Turn SIGTERM and SIGINT into ``Stopped`` inside the block, so the caller can stop its children with it."""
    def handler(signum: int, frame: Any) -> None:
        del frame  # Unused.
        raise Stopped(signum)

    old = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def stop_processes(procs: Iterable[subprocess.Popen], grace_s: float = 20.0) -> None:
    """SIGTERM the processes still running, wait up to ``grace_s`` for them, then SIGKILL any left."""
    procs = [p for p in procs if p.poll() is None]
    for p in procs:
        p.terminate()
    deadline = time.monotonic() + grace_s
    for p in procs:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
