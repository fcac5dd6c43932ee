"""``python -m jaxdeconf.reproduce``: parts write the page, finished parts are reused, a failed part resumes."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest
from conftest import TINY

from jaxdeconf import reproduce

SMALL = [a for k, v in {**TINY, "train.iterations": "2", "train.chunk": "2"}.items() for a in ("--set", f"{k}={v}")]


@pytest.fixture(scope="module")
def small_report(tmp_path_factory):
    """The bandit comparison (bc and dil, tiny networks, 2 iterations, 10 seeds) and Figure 1 from it."""
    out = tmp_path_factory.mktemp("report")
    code = reproduce.main(["--out", str(out), "--only", "bandit,figure1", "--algo", "bc,dil", *SMALL])
    return out, code


@pytest.mark.slow  # Two trainings and Figure 1's rollouts: about 2 min on one core.
@pytest.mark.timeout(900)
def test_report_page_holds_each_finished_part(small_report):
    out, code = small_report
    assert code == 0
    page = (out / "README.md").read_text()
    assert "## The confounded bandit (Figure 3)" in page and "## Figure 1: rollouts" in page
    done = json.loads((out / "parts" / "bandit" / "DONE.json").read_text())
    assert [row["algo"] for row in done["numbers"]["rows"]] == ["bc", "dil"]
    assert done["numbers"]["rows"][0]["seeds"] == 10
    for row in done["numbers"]["rows"]:  # Each algorithm's row in the page is the summary's number.
        assert f"| {row['algo']} | {row['return_mean']:.1f} ± {row['return_se']:.1f} |" in page
    refs = json.loads((out / "runs" / "bandit" / "references.json").read_text())
    assert f"| exact interventional | {refs['interventional_count']:.1f} | 54.1 |" in page  # Beside the paper's.
    assert (out / "parts" / "figure1" / "figure1.png").stat().st_size > 0
    assert "](parts/figure1/figure1.png)" in page and "](runs/bandit/comparison.png)" in page


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_finished_parts_are_reused(small_report, monkeypatch):
    out, _ = small_report
    before = (out / "parts" / "bandit" / "DONE.json").read_bytes()

    def no_training(*args, **kwargs):
        raise AssertionError("a finished part trained again")

    monkeypatch.setattr(reproduce, "train", no_training)
    assert reproduce.main(["--out", str(out), "--only", "bandit,figure1", "--algo", "bc,dil", *SMALL]) == 0
    assert (out / "parts" / "bandit" / "DONE.json").read_bytes() == before


def test_failed_part_stops_with_one_line_and_leaves_the_others(tmp_path, monkeypatch, capsys):
    def fail(ctx, name, *args, **kwargs):
        raise reproduce.PartFailedError(f"training {name} stopped with exit code 2", 2)

    monkeypatch.setattr(reproduce, "train", fail)
    quick = {"appendix_a": dataclasses.replace(reproduce.PARTS[1], run=lambda ctx: {"episodes": 7})}
    monkeypatch.setattr(reproduce, "PARTS", [quick.get(p.name, p) for p in reproduce.PARTS])
    assert reproduce.main(["--out", str(tmp_path), "--only", "appendix_a,bandit"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: training bandit stopped with exit code 2; rerun the same command to resume"]
    assert (tmp_path / "parts" / "appendix_a" / "DONE.json").exists()
    assert not (tmp_path / "parts" / "bandit").exists()
    page = (tmp_path / "README.md").read_text()
    assert "7 episodes per point" in page and page.count("Not run yet.") == 1


@pytest.mark.parametrize("argv, message", [
    (["--scale", "gpu"], "--scale 'gpu' is not one of cpu, paper"),
    (["--only", "bandit,figure3"], "--only 'figure3' is not a part"),
])
def test_bad_input_is_one_line(tmp_path, capsys, argv, message):
    assert reproduce.main(["--out", str(tmp_path / "r"), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {message}")
    assert not (tmp_path / "r" / "README.md").exists()


def _descendants(pid: int) -> set[int]:
    """Every process below ``pid`` (Linux /proc)."""
    parents = {}
    for stat in pathlib.Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, ValueError, IndexError):
            parents[int(stat.parent.name)] = int(stat.read_text().rpartition(")")[2].split()[1])
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier} - found
        found |= frontier
    return found


@pytest.mark.slow  # A real training started and stopped: about 30 s.
@pytest.mark.timeout(420)
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_sigterm_stops_the_running_training_with_the_report(tmp_path):
    """SIGTERM to the report stops the training it runs (and that training's workers), with exit 143."""
    long = [a for k, v in {**TINY, "train.iterations": "100000"}.items() for a in ("--set", f"{k}={v}")]
    out, log = tmp_path / "report", tmp_path / "stderr.txt"
    with open(log, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "jaxdeconf.reproduce", "--out", str(out), "--only", "bandit",
                                 "--algo", "bc", *long], stdout=subprocess.DEVNULL, stderr=err,
                                start_new_session=True)
    metrics, children, done = out / "runs" / "bandit" / "bc" / "metrics.jsonl", set(), False
    try:
        deadline = time.monotonic() + 180
        while not metrics.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)  # Until the worker has trained its first chunk.
        children = _descendants(proc.pid)
        assert metrics.exists() and len(children) >= 2, log.read_text()[-2000:]  # The run and its worker.
        proc.terminate()
        assert proc.wait(timeout=120) == 128 + signal.SIGTERM
        assert log.read_text().strip().splitlines()[-1] == (
            "error: stopped by SIGTERM; rerun the same command to resume")
        assert not [pid for pid in children if pathlib.Path(f"/proc/{pid}").exists()]
        done = True
    finally:  # Whatever failed, nothing of it keeps training.
        for pid in () if done else (proc.pid, *children):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.wait()


def test_training_minutes_sum_every_start_of_each_finished_training(tmp_path):
    """Per run folder: compile + chunk seconds over all starts where DONE has them, the last start's otherwise;
    trainings without DONE (still running) are left out."""
    runs = tmp_path / "runs"
    for folder, algo, done in (
        ("bandit", "bc", {"compile_s": 10.0, "run_s": 50.0, "total_compile_s": 30.0, "total_run_s": 90.0, "starts": 3}),
        ("bandit", "dil", {"compile_s": 20.0, "run_s": 100.0}),
        ("lunar_lander", "bc", None),
    ):
        (runs / folder / algo).mkdir(parents=True)
        if done is not None:
            (runs / folder / algo / "DONE").write_text(json.dumps(done))
    ctx = reproduce.Context(out=tmp_path, scale=reproduce.SCALES["cpu"])
    assert reproduce.training_minutes(ctx) == {"bandit": (30 + 90 + 20 + 100) / 60}
    assert "Total: 4." in "\n".join(reproduce._compute_section(ctx))
