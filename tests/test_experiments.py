"""The scripts in experiments/, run as a user runs them: each has a --help, refuses bad input with one line and exit
code 2, and on a tiny setting writes the files it promises."""

from __future__ import annotations

import json
import math
import pathlib
import subprocess
import sys

import pytest

EXPERIMENTS = pathlib.Path(__file__).parents[1] / "experiments"
SCRIPTS = {
    "bench.py": "seconds per iteration",
    "bench_scale.py": "One process of `make bench`'s seeds section",
    "train_expert.py": "PPO",
    "train_brax_expert.py": "Brax",
    "validate_lunar_lander.py": "Our JAX LunarLander against gymnasium's LunarLander-v3",
    "paper_scale.py": "ready for the accelerator",
}


def run(script: str, *args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    """``python experiments/<script> args`` in a subprocess, its output captured."""
    return subprocess.run([sys.executable, str(EXPERIMENTS / script), *args], capture_output=True, text=True,
                          timeout=timeout, check=False)


def test_experiments_holds_only_the_scripts_a_user_runs():
    """Expert training, validation against gymnasium and the benchmarks; nothing else."""
    assert sorted(p.name for p in EXPERIMENTS.glob("*.py")) == sorted(SCRIPTS)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_help_describes_the_script(script):
    proc = run(script, "--help", timeout=100)
    assert proc.returncode == 0, proc.stderr
    assert SCRIPTS[script].lower() in " ".join(proc.stdout.split()).lower(), proc.stdout


@pytest.mark.timeout(120)
@pytest.mark.parametrize(("script", "args", "message"), [
    ("bench.py", ["nope"], "error: unknown bench section 'nope'; allowed: seeds, e2e"),
    ("bench_scale.py", ["--devices", "0"], "error: --devices=0 is not allowed: need a positive integer"),
    ("validate_lunar_lander.py", ["--episodes", "0"], "error: --episodes=0 is not allowed: need a positive integer"),
    ("paper_scale.py", ["check", "--algo", "bc,sqil"], "error: unknown algorithm 'sqil'; allowed: bc, oracle"),
])
def test_bad_input_is_one_line_and_exit_code_2(script, args, message):
    proc = run(script, *args, timeout=100)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith(message), proc.stderr


@pytest.mark.timeout(300)
def test_validation_writes_both_engines_rows(tmp_path):
    """Two episodes per controller: four rows (ours and gymnasium's, heuristic and random), rates that sum to one,
    and the heuristic lands gymnasium's lander more often than random actions do (random actions always crash)."""
    proc = run("validate_lunar_lander.py", "--episodes", "2", "--out", str(tmp_path), timeout=280)
    assert proc.returncode == 0, proc.stderr
    def strict(constant: str) -> None:
        raise ValueError(f"validation.json holds {constant}, which strict JSON readers refuse")

    rows = json.loads((tmp_path / "validation.json").read_text(), parse_constant=strict)
    assert len(rows) == 4 and (tmp_path / "validation.md").exists()
    for row in rows.values():
        assert row["episodes"] == 2
        assert math.isclose(row["landing_rate"] + row["crash_rate"] + row["timeout_rate"], 1.0)
    gym = {k.split(", ")[1]: v for k, v in rows.items() if k.startswith("gymnasium")}
    assert gym["heuristic"]["return_mean"] > gym["random actions"]["return_mean"]
    assert gym["random actions"]["length_landed_mean"] is None  # None landed: null, not NaN.
    again = run("validate_lunar_lander.py", "--episodes", "2", "--out", str(tmp_path), timeout=100)
    assert again.returncode == 2 and "pass --overwrite" in again.stderr  # Nothing already written is replaced.


@pytest.mark.timeout(300)
def test_train_expert_writes_a_loadable_expert(tmp_path):
    """A 2048-step PPO run writes the expert's two files into --out, with the command and its evaluation."""
    proc = run("train_expert.py", "--steps", "2048", "--num-envs", "8", "--rollout", "16", "--minibatches", "2",
               "--out", str(tmp_path), timeout=280)
    assert proc.returncode == 0, proc.stderr
    meta = json.loads((tmp_path / "lunar_lander.json").read_text())
    assert meta["command"].startswith("python experiments/train_expert.py --steps 2048")
    assert meta["ppo"]["total_steps"] == 2048 and (tmp_path / "lunar_lander.msgpack").stat().st_size > 0
    assert all(math.isfinite(row["mean_return"]) for row in meta["evaluation_100_episodes_each"].values())


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_train_brax_expert_tiny_run(tmp_path):
    """A 4096-step Brax PPO run on half_cheetah writes the expert's two files into --out."""
    proc = run("train_brax_expert.py", "--env", "half_cheetah", "--steps", "4096", "--num-envs", "8",
               "--batch-size", "8", "--minibatches", "2", "--unroll", "4", "--evals", "1",
               "--work", str(tmp_path / "work"), "--out", str(tmp_path / "out"), timeout=880)
    assert proc.returncode == 0, proc.stderr
    meta = json.loads((tmp_path / "out" / "half_cheetah.json").read_text())
    assert meta["command"].startswith("python experiments/train_brax_expert.py --env half_cheetah")


@pytest.mark.slow
@pytest.mark.timeout(5400)
def test_every_paper_preset_compiles_runs_and_fits_an_h100():
    """One iteration of every algorithm at every env's paper preset on this CPU, each program's memory (the
    estimate, at least XLA's account of the compiled chunk, at 5 seeds) under the 75% of an H100's 80 GB that JAX's
    allocator may use."""
    proc = run("paper_scale.py", "check", timeout=5300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    rows = [line for line in proc.stdout.splitlines() if line.startswith("| ") and "|---" not in line][1:]
    assert len(rows) == 4 * 6, proc.stdout
    assert all(row.rstrip(" |").endswith("yes") for row in rows), proc.stdout
