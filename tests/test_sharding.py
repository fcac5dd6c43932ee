"""The seed axis split over devices: the same metrics on one device, on two host devices, across a resume on another
device count, and (slow tier) over two processes joined by ``jax.distributed``."""

from __future__ import annotations

import json
import pathlib
import shutil
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest
from conftest import TINY, assert_rows_close

from jaxdeconf.checkpoint import Checkpoints
from jaxdeconf.sharding import seed_layout

TINY_ARGS = [arg for k, v in TINY.items() for arg in ("--set", f"{k}={v}")]


def _cli(folder: pathlib.Path, *extra: str, seeds: int = 3, algo: str = "dil", timeout: float = 600) -> None:
    """One CLI run in its own process (a process's device count is fixed when JAX starts)."""
    cmd = [sys.executable, "-m", "jaxdeconf.run", "--algo", algo, "--seeds", str(seeds), "--quiet", "--jobs", "1",
           "--out", str(folder), *TINY_ARGS, *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]


def _results(folder: pathlib.Path, algo: str = "dil") -> dict[str, bytes]:
    """Metrics (bytes) and every curve (bytes) of a finished run."""
    out = {"metrics": (folder / algo / "metrics.jsonl").read_bytes()}
    with np.load(folder / algo / "curves.npz") as curves:
        out.update({k: curves[k].tobytes() for k in curves.files})
    return out


def test_layout_pads_seeds_to_the_device_count():
    fake = type("Mesh", (), {"size": 4})()  # Only the mesh's size matters to the padding.
    assert [seed_layout(1).__class__(s, fake).padded for s in (1, 3, 4, 5, 8)] == [4, 4, 4, 8, 8]
    layout = seed_layout(3, jax.devices()[:1])
    assert (layout.devices, layout.padded) == (1, 3)
    host = layout.to_host({"x": jax.numpy.arange(8).reshape(4, 2)})  # E.g. 3 seeds padded to 4.
    np.testing.assert_array_equal(host["x"], np.arange(6).reshape(3, 2))  # The real seeds only, as NumPy.


def test_checkpoint_restores_any_seed_count(tmp_path):
    """A checkpoint of 4 (padded) seeds restores into 3 (the first three) or 6 (padding repeats saved seeds)."""
    from flax import struct

    @struct.dataclass
    class State:
        x: jax.Array
        key: jax.Array

    def state(n: int, offset: float = 0.0) -> State:
        return State(x=jax.numpy.arange(n * 2, dtype=jax.numpy.float32).reshape(n, 2) + offset,
                     key=jax.vmap(jax.random.key)(jax.numpy.arange(n) + 10))

    ckpt = Checkpoints(tmp_path / "c")
    ckpt.save(2, state(4))
    for n in (3, 4, 6):
        got = ckpt.restore(2, state(n, offset=100.0))
        np.testing.assert_array_equal(got.x, np.asarray(state(4).x)[np.arange(n) % 4])
        np.testing.assert_array_equal(jax.random.key_data(got.key),
                                      np.asarray(jax.random.key_data(state(4).key))[np.arange(n) % 4])
    ckpt.close()


def _close(a: dict[str, bytes], b: dict[str, bytes]) -> None:
    """Same metrics rows and curves up to float32 rounding (see the test below)."""
    rows = [[json.loads(line) for line in r["metrics"].decode().splitlines()] for r in (a, b)]
    assert_rows_close(*rows)
    for key in a.keys() - {"metrics"}:
        np.testing.assert_allclose(np.frombuffer(a[key], np.float32), np.frombuffer(b[key], np.float32),
                                   rtol=1e-4, atol=1e-5, err_msg=key)


@pytest.mark.slow  # Three CLI runs of dil: 2-3 min on two cores.
@pytest.mark.timeout(900)
def test_two_host_devices_match_one_device_and_resume_on_one(tmp_path):
    """3 seeds (padded to 4) on 2 host devices give the metrics and curves of the same run on one device, to
    float32 rounding: XLA compiles the partitioned program with other fusions (its AdamW updates differ in the last
    bit), so bytes match only between runs on the same number of devices. A run taken back to its first chunk's
    checkpoint on 2 devices resumes on one device to the same results."""
    _cli(tmp_path / "one")
    _cli(tmp_path / "two", "--host-devices", "2")
    _close(_results(tmp_path / "two"), _results(tmp_path / "one"))

    # Take the 2-device run back to its first chunk (the resume trims metrics rows past the checkpoint itself).
    last = int(TINY["train.iterations"])
    shutil.rmtree(tmp_path / "two" / "dil" / "checkpoints" / str(last))
    for name in ("DONE", "curves.npz"):
        (tmp_path / "two" / "dil" / name).unlink()
    _cli(tmp_path / "two")
    _close(_results(tmp_path / "two"), _results(tmp_path / "one"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_two_processes_match_one_process(tmp_path):
    """8 seeds over 2 processes x 2 CPU devices (jax.distributed on localhost, process 0 writing) give the metrics
    and curves of the same 8 seeds in one process on 4 host devices, to the byte (the same partitioned program), and
    of one process on one device to float32 rounding."""
    _cli(tmp_path / "four", "--host-devices", "4", seeds=8, algo="bc")
    _cli(tmp_path / "one", seeds=8, algo="bc")
    port = _free_port()
    cmd = [sys.executable, "-m", "jaxdeconf.run", "--algo", "bc", "--seeds", "8", "--quiet", "--out",
           str(tmp_path / "multi"), "--host-devices", "2", "--coordinator", f"localhost:{port}",
           "--num-processes", "2", *TINY_ARGS]
    procs = [subprocess.Popen([*cmd, "--process-id", str(i)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for i in range(2)]
    try:
        outs = [p.communicate(timeout=900) for p in procs]
    finally:
        for p in procs:
            p.kill()
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-3000:]
    assert _results(tmp_path / "multi", "bc") == _results(tmp_path / "four", "bc")
    _close(_results(tmp_path / "multi", "bc"), _results(tmp_path / "one", "bc"))
    assert outs[1][0] == ""  # Process 1 prints nothing; process 0 prints the summary.
    assert "| bc" in outs[0][0], outs[0][0]
