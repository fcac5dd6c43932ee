"""Shared tiny configurations, so each compiled shape is built once per test run."""

from __future__ import annotations

import os
import pathlib
import shutil
import tempfile

import jax
import numpy as np
import pytest

from jaxdeconf.platform import available_cores, pin_to_core
from jaxdeconf.resolve import build


def pytest_configure(config):
    """Pin this process to a core, and share compiled programs across the test run's processes."""
    _pin(config)
    _share_compilations(config)


def pytest_unconfigure(config):
    if getattr(config, "_jax_cache_owner", False):
        shutil.rmtree(os.environ.pop("JAX_COMPILATION_CACHE_DIR"), ignore_errors=True)


def _share_compilations(config):
    """JAX's persistent compilation cache in a folder that lives as long as this test run: many tests build the same
    tiny programs, and the CLI tests retrain in new processes, so each program compiles once per run instead of once
    per test. The process that starts the run makes the folder; xdist workers and the CLI tests' subprocesses inherit
    it through the environment."""
    if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
        os.environ["JAX_COMPILATION_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxdeconf-tests-xla-")
        os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.5"
        config._jax_cache_owner = True
    jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs",
                      float(os.environ.get("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")))


def _pin(config):
    """Each test process runs on one core, so two test processes never compete for a core. Under pytest-xdist
    (``-n 2`` in pyproject.toml) worker gwN takes core N and the controller, which only distributes tests, stays
    unpinned, so the workers it starts inherit every core. The CLI tests' training subprocesses inherit their test
    process's core."""
    cores = available_cores()
    if hasattr(config, "workerinput"):
        pin_to_core(cores[int(config.workerinput["workerid"].removeprefix("gw")) % len(cores)])
    elif not getattr(config.option, "numprocesses", None):
        pin_to_core(cores[0])


#: The worked example of an env from the user's own code, named by file path so any working directory will do.
CARTPOLE = f"{pathlib.Path(__file__).parents[1] / 'examples' / 'cartpole.py'}:ConfoundedCartPole"

TINY = {
    "model.width": "16",
    "model.action_embed": "8",
    "model.gru": "16",
    "model.bc_gru": "16",
    "model.latent": "3",
    "train.iterations": "4",
    "train.warmup": "1",
    "train.chunk": "2",
    "train.episodes_per_iter": "4",
    "train.batch_size": "4",
    "train.buffer_episodes": "8",
    "train.policy_steps": "2",
    "train.encoder_steps": "2",
    "train.eval_episodes": "4",
    "env.horizon": "10",
}


@pytest.fixture
def tiny_config():
    """A few-second config of all three algorithms on a 10-step bandit."""
    return lambda seeds=2, **extra: build("bandit", "cpu", ("bc", "oracle", "dil"), seeds, {**TINY, **extra})


def assert_rows_close(a: list[dict], b: list[dict]) -> None:
    """Two lists of metrics rows hold the same keys, equal integers and strings, and floats equal to float32
    rounding (a seed's program inside a vmapped sweep may fuse differently from a lone run's)."""
    assert len(a) == len(b)
    for ra, rb in zip(a, b, strict=True):
        assert ra.keys() == rb.keys()
        for key in ra:
            if isinstance(ra[key], float):
                np.testing.assert_allclose(ra[key], rb[key], rtol=1e-4, atol=1e-5, err_msg=key)
            else:
                assert ra[key] == rb[key]
