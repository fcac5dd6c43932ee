"""The paper's theory on the bandit, as figures and tables: Theorem 1 (eq. 5), Appendix A and Figure 1.

Each part is one function that computes its numbers, writes its figure (PNG) and table (Markdown) into a folder and
returns the numbers, so a report can call it: ``theorem1``, ``appendix_a``, ``appendix_a_learned`` (with
``bandit_runs``) and ``figure1``. ``python -m jaxdeconf.paper_figures PART --out FOLDER`` runs one from the command
line (PART: theorem1, appendix_a, learned, figure1).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdeconf import theory
from jaxdeconf.actors import ExpertActor
from jaxdeconf.data import rollout
from jaxdeconf.envs.bandit import Bandit, BanditParams
from jaxdeconf.references import ReferenceActor, reference_curves

# Appendix A's grid: the expert's π(a = θ) from deterministic to uniform, and P(s' = 1 | a = θ) from deterministic to
# uninformative.
GRID_P = (1.0, 0.8, 0.6, 0.4, 0.2)
GRID_Q = (1.0, 0.875, 0.75, 0.625, 0.5)
POLICIES = ("expert", "interventional", "conditional")


def _pyplot() -> Any:
    """matplotlib with a file-only backend (imported here: ``import jaxdeconf`` stays light)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _write_table(path: pathlib.Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    path.write_text("\n".join(lines) + "\n")


# ---------------------------------------------------------------------------------------------------------------------
# Theorem 1.


def theorem1(
    out: pathlib.Path,
    demos: Sequence[int] = (10, 100, 1000),
    lengths: Sequence[int] = (10, 30, 100, 300, 1000),
    alpha: float = theory.ALPHA,
    short_lengths: Sequence[int] = (3, 10, 30, 100, 1000),
    short_settings: Sequence[tuple[int, float]] = ((1000, 0.0), (1000, 0.1), (1000, 1.0), (5000, 0.1)),
    episodes: int = 4000,
    short_episodes: int = 2000,
    ref_episodes: int = 40000,
    seed: int = 0,
) -> dict[str, Any]:
    """Eq. 5 on the paper's bandit against the exact interventional policy, over N demonstrations of H steps.

    Writes ``theorem1.png`` (online best-arm count and max per-step gap against N, one line per H, pseudo-count
    ``alpha``; and the short-demonstration regime against H, for each (N, α) of ``short_settings``) and
    ``theorem1.md``; returns the rows and the references. Each estimate acts for ``episodes`` online episodes
    (``short_episodes`` in the short regime); the gap's Monte-Carlo floor is the interventional policy against itself
    at ``episodes``.
    """
    out.mkdir(parents=True, exist_ok=True)
    params = BanditParams()
    key = jax.random.key(seed)
    key_ref, key_floor, key_est = jax.random.split(key, 3)
    refs = {k: np.asarray(v) for k, v in jax.jit(reference_curves, static_argnums=(1, 2))(
        key_ref, params, ref_episodes).items()}
    floor = jax.jit(reference_curves, static_argnums=(1, 2))(key_floor, params, episodes)
    floor_gap = float(np.max(np.abs(np.asarray(floor["interventional_online"]) - refs["interventional_online"])))
    curves = jax.jit(theory.estimator_curves, static_argnums=(1, 2, 3, 4))

    def one(n: int, h: int, alpha: float, num_episodes: int) -> dict[str, Any]:
        t0 = time.perf_counter()
        key_nh = jax.random.fold_in(jax.random.fold_in(key_est, n), h)
        est = curves(key_nh, params, n, h, num_episodes, alpha)
        gap = np.abs(np.asarray(est["online"]) - refs["interventional_online"])
        row = {"demos": n, "length": h, "alpha": alpha, "count": float(est["count"]),
               "count_se": float(est["count_se"]), "max_gap": float(np.max(gap)), "gap_step": int(np.argmax(gap)),
               "online": np.asarray(est["online"]).tolist(), "seconds": time.perf_counter() - t0}
        print(f"theorem1: N={n} H={h} alpha={alpha}: count {row['count']:.2f} +- {row['count_se']:.2f}, "
              f"max gap {row['max_gap']:.3f} ({row['seconds']:.0f} s)", flush=True)
        return row

    grid = [one(n, h, alpha, episodes) for h in lengths for n in demos]
    done = {(r["demos"], r["length"], r["alpha"]): r for r in grid}  # Reused: each (N, H) compiles anew.
    short = [done.get((n, h, a)) or one(n, h, a, short_episodes) for n, a in short_settings for h in short_lengths]
    result = {"grid": grid, "short": short, "floor_gap": floor_gap, "episodes": episodes, "alpha": alpha,
              "interventional_count": float(refs["interventional_count"]),
              "interventional_count_se": float(refs["interventional_count_se"]),
              "conditional_count": float(refs["conditional_count"]), "expert_count": float(refs["expert_count"])}
    _theorem1_table(out / "theorem1.md", result)
    _theorem1_plot(out / "theorem1.png", result, demos, lengths, short_settings)
    (out / "theorem1.json").write_text(json.dumps(result) + "\n")
    return result


def _theorem1_table(path: pathlib.Path, result: dict[str, Any]) -> None:
    """Count and max gap per (N, H), then the short-demonstration rows."""
    rows = [(r["demos"], r["length"], r["alpha"], f"{r['count']:.2f} ± {r['count_se']:.2f}", f"{r['max_gap']:.3f}")
            for r in result["grid"] + result["short"]]
    rows.append(("exact interventional", "", "", f"{result['interventional_count']:.2f} ± "
                 f"{result['interventional_count_se']:.2f}", f"(floor {result['floor_gap']:.3f})"))
    _write_table(path, ("N", "H", "α", "best-arm count / 100 steps", "max per-step gap"), rows)


def _theorem1_plot(
    path: pathlib.Path, result: dict[str, Any], demos: Sequence[int], lengths: Sequence[int],
    short_settings: Sequence[tuple[int, float]],
) -> None:
    """Three panels: count vs N, gap vs N (one line per H), count vs short H (one line per N and α)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for h in lengths:
        rows = [r for r in result["grid"] if r["length"] == h]
        axes[0].errorbar(demos, [r["count"] for r in rows], [r["count_se"] for r in rows], marker="o",
                         label=f"H = {h}", capsize=2)
        axes[1].plot(demos, [r["max_gap"] for r in rows], marker="o", label=f"H = {h}")
    for ax in axes[:2]:
        ax.set_xscale("log")
        ax.set_xlabel("demonstrations N")
    axes[0].axhline(result["interventional_count"], color="k", ls="--", label="exact interventional")
    axes[0].axhline(result["conditional_count"], color="tab:red", ls=":", label="exact conditional")
    axes[0].set_ylabel("online best-arm count / 100 steps")
    axes[0].legend(fontsize=7)
    axes[1].axhline(0.03, color="k", ls="--", label="0.03")
    axes[1].axhline(result["floor_gap"], color="gray", ls=":", label="Monte-Carlo floor")
    axes[1].set_yscale("log")
    axes[1].set_ylabel("max per-step |P(best) - interventional|")
    axes[1].legend(fontsize=7)
    for n, a in short_settings:
        rows = [r for r in result["short"] if r["demos"] == n and r["alpha"] == a]
        axes[2].errorbar([r["length"] for r in rows], [r["count"] for r in rows], [r["count_se"] for r in rows],
                         marker="o", capsize=2, label=f"N = {n}, α = {a:g}")
    axes[2].axhline(result["interventional_count"], color="k", ls="--", label="exact interventional")
    axes[2].axhline(20.0, color="gray", ls=":", label="uniform (no inference)")
    axes[2].set_xscale("log")
    axes[2].set_xlabel("demonstration length H (short: recurrence fails)")
    axes[2].set_ylabel("online best-arm count / 100 steps")
    axes[2].legend(fontsize=7)
    fig.suptitle(f"Theorem 1 (eq. 5) on the bandit (p = 0.6, q = 0.75); left and middle: α = {result['alpha']:g}")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------------------------------
# Appendix A.


def success_grid(
    key: jax.Array, ps: Sequence[float], qs: Sequence[float], episodes: int, horizon: int = 100
) -> dict[str, np.ndarray]:
    """Best-arm rate per step [len(ps), len(qs)] of the expert and the exact references, with standard errors.

    One compiled program: ``reference_curves`` vmapped over the flattened (p, q) grid.
    """
    pp, qq = np.meshgrid(np.asarray(ps, np.float32), np.asarray(qs, np.float32), indexing="ij")

    def point(p: jax.Array, q: jax.Array) -> dict[str, jax.Array]:
        return reference_curves(key, BanditParams(p=p, q=q, horizon=horizon), episodes)

    refs = jax.jit(jax.vmap(point))(jnp.asarray(pp.ravel()), jnp.asarray(qq.ravel()))
    shape = pp.shape
    out = {"p": pp, "q": qq, "expert": np.asarray(refs["expert_count"]).reshape(shape) / horizon,
           "expert_se": np.zeros(shape)}  # The expert's P(best) is p at every step: no Monte-Carlo error.
    for kind in ("interventional", "conditional"):
        out[kind] = np.asarray(refs[f"{kind}_count"]).reshape(shape) / horizon
        out[f"{kind}_se"] = np.asarray(refs[f"{kind}_count_se"]).reshape(shape) / horizon
    return out


def outcome_rate(best_rate: np.ndarray, q: np.ndarray) -> np.ndarray:
    """P(s' = 1) per step from the best-arm rate: q on the best arm, 1 - q elsewhere (the paper's r_t = s_{t+1})."""
    return q * best_rate + (1.0 - q) * (1.0 - best_rate)


def appendix_a(
    out: pathlib.Path, ps: Sequence[float] = GRID_P, qs: Sequence[float] = GRID_Q, episodes: int = 20000, seed: int = 0
) -> dict[str, Any]:
    """Appendix A's heatmaps: mean reward per step (best-arm rate) of the expert, interventional and conditional.

    Writes ``appendix_a.png`` and ``appendix_a.md`` (the best-arm rate, and the outcome rate P(s' = 1)); returns the
    grid as nested lists.
    """
    out.mkdir(parents=True, exist_ok=True)
    grid = success_grid(jax.random.key(seed), ps, qs, episodes)
    _appendix_a_table(out / "appendix_a.md", grid, ps, qs)
    _appendix_a_plot(out / "appendix_a.png", grid, ps, qs)
    result = {k: np.asarray(v).tolist() for k, v in grid.items()}
    result["episodes"] = episodes
    (out / "appendix_a.json").write_text(json.dumps(result) + "\n")
    return result


def _appendix_a_table(
    path: pathlib.Path, grid: dict[str, np.ndarray], ps: Sequence[float], qs: Sequence[float]
) -> None:
    """One row per (p, q): best-arm rate and outcome rate of the three policies."""
    rows = []
    for i, p in enumerate(ps):
        for j, q in enumerate(qs):
            best = [grid[k][i, j] for k in POLICIES]
            outcome = [outcome_rate(b, q) for b in best]
            rows.append((f"{p:g}", f"{q:g}", *(f"{b:.3f}" for b in best), *(f"{o:.3f}" for o in outcome)))
    header = ("π(a=θ)", "P(s'=1|a=θ)", *(f"{k} best-arm" for k in POLICIES), *(f"{k} P(s'=1)" for k in POLICIES))
    _write_table(path, header, rows)


def _appendix_a_plot(path: pathlib.Path, grid: dict[str, np.ndarray], ps: Sequence[float], qs: Sequence[float]) -> None:
    """Heatmaps as the paper's (expert deterministic at the bottom, environment deterministic on the left): the
    best-arm rate (the env's reward) on top, P(s' = 1) (the paper's r_t = s_{t+1}) below."""
    plt = _pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(11, 7), sharex=True, sharey=True)
    q_grid = np.asarray(qs, np.float32)[None, :]
    for row, (label, transform) in enumerate((("best-arm rate per step", lambda x: x),
                                              ("P(s'=1) per step", lambda x: outcome_rate(x, q_grid)))):
        for ax, kind in zip(axes[row], POLICIES, strict=True):
            values = transform(grid[kind])
            image = ax.imshow(values, origin="lower", vmin=0.0, vmax=1.0, cmap="viridis")
            for i in range(len(ps)):
                for j in range(len(qs)):
                    ax.text(j, i, f"{values[i, j]:.2f}", ha="center", va="center", fontsize=8,
                            color="white" if values[i, j] < 0.6 else "black")
            ax.set_xticks(range(len(qs)), [f"{q:g}" for q in qs])
            ax.set_yticks(range(len(ps)), [f"{p:g}" for p in ps])
            ax.set_title(f"{kind}: {label}", fontsize=9)
        axes[row, 0].set_ylabel("expert π(a=θ)")
        fig.colorbar(image, ax=axes[row], shrink=0.8)
    for ax in axes[1]:
        ax.set_xlabel("environment P(s'=1 | a=θ)")
    fig.suptitle("Appendix A: expert deterministic at the bottom, environment deterministic on the left")
    fig.savefig(path, dpi=80, bbox_inches="tight")
    plt.close(fig)


def learned_counts(folder: pathlib.Path, algo: str) -> dict[str, Any]:
    """Best-arm count per episode at the last evaluation of ``folder/algo``: mean, s.e. over seeds, and per seed."""
    path = folder / algo / "metrics.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line]
    rows = [r for r in rows if "eval_return" in r]
    last = max(r["iteration"] for r in rows)
    values = np.asarray([r["eval_return"] for r in rows if r["iteration"] == last])
    se = float(np.std(values, ddof=1) / np.sqrt(len(values))) if len(values) > 1 else 0.0
    return {"mean": float(np.mean(values)), "se": se, "seeds": values.tolist(), "iteration": last}


def appendix_a_learned(out: pathlib.Path, runs: dict[tuple[float, float], pathlib.Path]) -> list[dict[str, Any]]:
    """Learned ``bc`` and ``dil`` at grid points next to the exact policies there, from finished results folders.

    ``runs`` maps (p, q) to a folder written by ``python -m jaxdeconf.run --env bandit --algo bc,dil --set env.p=p
    --set env.q=q``; the exact references are the folder's own ``references.json``. Writes ``appendix_a_learned.md``.
    """
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for (p, q), folder in sorted(runs.items(), reverse=True):
        refs = json.loads((folder / "references.json").read_text())
        row = {"p": p, "q": q, **{k: float(refs[f"{k}_count"]) for k in POLICIES}}
        for algo in ("bc", "dil"):
            row[algo] = learned_counts(folder, algo)
        rows.append(row)
    table = [(f"{r['p']:g}", f"{r['q']:g}", f"{r['expert']:.1f}", f"{r['interventional']:.1f}",
              f"{r['dil']['mean']:.1f} ± {r['dil']['se']:.1f}", f"{r['conditional']:.1f}",
              f"{r['bc']['mean']:.1f} ± {r['bc']['se']:.1f}", len(r["bc"]["seeds"]), r["bc"]["iteration"])
             for r in rows]
    _write_table(out / "appendix_a_learned.md", ("π(a=θ)", "P(s'=1|a=θ)", "expert", "interventional", "dil",
                                                  "conditional", "bc", "seeds", "iterations"), table)
    (out / "appendix_a_learned.json").write_text(json.dumps(rows) + "\n")
    return rows


# ---------------------------------------------------------------------------------------------------------------------
# Figure 1.


def learned_actor(folder: pathlib.Path, algo: str, seed_index: int = 0) -> tuple[Any, Any, Any, Any]:
    """(env, env_params, actor, actor_params) of seed ``seed_index`` of a trained ``algo`` in a results folder."""
    from jaxdeconf import resolve
    from jaxdeconf.checkpoint import Checkpoints
    from jaxdeconf.train import build_algorithm, seed_keys

    config = resolve.from_dict(json.loads((folder / "config.json").read_text()))
    algo_obj = build_algorithm(config, algo)
    states = jax.jit(jax.vmap(algo_obj.init))(seed_keys(config))
    ckpt = Checkpoints(folder / algo / "checkpoints")
    step = ckpt.latest_step()
    if step is None:
        raise FileNotFoundError(f"no checkpoint of {algo} in {folder}")
    states = ckpt.restore(step, states)
    ckpt.close()
    state = jax.tree.map(lambda x: x[seed_index], states)
    return algo_obj.env, algo_obj.env_params, algo_obj.actor(), algo_obj.actor_params(state)


def rollout_actions(
    key: jax.Array, env: Any, env_params: Any, actor: Any, actor_params: Any, episodes: int
) -> tuple[np.ndarray, np.ndarray, float]:
    """Actions [episodes, T], the best arm θ [episodes] and the expected best-arm count per episode (the policy's
    P(best) summed over steps, averaged over episodes) of ``episodes`` online episodes."""
    traj, p_best = jax.jit(rollout, static_argnums=(0, 2, 5))(env, env_params, actor, actor_params, key, episodes)
    return np.asarray(traj.action).T, np.asarray(traj.best_action[0]), float(np.mean(np.sum(p_best, axis=0)))


def figure1(
    out: pathlib.Path, results: pathlib.Path | None = None, episodes: int = 8, count_episodes: int = 2000, seed: int = 0
) -> dict[str, Any]:
    """Figure 1's rollout rasters: actions per step of the expert, interventional and conditional policies, and of
    the trained ``bc``, ``dil`` and ``dil_plus`` of a results folder (when given), the correct arm in green.

    The same key drives every policy, so the rows share θ. A few rows can flatter or wrong a policy, so each label
    also gives its best-arm count per 100 steps over ``count_episodes`` episodes. Writes ``figure1.png``; returns the
    actions, the θs, each raster's fraction of correct pulls and each policy's count.
    """
    out.mkdir(parents=True, exist_ok=True)
    env = Bandit()
    params = BanditParams()
    policies: dict[str, tuple[Any, Any, Any, Any]] = {
        "expert": (env, params, ExpertActor(env, params), None),
        "interventional": (env, params, ReferenceActor("interventional", params), None),
        "conditional": (env, params, ReferenceActor("conditional", params), None),
    }
    if results is not None:
        for algo in ("bc", "dil", "dil_plus"):
            if (results / algo / "checkpoints").exists():
                policies[f"{algo} (trained)"] = learned_actor(results, algo)
    key, key_count = jax.random.split(jax.random.key(seed))
    actions, thetas, counts = {}, {}, {}
    for name, (e, p, actor, actor_params) in policies.items():
        actions[name], thetas[name], _ = rollout_actions(key, e, p, actor, actor_params, episodes)
        counts[name] = rollout_actions(key_count, e, p, actor, actor_params, count_episodes)[2]
    _figure1_plot(out / "figure1.png", actions, thetas, counts)
    result = {name: {"actions": a.tolist(), "theta": thetas[name].tolist(), "count": counts[name],
                     "correct": float(np.mean(a == thetas[name][:, None]))} for name, a in actions.items()}
    (out / "figure1.json").write_text(json.dumps(result) + "\n")
    return result


def _figure1_plot(
    path: pathlib.Path, actions: dict[str, np.ndarray], thetas: dict[str, np.ndarray], counts: dict[str, float]
) -> None:
    """One raster per policy: rows are episodes, columns steps; green is the correct arm, other arms other colours."""
    plt = _pyplot()
    from matplotlib.colors import ListedColormap

    cmap = ListedColormap(["tab:green", "tab:blue", "tab:orange", "tab:red", "tab:purple"])
    fig, axes = plt.subplots(len(actions), 1, figsize=(9, 1.0 + 0.9 * len(actions)), sharex=True)
    for ax, (name, a) in zip(np.atleast_1d(axes), actions.items(), strict=True):
        theta = thetas[name][:, None]
        # 0 is the correct arm; the wrong arms keep a fixed colour each (1..4, by their offset from θ).
        code = np.where(a == theta, 0, 1 + (a - theta - 1) % 4)
        ax.imshow(code, aspect="auto", cmap=cmap, vmin=0, vmax=4, interpolation="nearest")
        ax.set_yticks(range(a.shape[0]), [f"θ={t}" for t in thetas[name]], fontsize=6)
        label = f"{name}\nrows: {np.mean(a == theta):.0%} correct\ncount {counts[name]:.1f} / 100"
        ax.set_ylabel(label, rotation=0, ha="right", va="center", fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel("step")
    fig.suptitle("Rollouts on the bandit (p = 0.6, q = 0.75): correct arm green")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def bandit_runs(parent: pathlib.Path) -> dict[tuple[float, float], pathlib.Path]:
    """The bandit results folders directly under ``parent`` that finished ``bc`` and ``dil``, keyed by (p, q)."""
    defaults = BanditParams()
    runs = {}
    for config_path in sorted(parent.glob("*/config.json")):
        config = json.loads(config_path.read_text())
        folder = config_path.parent
        if config["env"] == "bandit" and all((folder / algo / "DONE").exists() for algo in ("bc", "dil")):
            env = config["env_params"]
            runs[(float(env.get("p", defaults.p)), float(env.get("q", defaults.q)))] = folder
    return runs


def main(argv: list[str] | None = None) -> int:
    """``python -m jaxdeconf.paper_figures PART --out FOLDER [--results FOLDER]``."""
    parser = argparse.ArgumentParser(prog="python -m jaxdeconf.paper_figures", description=__doc__)
    parser.add_argument("part", choices=("theorem1", "appendix_a", "learned", "figure1"))
    parser.add_argument("--out", default="report", help="folder for figures and tables")
    parser.add_argument("--results", default=None,
                        help="figure1: a bandit results folder with trained bc and dil; learned: a folder of such "
                             "folders, one per (env.p, env.q)")
    args = parser.parse_args(argv)
    out = pathlib.Path(args.out)
    results = pathlib.Path(args.results) if args.results else None
    if args.part == "theorem1":
        theorem1(out)
    elif args.part == "appendix_a":
        appendix_a(out)
    elif args.part == "learned":
        if results is None:
            parser.error("learned needs --results")
        appendix_a_learned(out, bandit_runs(results))
    else:
        figure1(out, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
