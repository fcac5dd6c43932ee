"""The committed report against the current code: every finished part under report/parts/ records each training's
resolved config, and the code must still resolve the same config from the same settings (``reproduce.stale_fields``),
so that a changed default, preset or setting cannot leave the committed numbers describing another config."""

from __future__ import annotations

import json
import pathlib

import pytest

from jaxdeconf import algos, reproduce

REPORT = pathlib.Path(__file__).resolve().parents[1] / "report"
DONE_FILES = sorted((REPORT / "parts").glob("*/DONE.json"))


@pytest.mark.parametrize("path", DONE_FILES or [None], ids=lambda p: p.parent.name if p else "no-parts")
def test_committed_part_is_what_the_code_resolves_today(path):
    if path is None:
        pytest.skip(f"no finished part in {REPORT} (no parts/*/DONE.json): run python -m jaxdeconf.reproduce and "
                    "commit report/ to check it here")
    stale = reproduce.stale_fields(json.loads(path.read_text()))
    assert not stale, (f"report part {path.parent.name} is stale; regenerate it (delete {path} and run the command "
                       "under its section of report/README.md) or restore the setting:\n" + "\n".join(stale))


def _done(tmp_path, algo="bc,dil", overrides=("train.iterations=3", "train.warmup=0", "seed_start=100")):
    """A DONE.json in ``tmp_path`` of one bandit training whose recorded config is today's, read back."""
    settings = {"name": "bandit", "env": "bandit", "preset": "cpu", "algo": algo, "seeds": 2,
                "overrides": list(overrides)}
    path = tmp_path / "DONE.json"
    path.write_text(json.dumps({"part": "bandit", "trainings": [{**settings,
                                                                  "config": reproduce.current_config(settings)}]}))
    return json.loads(path.read_text())


def test_a_current_part_has_no_stale_fields(tmp_path):
    done = _done(tmp_path)
    assert done["trainings"][0]["config"]["train"]["iterations"] == 3
    assert done["trainings"][0]["config"]["seed_start"] == 100
    assert reproduce.stale_fields(done) == []


def test_each_changed_field_is_named_with_both_values(tmp_path):
    done = _done(tmp_path)
    config = done["trainings"][0]["config"]
    config["train"]["iterations"] = 5  # A preset or default that changed since.
    config["model"]["retired"] = 1  # A setting the code no longer has (moved or removed).
    del config["seed_start"]
    assert reproduce.stale_fields(done) == ["runs/bandit: model.retired: recorded 1, current (absent)",
                                            "runs/bandit: seed_start: recorded (absent), current 100",
                                            "runs/bandit: train.iterations: recorded 5, current 3"]


def test_an_int_that_became_a_float_is_stale(tmp_path):
    done = _done(tmp_path)
    done["trainings"][0]["config"]["train"]["iterations"] = 3.0
    assert reproduce.stale_fields(done) == ["runs/bandit: train.iterations: recorded 3.0, current 3"]


def test_settings_that_no_longer_resolve_are_stale(tmp_path):
    done = _done(tmp_path)
    done["trainings"][0]["overrides"] = ["train.no_such_field=1"]
    (line,) = reproduce.stale_fields(done)
    assert line.startswith("runs/bandit: its settings no longer resolve (") and "no_such_field" in line


def test_all_algorithms_are_the_ones_registered_today(tmp_path):
    names = algos.names()
    if len(names) < 2:
        pytest.skip("needs two registered algorithms")
    done = _done(tmp_path, algo=names[0])
    done["trainings"][0]["algo"] = "all"  # Made with --algo all when only the first was registered.
    assert reproduce.stale_fields(done) == [
        f"runs/bandit: algos: recorded {json.dumps([names[0]])}, current {json.dumps(list(names))}"]


def test_a_part_without_recorded_configs_is_stale():
    assert reproduce.stale_fields({"numbers": {}, "seconds": 1.0}) == [
        "DONE.json records no trainings' configs; delete it to redo the part"]
    assert reproduce.stale_fields({"trainings": []}) == []  # A part that trains nothing (theorem1).


def test_a_damaged_record_is_stale_not_a_crash(tmp_path):
    done = _done(tmp_path)
    del done["trainings"][0]["config"]
    assert reproduce.stale_fields(done) == ["runs/bandit: its record in DONE.json lacks 'config'"]
