"""Crash-safe files: atomic writes, whole-line appends, strict JSON, and a lock per results folder.

A kill at any moment leaves each file either as it was or as it was meant to be, never half-written: new contents go
to a temporary file in the same folder, are flushed to disk, and replace the old file with one ``os.replace``.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import math
import os
import pathlib
import sys
import time
from collections.abc import Iterator
from typing import Any

from jaxdeconf.errors import ConfigError

#: Temporary files this module leaves behind when killed mid-write start with this prefix (cleaned up on next start).
TMP_PREFIX = ".tmp-"
LOCK_NAME = ".lock"


def write_atomic(path: pathlib.Path, data: bytes | str) -> None:
    """Replace ``path`` with ``data`` in one step (temporary file, fsync, rename, fsync of the folder)."""
    path = pathlib.Path(path)
    payload = data.encode() if isinstance(data, str) else data
    tmp = path.with_name(f"{TMP_PREFIX}{path.name}.{os.getpid()}")
    with open(tmp, "wb") as f:
        f.write(payload)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _fsync_dir(folder: pathlib.Path) -> None:
    """Make a rename in ``folder`` durable (a no-op where folders cannot be opened)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def remove_temporaries(folder: pathlib.Path) -> None:
    """Delete what a killed ``write_atomic`` left in ``folder``."""
    for p in pathlib.Path(folder).glob(f"{TMP_PREFIX}*"):
        with contextlib.suppress(OSError):
            p.unlink()


def _finite_or_none(value: Any) -> Any:
    """NaN and infinities as ``null``: strict JSON has no spelling for them."""
    return None if isinstance(value, float) and not math.isfinite(value) else value


def dumps_row(row: dict[str, Any]) -> str:
    """One metrics row as a strict-JSON line (non-finite numbers become null)."""
    return json.dumps({k: _finite_or_none(v) for k, v in row.items()}, allow_nan=False)


def append_lines(path: pathlib.Path, lines: list[str]) -> None:
    """Append whole lines with one write and fsync; a kill can leave at most a partial last line."""
    data = "".join(line + "\n" for line in lines).encode()
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        view = memoryview(data)
        while view:  # os.write may write less than asked (signals, pipes); loop until all of it is down.
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def read_lines(path: pathlib.Path) -> list[str]:
    """The lines of a JSON-lines file (none if it does not exist; undecodable bytes replaced)."""
    return path.read_bytes().decode(errors="replace").splitlines() if path.exists() else []


def parse_object(line: str) -> dict[str, Any] | None:
    """A JSON object from one line, or None for a partial or garbage line."""
    try:
        row = json.loads(line)
    except ValueError:
        return None
    return row if isinstance(row, dict) else None


def parse_row(line: str) -> dict[str, Any] | None:
    """A metrics row from one line (null read back as NaN), or None for a partial or garbage line."""
    row = parse_object(line)
    if row is None or not isinstance(row.get("iteration"), int) or not isinstance(row.get("seed"), int):
        return None
    return {k: math.nan if v is None else v for k, v in row.items()}


def read_rows(path: pathlib.Path) -> list[dict[str, Any]]:
    """The readable rows of a JSON-lines metrics file (a partial last line, what a kill mid-append leaves, is
    skipped)."""
    return [row for row in map(parse_row, read_lines(path)) if row is not None]


def read_json(path: pathlib.Path, recover: str) -> Any:
    """Parse a JSON file; a damaged one is a one-line ConfigError naming it and saying how to recover."""
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise ConfigError(f"{path} is unreadable ({_reason(err)}); {recover}") from None


def _reason(err: BaseException) -> str:
    """The first line of an exception's message, short."""
    text = str(err).strip()
    return text.splitlines()[0][:120] if text else type(err).__name__


class FolderLock:
    """An exclusive ``flock`` on ``<folder>/.lock`` held while a run works in the folder; the file names its holder.

    The kernel drops the lock when the holder exits, however it exits, so a killed run never leaves a stale lock.
    """

    def __init__(self, folder: pathlib.Path, holder: str) -> None:
        """Take the lock, or raise ConfigError naming the run that holds it."""
        self.path = pathlib.Path(folder) / LOCK_NAME
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            other = os.pread(self.fd, 4096, 0).decode(errors="replace").strip() or "another process"
            os.close(self.fd)
            if err.errno in (errno.EAGAIN, errno.EACCES):
                raise ConfigError(f"results folder {folder} is in use by another run ({other}); wait for it to "
                                  "finish or stop it, then run this command again") from None
            raise
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, f"pid {os.getpid()}, started {time.strftime('%Y-%m-%d %H:%M:%S')}: {holder}".encode(), 0)

    def release(self) -> None:
        """Give the lock up (also happens when the process exits)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def command_line() -> str:
    """This process's command line, for the lock file."""
    return " ".join([os.path.basename(sys.executable), *sys.argv])[:300]


@contextlib.contextmanager
def writable(path: pathlib.Path) -> Iterator[None]:
    """Turn an OSError while writing under ``path`` into a one-line ConfigError."""
    try:
        yield
    except OSError as err:
        where = err.filename or path
        raise ConfigError(f"cannot write {where}: {err.strerror or _reason(err)}") from None
