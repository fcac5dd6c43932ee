"""jaxdeconf: deconfounded imitation learning as seed-vmapped JAX programs.

Kept light on purpose: ``import jaxdeconf`` imports no Brax, MuJoCo or matplotlib, and changes no global state (XLA
flags and devices are the command-line tools' process set-up, ``jaxdeconf.platform``).
"""

__version__ = "0.1.0"
