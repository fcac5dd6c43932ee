"""The summary's numbers on hand-made metrics: final and last-four returns (mean ± s.e. over seeds) and the share
of the bc → oracle gap closed."""

from __future__ import annotations

import json
import types

import pytest

from jaxdeconf.results import summarize

RETURNS = {  # Per algorithm, per seed: eval_return at iterations 5, 10, 15, 20, 25.
    "bc": [[0, 0, 0, 0, 10], [0, 0, 0, 0, 20]],
    "oracle": [[100] * 5, [100, 100, 100, 100, 110]],
    "dil": [[50] * 5, [60] * 5],
}


def _write(folder, algo, per_seed):
    rows = []
    for seed, values in enumerate(per_seed):
        for i, value in enumerate(values):
            rows.append({"algo": algo, "seed": seed, "iteration": 5 * (i + 1), "eval_return": value})
            rows.append({"algo": algo, "seed": seed, "iteration": 5 * (i + 1) + 1, "policy_loss": 1.0})
    (folder / algo).mkdir()
    (folder / algo / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))


def test_summary_rows_hand_values(tmp_path):
    for algo, per_seed in RETURNS.items():
        _write(tmp_path, algo, per_seed)
    table = {row["algo"]: row for row in summarize(tmp_path, types.SimpleNamespace(algos=tuple(RETURNS)), None)}
    bc, oracle, dil = table["bc"], table["oracle"], table["dil"]
    # bc: finals 10 and 20; its seeds' last-four means 2.5 and 5.
    assert (bc["return_mean"], bc["return_se"]) == pytest.approx((15.0, 5.0))
    assert (bc["return_last4_mean"], bc["return_last4_se"]) == pytest.approx((3.75, 1.25))
    assert (oracle["return_mean"], oracle["return_last4_mean"]) == pytest.approx((105.0, 101.25))
    assert (dil["return_mean"], dil["return_se"], dil["return_last4_mean"]) == pytest.approx((55.0, 5.0, 55.0))
    assert dil["gap_closed"] == pytest.approx((55 - 15) / (105 - 15))
    assert dil["gap_closed_last4"] == pytest.approx((55 - 3.75) / (101.25 - 3.75))
    assert (bc["gap_closed"], oracle["gap_closed"], oracle["gap_closed_last4"]) == pytest.approx((0.0, 1.0, 1.0))
    assert bc["iterations"] == 26 and bc["seeds"] == 2
    # The report's MDP tables read the same last-four returns from the metrics.
    from jaxdeconf.reproduce import last_returns

    assert last_returns(tmp_path, "bc") == pytest.approx((3.75, 1.25))


def test_mean_se_skips_missing_seeds_and_a_zero_gap_is_nan():
    import math

    import numpy as np

    from jaxdeconf.results import add_gap_closed, mean_se

    mean, se = mean_se(np.array([1.0, np.nan, 3.0]))
    assert (float(mean), float(se)) == pytest.approx((2.0, 1.0))  # std of (1, 3) over sqrt(2), not sqrt(3).
    table = [{"algo": a, "return_mean": 5.0, "return_last4_mean": 5.0} for a in ("bc", "oracle", "dil")]
    add_gap_closed(table)
    assert all(math.isnan(row["gap_closed"]) and math.isnan(row["gap_closed_last4"]) for row in table)
