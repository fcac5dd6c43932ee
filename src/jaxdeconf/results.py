"""Results files a user opens: a summary table (Markdown and CSV) and PNG figures, read back from a run's folder."""

from __future__ import annotations

import csv
import io
import pathlib
import warnings
from typing import Any

import numpy as np

from jaxdeconf import algos
from jaxdeconf.config import Config
from jaxdeconf.files import read_rows, write_atomic

SMOOTH = 5  # Sliding window (evaluations) of comparison.png, as in the paper's figures.


def load_metrics(folder: pathlib.Path, algo: str) -> list[dict[str, Any]]:
    """Rows of ``<algo>/metrics.jsonl`` (null values as NaN)."""
    return read_rows(folder / algo / "metrics.jsonl")


def eval_table(rows: list[dict[str, Any]], key: str) -> tuple[np.ndarray, np.ndarray]:
    """(iterations [E], values [seeds, E]) of an eval metric."""
    rows = [r for r in rows if key in r]
    iters = sorted({r["iteration"] for r in rows})
    seeds = sorted({r["seed"] for r in rows})
    table = np.full((len(seeds), len(iters)), np.nan)
    for r in rows:
        table[seeds.index(r["seed"]), iters.index(r["iteration"])] = r[key]
    return np.asarray(iters), table


def mean_se(x: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard error over ``axis``, of the values that are not NaN (a standard error of 0 for one)."""
    n = np.sum(~np.isnan(x), axis=axis)
    mean = np.nanmean(x, axis=axis)
    if np.all(n <= 1):
        return mean, np.zeros_like(mean)
    return mean, np.nanstd(x, axis=axis, ddof=1) / np.sqrt(n)


def last_four(returns: np.ndarray) -> tuple[float, float]:
    """Return over the last four evaluations (or as many as there are) of a [seeds, evaluations] table: each seed's
    mean of them, then mean and standard error over seeds."""
    mean, se = mean_se(np.nanmean(returns[:, -4:], axis=1))
    return float(mean), float(se)


def summarize(folder: pathlib.Path, config: Config, refs: dict[str, Any] | None) -> list[dict[str, Any]]:
    """One summary row per algorithm, from its final evaluation (and its return over the last four, or as many as
    there are: each seed's mean of them, then mean and standard error over seeds)."""
    table = []
    for algo in config.algos:
        rows = load_metrics(folder, algo)
        if not rows:
            continue
        _, returns = eval_table(rows, "eval_return")
        final = returns[:, -1]
        m, se = mean_se(final)
        iterations = int(max(r["iteration"] for r in rows))
        last4_m, last4_se = last_four(returns)
        row: dict[str, Any] = {"algo": algo, "seeds": int(final.size), "iterations": iterations,
                               "return_mean": float(m), "return_se": float(se),
                               "return_last4_mean": last4_m, "return_last4_se": last4_se}
        extra_keys = sorted({k for r in rows for k in r if k.startswith("eval_") and k not in ("eval_return",)})
        for key in extra_keys:
            row[key] = float(np.nanmean(eval_table(rows, key)[1][:, -1]))
        curves_path = folder / algo / "curves.npz"
        if curves_path.exists() and refs is not None:
            curves = np.load(curves_path)
            online, expert = curves["p_best_online"].mean(0), curves["p_best_expert"].mean(0)
            row["p_best_last_step"] = float(online[-1])
            for kind in ("conditional", "interventional"):
                row[f"max_dev_online_vs_{kind}"] = float(np.max(np.abs(online - refs[f"{kind}_online"])))
                row[f"max_dev_expert_vs_{kind}"] = float(np.max(np.abs(expert - refs[f"{kind}_expert"])))
        table.append(row)
    add_gap_closed(table)
    return table


def add_gap_closed(table: list[dict[str, Any]]) -> None:
    """Add, when bc and the oracle are both in ``table``, each algorithm's share of the bc-to-oracle gap it closes,
    (return - bc) / (oracle - bc), at the final evaluation and over the last four (NaN where bc equals the oracle)."""
    rows = {row["algo"]: row for row in table}
    if not {"bc", "oracle"} <= rows.keys():
        return
    for row in table:
        for key, share in (("return_mean", "gap_closed"), ("return_last4_mean", "gap_closed_last4")):
            gap = rows["oracle"][key] - rows["bc"][key]
            row[share] = (row[key] - rows["bc"][key]) / gap if gap else float("nan")


def write_summary(folder: pathlib.Path, table: list[dict[str, Any]], refs: dict[str, Any] | None) -> str:
    """Write summary.csv and summary.md; return the Markdown text."""
    keys = sorted({k for row in table for k in row}, key=lambda k: (k not in ("algo", "seeds", "iterations"), k))
    buf = io.StringIO(newline="")
    writer = csv.DictWriter(buf, fieldnames=keys)
    writer.writeheader()
    writer.writerows(table)
    write_atomic(folder / "summary.csv", buf.getvalue())
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for row in table:
        cells = [f"{row[k]:.3f}" if isinstance(row.get(k), float) else str(row.get(k, "")) for k in keys]
        lines.append("| " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    if refs is not None:
        text += (
            f"\nExact references (best-arm count per episode): expert {refs['expert_count']:.2f}, "
            f"interventional {refs['interventional_count']:.2f} ± {refs['interventional_count_se']:.2f}, "
            f"conditional {refs['conditional_count']:.2f} ± {refs['conditional_count_se']:.2f}.\n"
        )
    write_atomic(folder / "summary.md", text)
    return text


def _save_figure(fig: Any, path: pathlib.Path) -> None:
    """Write a figure as a PNG atomically and close it."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=120)
    plt.close(fig)
    write_atomic(path, buf.getvalue())


def plot(folder: pathlib.Path, config: Config, refs: dict[str, Any] | None) -> list[pathlib.Path]:
    """learning_curves.png and, on the bandit, p_best.png; returns the written paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    fig, ax = plt.subplots(figsize=(6, 4))
    _return_curves(ax, folder, config, window=None, alpha=0.25)
    if refs is not None:
        for kind, style in (("expert", ":"), ("interventional", "--"), ("conditional", "-.")):
            ax.axhline(refs[f"{kind}_count"], color="k", ls=style, lw=1, label=f"exact {kind}")
    else:  # The MDPs: the expert's mean return over every episode it demonstrated during training.
        demo = expert_demo_return(folder, config)
        if demo is not None:
            ax.axhline(demo, color="k", ls=":", lw=1, label="expert (demonstrations)")
    ax.set_xlabel("iteration")
    ax.set_ylabel("best-arm count per episode" if refs is not None else "return")
    ax.set_title(f"{config.env}: mean ± s.e. over {config.seeds} seeds")
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save_figure(fig, folder / "learning_curves.png")
    written.append(folder / "learning_curves.png")

    written.append(plot_comparison(folder, config, refs))
    if refs is None:
        return [*written, *plot_diagnostics(folder, config)]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), sharey=True)
    for ax, where, title in zip(axes, ("expert", "online"), ("on expert data", "online"), strict=True):
        for algo in config.algos:
            path = folder / algo / "curves.npz"
            if not path.exists():
                continue
            m, se = mean_se(np.load(path)[f"p_best_{where}"])
            t = np.arange(m.size)
            ax.plot(t, m, color=algos.color(algo), label=algo)
            ax.fill_between(t, m - se, m + se, alpha=0.25, color=algos.color(algo))
        ax.plot(refs[f"interventional_{where}"], "k--", lw=1, label="exact interventional")
        ax.plot(refs[f"conditional_{where}"], "k-.", lw=1, label="exact conditional")
        ax.set_title(f"P(best arm) {title}")
        ax.set_xlabel("step t")
    axes[0].set_ylabel("P(best arm)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    _save_figure(fig, folder / "p_best.png")
    written.append(folder / "p_best.png")
    return written


def plot_diagnostics(folder: pathlib.Path, config: Config, bins: int = 6) -> list[pathlib.Path]:
    """diagnostics.png: the θ probe's held-out R² per step of each imitator with a belief (online, and on the
    expert's episodes), and each imitator's per-θ-bin performance at the final evaluation; mean ± s.e. over seeds."""
    import matplotlib.pyplot as plt

    from jaxdeconf.envs import make

    env, params = make(config.env, **config.env_params)
    curves = {a: dict(np.load(folder / a / "curves.npz")) for a in config.algos if (folder / a / "curves.npz").exists()}
    if not curves or "episode_theta" not in next(iter(curves.values())):
        return []
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    for algo, c in curves.items():
        for where, style in (("online", "-"), ("expert", "--")):
            probe = c.get(f"theta_probe_{where}")
            if probe is not None and np.isfinite(probe).any():
                m, se = mean_se(probe)
                t = np.arange(m.size)
                left.plot(t, m, style, color=algos.color(algo), label=f"{algo} ({where} episodes)")
                left.fill_between(t, m - se, m + se, alpha=0.2, color=algos.color(algo))
    left.set(xlabel="step t", ylabel="held-out R² of θ from the belief", title="how much of θ the belief carries")
    left.set_ylim(-0.2, 1.0)
    left.legend(fontsize=7)
    _per_theta_bin(right, curves, env, params, bins)
    fig.tight_layout()
    _save_figure(fig, folder / "diagnostics.png")
    return [folder / "diagnostics.png"]


def _per_theta_bin(ax: Any, curves: dict[str, dict[str, np.ndarray]], env: Any, params: Any, bins: int) -> None:
    """Each algorithm's per-episode performance (the env's ``diagnostic_extra`` per step, or the return) by θ bin."""
    extra = getattr(env, "diagnostic_extra", None)
    key, label = (f"episode_{extra[0]}", extra[1]) if extra else ("episode_return", "return")
    scale = env.horizon(params) if extra else 1
    thetas = np.concatenate([c["episode_theta"].ravel() for c in curves.values()]).astype(np.float64)
    values = np.unique(thetas)
    if values.size <= bins:  # A θ of a few values (LunarLander's swap): one bin each.
        centres, edges = values, np.r_[values[0] - 1.0, 0.5 * (values[1:] + values[:-1]), values[-1] + 1.0]
    else:
        edges = np.linspace(thetas.min(), thetas.max(), bins + 1)
        centres = 0.5 * (edges[1:] + edges[:-1])
    for algo, c in curves.items():
        which = np.clip(np.digitize(c["episode_theta"].astype(np.float64), edges) - 1, 0, centres.size - 1)
        per_seed = np.array([[np.mean(v[w == b]) / scale if np.any(w == b) else np.nan for b in range(centres.size)]
                             for v, w in zip(c[key], which, strict=True)])
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # A bin no episode of a seed fell in.
            m, se = mean_se(per_seed)
        ax.errorbar(centres, m, yerr=se, marker="o", ms=3, capsize=2, color=algos.color(algo), label=algo)
    ax.set(xlabel="θ (per episode; its norm when θ is a vector)", ylabel=label, title="final evaluation by θ")
    ax.legend(fontsize=7)


def _return_curves(ax: Any, folder: pathlib.Path, config: Config, window: int | None, alpha: float) -> None:
    """Each algorithm's evaluation return over iterations, mean ± s.e. over seeds, each seed first smoothed over
    ``window`` evaluations when one is given."""
    for algo in config.algos:
        rows = load_metrics(folder, algo)
        if not rows:
            continue
        iters, returns = eval_table(rows, "eval_return")
        m, se = mean_se(returns if window is None else smooth(returns, window))
        ax.plot(iters, m, label=algo, color=algos.color(algo))
        ax.fill_between(iters, m - se, m + se, alpha=alpha, color=algos.color(algo))


def smooth(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average along the last axis over up to ``window`` points (shorter at the start)."""
    csum = np.cumsum(np.nan_to_num(x), axis=-1)
    out = np.empty_like(csum, dtype=float)
    for i in range(x.shape[-1]):
        lo = max(0, i - window + 1)
        out[..., i] = (csum[..., i] - (csum[..., lo - 1] if lo else 0.0)) / (i - lo + 1)
    return out


def expert_demo_return(folder: pathlib.Path, config: Config) -> float | None:
    """The expert's mean return over every episode it demonstrated during training, or None."""
    demos = [r["expert_return"] for algo in config.algos for r in load_metrics(folder, algo) if "expert_return" in r]
    return float(np.mean(demos)) if demos else None


def plot_comparison(folder: pathlib.Path, config: Config, refs: dict[str, Any] | None) -> pathlib.Path:
    """comparison.png in the paper's style: return over iterations, each seed smoothed over ``SMOOTH`` evaluations,
    mean ± standard error over seeds, one line per algorithm, the expert's return as a reference line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    _return_curves(ax, folder, config, window=SMOOTH, alpha=0.2)
    expert = refs["expert_count"] if refs is not None else expert_demo_return(folder, config)
    if expert is not None:
        ax.axhline(float(expert), color="k", ls=":", lw=1, label="expert")
    if refs is not None:
        for kind, style in (("interventional", "--"), ("conditional", "-.")):
            ax.axhline(refs[f"{kind}_count"], color="gray", ls=style, lw=1, label=f"exact {kind}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("best-arm count per episode" if refs is not None else "return")
    ax.set_title(f"{config.env}: mean ± s.e. over {config.seeds} seeds, window {SMOOTH}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = folder / "comparison.png"
    _save_figure(fig, path)
    return path
