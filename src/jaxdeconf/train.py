"""The host loop: compile a seed-vmapped chunk once, run it chunk by chunk, show progress, write metrics and
checkpoints, and resume from the last checkpoint when a run is started again on the same folder."""

from __future__ import annotations

import dataclasses
import functools
import io
import json
import pathlib
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from jaxdeconf.algos import make_algorithm
from jaxdeconf.algos.base import Algorithm, TrainState
from jaxdeconf.checkpoint import Checkpoints
from jaxdeconf.config import Config
from jaxdeconf.envs import make
from jaxdeconf.errors import ConfigError
from jaxdeconf.files import (
    append_lines,
    dumps_row,
    parse_object,
    parse_row,
    read_lines,
    remove_temporaries,
    write_atomic,
)
from jaxdeconf.sharding import SeedLayout, is_primary, seed_layout, sync

CURVES = ("p_best_online", "p_best_expert")  # Every run's curves.npz holds these; any other array output also goes
# there (the diagnostics: per-step θ probes, per-episode θ, returns and extras).


def seed_keys(config: Config, count: int | None = None) -> jax.Array:
    """One typed key per seed; seed i is ``jax.random.key(seed_start + i)`` for every algorithm. ``count`` (default
    ``config.seeds``) may ask for padding seeds past the config's."""
    return jax.vmap(jax.random.key)(jnp.arange(config.seed_start, config.seed_start + (count or config.seeds)))


def build_algorithm(config: Config, name: str) -> Algorithm:
    """The named algorithm on the config's environment."""
    env, env_params = make(config.env, **config.env_params)
    return make_algorithm(name, env, env_params, config)


def over_seeds(fn: Any, config: Config, layout: SeedLayout | None = None) -> Any:
    """``fn`` of one seed as the jitted program of every seed: each device runs its own seeds, ``train.seed_batch``
    at a time (``shard_map`` over the layout's mesh; no communication between devices)."""
    batch = config.train.seed_batch

    def per_device(xs: Any) -> Any:
        return jax.vmap(fn)(xs) if batch == 0 else jax.lax.map(fn, xs, batch_size=batch)

    if layout is None:
        return jax.jit(per_device)
    spec = layout.sharding.spec
    # No collectives inside, so the varying-axis check (which scans with constant initial carries trip) is off.
    return jax.jit(jax.shard_map(per_device, mesh=layout.mesh, in_specs=spec, out_specs=spec, check_vma=False))


def compiled_chunk(algo: Algorithm, length: int, layout: SeedLayout | None = None) -> Any:
    """The program of a chunk of ``length`` iterations for every seed (``over_seeds``)."""
    return over_seeds(functools.partial(algo.train_chunk, length=length), algo.config, layout)


def initial_states(algo: Algorithm, config: Config, layout: SeedLayout) -> TrainState:
    """Every seed's fresh state (padding seeds included), placed on the layout's devices."""
    keys = layout.place(np.asarray(jax.random.key_data(seed_keys(config, layout.padded))))  # Raw: any process count.
    return over_seeds(lambda k: algo.init(jax.random.wrap_key_data(k)), config, layout)(keys)


def chunk_rows(name: str, config: Config, start: int, per_iter: dict, evals: dict) -> list[dict[str, Any]]:
    """Metrics rows (one per seed and iteration) from one chunk's outputs; eval metrics go on its last iteration."""
    per_iter = jax.tree.map(np.asarray, per_iter)
    evals = {k: np.asarray(v) for k, v in evals.items() if np.ndim(v) == 1}  # One number per seed; arrays: curves.
    length = next(iter(per_iter.values())).shape[1] if per_iter else 0
    rows = []
    for seed in range(config.seeds):
        for i in range(length):
            row = {"algo": name, "seed": config.seed_start + seed, "iteration": start + i + 1}
            row.update({k: float(v[seed, i]) for k, v in per_iter.items()})
            if i == length - 1:
                row.update({k: float(v[seed]) for k, v in evals.items()})
            rows.append(row)
    return rows


class DivergedError(ConfigError):
    """A non-finite loss or return: the run stops, keeping its last good checkpoint."""


def check_finite(name: str, config: Config, start: int, per_iter: dict, evals: dict) -> None:
    """Raise DivergedError naming the algorithm, seeds and first iteration where a loss or return is NaN or infinite.

    Policy losses are NaN by design during warm-up (no policy update yet), so NaN counts only after it.
    """
    length = next(iter(per_iter.values())).shape[1] if per_iter else 1
    for key in sorted(k for k in {**per_iter, **evals} if "loss" in k or "return" in k):
        if key in per_iter:
            value = np.asarray(per_iter[key], np.float64)  # [seeds, length]
            iteration = start + 1 + np.arange(length)
            bad = np.isinf(value) | (np.isnan(value) & (iteration > config.train.warmup)[None])
        else:  # An evaluation belongs to its chunk's last iteration, and is never NaN by design.
            value = np.asarray(evals[key], np.float64)[:, None]
            iteration = np.array([start + length])
            bad = ~np.isfinite(value)
        if bad.any():
            seeds = [config.seed_start + s for s in np.flatnonzero(bad.any(axis=1))]
            raise DivergedError(
                f"{name} diverged: {key} is {value[bad][0]} at iteration {int(iteration[bad.any(axis=0)][0])} for "
                f"seed(s) {', '.join(map(str, seeds))}; training stopped and its last good checkpoint "
                f"(iteration {start}) is kept; lower the learning rates (train.policy_lr, train.encoder_lr) and "
                "start over with --overwrite"
            )


def resume_metrics(path: pathlib.Path, config: Config, name: str, done: int) -> None:
    """Make ``metrics.jsonl`` hold exactly the rows of the ``done`` checkpointed iterations.

    Rows past ``done`` (a chunk whose checkpoint never landed), a partial last line (a kill mid-append) and unreadable
    lines are dropped by an atomic rewrite, never in place; rows missing before ``done`` are an error, since nothing
    can recompute them.
    """
    lines = read_lines(path)
    keep = [line for line in lines if (row := parse_row(line)) is not None and row["iteration"] <= done]
    check_rows(path, config, name, [parse_row(line) for line in keep], done)
    if len(keep) != len(lines):
        write_atomic(path, "".join(line + "\n" for line in keep))


def check_rows(path: pathlib.Path, config: Config, name: str, rows: list[dict], done: int) -> None:
    """Raise ConfigError unless ``rows`` are exactly one per seed and iteration 1 .. ``done``."""
    expected = {(config.seed_start + s, i) for s in range(config.seeds) for i in range(1, done + 1)}
    found = [(r["seed"], r["iteration"]) for r in rows]
    if len(found) != len(expected) or set(found) != expected:
        raise ConfigError(
            f"{path} is damaged: it holds {len(set(found) & expected)} of the {len(expected)} rows of the "
            f"{done} iterations done{' (some twice)' if len(set(found)) != len(found) else ''}; delete "
            f"{path.parent} to retrain {name}, or pass --overwrite to start over"
        )


def resume_timing(path: pathlib.Path, done: int) -> None:
    """Drop from ``timing.jsonl`` the chunks past the ``done`` checkpointed iterations (and a partial last line)."""
    lines = read_lines(path)
    keep = [line for line in lines if (row := parse_object(line)) is not None and row.get("iteration", 0) <= done]
    if len(keep) != len(lines):
        write_atomic(path, "".join(line + "\n" for line in keep))


def timing_totals(path: pathlib.Path) -> dict[str, float]:
    """A run's time over all its starts: compile seconds summed over starts, seconds of the kept chunks, starts."""
    rows = [row for line in read_lines(path) if (row := parse_object(line)) is not None]
    return {"total_compile_s": sum(r.get("compile_s", 0.0) for r in rows),
            "total_run_s": sum(r.get("chunk_s", 0.0) for r in rows),
            "starts": sum("compile_s" in r for r in rows)}


def curves_ok(path: pathlib.Path) -> bool:
    """Whether ``curves.npz`` exists and holds every curve, readable."""
    try:
        with np.load(path) as data:
            return all(np.asarray(data[k]).ndim == 2 for k in CURVES)
    except Exception:  # Any damage, whatever numpy raises for it, means the same: recompute it.
        return False


@dataclasses.dataclass
class _Loop:
    """The compiled chunks of one run and the time spent in them."""

    algo: Algorithm
    config: Config
    layout: SeedLayout
    full: Any = None  # The compiled full-length chunk.
    compile_s: float = 0.0
    run_s: float = 0.0
    last_s: float = 0.0  # The last chunk's seconds.

    def compile(self, states: TrainState) -> None:
        """Compile the full-length chunk (only a shorter last chunk compiles again)."""
        t0 = time.perf_counter()
        length = min(self.config.train.chunk, self.config.train.iterations)
        self.full = compiled_chunk(self.algo, length, self.layout).lower(states).compile()
        self.compile_s = time.perf_counter() - t0

    def chunk(self, states: TrainState, done: int) -> tuple[TrainState, int, dict, dict]:
        """Run the chunk that starts after ``done`` iterations: (states, its length, and the real seeds'
        per-iteration and eval outputs as NumPy arrays)."""
        t = self.config.train
        length = min(t.chunk, t.iterations - done)
        fn = self.full if length == min(t.chunk, t.iterations) else compiled_chunk(self.algo, length, self.layout)
        t1 = time.perf_counter()
        states, per_iter, evals = fn(states)
        jax.block_until_ready(states)
        self.last_s = time.perf_counter() - t1
        self.run_s += self.last_s
        return states, length, self.layout.to_host(per_iter), self.layout.to_host(evals)


def _save_curves(folder: pathlib.Path, evals: dict) -> None:
    """Write the last evaluation's curves atomically."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.asarray(v) for k, v in evals.items() if np.ndim(v) > 1})
    write_atomic(folder / "curves.npz", buf.getvalue())


def _recompute_curves(loop: _Loop, ckpt: Checkpoints, init: TrainState, folder: pathlib.Path) -> None:
    """Rebuild a finished run's ``curves.npz`` by rerunning its last chunk from the checkpoint before it (or from
    the start), exactly as it first ran: the final checkpoint's key is already past the evaluation's key."""
    t = loop.config.train
    last = t.iterations - ((t.iterations - 1) % t.chunk + 1)  # Where the last chunk started.
    if last and last not in ckpt.all_steps():
        raise ConfigError(f"{folder / 'curves.npz'} is missing or damaged and the checkpoint of iteration {last} "
                          f"needed to recompute it is gone; delete {folder} to retrain, or pass --overwrite")
    states = ckpt.restore(last, init) if last else init
    _, _, _, evals = loop.chunk(states, last)
    if is_primary():
        _save_curves(folder, evals)


def train_algorithm(
    config: Config, name: str, folder: pathlib.Path, progress: bool = True, position: int = 0
) -> dict[str, Any]:
    """Train ``name`` on all seeds into ``folder``, resuming from its last checkpoint; return timing info.

    ``position`` is the progress bar's row when several trainings share a terminal. Each chunk appends its metrics
    rows, then saves a checkpoint; the last chunk writes ``curves.npz`` before its checkpoint, and ``DONE`` comes
    last, so a kill at any moment leaves a folder the next start resumes to the same results.
    """
    primary = is_primary()
    if primary:
        folder.mkdir(parents=True, exist_ok=True)
        remove_temporaries(folder)
    sync(f"{folder}: ready")
    algo, layout = build_algorithm(config, name), seed_layout(config.seeds)
    ckpt = Checkpoints(folder / "checkpoints")
    try:
        init = initial_states(algo, config, layout)
        done = ckpt.latest_step() or 0
        states = ckpt.restore(done, init) if done else init
        if primary:
            resume_metrics(folder / "metrics.jsonl", config, name, done)
            resume_timing(folder / "timing.jsonl", done)
        loop = _Loop(algo, config, layout)
        finished = done == config.train.iterations and curves_ok(folder / "curves.npz")
        if not finished:  # A run killed between its last checkpoint and DONE has nothing left to compile.
            loop.compile(states)
            if primary:
                append_lines(folder / "timing.jsonl", [json.dumps({"from": done, "compile_s": loop.compile_s})])
            _train_loop(loop, ckpt, states, done, name, folder, progress and primary, position)
            sync(f"{folder}: trained")
            if not curves_ok(folder / "curves.npz"):
                _recompute_curves(loop, ckpt, init, folder)
    finally:
        ckpt.close()
    timing = {"compile_s": loop.compile_s, "run_s": loop.run_s, **timing_totals(folder / "timing.jsonl")}
    if primary:
        write_atomic(folder / "DONE", json.dumps(timing) + "\n")
    sync(f"{folder}: done")
    return timing


def _train_loop(loop: _Loop, ckpt: Checkpoints, states: TrainState, done: int, name: str, folder: pathlib.Path,
                progress: bool, position: int) -> None:
    """Train chunk by chunk from ``done`` to the end: check, append metrics, (last chunk: curves), checkpoint."""
    config, t = loop.config, loop.config.train
    bar = tqdm(total=t.iterations, initial=done, desc=f"{config.env}/{name} x{config.seeds} seeds",
               disable=not progress, unit="it", dynamic_ncols=True, position=position)
    if progress:
        bar.write(f"[{name}] compiled one {t.chunk}-iteration chunk for {config.seeds} seeds in {loop.compile_s:.1f} s")
    while done < t.iterations:
        states, length, per_iter, evals = loop.chunk(states, done)
        check_finite(name, config, done, per_iter, evals)
        rows = chunk_rows(name, config, done, per_iter, evals)
        done += length
        if is_primary():  # The one process that writes results; every process saves its shards of the checkpoint.
            append_lines(folder / "metrics.jsonl", [dumps_row(r) for r in rows])
            append_lines(folder / "timing.jsonl", [json.dumps({"iteration": done, "chunk_s": loop.last_s})])
            if done == t.iterations:
                _save_curves(folder, evals)  # Before the final checkpoint: a run with that checkpoint has its curves.
        sync(f"{folder}: chunk {done}")
        ckpt.save(done, states)
        if progress:
            bar.update(length)
            last = [r for r in rows if r["iteration"] == done]
            shown = {k: [r[k] for r in last] for k in last[0] if k not in ("algo", "seed", "iteration")}
            bar.set_postfix({k: f"{np.nanmean(v):.3g}" for k, v in shown.items() if not np.isnan(v).all()},
                            refresh=True)  # Warm-up iterations have no policy loss yet.
    bar.close()
