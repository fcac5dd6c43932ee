"""jaxdeconf: deconfounded imitation learning as seed-vmapped JAX programs.

Kept light on purpose: ``import jaxdeconf`` imports no Brax, MuJoCo or matplotlib.
"""

__version__ = "0.1.0"
