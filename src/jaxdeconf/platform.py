"""Process set-up of the command-line tools, done before JAX starts its backend: sharing a GPU between a run's
processes, how many devices this machine's CPU shows, joining a run spread over several processes or hosts, and
pinning a process to one core. A library user's process is left as JAX sets it up.
"""

from __future__ import annotations

import os
from typing import Any

import jax

from jaxdeconf.errors import ConfigError

# The usual variables of a multi-host launch, read when the flags leave them out (SLURM's are detected by JAX itself).
COORDINATOR_ENV, PROCESSES_ENV, PROCESS_ID_ENV = "JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"


# JAX's GPU-memory variables (jaxlib 0.10's names; XLA_PYTHON_CLIENT_MEM_FRACTION is the older spelling of the second).
GPU_MEMORY_ENV = ("XLA_PYTHON_CLIENT_PREALLOCATE", "XLA_CLIENT_MEM_FRACTION", "XLA_PYTHON_CLIENT_MEM_FRACTION",
                  "XLA_PYTHON_CLIENT_ALLOCATOR")


def share_accelerator() -> None:
    """Let the processes of one run share a GPU: each allocates what it uses instead of JAX's default, 75% of the
    device at its first use, which would leave the workers nothing after the parent's memory check, and a second
    worker nothing after the first. A user's own XLA_PYTHON_CLIENT_* memory setting stays."""
    if not any(name in os.environ for name in GPU_MEMORY_ENV):
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"


def set_host_devices(count: int) -> None:
    """Show this machine's CPU as ``count`` devices, so the seed axis can be split over them (each device runs on its
    own thread). Only the CPU backend is affected; a GPU's devices are what they are."""
    check_host_devices(count)
    jax.config.update("jax_num_cpu_devices", count)


def check_host_devices(count: int) -> None:
    """Raise ConfigError unless ``count`` is a valid ``--host-devices``."""
    if count < 1:
        raise ConfigError(f"--host-devices={count} is not allowed: need a positive integer")


def distributed_args(coordinator: str | None, processes: int | None, process_id: int | None) -> dict[str, Any] | None:
    """``jax.distributed.initialize``'s arguments from the flags, else the environment; None for a one-process run."""
    coordinator = coordinator or os.environ.get(COORDINATOR_ENV)
    if not coordinator:
        return None
    processes = processes if processes is not None else _env_int(PROCESSES_ENV)
    process_id = process_id if process_id is not None else _env_int(PROCESS_ID_ENV)
    host, sep, port = coordinator.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ConfigError(f"--coordinator {coordinator!r} is not allowed: need HOST:PORT, e.g. node001:12355")
    if processes is not None and processes < 1:
        raise ConfigError(f"--num-processes={processes} is not allowed: need a positive integer")
    if process_id is not None and not 0 <= process_id < (processes or 1 << 30):
        raise ConfigError(f"--process-id={process_id} is not allowed: need 0 .. {processes - 1} "
                          f"(--num-processes={processes})")
    return {"coordinator_address": coordinator, "num_processes": processes, "process_id": process_id}


def _env_int(name: str) -> int | None:
    """An integer environment variable, or None when unset."""
    value = os.environ.get(name)
    if value is None:
        return None
    try:
        return int(value)
    except ValueError:
        raise ConfigError(f"{name}={value!r} is not allowed: need an integer") from None


def join(args: dict[str, Any], timeout_s: int = 300) -> None:
    """Join the run's other processes (CPU collectives over gloo, so CPU hosts work too); every process blocks here
    until all have joined, or fails after ``timeout_s``."""
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(**args, initialization_timeout=timeout_s)


def pin_to_core(core: int) -> None:
    """Run this process on one CPU core (Linux; elsewhere a no-op), before JAX starts its backend: for measurements
    of one core's speed, and test processes that share a machine."""
    pin_to_cores([core])


def pin_to_cores(cores: list[int]) -> None:
    """Run this process on these CPU cores (Linux; elsewhere a no-op), before JAX starts its backend, so XLA sizes
    its thread pool to them."""
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, set(cores))


def worker_cores(slot: int, jobs: int, host_devices: int) -> list[int] | None:
    """The cores of side-by-side worker ``slot``: its own ``host_devices`` of the available cores when ``jobs`` such
    workers fit them, else None (unpinned, every worker on every core).

    Pinned, each worker's XLA thread pool is sized to its own cores; unpinned (the CLI's default), a worker can use
    a core another has left idle, and the default job ran 7% faster so (docs/scale.md, "Where the default job's time
    goes")."""
    if jobs * host_devices > len(_CORES):
        return None
    return _CORES[slot * host_devices:(slot + 1) * host_devices]


# The cores this process was allowed when it started (before any pinning of its own).
_CORES = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else [0]


def available_cores() -> list[int]:
    """Cores this process was started with (a user's ``taskset`` is respected)."""
    return list(_CORES)
