"""The host loop: compile a seed-vmapped chunk once, run it chunk by chunk, show progress, write metrics and
checkpoints, and resume from the last checkpoint when a run is started again on the same folder."""

from __future__ import annotations

import functools
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

CURVES = ("p_best_online", "p_best_expert")


def seed_keys(config: Config) -> jax.Array:
    """One typed key per seed; seed i is ``jax.random.key(seed_start + i)`` for every algorithm."""
    return jax.vmap(jax.random.key)(jnp.arange(config.seed_start, config.seed_start + config.seeds))


def build_algorithm(config: Config, name: str) -> Algorithm:
    """The named algorithm on the config's environment."""
    env, env_params = make(config.env, **config.env_params)
    return make_algorithm(name, env, env_params, config)


def compiled_chunk(algo: Algorithm, length: int) -> Any:
    """``jit(vmap(train_chunk))`` for chunks of ``length`` iterations."""
    return jax.jit(jax.vmap(functools.partial(algo.train_chunk, length=length)))


def chunk_rows(name: str, config: Config, start: int, per_iter: dict, evals: dict) -> list[dict[str, Any]]:
    """Metrics rows (one per seed and iteration) from one chunk's outputs; eval metrics go on its last iteration."""
    per_iter = jax.tree.map(np.asarray, per_iter)
    evals = {k: np.asarray(v) for k, v in evals.items() if k not in CURVES}
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


def _truncate_metrics(path: pathlib.Path, done: int) -> None:
    """Drop rows past ``done`` iterations (written by a chunk whose checkpoint never landed)."""
    if not path.exists():
        return
    keep = [line for line in path.read_text().splitlines() if line and json.loads(line)["iteration"] <= done]
    path.write_text("".join(line + "\n" for line in keep))


def train_algorithm(
    config: Config, name: str, folder: pathlib.Path, progress: bool = True, position: int = 0
) -> dict[str, Any]:
    """Train ``name`` on all seeds into ``folder``, resuming from its last checkpoint; return timing info.

    ``position`` is the progress bar's row when several trainings share a terminal.
    """
    folder.mkdir(parents=True, exist_ok=True)
    algo = build_algorithm(config, name)
    metrics_path = folder / "metrics.jsonl"
    ckpt = Checkpoints(folder / "checkpoints")
    states: TrainState = jax.jit(jax.vmap(algo.init))(seed_keys(config))
    done = ckpt.latest_step() or 0
    if done:
        states = ckpt.restore(done, states)
    _truncate_metrics(metrics_path, done)

    t = config.train
    t0 = time.perf_counter()
    full = compiled_chunk(algo, t.chunk).lower(states).compile()
    compile_s = time.perf_counter() - t0
    bar = tqdm(total=t.iterations, initial=done, desc=f"{config.env}/{name} x{config.seeds} seeds",
               disable=not progress, unit="it", dynamic_ncols=True, position=position)
    if progress:
        bar.write(f"[{name}] compiled one {t.chunk}-iteration chunk for {config.seeds} seeds in {compile_s:.1f} s")
    run_s = 0.0
    last_eval: dict[str, np.ndarray] = {}
    while done < t.iterations:
        length = min(t.chunk, t.iterations - done)
        fn = full if length == t.chunk else compiled_chunk(algo, length)  # Only a shorter last chunk recompiles.
        t1 = time.perf_counter()
        states, per_iter, evals = fn(states)
        jax.block_until_ready(states)
        run_s += time.perf_counter() - t1
        rows = chunk_rows(name, config, done, per_iter, evals)
        with metrics_path.open("a") as f:
            f.writelines(json.dumps(r) + "\n" for r in rows)
        done += length
        ckpt.save(done, states)
        last_eval = {k: np.asarray(v) for k, v in evals.items()}
        if progress:
            bar.update(length)
            last = [r for r in rows if r["iteration"] == done]
            shown = {k: [r[k] for r in last] for k in last[0] if k not in ("algo", "seed", "iteration")}
            bar.set_postfix({k: f"{np.nanmean(v):.3g}" for k, v in shown.items() if not np.isnan(v).all()},
                            refresh=True)  # Warm-up iterations have no policy loss yet.
    bar.close()
    ckpt.close()
    if last_eval:
        np.savez(folder / "curves.npz", **{k: last_eval[k] for k in CURVES})
    (folder / "DONE").write_text(json.dumps({"compile_s": compile_s, "run_s": run_s}) + "\n")
    return {"compile_s": compile_s, "run_s": run_s}
