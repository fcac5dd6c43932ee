"""Run the CLI (``python tests/kill_helper.py MOMENT ARGS...``) and SIGKILL this process at a chosen moment.

The kill is a real ``SIGKILL`` sent to itself from inside the write it interrupts, so nothing (no ``finally``, no
atexit, no flush) runs after it: exactly what a power cut or the OOM killer does at that instant.
"""

from __future__ import annotations

import os
import signal
import sys

from jaxdeconf import files, run
from jaxdeconf.checkpoint import Checkpoints


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def _kill_on_replace(name: str) -> None:
    """Die when ``write_atomic`` is about to rename its finished temporary file onto ``name``."""
    real = os.replace

    def replace(src, dst):
        if os.path.basename(dst) == name:
            _die()
        real(src, dst)

    files.os.replace = replace  # The os module itself: the name filter above keeps every other rename working.


def _kill_on_save(before: bool, step_of) -> None:
    """Die just before (``before``) or just after the checkpoint whose step ``step_of(self, step)`` selects."""
    real = Checkpoints.save

    def save(self, step, state):
        if step_of(step) and before:
            _die()
        real(self, step, state)
        if step_of(step):
            _die()

    Checkpoints.save = save


def _kill_during_save(step: int) -> None:
    """Die while orbax writes the checkpoint of ``step`` (its files are being written in a background thread)."""
    from jaxdeconf.checkpoint import _to_raw, ocp

    real = Checkpoints.save

    def save(self, s, state):
        if s != step:
            return real(self, s, state)
        self.manager.save(s, args=ocp.args.StandardSave(_to_raw(state)))  # Starts the write, returns early.
        _die()

    Checkpoints.save = save


def install(moment: str, iterations: int) -> None:
    """Arrange the kill for ``moment``."""
    if moment == "checkpoint_write":
        _kill_during_save(iterations // 2)
    elif moment == "before_done":
        _kill_on_save(False, lambda s: s == iterations)
    elif moment == "after_metrics_append":
        _kill_on_save(True, lambda s: s == iterations)
    elif moment in ("curves.npz", "config.json", "metrics.jsonl"):
        _kill_on_replace(moment)
    elif moment != "none":
        raise ValueError(moment)


if __name__ == "__main__":
    moment, iterations, argv = sys.argv[1], int(sys.argv[2]), sys.argv[3:]
    install(moment, iterations)
    sys.exit(run.main(argv))
