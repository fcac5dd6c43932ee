"""Rollouts to watch: ``python -m jaxdeconf.render <results folder> --algo dil --episodes 4``.

LunarLander becomes an animated GIF (a small 2-D drawing of terrain, helipad, hull, legs and the fired engine's
flame), the Brax envs Brax's HTML viewer (one file per episode), the bandit a raster image of the imitator's action
probabilities per step. Each shows θ, and for ``dil`` the imitator's belief: the posterior mean of q_φ.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxdeconf.errors import ConfigError
from jaxdeconf.policy import Policy, expert_policy, load_policy


def belief(policy: Policy, carry: Any) -> np.ndarray | None:
    """The posterior mean of q_φ [N, latent] held in a dil actor's carry (GRU encoder), or None for other actors."""
    encoder = getattr(policy.actor, "encoder", None)
    if encoder is None or not hasattr(encoder, "hidden"):
        return None
    gru = carry[0] if isinstance(carry, tuple) else carry
    out = encoder.apply(policy.params["encoder"], gru, method=lambda m, h: m.out(h))  # GRUCell: output = carry.
    return np.asarray(jnp.split(out, 2, axis=-1)[0])


def record(policy: Policy, episodes: int, seed: int) -> dict[str, Any]:
    """Run ``episodes`` episodes through the gymnasium wrapper; keep states [T+1], actions, rewards, head outputs and
    beliefs and valid masks [T] (all with the episode axis second) and θ [N]."""
    venv = policy.gym_env(episodes)
    obs, _ = venv.reset(seed=seed)
    state = policy.initial_state(seed=seed, num_envs=episodes)
    rec: dict[str, list] = {"state": [venv.core.slots.state], "action": [], "reward": [], "head": [], "belief": [],
                           "valid": []}
    alive = np.ones(episodes, bool)
    for _ in range(venv.core.horizon):
        head, _ = policy.head(obs, state)
        action, state = policy(obs, state)
        obs, reward, terminated, _, _ = venv.step(action)
        rec["head"].append(head)
        rec["belief"].append(belief(policy, state.carry))
        rec["action"].append(action)
        rec["reward"].append(reward * alive)
        rec["valid"].append(alive.copy())
        rec["state"].append(venv.core.slots.state)
        alive &= ~terminated
    out = {k: np.stack(v) for k, v in rec.items() if k not in ("state", "belief")}
    out["state"] = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *rec["state"])
    out["belief"] = None if rec["belief"][0] is None else np.stack(rec["belief"])
    out["theta"] = np.asarray(jax.vmap(policy.env.theta)(rec["state"][0]))
    return out


def _belief_text(z: np.ndarray | None) -> str:
    """The belief's first components as text."""
    if z is None:
        return ""
    return " · belief z = (" + ", ".join(f"{v:+.2f}" for v in z[:3]) + (", …)" if len(z) > 3 else ")")


def render_bandit(rec: dict[str, Any], algo: str, path: pathlib.Path) -> list[pathlib.Path]:
    """One raster per episode: the imitator's action probabilities per step, θ's row marked, actions as dots."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    probs = jax.nn.softmax(rec["head"], axis=-1)  # [T, N, arms]
    episodes = probs.shape[1]
    rows = 2 if rec["belief"] is not None else 1
    fig, axes = plt.subplots(rows * episodes, 1, figsize=(8, 1.6 * rows * episodes), squeeze=False)
    for i in range(episodes):
        ax = axes[rows * i, 0]
        ax.imshow(np.asarray(probs[:, i]).T, aspect="auto", cmap="viridis", vmin=0, vmax=1, origin="lower")
        ax.plot(np.arange(len(rec["action"])), rec["action"][:, i], "w.", markersize=2)
        ax.axhline(rec["theta"][i], color="tab:red", linewidth=0.8)
        ax.set_ylabel("arm")
        final = None if rec["belief"] is None else rec["belief"][-1, i]
        ax.set_title(f"{algo}, episode {i}: θ = best arm {int(rec['theta'][i])}, best-arm count "
                     f"{int(rec['reward'][:, i].sum())}{_belief_text(final)}", fontsize=8)
        if rec["belief"] is not None:
            axes[rows * i + 1, 0].plot(rec["belief"][:, i])
            axes[rows * i + 1, 0].set_ylabel("belief z", fontsize=7)
    axes[-1, 0].set_xlabel("step (colour: P(arm); dots: pulled arm; red: θ)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return [path]


def _lander_frame(ax: Any, env: Any, params: Any, state: Any, action: int, title: str) -> None:
    """Draw one LunarLander state: terrain, helipad, hull, legs and the commanded engine's flame."""
    from jaxdeconf.envs import lunar_lander as ll

    ax.clear()
    ax.set_xlim(0, ll.W)
    ax.set_ylim(0, ll.H)
    ax.set_axis_off()
    xs = np.linspace(0, ll.W, ll.CHUNKS)
    ax.fill_between(xs, 0, state.terrain, color="0.35")
    pad = (xs[ll.CHUNKS // 2 - 1], xs[ll.CHUNKS // 2 + 1])
    for x in pad:
        ax.plot([x, x], [ll.HELIPAD_Y, ll.HELIPAD_Y + 1.0], color="w", linewidth=1)
        ax.fill([x, x, x + 0.6], [ll.HELIPAD_Y + 1.0, ll.HELIPAD_Y + 0.7, ll.HELIPAD_Y + 0.85], color="gold")
    c, s = np.cos(state.angle), np.sin(state.angle)
    rot = np.array([[c, -s], [s, c]])
    origin = np.asarray(ll.origin(state))
    hull = origin + ll.HULL_VERTICES @ rot.T
    ax.fill(hull[:, 0], hull[:, 1], color="mediumpurple", edgecolor="k", linewidth=0.5)
    for k in range(2):
        leg_angle = ll.LEG_ANGLES[k] + ll.LEG_FOLD_SIGN[k] * float(state.fold[k])
        lc, ls = np.cos(leg_angle), np.sin(leg_angle)
        corners = np.array([[sx, sy] for sx, sy in [(1, -1), (1, 1), (-1, 1), (-1, -1)]]) * ll.LEG_HALF
        leg = origin + (ll.LEG_CENTRES[k] + corners @ np.array([[lc, -ls], [ls, lc]]).T) @ rot.T
        ax.fill(leg[:, 0], leg[:, 1], color="green" if state.legs[k] else "mediumpurple", edgecolor="k", linewidth=0.5)
    engine = int(np.asarray(env.permutation(state.theta, params))[action])
    if engine:  # 1 left orientation engine (pushes right), 2 main, 3 right orientation engine.
        nozzle = {1: (-ll.SIDE_ENGINE_AWAY, ll.SIDE_ENGINE_HEIGHT - 8, -1, 0), 2: (0, -10, 0, -1),
                  3: (ll.SIDE_ENGINE_AWAY, ll.SIDE_ENGINE_HEIGHT - 8, 1, 0)}[engine]
        start = origin + rot @ (np.array(nozzle[:2]) / ll.SCALE)
        end = start + rot @ (np.array(nozzle[2:]) * (0.7 if engine == 2 else 0.4))
        ax.plot([start[0], end[0]], [start[1], end[1]], color="orangered", linewidth=3 if engine == 2 else 2)
    ax.set_title(title, fontsize=7)


def render_lander(rec: dict[str, Any], env: Any, params: Any, algo: str, path: pathlib.Path,
                  every: int = 4) -> list[pathlib.Path]:
    """An animated GIF of the episodes one after another, every ``every``-th step, until each ends."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

    frames = []
    for i in range(rec["theta"].shape[0]):
        length = int(rec["valid"][:, i].sum())
        frames += [(i, t) for t in range(0, min(length, len(rec["action"])), every)]
    fig, ax = plt.subplots(figsize=(3.6, 2.7))
    fig.subplots_adjust(0, 0, 1, 0.84)

    def draw(frame: tuple[int, int]) -> None:
        i, t = frame
        state = jax.tree.map(lambda x: x[t, i], rec["state"])
        belief_now = None if rec["belief"] is None else rec["belief"][t, i]
        total = rec["reward"][: t + 1, i].sum()
        title = (f"{algo}, episode {i}: θ = {int(rec['theta'][i])} ({'swapped' if rec['theta'][i] else 'identity'})"
                 f"\nstep {t}, return {total:.0f}{_belief_text(belief_now)}")
        _lander_frame(ax, env, params, state, int(rec["action"][t, i]), title)

    FuncAnimation(fig, draw, frames=frames).save(path, writer=PillowWriter(fps=12), dpi=80)
    plt.close(fig)
    return [path]


def render_brax(rec: dict[str, Any], env: Any, params: Any, algo: str, folder: pathlib.Path) -> list[pathlib.Path]:
    """One Brax HTML viewer file per episode, with θ and the final belief in a heading."""
    from brax.io import html

    paths = []
    sys_ = env.brax_env(params).sys
    for i in range(rec["theta"].shape[0]):
        steps = int(rec["valid"][:, i].sum())
        states = [jax.tree.map(lambda x, t=t, i=i: x[t, i], rec["state"].brax.pipeline_state)
                  for t in range(steps + 1)]
        theta = np.round(np.asarray(rec["theta"][i]), 2).tolist()
        belief_end = None if rec["belief"] is None else rec["belief"][steps - 1, i]
        heading = (f"<h3 style='font-family:sans-serif'>{env.name}, {algo}, episode {i}: θ = {theta}, return "
                   f"{rec['reward'][:, i].sum():.1f}{_belief_text(belief_end)}</h3>")
        page = html.render(sys_, states).replace("<body>", "<body>" + heading, 1)
        path = folder / f"{env.name}_{algo}_episode{i}.html"
        path.write_text(page)
        paths.append(path)
    return paths


def render(folder: str | pathlib.Path, algo: str, episodes: int = 4, seed: int = 0, run_seed: int | None = None,
           out: str | pathlib.Path | None = None) -> list[pathlib.Path]:
    """Render ``episodes`` episodes (env seed ``seed``) of ``algo`` trained with ``run_seed`` in ``folder``."""
    folder = pathlib.Path(folder)
    if algo == "expert":
        policy = expert_policy(folder)
    else:
        policy = load_policy(folder, algo, seed=0 if run_seed is None else run_seed)
    rec = record(policy, episodes, seed)
    env = policy.raw_env
    target = pathlib.Path(out) if out else folder / "render"
    target.mkdir(parents=True, exist_ok=True)
    if env.name == "bandit":
        return render_bandit(rec, algo, target / f"bandit_{algo}.png")
    if env.name == "lunar_lander":
        return render_lander(rec, env, policy.env_params, algo, target / f"lunar_lander_{algo}.gif")
    if hasattr(env, "brax_env"):
        return render_brax(rec, env, policy.env_params, algo, target)
    raise ConfigError(f"no renderer for env {env.name!r}; renderers exist for bandit, lunar_lander and the Brax envs")


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code (2 for bad input)."""
    p = argparse.ArgumentParser(prog="python -m jaxdeconf.render", description=__doc__.splitlines()[0])
    p.add_argument("folder", help="a results folder written by python -m jaxdeconf.run")
    p.add_argument("--algo", default="dil", help="which trained imitator (default: dil), or expert (the env's own)")
    p.add_argument("--episodes", type=int, default=4, help="episodes to render (default: 4)")
    p.add_argument("--seed", type=int, default=0, help="the episodes' seed (default: 0)")
    p.add_argument("--run-seed", type=int, default=None, help="which training seed's imitator (default: the first)")
    p.add_argument("--out", default=None, help="output folder (default: <folder>/render)")
    args = p.parse_args(argv)
    try:
        if args.episodes < 1:
            raise ConfigError(f"--episodes={args.episodes} is not allowed: need a positive integer")
        for path in render(args.folder, args.algo, args.episodes, args.seed, args.run_seed, args.out):
            print(f"wrote {path}")
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
