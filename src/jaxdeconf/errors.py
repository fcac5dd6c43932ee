"""Errors shared across the package (a leaf module: it imports nothing of jaxdeconf)."""


class ConfigError(ValueError):
    """Bad user input; the CLI prints it as one line and exits with code 2."""
