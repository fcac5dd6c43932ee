"""The CLI end to end on a tiny config, and every kind of bad input: one line, exit code 2, nothing lost."""

from __future__ import annotations

import pathlib

import pytest
from conftest import TINY

from jaxdeconf.run import main

TINY_ARGS = [arg for k, v in TINY.items() for arg in ("--set", f"{k}={v}")]


def _snapshot(folder: pathlib.Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _bad(capfd, argv, expected):
    assert main(argv) == 2
    err = capfd.readouterr().err.strip()  # capfd: training runs in worker processes.
    assert len(err.splitlines()) == 1, err
    assert err.startswith("error: ") and expected in err, err


def test_bad_input_one_line_exit_2(tmp_path, capfd):
    out = ["--out", str(tmp_path / "r")]
    _bad(capfd, ["--env", "cartpole", *out],
         "unknown env 'cartpole'; allowed: ant_goal, bandit, half_cheetah, lunar_lander")
    _bad(capfd, ["--algo", "bc,sqil", *out], "unknown algorithm 'sqil'; allowed: bc, oracle, dil, dagger, gail")
    _bad(capfd, ["--set", "dagger.anneal_iterations=-1", *out], "dagger.anneal_iterations=-1 is not allowed")
    _bad(capfd, ["--set", "gail.disc_steps=0", *out], "gail.disc_steps=0 is not allowed: need a positive integer")
    _bad(capfd, ["--set", "gail.lr=nan", *out], "gail.lr=nan is not allowed: need a finite number > 0")
    _bad(capfd, ["--set", "gail.gamma=1.5", *out], "gail.gamma=1.5 is not allowed: need a number in [0, 1]")
    _bad(capfd, ["--set", "gail.disc_input=image", *out], "gail.disc_input='image' is not allowed")
    _bad(capfd, ["--set", "gail.reward=sparse", *out], "gail.reward='sparse' is not allowed; allowed: discriminator")
    _bad(capfd, ["--set", "gail.minibatches=5", *out], "gail.minibatches=5 must divide the generator's 128 episodes")
    _bad(capfd, ["--set", "gail.nope=1", *out], "unknown field 'gail.nope'")
    _bad(capfd, ["--seeds", "0", *out], "seeds=0 is not allowed: need a positive integer")
    _bad(capfd, ["--set", "train.iterations=-3", *out], "train.iterations=-3 is not allowed")
    _bad(capfd, ["--set", "env.p=1.5", *out], "p=1.5 is outside the allowed range (0, 1]")
    _bad(capfd, ["--set", "env.q=0", *out], "q=0.0 is outside the allowed range (0, 1]")
    _bad(capfd, ["--set", "train.nope=1", *out], "unknown field 'train.nope'")
    _bad(capfd, ["--set", "model.gru=abc", *out], "model.gru='abc' is not a valid int")
    _bad(capfd, ["--set", "model.encoder=lstm", *out], "model.encoder='lstm' is not allowed; allowed: gru, evidence")
    _bad(capfd, ["--set", "model.encoder_deltas=maybe", *out], "model.encoder_deltas='maybe' is not a boolean")
    _bad(capfd, ["--env", "ant", "--set", "env.raw_bearing=maybe", *out],
         "env ant_goal parameter raw_bearing='maybe' is not a boolean (allowed: true, false)")
    _bad(capfd, ["--preset", "huge", *out], "unknown preset 'huge'")
    assert not (tmp_path / "r").exists()  # Nothing was written for bad input.


def test_run_then_protect_results(tmp_path, capfd):
    folder = tmp_path / "run"
    argv = ["--algo", "bc,dil", "--seeds", "2", "--out", str(folder), "--quiet", *TINY_ARGS]
    assert main(argv) == 0
    for name in ("config.json", "references.json", "summary.md", "summary.csv", "learning_curves.png", "p_best.png",
                 "bc/metrics.jsonl", "dil/metrics.jsonl", "dil/curves.npz", "dil/DONE"):
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

    # A different config on the same folder is refused, naming the difference.
    _bad(capfd, [*argv, "--set", "train.iterations=6"], "holds a different config (train.iterations: 4 there, 6 now)")
    assert _snapshot(folder) == after

    # A corrupt checkpoint is reported in one line and left in place.
    (folder / "dil" / "DONE").unlink()
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
    from jaxdeconf.config import build

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
