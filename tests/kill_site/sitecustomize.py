"""Kill points among a run's file writes, for tests/test_resume.py (on PYTHONPATH only in that test's subprocesses).

Every process of a CLI run (the parent and each ``--worker``) counts its file-system events: each ``os.replace``
(an atomic write's rename, or orbax's), each ``os.fsync`` (a write's data reaching the disk) and each checkpoint
save. ``JAXDECONF_KILL_AT=ROLE:K`` makes the process whose role is ROLE (``parent`` or the worker's algorithm) SIGKILL
itself just before its K-th event, so nothing (no ``finally``, no flush) runs after it. ``JAXDECONF_KILL_COUNT=DIR``
instead writes each process's event count to ``DIR/ROLE`` when it exits, so a test can draw K among real events.
"""

from __future__ import annotations

import atexit
import os
import pathlib
import signal
import sys


def _role() -> str:
    argv = sys.argv
    return argv[argv.index("--worker") + 1] if "--worker" in argv else "parent"


def _install(role: str, kill_at: int | None, count_dir: str | None) -> None:
    from jaxdeconf.checkpoint import Checkpoints

    events = [0]

    def event() -> None:
        events[0] += 1
        if events[0] == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)

    def counted(real):
        def call(*args, **kwargs):
            event()
            return real(*args, **kwargs)

        return call

    os.replace, os.fsync, Checkpoints.save = counted(os.replace), counted(os.fsync), counted(Checkpoints.save)
    if count_dir:
        atexit.register(lambda: pathlib.Path(count_dir, role).write_text(str(events[0])))


_kill = os.environ.get("JAXDECONF_KILL_AT", "")
_count = os.environ.get("JAXDECONF_KILL_COUNT")
if _kill or _count:  # Set only by the test, for ``python -m jaxdeconf.run`` (whose argv here is ['-m', ...]).
    _who, _, _k = _kill.partition(":")
    _install(_role(), int(_k) if _who == _role() else None, _count)
