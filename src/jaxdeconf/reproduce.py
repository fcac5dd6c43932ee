"""``python -m jaxdeconf.reproduce [--scale cpu|paper] [--out report]``: every table and figure of the paper, and ours
for the theory and the offline variant, regenerated into one folder with a Markdown page beside the paper's numbers.

The work is a list of parts (the theory on the bandit, the bandit comparison, each MDP's comparison, Appendix A's
learned grid points, Figure 1). Each part writes into ``<out>/parts/<name>/`` (a training part's results folder is
``<out>/runs/<name>/``) and marks itself finished with ``<out>/parts/<name>/DONE.json``; a rerun of the same command
skips finished parts and resumes an interrupted training from its last checkpoint. ``<out>/README.md`` is rewritten
after every part, so the page is readable while later parts still run.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
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
class Part:
    """One unit of work: ``run(ctx)`` does it and returns its numbers; ``section(ctx, numbers)`` is its Markdown."""

    name: str
    title: str
    estimate_s: float  # At the cpu scale on two cores, for the ETA (half the one-core times measured, where known).
    run: Callable[[Context], dict[str, Any]]
    section: Callable[[Context, dict[str, Any]], str]


@dataclasses.dataclass(frozen=True)
class Context:
    """Where the parts write, and the settings every training run of them shares."""

    out: pathlib.Path
    scale: Scale
    algos: str = "all"  # The algorithms of the comparison parts.
    overrides: tuple[str, ...] = ()  # Extra ``--set`` for every training run (a smaller, quicker report).

    def part_dir(self, name: str) -> pathlib.Path:
        return self.out / "parts" / name

    def run_dir(self, name: str) -> pathlib.Path:
        return self.out / "runs" / name


def train(ctx: Context, name: str, env: str, seeds: int, extra: tuple[str, ...] = (), algo: str = "") -> pathlib.Path:
    """``python -m jaxdeconf.run`` into ``<out>/runs/<name>``; it resumes a stopped run and reuses a finished one."""
    folder = ctx.run_dir(name)
    sets = [a for item in (*extra, *ctx.overrides) for a in ("--set", item)]
    cmd = [sys.executable, "-m", "jaxdeconf.run", "--env", env, "--algo", algo or ctx.algos, "--seeds", str(seeds),
           "--preset", ctx.scale.preset, "--out", str(folder), *sets]
    procs: list[subprocess.Popen] = []
    try:  # Its own process group: Ctrl-C reaches the report alone, which then stops the training and its workers.
        procs.append(subprocess.Popen(cmd, start_new_session=True))
        code = procs[0].wait()
    finally:  # On SIGTERM or Ctrl-C (``Stopped``) the training stops with the report, checkpointed. The training
        # gives its workers 20 s; this waits longer, then kills what is left of its process group.
        stop_processes(procs, grace_s=40.0, group=True)
    if code != 0:
        raise PartFailedError(f"training {name} ({' '.join(cmd[2:])}) stopped with exit code {code}", code)
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


# --- The parts. -------------------------------------------------------------------------------------------------------


def run_theorem1(ctx: Context) -> dict[str, Any]:
    from jaxdeconf import paper_figures

    result = paper_figures.theorem1(ctx.part_dir("theorem1"))
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


def run_bandit(ctx: Context) -> dict[str, Any]:
    folder = train(ctx, "bandit", "bandit", ctx.scale.bandit_seeds)
    return {"rows": summary_rows(folder)}


def section_bandit(ctx: Context, n: dict[str, Any]) -> str:
    folder = ctx.run_dir("bandit")
    refs = read_json(folder / "references.json", "delete it and rerun")
    lines = ["| algorithm | best-arm count (ours, final evaluation) | the paper |", "|---|---|---|"]
    for row in n["rows"]:
        paper = PAPER_BANDIT.get(row["algo"], "not in the paper" if row["algo"] == "dil_offline" else "")
        lines.append(f"| {row['algo']} | {row['return_mean']:.1f} ± {row['return_se']:.1f} | {paper} |")
    lines.append(f"| exact interventional | {refs['interventional_count']:.1f} | {PAPER_BANDIT['interventional']} |")
    lines.append(f"| exact conditional | {refs['conditional_count']:.1f} | {PAPER_BANDIT['conditional']} |")
    return ("The paper's Figure 3: P(best arm) per step on expert histories and online, and the learning curves. "
            f"{int(n['rows'][0]['seeds'])} seeds, mean ± s.e.\n\n" + "\n".join(lines) + "\n\n"
            + _link(ctx, folder / "p_best.png", "P(best arm) per step") + "\n\n"
            + _link(ctx, folder / "comparison.png", "learning curves"))


def run_mdp(env: str) -> Callable[[Context], dict[str, Any]]:
    def run(ctx: Context) -> dict[str, Any]:
        return {"rows": summary_rows(train(ctx, env, env, ctx.scale.mdp_seeds))}

    return run


def section_mdp(env: str) -> Callable[[Context, dict[str, Any]], str]:
    def section(ctx: Context, n: dict[str, Any]) -> str:
        folder = ctx.run_dir(env)
        lines = ["| algorithm | return (final evaluation) | share of the bc → oracle gap closed: final / last 4 "
                 "evaluations | the paper's share |", "|---|---|---|---|"]
        for row in n["rows"]:
            gap = (f"{row['gap_closed']:.0%} / {row['gap_closed_last4']:.0%}"
                   if isinstance(row.get("gap_closed"), float) else "")
            paper = f"≈ {PAPER_GAP_CLOSED[env]:.0%}" if row["algo"] == "dil" else ""
            lines.append(f"| {row['algo']} | {row['return_mean']:.1f} ± {row['return_se']:.1f} | {gap} | {paper} |")
        return (f"The paper's Figure 4 ({env}), {int(n['rows'][0]['seeds'])} seeds, mean ± s.e. The paper's "
                f"ordering: {PAPER_ORDER}.\n\n" + "\n".join(lines) + "\n\n"
                + _link(ctx, folder / "comparison.png", f"{env} learning curves"))

    return section


def run_learned(ctx: Context) -> dict[str, Any]:
    from jaxdeconf import paper_figures

    s = ctx.scale
    runs = {(p, q): train(ctx, f"grid-p{p:g}-q{q:g}", "bandit", s.grid_seeds, algo="bc,dil",
                          extra=(f"env.p={p}", f"env.q={q}", f"train.iterations={s.grid_iterations}"))
            for p, q in GRID_POINTS}
    runs[(0.6, 0.75)] = ctx.run_dir("bandit")
    return {"rows": paper_figures.appendix_a_learned(ctx.part_dir("appendix_a_learned"), runs)}


def section_learned(ctx: Context, n: dict[str, Any]) -> str:
    return ("Beyond the paper: the learned `bc` and `dil` (best-arm count per 100 steps) at points of Appendix A's "
            "grid, beside the exact policies there. `dil` should follow the interventional column and `bc` the "
            "conditional one.\n\n" + _include(ctx.part_dir("appendix_a_learned") / "appendix_a_learned.md"))


def run_figure1(ctx: Context) -> dict[str, Any]:
    from jaxdeconf import paper_figures

    result = paper_figures.figure1(ctx.part_dir("figure1"), ctx.run_dir("bandit"))
    return {name: r["count"] for name, r in result.items()}


def section_figure1(ctx: Context, n: dict[str, Any]) -> str:
    counts = ", ".join(f"{name} {count:.1f}" for name, count in n.items())
    return ("The paper's Figure 1: actions per step of five rollouts per policy, the correct arm in green; the "
            f"trained imitators are the bandit part's seed 0. Best-arm counts over 2000 episodes: {counts}.\n\n"
            + _link(ctx, ctx.part_dir("figure1") / "figure1.png", "Figure 1 rollouts"))


PARTS = [
    Part("theorem1", "Theorem 1: the tabular estimator (eq. 5)", 240, run_theorem1, section_theorem1),
    Part("appendix_a", "Appendix A: when confounding bites", 60, run_appendix_a, section_appendix_a),
    Part("bandit", "The confounded bandit (Figure 3)", 2700, run_bandit, section_bandit),
    Part("figure1", "Figure 1: rollouts", 120, run_figure1, section_figure1),
    Part("appendix_a_learned", "Appendix A, learned", 1500, run_learned, section_learned),
    *[Part(env, f"{env} (Figure 4)", est, run_mdp(env), section_mdp(env))
      for env, est in zip(MDPS, (3700, 4700, 3100), strict=True)],
]


# --- The loop. --------------------------------------------------------------------------------------------------------


def _done(ctx: Context, part: Part) -> dict[str, Any] | None:
    path = ctx.part_dir(part.name) / "DONE.json"
    return read_json(path, "delete it to redo the part") if path.exists() else None


def write_page(ctx: Context, parts: list[Part]) -> None:
    """``<out>/README.md``: each finished part's section, and the parts still to run."""
    lines = [f"# Deconfounding imitation learning: the paper, reproduced (`--scale {ctx.scale.preset}`)", "",
             "Regenerate or resume with `python -m jaxdeconf.reproduce --out "
             f"{ctx.out} --scale {ctx.scale.preset}`. Each section is one part; its files are under `parts/` and "
             "its trainings under `runs/`.", ""]
    for part in parts:
        done = _done(ctx, part)
        lines += [f"## {part.title}", ""]
        if done is None:
            lines += ["Not run yet.", ""]
            continue
        lines += [part.section(ctx, done["numbers"]), "",
                  f"*{done['seconds'] / 60:.1f} min, finished {done['finished']}.*", ""]
    lines += _compute_section(ctx)
    write_atomic(ctx.out / "README.md", "\n".join(lines))


def training_minutes(ctx: Context) -> dict[str, float]:
    """Core-minutes of each finished training under ``<out>/runs``, summed over its algorithms: compilations and
    the chunks kept, over every start of a resumed run (runs without ``timing.jsonl``: their last start)."""
    minutes = {}
    for folder in sorted(p for p in (ctx.out / "runs").glob("*") if p.is_dir()):
        done = [read_json(d, "delete it to retrain") for d in sorted(folder.glob("*/DONE"))]
        seconds = [d.get("total_compile_s", d["compile_s"]) + d.get("total_run_s", d["run_s"]) for d in done]
        if seconds:
            minutes[folder.name] = sum(seconds) / 60
    return minutes


def _compute_section(ctx: Context) -> list[str]:
    minutes = training_minutes(ctx)
    if not minutes:
        return []
    rows = [f"| {name} | {m:.0f} |" for name, m in minutes.items()]
    return ["## Compute", "", "Training time of the finished trainings of each run folder, summed over its algorithms "
            "(each trains on one core; compilation and the kept chunks over every start of a resumed run), in "
            f"core-minutes. Total: {sum(minutes.values()):.0f}.", "", "| run | core-minutes |", "|---|---|", *rows, ""]


def _eta(parts: list[Part], ctx: Context, current: Part) -> str:
    left = sum(p.estimate_s for p in parts if _done(ctx, p) is None)
    return f"{current.name}: about {current.estimate_s / 60:.0f} min; all parts left: about {left / 60:.0f} min"


def reproduce(ctx: Context, parts: list[Part]) -> None:
    """Run every part not yet finished, in order, rewriting the page after each."""
    todo = [p for p in parts if _done(ctx, p) is None]
    print(f"reproduce: {len(parts) - len(todo)} of {len(parts)} parts already finished; writing {ctx.out}/README.md",
          flush=True)
    for i, part in enumerate(todo, 1):
        print(f"[{i}/{len(todo)}] {part.title} — estimated {_eta(parts, ctx, part)} (cpu scale)", flush=True)
        t0 = time.monotonic()
        numbers = part.run(ctx)
        record = {"numbers": numbers, "seconds": time.monotonic() - t0,
                  "finished": time.strftime("%Y-%m-%d %H:%M:%S")}
        ctx.part_dir(part.name).mkdir(parents=True, exist_ok=True)
        write_atomic(ctx.part_dir(part.name) / "DONE.json", json.dumps(record, indent=1) + "\n")
        write_page(ctx, parts)
        print(f"[{i}/{len(todo)}] {part.name} finished in {record['seconds'] / 60:.1f} min", flush=True)
    write_page(ctx, parts)


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
                reproduce(Context(out, SCALES[args.scale], args.algo, tuple(args.set)), parts)
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
