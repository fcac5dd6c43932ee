"""``python -m jaxdeconf.reproduce``: parts write the page, finished parts are reused, a failed part resumes, and a
finished part records where it came from (commit, seeds, wall time, each training's config)."""

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
        assert (f"| {row['algo']} | {row['return_mean']:.1f} ± {row['return_se']:.1f} | "
                f"{row['max_dev_online_vs_interventional']:.3f} | {row['max_dev_expert_vs_conditional']:.3f} |") in page
    refs = json.loads((out / "runs" / "bandit" / "references.json").read_text())
    assert f"| exact interventional | {refs['interventional_count']:.1f} | | | 54.1 |" in page  # Beside the paper's.
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
    def fail(ctx, spec):
        raise reproduce.PartFailedError(f"training {spec.name} stopped with exit code 2", 2)

    monkeypatch.setattr(reproduce, "train", fail)
    quick = {"appendix_a": dataclasses.replace(reproduce.PARTS[1], run=lambda ctx: {"episodes": 7})}
    monkeypatch.setattr(reproduce, "PARTS", [quick.get(p.name, p) for p in reproduce.PARTS])
    assert reproduce.main(["--out", str(tmp_path), "--only", "appendix_a,bandit"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: training bandit stopped with exit code 2; rerun the same command to resume"]
    assert (tmp_path / "parts" / "appendix_a" / "DONE.json").exists()
    assert not (tmp_path / "parts" / "bandit").exists()
    page = (tmp_path / "README.md").read_text()
    assert "7 episodes per point" in page  # The page lists every part, not only those of --only.
    assert page.count("Not run yet.") == len(reproduce.PARTS) - 1


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


def test_core_seconds_sum_every_start_of_each_finished_training(tmp_path):
    """Compile + chunk seconds over all starts where DONE has them, the last start's otherwise; trainings without
    DONE (still running) are left out, and a folder with none finished has None."""
    for algo, done in (
        ("bc", {"compile_s": 10.0, "run_s": 50.0, "total_compile_s": 30.0, "total_run_s": 90.0, "starts": 3}),
        ("dil", {"compile_s": 20.0, "run_s": 100.0}),
        ("oracle", None),
    ):
        (tmp_path / "bandit" / algo).mkdir(parents=True)
        if done is not None:
            (tmp_path / "bandit" / algo / "DONE").write_text(json.dumps(done))
    assert reproduce.core_seconds(tmp_path / "bandit") == 30 + 90 + 20 + 100
    assert reproduce.core_seconds(tmp_path / "bandit" / "oracle") is None


def test_compute_section_totals_the_wall_time_and_counts_a_training_once():
    bandit = {"name": "bandit", "core_s": 600.0}
    records = {"bandit": {"seconds": 120.0, "machine": "m1", "trainings": [bandit]},
               "theorem1": {"seconds": 30.0, "machine": "m2", "trainings": []},
               "figure1": {"seconds": 60.0, "machine": "m1", "trainings": [bandit]}}
    text = "\n".join(reproduce.compute_section(records))
    assert "Total wall time of the 3 finished parts: **3.5 min**, on m1; m2." in text
    assert "| bandit | 2.0 | 10 |" in text and "| theorem1 | 0.5 |  |" in text and "| figure1 | 1.0 |  |" in text
    assert reproduce.compute_section({}) == []


def test_seeds_text():
    assert reproduce.seeds_text([]) == "no trained seeds"
    assert reproduce.seeds_text([{"seed_start": 100, "count": 10, "trainings": ["bandit"]}]) == "seeds 100–109"
    assert reproduce.seeds_text([{"seed_start": 0, "count": 3, "trainings": ["a", "b"]},
                                 {"seed_start": 5, "count": 1, "trainings": ["c"]}]) == "seeds 0–2 (a, b); 5 (c)"


def _git(repo, *args):
    return subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false", *args],
                          cwd=repo, check=True, capture_output=True, text=True).stdout


def test_git_state_names_the_commit_and_the_changes_outside_the_report(tmp_path):
    repo = tmp_path / "repo"
    (repo / "src").mkdir(parents=True)
    (repo / "src" / "a.py").write_text("x = 1\n")
    (repo / "report").mkdir()
    (repo / "report" / "README.md").write_text("page\n")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "commit", "-qm", "one")
    head = _git(repo, "rev-parse", "HEAD").strip()
    (repo / "report" / "README.md").write_text("page, regenerated\n")  # The report's own files never count.
    (repo / "report" / "parts").mkdir()
    (repo / "report" / "parts" / "DONE.json").write_text("{}")
    assert reproduce.git_state(repo / "report", code=repo / "src") == {"commit": head, "dirty": False,
                                                                        "dirty_paths": []}
    (repo / "src" / "a.py").write_text("x = 2\n")
    (repo / "new.py").write_text("")
    state = reproduce.git_state(repo / "report", code=repo / "src")
    assert state["dirty"] is True and state["dirty_paths"] == ["src/a.py", "new.py"]
    (tmp_path / "plain").mkdir()
    assert reproduce.git_state(repo / "report", code=tmp_path / "plain")["commit"] is None


def test_changed_paths_skip_a_renames_old_path():
    assert reproduce.changed_paths("R  new.py\0old.py\0 M a.py\0?? report/\0") == ["new.py", "a.py", "report/"]


def _fake_part(runs):
    """A part with one training whose run writes the config.json ``python -m jaxdeconf.run`` would (no training)."""
    spec = reproduce.Training("t", "bandit", 3, extra=("train.iterations=2", "train.warmup=0"))

    def run(ctx):
        runs.append(ctx.out)
        settings = {"env": spec.env, "preset": ctx.scale.preset, "algo": ctx.algos, "seeds": spec.seeds,
                    "overrides": list(reproduce.training_overrides(ctx, spec))}
        ctx.run_dir(spec.name).mkdir(parents=True, exist_ok=True)
        (ctx.run_dir(spec.name) / "config.json").write_text(json.dumps(reproduce.current_config(settings)))
        return {"value": 1.5}

    return reproduce.Part("fake", "A fake part", 1, run, lambda ctx, n: f"value {n['value']}", lambda ctx: (spec,))


FAKE_ARGS = ["--only", "fake", "--algo", "bc,dil", "--set", "seed_start=100"]


def test_done_json_records_commit_seeds_time_and_each_trainings_config(tmp_path, monkeypatch):
    runs = []
    monkeypatch.setattr(reproduce, "PARTS", [_fake_part(runs)])
    heads = {_git(pathlib.Path(reproduce.__file__).parent, "rev-parse", "HEAD").strip()}
    assert reproduce.main(["--out", str(tmp_path), *FAKE_ARGS]) == 0
    heads.add(_git(pathlib.Path(reproduce.__file__).parent, "rev-parse", "HEAD").strip())  # Others may commit.
    done = json.loads((tmp_path / "parts" / "fake" / "DONE.json").read_text())
    assert done["commit"] in heads and isinstance(done["dirty"], bool) and done["seconds"] >= 0
    assert done["command"] == f"python -m jaxdeconf.reproduce --out {tmp_path} {' '.join(FAKE_ARGS)}"
    assert done["overrides"] == ["seed_start=100"] and done["algos"] == "bc,dil" and done["scale"] == "cpu"
    assert done["seeds"] == [{"seed_start": 100, "count": 3, "trainings": ["t"]}]
    (training,) = done["trainings"]
    assert training["overrides"] == ["train.iterations=2", "train.warmup=0", "seed_start=100"]
    assert training["config"] == json.loads((tmp_path / "runs" / "t" / "config.json").read_text())
    assert training["config"]["train"]["iterations"] == 2 and training["core_s"] is None
    page = (tmp_path / "README.md").read_text()
    dirty = " with uncommitted changes" if done["dirty"] else ""
    command = "python -m jaxdeconf.reproduce --scale cpu --only fake --algo bc,dil --set seed_start=100"
    assert (f"*Made at commit `{done['commit'][:7]}`{dirty} · seeds 100–102 · {done['seconds'] / 60:.1f} min wall "
            f"time · `{command}`*") in page
    assert f"Total wall time of the 1 finished parts: **{done['seconds'] / 60:.1f} min**, on {done['machine']}." in page


def test_page_is_the_same_wherever_the_report_lies(tmp_path, monkeypatch):
    """Two folders made by the same command hold the same page once they hold the same DONE.json: nothing else on
    the page changes from one run or folder to the next."""
    runs = []
    monkeypatch.setattr(reproduce, "PARTS", [_fake_part(runs)])
    for name in ("a", "b"):
        assert reproduce.main(["--out", str(tmp_path / name), *FAKE_ARGS]) == 0
    done = tmp_path / "a" / "parts" / "fake" / "DONE.json"
    (tmp_path / "b" / "parts" / "fake" / "DONE.json").write_bytes(done.read_bytes())
    reproduce.write_page(reproduce.Context(tmp_path / "b", reproduce.SCALES["cpu"]), reproduce.PARTS)
    page = (tmp_path / "a" / "README.md").read_text()
    assert (tmp_path / "b" / "README.md").read_text() == page and str(tmp_path) not in page


def test_a_stale_finished_part_is_kept_with_a_warning(tmp_path, monkeypatch, capsys):
    runs = []
    monkeypatch.setattr(reproduce, "PARTS", [_fake_part(runs)])
    assert reproduce.main(["--out", str(tmp_path), *FAKE_ARGS]) == 0
    path = tmp_path / "parts" / "fake" / "DONE.json"
    done = json.loads(path.read_text())
    done["trainings"][0]["config"]["train"]["iterations"] = 99  # As if the code had resolved 99 when it was made.
    path.write_text(json.dumps(done))
    capsys.readouterr()
    assert reproduce.main(["--out", str(tmp_path), *FAKE_ARGS]) == 0
    assert len(runs) == 1 and json.loads(path.read_text()) == done  # Reused as it is.
    warnings = [line for line in capsys.readouterr().out.splitlines() if "warning" in line]
    assert warnings == [f"reproduce: warning: finished part fake is stale, kept as is: runs/t: train.iterations: "
                        f"recorded 99, current 2; delete {path} to redo it"]
    assert reproduce.main(["--out", str(tmp_path), *FAKE_ARGS[:-2]]) == 0  # Without its --set seed_start=100.
    warnings = [line for line in capsys.readouterr().out.splitlines() if "warning" in line]
    assert warnings == [f"reproduce: warning: finished part fake is stale, kept as is: runs/t: train.iterations: "
                        f"recorded 99, current 2 (and 1 more); delete {path} to redo it"]
    assert reproduce.settings_differ(reproduce.Context(tmp_path, reproduce.SCALES["cpu"], "bc,dil"), done) == [
        "made with `--scale cpu --algo bc,dil --set seed_start=100`, this command has `--scale cpu --algo bc,dil`"]


def test_drop_keys_at_any_depth():
    data = {"grid": [{"count": 1.0, "seconds": 2.0}], "seconds": 3.0, "online": [[1, 2]]}
    assert reproduce.drop_keys(data, frozenset({"seconds"})) == {"grid": [{"count": 1.0}], "online": [[1, 2]]}


def test_theorem1_keeps_no_wall_time_in_its_committed_json(tmp_path, monkeypatch):
    from jaxdeconf import paper_figures

    result = {"grid": [{"demos": 10, "length": 3, "count": 50.0, "max_gap": 0.1, "seconds": 4.2}],
              "interventional_count": 54.1, "floor_gap": 0.01}

    def theorem1(out):
        out.mkdir(parents=True)
        (out / "theorem1.json").write_text(json.dumps(result) + "\n")
        return result

    monkeypatch.setattr(paper_figures, "theorem1", theorem1)
    ctx = reproduce.Context(out=tmp_path, scale=reproduce.SCALES["cpu"])
    assert reproduce.run_theorem1(ctx)["count"] == 50.0
    saved = json.loads((tmp_path / "parts" / "theorem1" / "theorem1.json").read_text())
    assert saved == reproduce.drop_keys(result, frozenset({"seconds"})) and "seconds" not in json.dumps(saved)


def test_figure1_trains_the_bandit_it_reads(tmp_path, monkeypatch):
    """Its trained rows need checkpoints, which a fresh clone lacks: the part trains (or reuses) the bandit first."""
    from jaxdeconf import paper_figures

    trained, read = [], []
    monkeypatch.setattr(reproduce, "train", lambda ctx, spec: trained.append(spec) or ctx.run_dir(spec.name))
    monkeypatch.setattr(paper_figures, "figure1", lambda out, results: read.append(results) or {"bc": {"count": 1.0}})
    ctx = reproduce.Context(out=tmp_path, scale=reproduce.SCALES["cpu"])
    assert reproduce.run_figure1(ctx) == {"bc": 1.0}
    assert trained == [reproduce.bandit_training(ctx)] and read == [tmp_path / "runs" / "bandit"]
