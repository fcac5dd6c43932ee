"""The CLI end to end on a tiny config, and every kind of bad input: one line, exit code 2, nothing lost."""

from __future__ import annotations

import json
import os
import pathlib

import numpy as np
import pytest
from conftest import TINY

from jaxdeconf.errors import ConfigError
from jaxdeconf.run import main

TINY_ARGS = [arg for k, v in TINY.items() for arg in ("--set", f"{k}={v}")]


def _snapshot(folder: pathlib.Path) -> dict[str, bytes]:
    """Every file's bytes, but the lock files' (each start writes its pid there)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".lock"}


def _bad(capfd, argv, expected):
    assert main(argv) == 2
    err = capfd.readouterr().err.strip()  # capfd: training runs in worker processes.
    assert len(err.splitlines()) == 1, err
    assert err.startswith("error: ") and expected in err, err


# Every kind of bad input a user can give: (arguments, what the one line must say). Each must end in exactly one
# ``error:`` line on stderr and exit code 2, before anything is written or compiled.
BAD_INPUTS = [
    (["--env", "cartpole"], "unknown env 'cartpole'; allowed: ant_goal, bandit, half_cheetah, lunar_lander"),
    (["--algo", "bc,sqil"], "unknown algorithm 'sqil'; allowed: bc, oracle, dil, dil_plus, dil_offline, dagger, gail"),
    (["--set", "dagger.anneal_iterations=-1"], "dagger.anneal_iterations=-1 is not allowed: need an integer >= 0"),
    (["--set", "gail.disc_steps=0"], "gail.disc_steps=0 is not allowed: need a positive integer"),
    (["--set", "gail.lr=nan"], "gail.lr=nan is not allowed: need a finite number"),
    (["--set", "gail.gamma=1.5"], "gail.gamma=1.5 is not allowed: need a number in [0, 1]"),
    (["--set", "gail.reward=sparse"], "gail.reward='sparse' is not allowed; allowed: discriminator, env"),
    (["--set", "dil.policy_latent=final"], "dil.policy_latent='final' is not allowed; allowed: current, matched"),
    (["--set", "model.latent_norm=expert"], "unknown field 'model.latent_norm'; allowed model.* fields: action_embed"),
    (["--set", "dil.policy_fusion=middle"], "dil.policy_fusion='middle' is not allowed; allowed: late, early"),
    (["--set", "gail.minibatches=5"], "gail.minibatches=5 must divide the generator's 128 episodes"),
    (["--set", "gail.nope=1"], "unknown field 'gail.nope'"),
    (["--algo", "bc,bc"], "algorithm 'bc' is given twice"),
    (["--algo", ","], "no algorithm given"),
    (["--seeds", "0"], "seeds=0 is not allowed: need a positive integer"),
    (["--seeds", "abc"], "argument --seeds: invalid int value: 'abc'"),
    (["--seeds", "100000"], "seeds=100000 is too large: the run needs an estimated"),
    (["--jobs", "-1"], "--jobs=-1 is not allowed"),
    (["--host-devices", "0"], "--host-devices=0 is not allowed: need a positive integer"),
    (["--coordinator", "nohost"], "--coordinator 'nohost' is not allowed: need HOST:PORT"),
    (["--coordinator", "localhost:1", "--num-processes", "0"], "--num-processes=0 is not allowed"),
    (["--coordinator", "localhost:1", "--num-processes", "2", "--process-id", "2"],
     "--process-id=2 is not allowed: need 0 .. 1 (--num-processes=2)"),
    (["--preset", "huge"], "unknown preset 'huge'"),
    (["--no-such-flag"], "unrecognized arguments: --no-such-flag"),
    (["--out", ""], "--out is empty"),
    (["--out", " "], "--out is empty"),
    (["--out", "/sys/jaxdeconf-results"], "cannot write /sys/jaxdeconf-results: "),  # A read-only file system.
    (["--set", "train.iterations=-3"], "train.iterations=-3 is not allowed: need a positive integer"),
    (["--set", f"train.iterations={10**12}"], "train.iterations=1000000000000 is too large: need at most 2147483647"),
    (["--set", "train.chunk=0"], "train.chunk=0 is not allowed"),
    (["--set", "train.chunk=1000000"], "train.chunk=1000000 is not allowed: need at most train.iterations=300"),
    (["--set", "train.warmup=-1"], "train.warmup=-1 is not allowed: need an integer >= 0"),
    (["--set", "train.warmup=300"], "train.warmup=300 is not allowed: need 0 <= warmup < train.iterations"),
    (["--set", "train.batch_size=64"], "train.batch_size=64 exceeds train.buffer_episodes=32"),
    (["--set", "train.policy_lr=nan"], "train.policy_lr=nan is not allowed: need a finite number"),
    (["--set", "train.policy_lr=inf"], "train.policy_lr=inf is not allowed: need a finite number"),
    (["--set", "train.policy_lr=0"], "train.policy_lr=0.0 is not allowed: need a number > 0"),
    (["--set", "train.encoder_lr=-1e-3"], "train.encoder_lr=-0.001 is not allowed: need a number > 0"),
    (["--set", "train.beta=NaN"], "train.beta=nan is not allowed: need a finite number"),
    (["--set", "train.beta=-0.5"], "train.beta=-0.5 is not allowed: need a number >= 0"),
    (["--set", "train.weight_decay=-inf"], "train.weight_decay=-inf is not allowed: need a finite number"),
    (["--set", "train.encoder_clip=nan"], "train.encoder_clip=nan is not allowed: need a finite number"),
    (["--set", "train.policy_clip=0"], "train.policy_clip=0.0 is not allowed: need a number > 0"),
    (["--set", "train.buffer_episodes=1000000000"], "train.buffer_episodes=1000000000 is too large: the run needs"),
    (["--set", "train.eval_episodes=0"], "train.eval_episodes=0 is not allowed"),
    (["--set", "train.nope=1"], "unknown field 'train.nope'"),
    (["--set", "nope=1"], "unknown field 'nope'"),
    (["--set", "train.iterations"], "--set 'train.iterations' is not of the form FIELD=VALUE"),
    (["--set", "train.iterations=2.5"], "train.iterations='2.5' is not a valid int"),
    (["--set", "model.gru=abc"], "model.gru='abc' is not a valid int"),
    (["--set", "model.gru=0"], "model.gru=0 is not allowed: need a positive integer"),
    (["--set", "dil.encoder=lstm"], "dil.encoder='lstm' is not allowed; allowed: gru, evidence, filter"),
    (["--set", "dil.encoder_deltas=maybe"], "dil.encoder_deltas='maybe' is not a boolean"),
    (["--set", "seed_start=-1"], "seed_start=-1 is not allowed: need an integer >= 0"),
    (["--set", f"seed_start={2**32}"], "seed_start=4294967296 is too large"),
    (["--set", f"seed_start={2**63}"], "seed_start=9223372036854775808 is too large"),
    (["--set", f"seed_start={2**31 - 5}"], "seed_start=2147483643 is too large: seeds seed_start .. seed_start"),
    (["--set", "env.p=1.5"], "p=1.5 is outside the allowed range (0, 1]"),
    (["--set", "env.q=0"], "q=0.0 is outside the allowed range (0, 1]"),
    (["--set", "env.p=nan"], "p=nan is outside the allowed range (0, 1]"),
    (["--set", "env.horizon=0"], "bandit horizon=0 is not allowed"),
    (["--set", "env.horizon=10000000"], "env.horizon=10000000 is too large: the run needs an estimated"),
    (["--set", f"env.horizon={2**40}"], "env.horizon=1099511627776 is too large: need at most 2147483647"),
    (["--set", "env.arms=1"], "bandit arms=1 is not allowed"),
    (["--set", "env.nope=1"], "unknown parameter 'nope' for env 'bandit'"),
    (["--env", "ant", "--set", "env.raw_bearing=maybe"],
     "env ant_goal parameter raw_bearing='maybe' is not a boolean (allowed: true, false)"),
]


@pytest.mark.timeout(300)
def test_bad_input_one_line_exit_2(tmp_path, capfd):
    out = ["--out", str(tmp_path / "r")]
    for argv, expected in BAD_INPUTS:
        _bad(capfd, [*argv, *out] if "--out" not in argv else argv, expected)
    assert not (tmp_path / "r").exists()  # Nothing was written for bad input.


def _results_folder(folder: pathlib.Path, config_text: str | None = None) -> list[str]:
    """A results folder as a first start leaves it (config.json only); returns the CLI arguments that made it."""
    from jaxdeconf.folders import prepare_folder
    from jaxdeconf.resolve import build

    argv = ["--algo", "bc", "--seeds", "2", "--out", str(folder), "--quiet", *TINY_ARGS]
    prepare_folder(folder, build("bandit", "cpu", ("bc",), 2, TINY), overwrite=False).release()
    if config_text is not None:
        (folder / "config.json").write_text(config_text)
    return argv


def _finished_bc(folder: pathlib.Path, rows: int) -> list[str]:
    """A results folder whose bc says DONE but whose metrics.jsonl holds only ``rows`` of its 8 rows."""
    argv = _results_folder(folder)
    (folder / "bc").mkdir()
    (folder / "bc" / "DONE").write_text("{}\n")
    lines = [json.dumps({"algo": "bc", "seed": s, "iteration": i}) for s in (0, 1) for i in range(1, 5)]
    (folder / "bc" / "metrics.jsonl").write_text("".join(line + "\n" for line in lines[:rows]))
    return argv


def test_bad_paths_and_damaged_files(tmp_path, capfd):
    """Paths that cannot be a results folder, and damaged result files: one line each, naming the file and how to
    recover, and nothing changed on disk."""
    a_file = tmp_path / "a_file"
    a_file.write_text("mine")
    _bad(capfd, ["--out", str(a_file)], "is a file, not a folder")
    _bad(capfd, ["--out", str(a_file / "sub")], "which is a file")
    assert a_file.read_text() == "mine"

    argv = _results_folder(tmp_path / "empty_config", "")
    _bad(capfd, argv, "config.json is unreadable (Expecting value")
    argv = _results_folder(tmp_path / "garbage_config", '{"env": "bandit"}')
    _bad(capfd, argv, "config.json is not a valid config (KeyError")
    argv = _finished_bc(tmp_path / "rows_missing", rows=5)
    _bad(capfd, argv, "bc/metrics.jsonl is damaged: it holds 5 of the 8 rows")
    (tmp_path / "rows_missing" / "bc" / "metrics.jsonl").unlink()
    _bad(capfd, argv, "bc/metrics.jsonl is damaged: it holds 0 of the 8 rows")
    argv = _finished_bc(tmp_path / "rows_twice", rows=8)
    with (tmp_path / "rows_twice" / "bc" / "metrics.jsonl").open("a") as f:
        f.write(json.dumps({"algo": "bc", "seed": 0, "iteration": 4}) + "\n")
    _bad(capfd, argv, "(some twice)")

    # A checkpoint folder the workers could not write (orbax would retry for minutes) is refused at once.
    argv = _finished_bc(tmp_path / "read_only", rows=8)
    (tmp_path / "read_only" / "bc" / "DONE").unlink()
    (tmp_path / "read_only" / "bc" / "checkpoints").mkdir()
    real_access = os.access
    with pytest.MonkeyPatch.context() as mp:  # Tests may run as root, for whom chmod does not stop writes.
        mp.setattr(os, "access", lambda p, mode: not str(p).endswith("checkpoints") and real_access(p, mode))
        _bad(capfd, argv, "bc/checkpoints: permission denied; make it writable, or use another --out")

    # The same config with an env parameter spelled differently is the same config.
    _results_folder(tmp_path / "typed")
    from jaxdeconf.folders import _check_same_config, typed_env_params
    from jaxdeconf.resolve import build

    _check_same_config(tmp_path / "typed" / "config.json",
                       typed_env_params(build("bandit", "cpu", ("bc",), 2, {**TINY, "env.horizon": "010"})))


def test_overwrite_refuses_folders_it_did_not_write(tmp_path, capfd):
    """--overwrite deletes only what this tool wrote: a folder of the user's files is refused, untouched."""
    mine = tmp_path / "mine"
    (mine / "notes").mkdir(parents=True)
    (mine / "thesis.tex").write_text("years of work")
    (mine / "notes" / "a.txt").write_text("a")
    before = _snapshot(mine)
    for extra in ([], ["--overwrite"]):
        _bad(capfd, ["--out", str(mine), *extra, *TINY_ARGS], "holds files this tool did not write")
        assert _snapshot(mine) == before
    # A results folder with a file of the user's added to it is refused too.
    argv = _results_folder(tmp_path / "results")
    (tmp_path / "results" / "my_notes.txt").write_text("keep")
    _bad(capfd, [*argv, "--overwrite"], "holds files this tool did not write (my_notes.txt)")
    assert (tmp_path / "results" / "my_notes.txt").read_text() == "keep"


def test_folder_in_use_is_refused(tmp_path, capfd):
    """A second run on a folder in use is refused with one line naming the running one."""
    from jaxdeconf.files import FolderLock

    argv = _results_folder(tmp_path / "busy")
    lock = FolderLock(tmp_path / "busy", "python -m jaxdeconf.run --the-first-one")
    try:
        _bad(capfd, argv, f"is in use by another run (pid {os.getpid()}, started")
        _bad(capfd, [*argv, "--overwrite"], "--the-first-one")
    finally:
        lock.release()
    assert (tmp_path / "busy" / "config.json").exists()


def test_memory_estimate_bounds_the_state(tiny_config):
    """The estimate is at least what the state of every seed really takes (checked on the real shapes)."""
    import jax

    from jaxdeconf.memory import estimate
    from jaxdeconf.train import build_algorithm, seed_keys

    config = tiny_config(seeds=3)
    for name in ("bc", "dil"):
        algo = build_algorithm(config, name)
        shapes = jax.eval_shape(jax.vmap(algo.init), seed_keys(config))
        real = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(shapes))
        guess = estimate(config, name, algo.env, algo.env_params)
        assert real <= guess.buffers + guess.params <= 20 * real, (name, real, guess)


@pytest.mark.timeout(300)
def test_memory_estimate_bounds_the_compiled_elbo_chunk(tiny_config):
    """dil's estimate is at least XLA's own account of its compiled chunk (arguments, outputs, temporaries) when the
    ELBO's K-step decoding is the largest working set: 8 episodes of 40 steps decoded 12 steps ahead."""
    import jax

    from jaxdeconf.memory import estimate
    from jaxdeconf.train import build_algorithm, compiled_chunk, seed_keys

    config = tiny_config(seeds=2, **{"env.horizon": "40", "train.prediction_steps": "12", "model.width": "32",
                                     "train.batch_size": "8"})
    algo = build_algorithm(config, "dil")
    compiled = compiled_chunk(algo, 1).lower(jax.jit(jax.vmap(algo.init))(seed_keys(config))).compile()
    xla = compiled.memory_analysis()
    xla_bytes = xla.argument_size_in_bytes + xla.output_size_in_bytes + xla.temp_size_in_bytes
    guess = estimate(config, "dil", algo.env, algo.env_params)
    assert xla_bytes <= guess.total <= 10 * xla_bytes, (xla_bytes, guess)
    bc = estimate(config, "bc", algo.env, algo.env_params)  # The rollouts' working set alone, the same for both.
    assert guess.working > 5 * bc.working, (guess, bc)


@pytest.mark.timeout(1200)  # Five runs of the CLI, three of which train.
def test_run_then_protect_results(tmp_path, capfd):
    folder = tmp_path / "run"
    argv = ["--algo", "dil", "--seeds", "2", "--out", str(folder), "--quiet", *TINY_ARGS]
    assert main(argv) == 0
    for name in ("config.json", "references.json", "summary.md", "summary.csv", "learning_curves.png", "p_best.png",
                 "dil/metrics.jsonl", "dil/curves.npz", "dil/DONE"):
        assert (folder / name).exists(), name
    assert "| dil |" in (folder / "summary.md").read_text()
    before = _snapshot(folder)

    # The same command on a finished run trains nothing and rewrites no results.
    capfd.readouterr()
    assert main(argv) == 0
    assert "already finished" in capfd.readouterr().out
    after = _snapshot(folder)
    for name, data in before.items():
        if name.endswith(("metrics.jsonl", ".npz", "DONE", "config.json")) or "checkpoints" in name:
            assert after[name] == data, name

    # Files a finished run writes after its last checkpoint are recomputed, identical, when damaged: a half-written
    # curves.npz (what a kill mid-write left before writes were atomic) and a cached references.json.
    with np.load(folder / "dil" / "curves.npz") as f:
        curves = {k: f[k] for k in f.files}
    data = (folder / "dil" / "curves.npz").read_bytes()
    (folder / "dil" / "curves.npz").write_bytes(data[: len(data) // 2])
    (folder / "references.json").write_text('{"expert_count": ')
    assert main(argv) == 0
    out = capfd.readouterr().out
    assert "curves.npz is missing or damaged: recomputing it" in out and "references.json is damaged" in out, out
    with np.load(folder / "dil" / "curves.npz") as f:
        assert {k: f[k].tobytes() for k in f.files} == {k: v.tobytes() for k, v in curves.items()}
    after = _snapshot(folder)
    for name in ("dil/metrics.jsonl", "references.json", "summary.csv"):
        assert after[name] == before[name], name

    # A different config on the same folder is refused, naming the difference.
    _bad(capfd, [*argv, "--set", "train.iterations=6"], "holds a different config (train.iterations: 4 there, 6 now)")
    assert _snapshot(folder) == after

    # A truncated checkpoint (half its largest array file) and a corrupt one are each reported in one line and left
    # in place (the truncated one's abandoned reads once printed a traceback per array as the worker shut down).
    (folder / "dil" / "DONE").unlink()
    for step in (folder / "dil" / "checkpoints").iterdir():
        largest = max((p for p in step.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
        largest.write_bytes(largest.read_bytes()[: largest.stat().st_size // 2])
    damaged = _snapshot(folder)
    _bad(capfd, argv, "is unreadable")
    assert _snapshot(folder) == damaged
    for p in (folder / "dil" / "checkpoints").rglob("*"):
        if p.is_file() and p.stat().st_size > 0:
            p.write_bytes(b"garbage")
    damaged = _snapshot(folder)
    _bad(capfd, argv, "is unreadable")
    assert _snapshot(folder) == damaged

    # --overwrite is the one way to start over.
    assert main([*argv, "--overwrite"]) == 0
    assert (folder / "dil" / "DONE").exists()


@pytest.mark.parametrize("value", ["1.0", "0.5"])
def test_probabilities_in_range_are_accepted(tmp_path, value):
    from jaxdeconf.resolve import build

    config = build("bandit", "cpu", ("bc",), 1, {"env.p": value, "env.q": value})
    assert config.env_params == {"p": value, "q": value}


def test_env_booleans_from_strings():
    """Command-line strings reach env parameters as the boolean they spell (``bool("false")`` would be True)."""
    from jaxdeconf.envs import make

    for text, expected in [("false", False), ("False", False), ("0", False), ("no", False), ("true", True),
                           ("1", True), ("yes", True)]:
        _, params = make("ant_goal", l1_reward=text, raw_bearing=text)
        assert params.l1_reward is expected and params.raw_bearing is expected
        _, params = make("half_cheetah", expert_sees_indicator=text)
        assert params.expert_sees_indicator is expected


def test_pinned_workers_get_disjoint_cores_or_none():
    """``--pin``: slot i of side-by-side workers gets its own ``host_devices`` cores, and no pinning when they do not
    all fit the available cores."""
    from jaxdeconf.platform import available_cores, worker_cores

    cores = available_cores()
    assert worker_cores(0, len(cores), 1) == cores[:1]
    assert worker_cores(len(cores) - 1, len(cores), 1) == cores[-1:]
    assert worker_cores(0, 1, len(cores)) == cores
    assert worker_cores(0, len(cores) + 1, 1) is None
    assert worker_cores(0, len(cores), 2) is None


def test_automatic_jobs_are_as_many_as_fit_and_explicit_jobs_must_fit(tiny_config, monkeypatch):
    """With memory for the two largest programs, an automatic run of three trains two at a time; ``--jobs 3`` is
    refused in one line; with no memory for the largest alone, an automatic run is refused too."""
    from jaxdeconf import memory
    from jaxdeconf.train import build_algorithm

    config = tiny_config(seeds=2)
    bc = build_algorithm(config, "bc")
    env, params = bc.env, bc.env_params
    sizes = sorted((memory.estimate(config, a, env, params).total for a in config.algos), reverse=True)
    monkeypatch.setattr(memory, "device_memory", lambda: (sizes[0] + sizes[1], "test device"))
    assert memory.check_fits(config, env, params, 3, automatic=True) == 2
    assert memory.check_fits(config, env, params, 2) == 2
    with pytest.raises(ConfigError, match=r"\(dil, .*, .* at once; .* but the test device has"):
        memory.check_fits(config, env, params, 3)
    monkeypatch.setattr(memory, "device_memory", lambda: (sizes[0] - 1, "test device"))
    with pytest.raises(ConfigError, match=r"is too large: .* \(dil at once"):
        memory.check_fits(config, env, params, 3, automatic=True)


def test_processes_share_a_gpu_unless_the_user_set_its_memory(monkeypatch):
    from jaxdeconf.platform import GPU_MEMORY_ENV, share_accelerator

    for name in GPU_MEMORY_ENV:
        monkeypatch.delenv(name, raising=False)
    share_accelerator()
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE")
    monkeypatch.setenv("XLA_CLIENT_MEM_FRACTION", ".3")
    share_accelerator()
    assert "XLA_PYTHON_CLIENT_PREALLOCATE" not in os.environ
