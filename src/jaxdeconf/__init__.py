"""jaxdeconf: deconfounded imitation learning as seed-vmapped JAX programs.

Kept light on purpose: ``import jaxdeconf`` imports no Brax, MuJoCo or matplotlib.
"""

import os

# XLA's CPU runtime (jaxlib 0.10.2) deadlocked here, reproducibly, running the vmapped training chunk at 4 seeds:
# every worker thread idle, the host waiting forever. Its concurrency-optimised scheduler is the trigger; turning it
# off fixed every case measured (4, 10 and 16 seeds). XLA reads the flag when the backend starts, so setting it at
# import suffices as long as nothing has run a computation before. It does not affect GPU backends.
_FLAG = "--xla_cpu_enable_concurrency_optimized_scheduler=false"
if _FLAG.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _FLAG).strip()

__version__ = "0.1.0"
