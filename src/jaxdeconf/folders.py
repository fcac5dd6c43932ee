"""The rules of a results folder: what this tool writes there, when a run may use a folder (not a file, none of the
user's files, the same config, writable, not in use), which algorithms in it are finished, and its cached bandit
references. The low-level writes and the lock are files.py's."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import pathlib
import shutil
from typing import Any

from jaxdeconf import config as cfg
from jaxdeconf import resolve
from jaxdeconf.errors import ConfigError
from jaxdeconf.files import (
    LOCK_NAME,
    TMP_PREFIX,
    FolderLock,
    command_line,
    read_json,
    read_rows,
    remove_temporaries,
    writable,
    write_atomic,
)

# What this tool writes in a results folder, and in each algorithm's subfolder: --overwrite deletes nothing else.
RESULT_FILES = {"config.json", "references.json", "summary.md", "summary.csv", "learning_curves.png", "p_best.png",
                "diagnostics.png",
                "comparison.png", "render", LOCK_NAME}
ALGO_FILES = {"metrics.jsonl", "timing.jsonl", "curves.npz", "DONE", "checkpoints", LOCK_NAME}


def _foreign(folder: pathlib.Path) -> list[str]:
    """Entries of ``folder`` that this tool did not write (temporaries of its atomic writes are its own)."""
    def ours(p: pathlib.Path, names: set[str]) -> bool:
        """Whether ``p`` is one of ``names``, or a temporary of an atomic write."""
        return p.name in names or p.name.startswith(TMP_PREFIX)

    out = []
    for p in sorted(folder.iterdir()):
        if p.is_dir() and not p.is_symlink() and p.name not in RESULT_FILES:
            out += [f"{p.name}/{q.name}" for q in sorted(p.iterdir()) if not ours(q, ALGO_FILES)]
        elif not ours(p, RESULT_FILES) or p.is_symlink():
            out.append(p.name)
    return out


def _check_out(folder: pathlib.Path) -> None:
    """Refuse an --out that is a file, or a folder of someone else's files (with or without --overwrite)."""
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"--out {folder} is a file, not a folder; use another --out")
    for parent in folder.parents:
        if parent.exists() and not parent.is_dir():
            raise ConfigError(f"--out {folder} lies inside {parent}, which is a file; use another --out")
    if not folder.exists():
        return
    foreign = _foreign(folder)
    ours = [p for p in folder.iterdir() if p.name != LOCK_NAME and not p.name.startswith(TMP_PREFIX)]
    if foreign or (ours and not (folder / "config.json").exists()):
        what = f"holds files this tool did not write ({', '.join(foreign[:3])})" if foreign else \
            "is not empty and has no config.json"
        raise ConfigError(f"results folder {folder} {what}; nothing was changed: use another --out"
                          + (" (--overwrite only deletes results folders this tool wrote)" if foreign else ""))


def prepare_folder(folder: pathlib.Path, config: cfg.Config, overwrite: bool) -> FolderLock:
    """Create the results folder, or check an existing one holds the same config (never clobber results); return the
    folder's lock, held until this process exits."""
    _check_out(folder)
    with writable(folder):
        folder.mkdir(parents=True, exist_ok=True)
        lock = FolderLock(folder, command_line())
    try:
        _fill_folder(folder, config, overwrite)
    except BaseException:
        lock.release()  # Refused: the folder is free again at once (main() may be called again in this process).
        raise
    return lock


def _fill_folder(folder: pathlib.Path, config: cfg.Config, overwrite: bool) -> None:
    """Under the lock: drop temporaries, empty the folder for --overwrite, then write or check config.json."""
    with writable(folder):
        remove_temporaries(folder)
        if overwrite:
            for p in folder.iterdir():
                if p.name != LOCK_NAME:
                    shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        config_path = folder / "config.json"
        if config_path.exists():
            _check_same_config(config_path, config)
        else:
            write_atomic(config_path, cfg.dumps(config) + "\n")  # Once: a restart never rewrites it.


def _check_same_config(path: pathlib.Path, config: cfg.Config) -> None:
    """Raise ConfigError unless the folder's config.json is ``config`` (env parameters compared as typed values)."""
    recover = "pass --overwrite to start over, or delete the folder"
    try:
        old = typed_env_params(resolve.from_dict(read_json(path, recover)))
    except ConfigError:
        raise
    except Exception as err:  # A parsable file with missing or mistyped fields.
        raise ConfigError(f"{path} is not a valid config ({type(err).__name__}: {err}); {recover}") from None
    if cfg.dumps(old) != cfg.dumps(config):
        diff = _first_difference(old.to_dict(), config.to_dict())
        raise ConfigError(
            f"results folder {path.parent} holds a different config ({diff}); use another --out, or --overwrite"
        )


def typed_env_params(config: cfg.Config) -> cfg.Config:
    """``config`` with its env parameters as the env's own typed values (``horizon=020`` is ``20``), validated."""
    from jaxdeconf.envs import make

    try:
        _, params = make(config.env, **config.env_params)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    typed = {k: getattr(params, k) for k in config.env_params}
    for key, value in typed.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"env.{key}={value} is not allowed: need a finite number")
        if isinstance(value, int) and not isinstance(value, bool) and abs(value) > cfg.INT32_MAX:
            raise ConfigError(f"env.{key}={value} is too large: need at most {cfg.INT32_MAX}")
    return dataclasses.replace(config, env_params=typed)


def _first_difference(old: Any, new: Any, path: str = "") -> str:
    """Describe the first differing field of two nested dicts."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            if old.get(key) != new.get(key):
                return _first_difference(old.get(key), new.get(key), f"{path}.{key}" if path else key)
    return f"{path}: {old!r} there, {new!r} now"


def check_writable(folder: pathlib.Path, algos: tuple[str, ...]) -> None:
    """Refuse at once a folder the workers could not write (orbax would retry for minutes, then fail at length)."""
    for path in [folder, *(folder / a for a in algos), *(folder / a / "checkpoints" for a in algos)]:
        if path.is_dir() and not os.access(path, os.W_OK | os.X_OK):
            raise ConfigError(f"cannot write {path}: permission denied; make it writable, or use another --out")


def finished(config: cfg.Config, folder: pathlib.Path, algo: str) -> bool:
    """Whether ``algo`` finished in ``folder`` with all its files intact; a finished run whose curves are missing or
    damaged is not (its worker recomputes them), one whose metrics are is an error (nothing can recompute them)."""
    from jaxdeconf.train import check_rows, curves_ok

    if not (folder / algo / "DONE").exists():
        return False
    path = folder / algo / "metrics.jsonl"
    check_rows(path, config, algo, read_rows(path), config.train.iterations)
    if not curves_ok(folder / algo / "curves.npz"):
        print(f"[{algo}] finished, but its curves.npz is missing or damaged: recomputing it from the checkpoints")
        return False
    print(f"[{algo}] already finished in {folder}; kept as is (use --overwrite to retrain)")
    return True


# What the summary and figures read from references.json.
REFERENCE_KEYS = {f"{kind}_{what}" for kind in ("interventional", "conditional")
                  for what in ("online", "expert", "count", "count_se")} | {"expert_count"}


def cached_references(config: cfg.Config, folder: pathlib.Path) -> dict[str, Any] | None:
    """Exact bandit references (computed once per folder and cached in references.json; recomputed if damaged)."""
    if config.env != "bandit":
        return None
    import numpy as np

    path = folder / "references.json"
    if path.exists():
        with contextlib.suppress(ConfigError, AttributeError, TypeError, ValueError):
            refs = {k: np.asarray(v, np.float64) for k, v in read_json(path, "").items()}
            if set(refs) >= REFERENCE_KEYS:
                return refs
        print(f"{path} is damaged; computing it again")  # A cache of exact values: nothing is lost.
    import jax

    from jaxdeconf.envs import make
    from jaxdeconf.references import reference_curves

    _, params = make(config.env, **config.env_params)
    refs = jax.jit(reference_curves, static_argnums=(1, 2))(jax.random.key(12345), params, 20000)
    refs = {k: np.asarray(v) for k, v in refs.items()}
    with writable(path):
        write_atomic(path, json.dumps({k: v.tolist() for k, v in refs.items()}) + "\n")
    return refs
