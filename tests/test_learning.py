"""Slow tier: the paper's bandit result at the CPU preset, on seeds the preset was not tuned on (100-103).

Tolerances come from the 10-seed runs of seeds 0-9 reported in docs/results.md (one iteration's expert data in the
buffer): dil's final best-arm count had mean 54.1 and per-seed standard deviation 1.2, so the mean of 4 seeds lies
above 52.5 with margin (2.7 standard errors); its online P(best arm) curve stayed within 0.020 of the exact
interventional one. Naive BC ended at 34.9 (per-seed standard deviation 2.3), within 0.007 of the exact conditional
policy on expert histories and within 0.039 online (it drifts above the conditional late in the episode). The bounds
fail for an imitator that does not deconfound (BC's count stays far below 52) and for one that does not learn
(chance is 20).
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest
from jaxdeconf.envs import make

from jaxdeconf.references import reference_curves
from jaxdeconf.resolve import build
from jaxdeconf.results import load_metrics
from jaxdeconf.train import train_algorithm

pytestmark = [pytest.mark.slow, pytest.mark.timeout(3600)]
SEEDS, SEED_START = 4, 100


@pytest.fixture(scope="module")
def refs():
    _, params = make("bandit")
    out = jax.jit(reference_curves, static_argnums=(1, 2))(jax.random.key(7), params, 20000)
    return {k: np.asarray(v) for k, v in out.items()}


def _train(tmp_path, algo):
    config = dataclasses.replace(build("bandit", "cpu", (algo,), SEEDS, {}), seed_start=SEED_START)
    train_algorithm(config, algo, tmp_path / algo, progress=False)
    curves = np.load(tmp_path / algo / "curves.npz")
    rows = [r for r in load_metrics(tmp_path, algo) if r["iteration"] == config.train.iterations]
    return np.array([r["eval_return"] for r in rows]), curves["p_best_online"].mean(0), curves["p_best_expert"].mean(0)


def test_deconfounded_imitator_reaches_the_interventional_policy(tmp_path, refs):
    returns, online, _ = _train(tmp_path, "dil")
    assert returns.mean() >= 52.5, returns
    assert np.max(np.abs(online - refs["interventional_online"])) <= 0.035


def test_naive_bc_deludes_itself_like_the_conditional_policy(tmp_path, refs):
    returns, online, expert = _train(tmp_path, "bc")
    assert returns.mean() <= 42.0, returns
    assert np.max(np.abs(expert - refs["conditional_expert"])) <= 0.03
    assert np.max(np.abs(online - refs["conditional_online"])) <= 0.07
