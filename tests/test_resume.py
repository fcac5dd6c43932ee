"""Checkpoints: an interrupted run resumes exactly (its own file, so pytest-xdist can run it beside test_train.py)."""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from conftest import TINY

from jaxdeconf import folders
from jaxdeconf.checkpoint import Checkpoints
from jaxdeconf.resolve import build
from jaxdeconf.train import resume_timing, timing_totals, train_algorithm


def _rows(folder):
    return [json.loads(line) for line in (folder / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.parametrize("overrides", [{}, {"dil.policy_latent": "matched"}], ids=["plain", "matched"])
def test_interrupted_run_resumes_exactly(tmp_path, tiny_config, monkeypatch, overrides):
    """Resumed from its checkpoint, a run is the uninterrupted one (also where the policy's latents are matched
    against the own buffer, which the checkpoint must restore whole)."""
    config = tiny_config(**overrides)
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
    timing = train_algorithm(config, "dil", tmp_path / "cut", progress=False)  # Resumes at iteration 2.
    assert calls == [2, 4]
    assert _rows(tmp_path / "cut") == _rows(tmp_path / "whole")
    # timing.jsonl: a compile per start and each kept chunk once; DONE sums them over both starts.
    lines = [json.loads(line) for line in (tmp_path / "cut" / "timing.jsonl").read_text().splitlines()]
    assert [r["from"] for r in lines if "compile_s" in r] == [0, 2]
    assert [r["iteration"] for r in lines if "chunk_s" in r] == [2, 4]
    assert timing["starts"] == 2 and timing["total_run_s"] == pytest.approx(sum(r.get("chunk_s", 0) for r in lines))
    assert timing["total_run_s"] > timing["run_s"] > 0 and timing["total_compile_s"] > timing["compile_s"] > 0
    assert json.loads((tmp_path / "cut" / "DONE").read_text()) == timing


def test_resume_timing_drops_chunks_past_the_checkpoint(tmp_path):
    path = tmp_path / "timing.jsonl"
    path.write_text('{"from": 0, "compile_s": 3.0}\n{"iteration": 2, "chunk_s": 1.5}\n{"iteration": 4, "chunk_s": 2.0}'
                    '\n{"itera')
    resume_timing(path, 2)
    assert path.read_text() == '{"from": 0, "compile_s": 3.0}\n{"iteration": 2, "chunk_s": 1.5}\n'
    assert timing_totals(path) == {"total_compile_s": 3.0, "total_run_s": 1.5, "starts": 1}


# --- Kills (SIGKILL) at chosen moments of a small CLI run, each followed by a rerun of the same command. ---

HELPER = pathlib.Path(__file__).with_name("kill_helper.py")
SEEDS = 2
CLI = ["--algo", "bc", "--seeds", str(SEEDS), "--quiet", "--jobs", "1",
       *[arg for k, v in TINY.items() for arg in ("--set", f"{k}={v}")]]
ITERATIONS = int(TINY["train.iterations"])


def _env(cache: pathlib.Path) -> dict[str, str]:
    """Subprocesses share a persistent compilation cache: the same programs, compiled once (this only saves time;
    a cached executable is the same program, so results are unchanged)."""
    return {**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
            "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "-1", "PYTHONPATH": str(HELPER.parent)}


def _cli(folder: pathlib.Path, cache: pathlib.Path, moment: str = "none", worker: bool = False,
         timeout: float = 1200) -> int:
    """Run the CLI (or, with ``worker``, one worker of a prepared folder) in a subprocess with the kill ``moment``."""
    argv = ["--worker", "bc", "--out", str(folder), "--quiet"] if worker else [*CLI, "--out", str(folder)]
    proc = subprocess.run([sys.executable, str(HELPER), moment, str(ITERATIONS), *argv], env=_env(cache),
                          timeout=timeout, capture_output=True, text=True)
    assert proc.returncode in (0, -signal.SIGKILL), proc.stderr[-3000:]
    return proc.returncode


def results_of(folder: pathlib.Path, algos: tuple[str, ...] = ("bc",)) -> dict[str, object]:
    """What a finished run's user reads: metrics files (bytes), curves (arrays) and the summary table."""
    out: dict[str, object] = {"summary.csv": (folder / "summary.csv").read_text()}
    for algo in algos:
        assert (folder / algo / "DONE").exists(), algo
        out[f"{algo}/metrics.jsonl"] = (folder / algo / "metrics.jsonl").read_bytes()
        with np.load(folder / algo / "curves.npz") as curves:
            out.update({f"{algo}/{k}": curves[k].tobytes() for k in curves.files})
    return out


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    """The reference: the same command, never interrupted (it also fills the compilation cache)."""
    base = tmp_path_factory.mktemp("kills")
    cache = base / "cache"
    assert _cli(base / "whole", cache) == 0
    return base, cache, results_of(base / "whole")


def _prepare(folder: pathlib.Path) -> None:
    """What the CLI's parent does before it starts a worker: the folder and its config.json."""
    config = build("bandit", "cpu", ("bc",), SEEDS, TINY)
    folders.prepare_folder(folder, config, overwrite=False).release()


MOMENTS = [
    # (moment, what is killed). The kill lands in the worker, except for config.json (the parent writes it).
    "before_done",  # Between the last checkpoint and DONE.
    pytest.param("curves.npz", marks=pytest.mark.slow),  # While curves.npz is written.
    pytest.param("checkpoint_write", marks=pytest.mark.slow),  # While orbax writes a checkpoint.
    pytest.param("config.json", marks=pytest.mark.slow),  # While config.json is written.
    pytest.param("metrics.jsonl", marks=pytest.mark.slow),  # During the resume's rewrite of metrics.jsonl.
]


@pytest.mark.timeout(2400)
@pytest.mark.parametrize("moment", MOMENTS)
def test_kill_then_rerun_is_identical(uninterrupted, moment):
    base, cache, expected = uninterrupted
    folder = base / moment
    if moment == "config.json":
        assert _cli(folder, cache, moment) == -signal.SIGKILL
        assert not (folder / "config.json").exists()
    else:
        _prepare(folder)
        if moment == "metrics.jsonl":  # Rows past the last checkpoint first, then a kill while resuming drops them.
            assert _cli(folder, cache, "after_metrics_append", worker=True) == -signal.SIGKILL
        assert _cli(folder, cache, moment, worker=True) == -signal.SIGKILL
        assert not (folder / "bc" / "DONE").exists()
    assert _cli(folder, cache) == 0  # The same command again: it resumes and finishes.
    assert results_of(folder) == expected
    assert not [p for p in folder.rglob(".tmp-*")], "temporary files left behind"


KILL_SITE = pathlib.Path(__file__).with_name("kill_site")  # Its sitecustomize.py arms the kill points.
RANDOM_ARGV = ["--algo", "bc,dil", "--seeds", "3", "--quiet",
               *[a for k, v in TINY.items() for a in ("--set", f"{k}={v}")]]


def _random_run(folder: pathlib.Path, cache: pathlib.Path, timeout: float = 1800, **env: str) -> subprocess.Popen:
    """Start the 3-seed bc + dil bandit CLI run in its own process group, with the kill site on its path."""
    env = {**_env(cache), "PYTHONPATH": str(KILL_SITE), **env}
    return subprocess.Popen([sys.executable, "-m", "jaxdeconf.run", *RANDOM_ARGV, "--out", str(folder)], env=env,
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _finish(proc: subprocess.Popen, timeout: float = 1800) -> int:
    try:
        proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    return proc.returncode


def _kill_at_random_time(folder, cache, rng, length) -> str | None:
    """SIGKILL the whole run (parent and workers at once) at a time uniform over an uninterrupted run's length."""
    at = float(rng.uniform(0.5, length))
    proc = _random_run(folder, cache)
    try:
        proc.wait(timeout=at)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
    _finish(proc, 60)
    return f"all processes at {at:.1f} s" if proc.returncode == -signal.SIGKILL else None


def _kill_at_random_event(folder, cache, rng, counts) -> str | None:
    """SIGKILL one process (the parent, or one worker, as the OOM killer would) just before one of its file writes,
    renames or checkpoint saves, drawn uniformly among the events that process has in an uninterrupted run."""
    role = str(rng.choice(sorted(counts)))
    k = int(rng.integers(1, counts[role] + 1))
    code = _finish(_random_run(folder, cache, JAXDECONF_KILL_AT=f"{role}:{k}"))
    return f"{role} before its event {k} of {counts[role]}" if code != 0 else None


@pytest.mark.slow
@pytest.mark.timeout(7200)
def test_random_kills_resume_identically(tmp_path):
    """20 random SIGKILLs of a 3-seed bc + dil bandit run, alternately at a random time (every process at once) and
    at a random file-system event of one process; after each, the same command again finishes with results
    identical to the uninterrupted run's. A drawn moment the run got past unharmed is drawn again."""
    rng = np.random.default_rng(19)
    cache, counted = tmp_path / "cache", tmp_path / "counts"
    counted.mkdir()
    assert _finish(_random_run(tmp_path / "whole", cache)) == 0  # Also fills the compilation cache.
    expected = results_of(tmp_path / "whole", ("bc", "dil"))
    t0 = time.monotonic()
    assert _finish(_random_run(tmp_path / "timing", cache, JAXDECONF_KILL_COUNT=str(counted))) == 0
    length = time.monotonic() - t0
    counts = {p.name: int(p.read_text()) for p in counted.iterdir()}
    assert set(counts) == {"parent", "bc", "dil"} and min(counts.values()) > 0, counts
    print(f"uninterrupted run {length:.1f} s; file-system events per process {counts}")
    kills = draws = 0
    while kills < int(os.environ.get("KILL_TRIALS", "20")):  # Fewer, to try the test on a busy machine.
        draws += 1
        assert draws < 60, "the drawn moments keep missing the run"
        folder = tmp_path / f"kill{draws}"
        how = (_kill_at_random_time(folder, cache, rng, length) if kills % 2 == 0
               else _kill_at_random_event(folder, cache, rng, counts))
        if how is None:
            continue
        kills += 1
        print(f"kill {kills}: {how}", flush=True)
        assert _finish(_random_run(folder, cache)) == 0, f"rerun after kill {kills} ({how}) failed"
        assert results_of(folder, ("bc", "dil")) == expected, f"kill {kills} ({how})"
        assert not [p for p in folder.rglob(".tmp-*")], "temporary files left behind"


def test_non_finite_loss_stops_with_one_line(tiny_config):
    """NaN after warm-up (or an infinity anywhere) names the algorithm, seeds and iteration; warm-up NaN is fine."""
    from jaxdeconf.train import DivergedError, check_finite

    config = tiny_config(seeds=3)  # Warm-up: iteration 1.
    nan = float("nan")
    evals = {"eval_return": np.ones(3), "p_best_online": np.full((3, 10), nan)}
    check_finite("bc", config, 0, {"policy_loss": np.array([[nan, 1.0]] * 3)}, evals)  # Warm-up NaN: fine.
    with pytest.raises(DivergedError, match=r"^bc diverged: policy_loss is nan at iteration 4 for seed\(s\) 1, 2; "
                                            r".*last good checkpoint \(iteration 2\) is kept"):
        check_finite("bc", config, 2, {"policy_loss": np.array([[1.0, 1.0], [1.0, nan], [1.0, nan]])}, evals)
    with pytest.raises(DivergedError, match=r"elbo_loss is inf at iteration 1 for seed\(s\) 0"):
        check_finite("dil", config, 0, {"elbo_loss": np.array([[np.inf, 1.0], [1.0, 1.0], [1.0, 1.0]])}, evals)
    with pytest.raises(DivergedError, match=r"eval_return is nan at iteration 2 for seed\(s\) 2"):
        check_finite("dil", config, 0, {"loss": np.ones((3, 2))}, {**evals, "eval_return": np.array([1, 1, nan])})


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_diverging_run_keeps_last_good_checkpoint(tmp_path, tiny_config):
    """A learning rate that blows the policy up stops training at the end of the chunk; nothing bad is written."""
    from jaxdeconf.train import DivergedError

    config = tiny_config(**{"train.policy_lr": "1e30"})
    with pytest.raises(DivergedError, match="bc diverged: policy_loss is"):
        train_algorithm(config, "bc", tmp_path / "bc", progress=False)
    rows = _rows(tmp_path / "bc")
    done = Checkpoints(tmp_path / "bc" / "checkpoints").latest_step() or 0
    assert all(r["iteration"] <= done for r in rows) and not (tmp_path / "bc" / "DONE").exists()


@pytest.mark.timeout(900)
@pytest.mark.parametrize("signum", [pytest.param(signal.SIGTERM, marks=pytest.mark.slow),
                                    pytest.param(signal.SIGINT, marks=pytest.mark.slow)])
def test_signal_stops_workers_with_one_line(tmp_path, signum):
    """SIGTERM to the run (or Ctrl-C, which a terminal sends to every process of it) stops its workers too."""
    folder = tmp_path / "r"
    proc = subprocess.Popen([sys.executable, "-m", "jaxdeconf.run", *CLI, "--out", str(folder)],
                            start_new_session=True, stderr=subprocess.PIPE, text=True)
    lock = folder / "bc" / ".lock"
    deadline = time.monotonic() + 600
    while not (lock.exists() and lock.read_text().startswith("pid")) and time.monotonic() < deadline:
        time.sleep(0.2)
    worker = int(lock.read_text().split()[1].rstrip(","))
    if signum == signal.SIGTERM:
        proc.send_signal(signum)
    else:
        os.killpg(proc.pid, signum)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signum
    assert err.strip().splitlines() == [f"error: stopped by {signal.Signals(signum).name}; finished chunks are "
                                        "checkpointed: run the same command again to resume"], err
    with pytest.raises(ProcessLookupError):
        os.kill(worker, 0)  # No orphan left.


def test_resume_metrics_drops_exactly_the_rows_past_the_checkpoint(tmp_path, tiny_config):
    """Rows past the checkpoint, a partial last line and garbage go (by an atomic rewrite); missing rows are an
    error naming the file; rows are strict JSON (NaN written as null)."""
    from jaxdeconf.errors import ConfigError
    from jaxdeconf.files import append_lines, dumps_row, read_rows
    from jaxdeconf.train import resume_metrics

    config = tiny_config(seeds=2)
    path = tmp_path / "metrics.jsonl"
    rows = [{"algo": "bc", "seed": s, "iteration": i, "policy_loss": float("nan") if i == 1 else 0.5}
            for i in (1, 2, 3) for s in (0, 1)]
    append_lines(path, [dumps_row(r) for r in rows])
    kept = path.read_text().splitlines()[:4]  # Iterations 1 and 2.
    for line in path.read_text().splitlines():
        json.loads(line, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    with path.open("a") as f:
        f.write('not json\n{"algo": "bc", "seed": 0, "itera')  # Garbage, then what a kill mid-append leaves.
    inode = path.stat().st_ino
    resume_metrics(path, config, "bc", done=2)
    assert path.read_text().splitlines() == kept
    assert path.stat().st_ino != inode  # Replaced by a new file, not rewritten in place.
    assert np.isnan(read_rows(path)[0]["policy_loss"]) and read_rows(path)[3]["policy_loss"] == 0.5
    inode = path.stat().st_ino
    resume_metrics(path, config, "bc", done=2)  # Nothing to drop: the file is left alone.
    assert path.stat().st_ino == inode and path.read_text().splitlines() == kept
    with pytest.raises(ConfigError, match=r"metrics.jsonl is damaged: it holds 4 of the 6 rows of the 3 iterations"):
        resume_metrics(path, config, "bc", done=3)
