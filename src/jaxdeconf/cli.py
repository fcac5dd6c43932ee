"""The flags of ``python -m jaxdeconf.run``: parsing only (what they mean is for run.py, folders.py and workers.py)."""

from __future__ import annotations

import argparse
from typing import Any

from jaxdeconf import algos
from jaxdeconf.errors import ConfigError

#: The ``--help`` text's description.
DESCRIPTION = ("Command line: ``python -m jaxdeconf.run --env bandit --algo bc,dil --seeds 10 [--preset cpu] "
               "[--set k=v ...]``.")


class _Parser(argparse.ArgumentParser):
    """argparse, with a bad flag as a one-line ConfigError instead of the usage text and exit."""

    def error(self, message: str) -> None:  # type: ignore[override]
        """Raise instead of printing the usage."""
        raise ConfigError(message)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """Command-line flags."""
    p = _Parser(prog="python -m jaxdeconf.run", description=DESCRIPTION)
    p.add_argument("--env", default="bandit", help="environment name (default: bandit)")
    p.add_argument("--algo", default="bc,dil",
                   help=f"comma-separated algorithms from {', '.join(algos.names())}, or all")
    p.add_argument("--seeds", type=int, default=10, help="number of seeds, trained together in one program")
    p.add_argument("--preset", default="cpu", help="preset of the environment (cpu, paper)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="override a config field, e.g. train.iterations=100, model.gru=256, env.p=0.7")
    p.add_argument("--out", default=None, help="results folder (default: results/<env>-<preset>)")
    p.add_argument("--overwrite", action="store_true", help="delete an existing results folder and start over")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--jobs", type=int, default=0,
                   help="algorithms trained at once, each in its own process "
                        "(default: one per algorithm, at most one per available core and as many as fit in "
                        "memory together)")
    p.add_argument("--pin", action="store_true",
                   help="pin each side-by-side algorithm to its own core(s) when they fit (default: unpinned, each "
                        "free to use an idle core)")
    p.add_argument("--host-devices", type=int, default=1,
                   help="split this machine's CPU into N devices and the seeds over them (default: 1)")
    p.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="multi-host run: process 0's address (or $JAX_COORDINATOR_ADDRESS); seeds are split over "
                        "every process's devices and process 0 writes the results")
    p.add_argument("--num-processes", type=int, default=None, help="multi-host run: processes in all")
    p.add_argument("--process-id", type=int, default=None, help="multi-host run: this process's rank")
    p.add_argument("--worker", default=None, help=argparse.SUPPRESS)  # Internal: train one algorithm of --out.
    p.add_argument("--position", type=int, default=0, help=argparse.SUPPRESS)  # Internal: its progress-bar row.
    p.add_argument("--cores", default="", help=argparse.SUPPRESS)  # Internal: the cores it is pinned to.
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
