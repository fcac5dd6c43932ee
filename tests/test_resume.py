"""Checkpoints: an interrupted run resumes exactly (its own file, so pytest-xdist can run it beside test_train.py)."""

from __future__ import annotations

import json

import pytest

from jaxdeconf.checkpoint import Checkpoints
from jaxdeconf.train import train_algorithm


def _rows(folder):
    return [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()]


def test_interrupted_run_resumes_exactly(tmp_path, tiny_config, monkeypatch):
    config = tiny_config()
    train_algorithm(config, "dil", tmp_path / "whole", progress=False)

    real_save = Checkpoints.save
    calls = []

    def save_then_die(self, step, state):
        real_save(self, step, state)
        calls.append(step)
        if len(calls) == 1:
            raise KeyboardInterrupt  # As if the user pressed Ctrl-C after the first chunk.

    monkeypatch.setattr(Checkpoints, "save", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        train_algorithm(config, "dil", tmp_path / "cut", progress=False)
    assert not (tmp_path / "cut" / "DONE").exists()
    assert max(r["iteration"] for r in _rows(tmp_path / "cut")) == 2
    train_algorithm(config, "dil", tmp_path / "cut", progress=False)  # Resumes at iteration 2.
    assert calls == [2, 4]
    assert _rows(tmp_path / "cut") == _rows(tmp_path / "whole")
