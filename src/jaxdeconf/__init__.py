"""jaxdeconf: deconfounded imitation learning as seed-vmapped JAX programs.

Kept light on purpose: ``import jaxdeconf`` imports no Brax, MuJoCo or matplotlib.
"""

import os

# XLA's CPU runtime in jaxlib 0.10.2 deadlocked here, intermittently, on the seed-vmapped programs at 4+ seeds on the
# 2-core machine: every worker thread (Eigen pool and llvm-worker codegen threads) idle, the host waiting forever.
# The flags below fixed every isolated reproducer but not the full 10-seed run; what did is running each training
# process on one core (``jaxdeconf.run.pin_to_core``). The flags stay as a second line of defence: on one core the
# multi-threaded Eigen pool has nothing to gain anyway.
# XLA reads XLA_FLAGS when the CPU backend starts, so setting them at import works as long as no computation ran
# before. They only affect the CPU backend; a user's own XLA_FLAGS setting of the same flag wins.
_CPU_FLAGS = (
    "--xla_force_host_platform_device_count=8",
    "--xla_cpu_parallel_codegen_split_count=1",
    "--xla_cpu_multi_thread_eigen=false",
    "--xla_cpu_use_xnnpack=false",
    "--xla_cpu_enable_concurrency_optimized_scheduler=false",
)
_current = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = " ".join([_current, *(f for f in _CPU_FLAGS if f.split("=")[0] not in _current)]).strip()

__version__ = "0.1.0"
