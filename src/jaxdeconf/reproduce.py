"""``python -m jaxdeconf.reproduce [--scale cpu|paper] [--out report]``: every table and figure of the paper, and ours
for the theory and the offline variant, regenerated into one folder with a Markdown page beside the paper's numbers.

The work is a list of parts (the theory on the bandit, the bandit comparison, each MDP's comparison, Appendix A's
learned grid points, Figure 1). Each part writes into ``<out>/parts/<name>/`` (a training part's results folder is
``<out>/runs/<name>/``) and marks itself finished with ``<out>/parts/<name>/DONE.json``; a rerun of the same command
skips finished parts and resumes an interrupted training from its last checkpoint. ``<out>/README.md`` is rewritten
after every part, so the page is readable while later parts still run.

The report is committed part by part (``git add report``; .gitignore keeps checkpoints, curves, timings and locks
out). DONE.json is the one file that holds when, where and from which commit a part was made, and each of its
trainings' resolved config; every other file of a part is the same whoever regenerates it. ``stale_fields`` compares
a part's recorded configs with what the current code resolves from the same settings (tests/test_report_drift.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import platform
import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from typing import Any

from jaxdeconf.errors import ConfigError
from jaxdeconf.files import FolderLock, command_line, read_json, remove_temporaries, writable, write_atomic
from jaxdeconf.processes import Stopped, signals_raise, stop_processes

# The paper's own numbers, for the page (its text and appendix; the MDP shares are read off its Figure 4).
PAPER_BANDIT = {"expert": 60.0, "interventional": 54.1, "conditional": 32.4, "dil": "≈ 54", "bc": "≈ 33–40"}
PAPER_GAP_CLOSED = {"lunar_lander": 0.98, "half_cheetah": 0.95, "ant_goal": 0.92}
PAPER_ORDER = "oracle ≈ DAgger ≥ deconfounded ≫ naive BC; GAIL between them or below naive BC"


@dataclasses.dataclass(frozen=True)
class Scale:
    """How much each part trains: the preset of every run, seeds, and Appendix A's learned grid."""

    preset: str
    bandit_seeds: int
    mdp_seeds: int
    grid_seeds: int
    grid_iterations: int


SCALES = {
    "cpu": Scale(preset="cpu", bandit_seeds=10, mdp_seeds=5, grid_seeds=3, grid_iterations=125),
    "paper": Scale(preset="paper", bandit_seeds=10, mdp_seeds=5, grid_seeds=10, grid_iterations=300),
}
# Appendix A's grid points trained besides the default (p, q) = (0.6, 0.75), which the bandit part trains.
GRID_POINTS = ((1.0, 0.75), (0.8, 0.875), (0.6, 1.0))
MDPS = ("lunar_lander", "half_cheetah", "ant_goal")


@dataclasses.dataclass(frozen=True)
class Training:
    """One ``python -m jaxdeconf.run`` of a part: its results folder ``<out>/runs/<name>`` and its settings."""

    name: str
    env: str
    seeds: int
    extra: tuple[str, ...] = ()  # ``--set`` items of this training, before the report's own.
    algo: str = ""  # Comma-separated algorithms; empty: the report's ``--algo``.


def _no_trainings(ctx: Context) -> tuple[Training, ...]:
    del ctx  # Unused.
    return ()


@dataclasses.dataclass(frozen=True)
class Part:
    """One unit of work: ``run(ctx)`` does it and returns its numbers; ``section(ctx, numbers)`` is its Markdown;
    ``trainings(ctx)`` are the results folders it trains or reads, recorded in its DONE.json."""

    name: str
    title: str
    estimate_s: float  # At the cpu scale on two cores, for the ETA (half the one-core times measured, where known).
    run: Callable[[Context], dict[str, Any]]
    section: Callable[[Context, dict[str, Any]], str]
    trainings: Callable[[Context], tuple[Training, ...]] = _no_trainings


@dataclasses.dataclass(frozen=True)
class Context:
    """Where the parts write, and the settings every training run of them shares."""

    out: pathlib.Path
    scale: Scale
    algos: str = "all"  # The algorithms of the comparison parts.
    overrides: tuple[str, ...] = ()  # Extra ``--set`` for every training run (a smaller, quicker report).
    command: str = ""  # The command line that made the report, for DONE.json.

    def part_dir(self, name: str) -> pathlib.Path:
        return self.out / "parts" / name

    def run_dir(self, name: str) -> pathlib.Path:
        return self.out / "runs" / name


def training_overrides(ctx: Context, spec: Training) -> tuple[str, ...]:
    """The ``--set`` items of a training: its own, then the report's (a later item wins)."""
    return (*spec.extra, *ctx.overrides)


def train(ctx: Context, spec: Training) -> pathlib.Path:
    """``python -m jaxdeconf.run`` into ``<out>/runs/<name>``; it resumes a stopped run and reuses a finished one."""
    folder = ctx.run_dir(spec.name)
    sets = [a for item in training_overrides(ctx, spec) for a in ("--set", item)]
    cmd = [sys.executable, "-m", "jaxdeconf.run", "--env", spec.env, "--algo", spec.algo or ctx.algos, "--seeds",
           str(spec.seeds), "--preset", ctx.scale.preset, "--out", str(folder), *sets]
    procs: list[subprocess.Popen] = []
    try:  # Its own process group: Ctrl-C reaches the report alone, which then stops the training and its workers.
        procs.append(subprocess.Popen(cmd, start_new_session=True))
        code = procs[0].wait()
    finally:  # On SIGTERM or Ctrl-C (``Stopped``) the training stops with the report, checkpointed. The training
        # gives its workers 20 s; this waits longer, then kills what is left of its process group.
        stop_processes(procs, grace_s=40.0, group=True)
    if code != 0:
        raise PartFailedError(f"training {spec.name} ({' '.join(cmd[2:])}) stopped with exit code {code}", code)
    return folder


class PartFailedError(RuntimeError):
    """A part could not finish; ``code`` is the exit code to leave with."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def summary_rows(folder: pathlib.Path) -> list[dict[str, Any]]:
    """A results folder's summary.csv as dicts (numbers as floats)."""
    import csv

    with open(folder / "summary.csv", newline="") as f:
        return [{k: _number(v) for k, v in row.items()} for row in csv.DictReader(f)]


def _number(text: str) -> Any:
    try:
        return float(text)
    except ValueError:
        return text


def _link(ctx: Context, path: pathlib.Path, alt: str) -> str:
    return f"![{alt}]({path.relative_to(ctx.out).as_posix()})"


def _include(path: pathlib.Path) -> str:
    return path.read_text().strip() if path.exists() else "(missing)"


def drop_keys(data: Any, keys: frozenset[str]) -> Any:
    """``data`` (nested dicts and lists) without the dict entries named in ``keys``, at any depth."""
    if isinstance(data, dict):
        return {k: drop_keys(v, keys) for k, v in data.items() if k not in keys}
    if isinstance(data, list):
        return [drop_keys(v, keys) for v in data]
    return data


# --- The parts. -------------------------------------------------------------------------------------------------------


def run_theorem1(ctx: Context) -> dict[str, Any]:
    from jaxdeconf import paper_figures

    result = paper_figures.theorem1(ctx.part_dir("theorem1"))
    # Each estimate's wall time is in its row: the committed file keeps the results alone, the same on any machine.
    path = ctx.part_dir("theorem1") / "theorem1.json"
    write_atomic(path, json.dumps(drop_keys(json.loads(path.read_text()), frozenset({"seconds"}))) + "\n")
    best = next(r for r in result["grid"] if r["demos"] == max(x["demos"] for x in result["grid"])
                and r["length"] == max(x["length"] for x in result["grid"]))
    return {"demos": best["demos"], "length": best["length"], "count": best["count"], "max_gap": best["max_gap"],
            "interventional": result["interventional_count"], "floor_gap": result["floor_gap"]}


def section_theorem1(ctx: Context, n: dict[str, Any]) -> str:
    folder = ctx.part_dir("theorem1")
    return (f"Eq. 5's tabular estimator, online, against the exact interventional policy (the paper states the "
            f"theorem and gives no numbers). With N = {n['demos']} demonstrations of H = {n['length']} steps: "
            f"best-arm count **{n['count']:.2f}** against {n['interventional']:.2f}, largest per-step gap "
            f"**{n['max_gap']:.3f}** (Monte-Carlo floor {n['floor_gap']:.3f}).\n\n"
            f"{_link(ctx, folder / 'theorem1.png', 'Theorem 1 convergence')}\n\n{_include(folder / 'theorem1.md')}")


def run_appendix_a(ctx: Context) -> dict[str, Any]:
    from jaxdeconf import paper_figures

    grid = paper_figures.appendix_a(ctx.part_dir("appendix_a"))
    return {"episodes": grid["episodes"]}


def section_appendix_a(ctx: Context, n: dict[str, Any]) -> str:
    folder = ctx.part_dir("appendix_a")
    return ("Expected success (best-arm rate per step) of the expert and the exact interventional and conditional "
            "policies over the expert's π(a = θ) (rows) and the environment's P(s' = 1 | a = θ) (columns), "
            f"{n['episodes']} episodes per point. The paper's claim: the conditional policy fails where the "
            "environment is stochastic and the expert nearly deterministic.\n\n"
            f"{_link(ctx, folder / 'appendix_a.png', 'Appendix A heatmaps')}\n\n{_include(folder / 'appendix_a.md')}")


def bandit_training(ctx: Context) -> Training:
    """The bandit comparison, which Figure 1 and Appendix A's learned grid read as well."""
    return Training("bandit", "bandit", ctx.scale.bandit_seeds)


def run_bandit(ctx: Context) -> dict[str, Any]:
    return {"rows": summary_rows(train(ctx, bandit_training(ctx)))}


def section_bandit(ctx: Context, n: dict[str, Any]) -> str:
    folder = ctx.run_dir("bandit")
    refs = read_json(folder / "references.json", "delete it and rerun")
    lines = ["| algorithm | best-arm count (ours, final evaluation) | largest per-step gap of P(best arm) to the exact "
             "interventional policy, online | to the exact conditional policy, on expert histories | the paper |",
             "|---|---|---|---|---|"]
    for row in n["rows"]:
        paper = PAPER_BANDIT.get(row["algo"], "not in the paper" if row["algo"] == "dil_offline" else "")
        lines.append(f"| {row['algo']} | {row['return_mean']:.1f} ± {row['return_se']:.1f} | "
                     f"{row['max_dev_online_vs_interventional']:.3f} | {row['max_dev_expert_vs_conditional']:.3f} | "
                     f"{paper} |")
    lines.append(f"| exact interventional | {refs['interventional_count']:.1f} | | | "
                 f"{PAPER_BANDIT['interventional']} |")
    lines.append(f"| exact conditional | {refs['conditional_count']:.1f} | | | {PAPER_BANDIT['conditional']} |")
    return ("The paper's Figure 3: P(best arm) per step on expert histories and online, and the learning curves. "
            f"{int(n['rows'][0]['seeds'])} seeds, mean ± s.e.\n\n" + "\n".join(lines) + "\n\n"
            + _link(ctx, folder / "p_best.png", "P(best arm) per step") + "\n\n"
            + _link(ctx, folder / "comparison.png", "learning curves"))


def mdp_trainings(env: str) -> Callable[[Context], tuple[Training, ...]]:
    """The trainings of an MDP's comparison: one, named after the env."""

    def trainings(ctx: Context) -> tuple[Training, ...]:
        return (Training(env, env, ctx.scale.mdp_seeds),)

    return trainings


def run_mdp(env: str) -> Callable[[Context], dict[str, Any]]:
    def run(ctx: Context) -> dict[str, Any]:
        return {"rows": summary_rows(train(ctx, mdp_trainings(env)(ctx)[0]))}

    return run


def last_returns(folder: pathlib.Path, algo: str) -> tuple[float, float]:
    """Return over the last four evaluations (each seed's mean), mean and standard error over seeds, from the
    training's metrics: for a part whose summary was written before it had these columns."""
    from jaxdeconf import results

    return results.last_four(results.eval_table(results.load_metrics(folder, algo), "eval_return")[1])


def section_mdp(env: str) -> Callable[[Context, dict[str, Any]], str]:
    def section(ctx: Context, n: dict[str, Any]) -> str:
        folder = ctx.run_dir(env)
        lines = ["| algorithm | return, final evaluation | return, last 4 evaluations | share of the bc → oracle gap "
                 "closed: final / last 4 | the paper's share |", "|---|---|---|---|---|"]
        for row in n["rows"]:
            gap = (f"{row['gap_closed']:.0%} / {row['gap_closed_last4']:.0%}"
                   if isinstance(row.get("gap_closed"), float) else "")
            paper = f"≈ {PAPER_GAP_CLOSED[env]:.0%} (its Figure 4)" if row["algo"] == "dil" else ""
            last4 = ((row["return_last4_mean"], row["return_last4_se"]) if "return_last4_mean" in row
                     else last_returns(folder, row["algo"]))
            lines.append(f"| {row['algo']} | {row['return_mean']:.1f} ± {row['return_se']:.1f} | {last4[0]:.1f} ± "
                         f"{last4[1]:.1f} | {gap} | {paper} |")
        return (f"The paper's Figure 4 ({env}), {int(n['rows'][0]['seeds'])} seeds, mean ± s.e. The paper's "
                f"ordering: {PAPER_ORDER}.\n\n" + "\n".join(lines) + "\n\n"
                + _link(ctx, folder / "comparison.png", f"{env} learning curves"))

    return section


def grid_trainings(ctx: Context) -> tuple[Training, ...]:
    """Appendix A's learned grid points, in the order of ``GRID_POINTS``."""
    s = ctx.scale
    return tuple(Training(f"grid-p{p:g}-q{q:g}", "bandit", s.grid_seeds, algo="bc,dil",
                          extra=(f"env.p={p}", f"env.q={q}", f"train.iterations={s.grid_iterations}"))
                 for p, q in GRID_POINTS)


def learned_trainings(ctx: Context) -> tuple[Training, ...]:
    """What Appendix A's learned part reads: its grid points and the bandit comparison's default point."""
    return (*grid_trainings(ctx), bandit_training(ctx))


def run_learned(ctx: Context) -> dict[str, Any]:
    from jaxdeconf import paper_figures

    runs = {point: train(ctx, spec) for point, spec in zip(GRID_POINTS, grid_trainings(ctx), strict=True)}
    runs[(0.6, 0.75)] = ctx.run_dir("bandit")  # Its summary and metrics, committed with the bandit part.
    return {"rows": paper_figures.appendix_a_learned(ctx.part_dir("appendix_a_learned"), runs)}


def section_learned(ctx: Context, n: dict[str, Any]) -> str:
    return ("Beyond the paper: the learned `bc` and `dil` (best-arm count per 100 steps) at points of Appendix A's "
            "grid, beside the exact policies there. `dil` should follow the interventional column and `bc` the "
            "conditional one.\n\n" + _include(ctx.part_dir("appendix_a_learned") / "appendix_a_learned.md"))


def run_figure1(ctx: Context) -> dict[str, Any]:
    from jaxdeconf import paper_figures

    # Its trained rows need the bandit's checkpoints, which are not committed: a fresh clone trains them again.
    result = paper_figures.figure1(ctx.part_dir("figure1"), train(ctx, bandit_training(ctx)))
    return {name: r["count"] for name, r in result.items()}


def section_figure1(ctx: Context, n: dict[str, Any]) -> str:
    counts = ", ".join(f"{name} {count:.1f}" for name, count in n.items())
    return ("The paper's Figure 1: actions per step of five rollouts per policy, the correct arm in green; the "
            f"trained imitators are the bandit part's first seed. Best-arm counts over 2000 episodes: {counts}.\n\n"
            + _link(ctx, ctx.part_dir("figure1") / "figure1.png", "Figure 1 rollouts"))


PARTS = [
    Part("theorem1", "Theorem 1: the tabular estimator (eq. 5)", 240, run_theorem1, section_theorem1),
    Part("appendix_a", "Appendix A: when confounding bites", 60, run_appendix_a, section_appendix_a),
    Part("bandit", "The confounded bandit (Figure 3)", 2700, run_bandit, section_bandit,
         lambda ctx: (bandit_training(ctx),)),
    Part("figure1", "Figure 1: rollouts", 120, run_figure1, section_figure1, lambda ctx: (bandit_training(ctx),)),
    Part("appendix_a_learned", "Appendix A, learned", 1500, run_learned, section_learned, learned_trainings),
    *[Part(env, f"{env} (Figure 4)", est, run_mdp(env), section_mdp(env), mdp_trainings(env))
      for env, est in zip(MDPS, (3700, 4700, 3100), strict=True)],
]


# --- What a finished part records. -----------------------------------------------------------------------------------


def _git(cwd: pathlib.Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout


def changed_paths(status: str) -> list[str]:
    """The paths of ``git status --porcelain -z`` output (a rename's entry is followed by its old path, skipped)."""
    paths, entries = [], iter(status.split("\0"))
    for entry in entries:
        if entry:
            paths.append(entry[3:])
            if entry[0] in "RC":
                next(entries, None)
    return paths


def git_state(out: pathlib.Path, code: pathlib.Path | None = None) -> dict[str, Any]:
    """The commit of the checkout holding ``code`` (default: this package), and whether its tree differs from that
    commit (tracked changes and untracked files, outside the report folder ``out``); null where the code is no git
    checkout (an installed package)."""
    code = code or pathlib.Path(__file__).resolve().parent
    try:
        root = pathlib.Path(_git(code, "rev-parse", "--show-toplevel").strip())
        commit = _git(root, "rev-parse", "HEAD").strip()
        status = _git(root, "status", "--porcelain", "-z", "--untracked-files=normal")
    except (OSError, subprocess.CalledProcessError):
        return {"commit": None, "dirty": None, "dirty_paths": []}
    out = out.resolve()
    report = out.relative_to(root).as_posix() if out.is_relative_to(root) and out != root else None
    paths = [p for p in changed_paths(status)
             if report is None or not (p.rstrip("/") == report or p.startswith(report + "/"))]
    return {"commit": commit, "dirty": bool(paths), "dirty_paths": paths[:20]}


def machine() -> str:
    """This machine in words: CPU model, the cores this process may use, NVIDIA GPUs (read from /proc, so that no JAX
    backend starts in the report's process)."""
    def field(path: pathlib.Path, name: str) -> str | None:
        text = path.read_text() if path.exists() else ""
        return next((line.partition(":")[2].strip() for line in text.splitlines() if line.startswith(name)), None)

    cpu = field(pathlib.Path("/proc/cpuinfo"), "model name") or platform.machine()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    gpus = [field(info, "Model") for info in sorted(pathlib.Path("/proc/driver/nvidia/gpus").glob("*/information"))]
    return ", ".join([cpu, f"{cores} cores", *filter(None, gpus)])


def core_seconds(folder: pathlib.Path) -> float | None:
    """Core-seconds of a results folder's finished trainings, summed over its algorithms: compilations and the chunks
    kept, over every start of a resumed run (runs without ``timing.jsonl``: their last start); None if none finished."""
    done = [read_json(d, "delete it to retrain") for d in sorted(folder.glob("*/DONE"))]
    seconds = [d.get("total_compile_s", d["compile_s"]) + d.get("total_run_s", d["run_s"]) for d in done]
    return sum(seconds) if seconds else None


def training_record(ctx: Context, spec: Training) -> dict[str, Any]:
    """A training's settings as the report passed them, and the config its results folder resolved (config.json as
    written: it holds settings only, no path, time or host)."""
    folder = ctx.run_dir(spec.name)
    return {"name": spec.name, "env": spec.env, "preset": ctx.scale.preset, "algo": spec.algo or ctx.algos,
            "seeds": spec.seeds, "overrides": list(training_overrides(ctx, spec)),
            "config": read_json(folder / "config.json", f"delete {folder} to retrain it"),
            "core_s": core_seconds(folder)}


def seed_ranges(trainings: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The trainings grouped by their seeds (``seed_start`` and count, from their configs), in order."""
    ranges: dict[tuple[int, int], list[str]] = {}
    for t in trainings:
        ranges.setdefault((t["config"].get("seed_start", 0), t["config"]["seeds"]), []).append(t["name"])
    return [{"seed_start": start, "count": count, "trainings": names} for (start, count), names in ranges.items()]


def part_record(ctx: Context, part: Part, numbers: dict[str, Any], seconds: float,
                state: dict[str, Any]) -> dict[str, Any]:
    """A finished part's DONE.json: its numbers; the commit (``state``), wall time, machine and command it was made
    with; its seeds; and each of its trainings' settings and resolved config."""
    trainings = [training_record(ctx, spec) for spec in part.trainings(ctx)]
    return {"part": part.name, "numbers": numbers, **state, "seconds": seconds,
            "finished": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": machine(), "command": ctx.command,
            "scale": ctx.scale.preset, "algos": ctx.algos, "overrides": list(ctx.overrides),
            "seeds": seed_ranges(trainings), "trainings": trainings}


# --- Drift: a finished part against the current code. ----------------------------------------------------------------


def current_config(training: dict[str, Any]) -> dict[str, Any]:
    """The config ``python -m jaxdeconf.run`` resolves today from a recorded training's env, preset, algorithms, seeds
    and overrides, as its config.json would hold it."""
    from jaxdeconf import algos, resolve
    from jaxdeconf import config as cfg
    from jaxdeconf.cli import parse_overrides
    from jaxdeconf.folders import typed_env_params

    text = training["algo"]
    names = algos.names() if text.strip() == "all" else tuple(a.strip() for a in text.split(",") if a.strip())
    config = resolve.build(training["env"], training["preset"], names, training["seeds"],
                           parse_overrides(list(training["overrides"])))
    return json.loads(cfg.dumps(typed_env_params(config)))


def flatten(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts as one dict of dotted names (``train.iterations``); lists stay values."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        out.update(flatten(value, f"{name}.") if isinstance(value, dict) else {name: value})
    return out


def config_differences(recorded: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """``<field>: recorded <value>, current <value>`` for each field that differs (values as JSON, so 1 is not
    1.0), or is in one config only."""
    old, new = flatten(recorded), flatten(current)

    def shown(values: dict[str, Any], key: str) -> str:
        return json.dumps(values[key]) if key in values else "(absent)"

    return [f"{key}: recorded {shown(old, key)}, current {shown(new, key)}" for key in sorted(old.keys() | new.keys())
            if shown(old, key) != shown(new, key)]


def stale_fields(done: dict[str, Any]) -> list[str]:
    """What makes a finished part stale: for each training in its DONE.json, ``runs/<name>: <field>: recorded ...,
    current ...`` where the config the current code resolves from the recorded settings differs from the recorded
    one (or a line saying the settings no longer resolve); empty when the part is current."""
    if "trainings" not in done:
        return ["DONE.json records no trainings' configs; delete it to redo the part"]
    lines = []
    for training in done["trainings"]:
        try:
            diff = config_differences(training["config"], current_config(training))
        except ConfigError as err:
            diff = [f"its settings no longer resolve ({err})"]
        except KeyError as err:
            diff = [f"its record in DONE.json lacks {err}"]
        lines += [f"runs/{training.get('name', '?')}: {line}" for line in diff]
    return lines


def _flags(scale: str, algos: str, overrides: list[str]) -> str:
    return shlex.join(["--scale", scale, "--algo", algos, *[a for item in overrides for a in ("--set", item)]])


def settings_differ(ctx: Context, done: dict[str, Any]) -> list[str]:
    """A line when a finished part's trainings were made with other report settings than this command's."""
    if not done.get("trainings"):
        return []
    made = _flags(done.get("scale", "?"), done.get("algos", "?"), done.get("overrides", []))
    now = _flags(ctx.scale.preset, ctx.algos, list(ctx.overrides))
    return [] if made == now else [f"made with `{made}`, this command has `{now}`"]


# --- The page. --------------------------------------------------------------------------------------------------------


def _done(ctx: Context, part: Part) -> dict[str, Any] | None:
    path = ctx.part_dir(part.name) / "DONE.json"
    return read_json(path, "delete it to redo the part") if path.exists() else None


def _duration(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def seeds_text(ranges: list[dict[str, Any]]) -> str:
    """``seeds 0–9``, or each range with its trainings where a part's trainings differ."""
    def span(r: dict[str, Any]) -> str:
        last = r["seed_start"] + r["count"] - 1
        return f"{r['seed_start']}" if last == r["seed_start"] else f"{r['seed_start']}–{last}"

    if not ranges:
        return "no trained seeds"
    if len(ranges) == 1:
        return f"seeds {span(ranges[0])}"
    return "seeds " + "; ".join(f"{span(r)} ({', '.join(r['trainings'])})" for r in ranges)


def regenerate_command(name: str, done: dict[str, Any]) -> str:
    """The command that makes the part again as it was made (into the default ``--out report``)."""
    cmd = ["python", "-m", "jaxdeconf.reproduce", "--scale", done.get("scale", "cpu"), "--only", name]
    if done.get("trainings"):
        cmd += [*(["--algo", done["algos"]] if done.get("algos", "all") != "all" else []),
                *[a for item in done.get("overrides", []) for a in ("--set", item)]]
    return shlex.join(cmd)


def provenance(name: str, done: dict[str, Any]) -> str:
    """A part's line under its section: commit, seeds, wall time and the command, all from its DONE.json."""
    commit = done.get("commit")
    made = f"commit `{commit[:7]}`" if commit else "no recorded commit"
    if done.get("dirty"):
        made += " with uncommitted changes"
    return (f"*Made at {made} · {seeds_text(done.get('seeds', []))} · {_duration(done['seconds'])} wall time · "
            f"`{regenerate_command(name, done)}`*")


def write_page(ctx: Context, parts: list[Part]) -> None:
    """``<out>/README.md``: each finished part's section, and the parts still to run. It is made from the parts'
    files alone, so it reads the same wherever the report lies; what changes from one run to the next (commit, seeds,
    wall time) comes from their DONE.json."""
    lines = [f"# Deconfounding imitation learning: the paper, reproduced (`--scale {ctx.scale.preset}`)", "",
             f"Regenerate or resume with `python -m jaxdeconf.reproduce --scale {ctx.scale.preset}` (into `report/`). "
             "Each section is one part; its files are under `parts/` and its trainings under `runs/`. To make a part "
             "again, delete its `parts/<name>/DONE.json` and run the command under its section.", ""]
    records = {}
    for part in parts:
        done = _done(ctx, part)
        lines += [f"## {part.title}", ""]
        if done is None:
            lines += ["Not run yet.", ""]
            continue
        records[part.name] = done
        lines += [part.section(ctx, done["numbers"]), "", provenance(part.name, done), ""]
    lines += compute_section(records)
    write_atomic(ctx.out / "README.md", "\n".join(lines))


def compute_section(records: dict[str, dict[str, Any]]) -> list[str]:
    """The wall time of every finished part and its total, and the core-minutes of the trainings each part trained
    (a results folder counts for the first part that lists it)."""
    if not records:
        return []
    seen: set[str] = set()
    rows = []
    for name, done in records.items():
        new = [t for t in done.get("trainings", []) if t["name"] not in seen and t.get("core_s") is not None]
        seen |= {t["name"] for t in new}
        core = f"{sum(t['core_s'] for t in new) / 60:.0f}" if new else ""
        rows.append(f"| {name} | {done['seconds'] / 60:.1f} | {core} |")
    machines = "; ".join(dict.fromkeys(done.get("machine", "an unrecorded machine") for done in records.values()))
    total = sum(done["seconds"] for done in records.values())
    return ["## Compute", "", f"Total wall time of the {len(records)} finished parts: **{_duration(total)}**, on "
            f"{machines}. Core-minutes: training time summed over each training's algorithms (each trains on one "
            "core; compilation and the kept chunks over every start of a resumed run).", "",
            "| part | wall time (min) | training core-minutes |", "|---|---|---|", *rows, ""]


# --- The loop. --------------------------------------------------------------------------------------------------------


def _eta(parts: list[Part], ctx: Context, current: Part) -> str:
    left = sum(p.estimate_s for p in parts if _done(ctx, p) is None)
    return f"{current.name}: about {current.estimate_s / 60:.0f} min; all parts left: about {left / 60:.0f} min"


def warn_stale(ctx: Context, parts: list[Part]) -> None:
    """One warning line for each finished part whose recorded configs the current code no longer resolves, or that
    was made with other settings than this command's; such a part is kept as it is (the drift test fails on it)."""
    for part in parts:
        done = _done(ctx, part)
        stale = [] if done is None else stale_fields(done) + settings_differ(ctx, done)
        if stale:
            more = f" (and {len(stale) - 1} more)" if len(stale) > 1 else ""
            print(f"reproduce: warning: finished part {part.name} is stale, kept as is: {stale[0]}{more}; delete "
                  f"{ctx.part_dir(part.name) / 'DONE.json'} to redo it", flush=True)


def run_part(ctx: Context, part: Part) -> dict[str, Any]:
    """Do one part; return its DONE.json record."""
    state = git_state(ctx.out)  # Before it runs: the code it runs.
    t0 = time.monotonic()
    numbers = part.run(ctx)
    return part_record(ctx, part, numbers, time.monotonic() - t0, state)


def reproduce(ctx: Context, parts: list[Part]) -> None:
    """Run every part of ``parts`` not yet finished, in order, rewriting the page (of every part) after each."""
    todo = [p for p in parts if _done(ctx, p) is None]
    print(f"reproduce: {len(parts) - len(todo)} of {len(parts)} parts already finished; writing {ctx.out}/README.md",
          flush=True)
    warn_stale(ctx, [p for p in parts if p not in todo])
    for i, part in enumerate(todo, 1):
        print(f"[{i}/{len(todo)}] {part.title} — estimated {_eta(parts, ctx, part)} (cpu scale)", flush=True)
        record = run_part(ctx, part)
        ctx.part_dir(part.name).mkdir(parents=True, exist_ok=True)
        write_atomic(ctx.part_dir(part.name) / "DONE.json", json.dumps(record, indent=1) + "\n")
        write_page(ctx, PARTS)
        print(f"[{i}/{len(todo)}] {part.name} finished in {record['seconds'] / 60:.1f} min", flush=True)
    write_page(ctx, PARTS)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m jaxdeconf.reproduce", description=__doc__.split("\n\n")[0])
    p.add_argument("--scale", default="cpu", help="cpu (two cores, an evening) or paper (a GPU)")
    p.add_argument("--out", default="report", help="report folder (default: report)")
    p.add_argument("--only", default="", help=f"comma-separated parts from {', '.join(x.name for x in PARTS)}")
    p.add_argument("--algo", default="all", help="algorithms of the comparisons (default: all registered)")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="an override for every training run, e.g. train.iterations=20 (a quicker, smaller report)")
    return p.parse_args(argv)


def _select(only: str) -> list[Part]:
    names = [n.strip() for n in only.split(",") if n.strip()]
    known = {p.name: p for p in PARTS}
    bad = [n for n in names if n not in known]
    if bad:
        raise ConfigError(f"--only {bad[0]!r} is not a part; choose from {', '.join(known)}")
    return [known[n] for n in names] if names else PARTS


def main(argv: list[str] | None = None) -> int:
    """Command line; one ``error:`` line and exit code 2 for bad input, the failing training's code otherwise, 128 +
    the signal's number when stopped by SIGTERM or Ctrl-C (the running training stops with it)."""
    from jaxdeconf.platform import share_accelerator

    share_accelerator()  # Its in-process figures and its trainings' workers share the GPU.
    args = parse_args(argv)
    try:
        with signals_raise():
            if args.scale not in SCALES:
                raise ConfigError(f"--scale {args.scale!r} is not one of {', '.join(SCALES)}")
            parts, out = _select(args.only), pathlib.Path(args.out)
            with writable(out):
                out.mkdir(parents=True, exist_ok=True)
                lock = FolderLock(out, command_line())
            try:
                for folder in (out, *(out / "parts").glob("*")):  # What a stopped ``write_atomic`` left.
                    remove_temporaries(folder)
                command = shlex.join(["python", "-m", "jaxdeconf.reproduce", *(sys.argv[1:] if argv is None else argv)])
                reproduce(Context(out, SCALES[args.scale], args.algo, tuple(args.set), command), parts)
            finally:
                lock.release()
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except PartFailedError as err:
        print(f"error: {err}; rerun the same command to resume", file=sys.stderr)
        return err.code
    except Stopped as stop:
        print(f"error: stopped by {stop.name}; rerun the same command to resume", file=sys.stderr)
        return 128 + stop.signum
    return 0


if __name__ == "__main__":
    sys.exit(main())
