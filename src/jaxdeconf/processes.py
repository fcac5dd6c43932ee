"""Stopping a tree of processes cleanly: SIGTERM and SIGINT (Ctrl-C) become an exception in the parent, which then
stops its children before it exits, so no training outlives the command that started it."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from collections.abc import Iterable, Iterator
from typing import Any

SIGNALS = (signal.SIGTERM, signal.SIGINT)


class Stopped(BaseException):  # Like KeyboardInterrupt: no `except Exception` swallows it.
    """SIGTERM or SIGINT arrived."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum
        self.name = signal.Signals(signum).name


@contextlib.contextmanager
def signals_raise() -> Iterator[None]:
    """Turn the first SIGTERM or SIGINT inside the block into ``Stopped``; later ones are ignored, so the clean-up
    that ``Stopped`` starts (stopping children, which ends in SIGKILL anyway) is not cut short."""
    def handler(signum: int, frame: Any) -> None:
        del frame  # Unused.
        for s in SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        raise Stopped(signum)

    old = {s: signal.signal(s, handler) for s in SIGNALS}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def stop_processes(procs: Iterable[subprocess.Popen], grace_s: float = 20.0, group: bool = False) -> None:
    """SIGTERM the processes still running, wait up to ``grace_s`` for them, then SIGKILL any left; with ``group``
    (processes started with ``start_new_session=True``) the SIGKILL goes to each one's whole process group, so its
    own children go with it."""
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
        if group:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, signal.SIGKILL)  # Whatever of its group is left (a worker mid-chunk).
