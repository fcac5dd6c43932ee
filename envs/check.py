"""``check_env``: does an environment keep the contract of ``jaxdeconf.envs.base``?

One compiled program (``jit(vmap(episode))`` over a batch of keys, the expert acting for the whole horizon) plus two
abstract traces of ``reset`` and ``step`` cover shapes and dtypes, purity, determinism, the horizon, the expert's
actions, and that the imitator's view carries no copy of θ. A failed check raises ``EnvCheckError`` naming it.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxdeconf.envs.base import LIKELIHOODS, ActionSpace, Environment, Observation, StepResult

VIEWS = ("expert", "imitator", "oracle")


class EnvCheckError(ValueError):
    """An environment breaks the contract; the message names the check."""


def _fail(env: Environment, message: str) -> EnvCheckError:
    """The error for ``env`` with a uniform prefix."""
    return EnvCheckError(f"check_env({getattr(env, 'name', '') or type(env).__name__}): {message}")


def _check_static(env: Environment, params: Any) -> tuple[int, ActionSpace, Observation]:
    """Params, horizon, action space, view sizes and likelihood: what needs no tracing."""
    if not dataclasses.is_dataclass(params) or not hasattr(params, "replace"):
        raise _fail(env, f"params must be a flax.struct.dataclass, got {type(params).__name__}")
    horizon = env.horizon(params)
    if not isinstance(horizon, int) or isinstance(horizon, bool) or horizon < 1:
        raise _fail(env, f"horizon(params) must be a positive Python int (a static field), got {horizon!r}")
    space = env.action_space(params)
    if not isinstance(space, ActionSpace) or space.kind not in ("discrete", "box") or int(space.n) < 1:
        raise _fail(env, f"action_space(params) must be ActionSpace('discrete' or 'box', n >= 1), got {space!r}")
    sizes = env.obs_sizes(params)
    if not isinstance(sizes, Observation) or not all(
        isinstance(getattr(sizes, v), int | np.integer) and int(getattr(sizes, v)) >= 1 for v in VIEWS
    ):
        raise _fail(env, f"obs_sizes(params) must be an Observation of positive ints, got {sizes!r}")
    if env.obs_likelihood not in ("gaussian", "bernoulli"):
        raise _fail(env, f"obs_likelihood must be 'gaussian' or 'bernoulli', got {env.obs_likelihood!r}")
    groups = env.obs_groups(params)
    if any(g.likelihood not in LIKELIHOODS or int(g.size) < 1 for g in groups) or sum(
            int(g.size) for g in groups) != int(sizes.imitator):
        raise _fail(env, f"obs_groups(params) must split the imitator's {sizes.imitator} dimensions into groups of "
                         f"size >= 1 with a likelihood from {LIKELIHOODS}, got {groups!r}")
    return horizon, space, sizes


def _attribute_fingerprint(env: Environment) -> dict[str, Any]:
    """What ``reset``/``step`` must leave alone: each attribute's identity, and the length of mutable containers.
    ``functools.cached_property`` values are left out: computing one on first use (a loaded expert) is allowed."""
    return {name: (id(value), len(value) if isinstance(value, list | dict | set) else None)
            for name, value in vars(env).items()
            if not isinstance(getattr(type(env), name, None), functools.cached_property)}


def _jaxpr_fingerprint(fn: Any, *args: Any) -> tuple[str, list[np.ndarray]]:
    """The traced program of ``fn`` and its constants; an impure function traces differently each time."""
    closed = jax.make_jaxpr(lambda *a: fn(*a))(*args)  # A fresh function each time: JAX caches traces per function.
    return str(closed.jaxpr), [np.asarray(c) for c in closed.consts if hasattr(c, "shape")]


def _same_fingerprint(a: tuple[str, list[np.ndarray]], b: tuple[str, list[np.ndarray]]) -> bool:
    """Whether two traces are the same program with equal constants."""
    return a[0] == b[0] and len(a[1]) == len(b[1]) and all(
        x.shape == y.shape and np.array_equal(x, y, equal_nan=True) for x, y in zip(a[1], b[1], strict=True)
    )


def _check_attributes(env: Environment, before: dict[str, Any], where: str) -> None:
    """The env object's attributes are as they were before ``where`` ran."""
    after = _attribute_fingerprint(env)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    if changed:
        raise _fail(env, f"{where} is not pure: it changed the environment object's attribute(s) "
                         f"{', '.join(changed)}; keep everything that changes in the state")


def _check_purity(env: Environment, params: Any, before: dict[str, Any]) -> None:
    """Trace reset and step twice each: the traces must match and the env object must be left unchanged."""
    key = jax.random.key(0)
    state, _ = jax.eval_shape(env.reset, key, params)
    space = env.action_space(params)
    action = (jax.ShapeDtypeStruct((), jnp.int32) if space.discrete
              else jax.ShapeDtypeStruct((space.n,), jnp.float32))
    for name, fn, args in (("reset", env.reset, (key, params)), ("step", env.step, (key, state, action, params))):
        first = _jaxpr_fingerprint(fn, *args)
        second = _jaxpr_fingerprint(fn, *args)
        if not _same_fingerprint(first, second):
            raise _fail(env, f"{name} is not pure: two traces with the same inputs gave different programs or "
                             "constants (Python-side state, numpy randomness or a counter read inside it?)")
        _check_attributes(env, before, name)


def _episode(env: Environment, params: Any, key: jax.Array) -> dict[str, Any]:
    """One episode with the expert acting on every step: θ, all observations, actions, rewards, dones, extras."""
    space = env.action_space(params)
    key_reset, key_steps = jax.random.split(key)
    state, obs = env.reset(key_reset, params)
    theta = env.theta(state)

    def body(carry: tuple[Any, Observation], step_key: jax.Array) -> tuple[tuple, dict[str, Any]]:
        state, obs = carry
        key_act, key_env = jax.random.split(step_key)
        action = env.expert_action(key_act, obs, params)
        probs = env.expert_probs(obs, params) if space.discrete else None
        state, result = env.step(key_env, state, action, params)
        if not isinstance(result, StepResult):
            raise _fail(env, f"step must return (state, StepResult), got a {type(result).__name__} second")
        record = {"obs": result.obs, "action": action, "reward": result.reward, "done": result.done,
                  "extras": result.extras, "probs": probs}
        return (state, result.obs), record

    _, rec = jax.lax.scan(body, (state, obs), jax.random.split(key_steps, env.horizon(params)))
    rec["first_obs"] = obs
    rec["theta"] = theta
    return rec


def _check_layout(env: Environment, params: Any, out: dict[str, Any], space: ActionSpace, sizes: Observation,
                  samples: int, horizon: int) -> None:
    """Shapes, dtypes and finiteness of everything one batch of episodes produced."""
    for view in VIEWS:
        for where, arr, lead in (("reset", getattr(out["first_obs"], view), (samples,)),
                                 ("step", getattr(out["obs"], view), (samples, horizon))):
            want = (*lead, int(getattr(sizes, view)))
            if arr.shape != want or arr.dtype != np.float32:
                raise _fail(env, f"the {view} view from {where} has shape {arr.shape[len(lead):]} and dtype "
                                 f"{arr.dtype}; "
                                 f"obs_sizes says {want[-1]}, and views must be float32 vectors")
    for name, dtype in (("reward", np.float32), ("done", np.bool_)):
        if out[name].shape != (samples, horizon) or out[name].dtype != dtype:
            raise _fail(env, f"step's {name} must be a {np.dtype(dtype).name} scalar, got shape "
                             f"{out[name].shape[2:]} and dtype {out[name].dtype}")
    if set(out["extras"]) != set(env.extras_names):
        raise _fail(env, f"step's extras {sorted(out['extras'])} differ from extras_names {list(env.extras_names)}")
    for name, value in out["extras"].items():
        if value.shape != (samples, horizon):
            raise _fail(env, f"extra {name!r} must be a scalar per step, got shape {value.shape[2:]}")
    valid = np.concatenate([np.ones((samples, 1), bool), ~np.cumsum(out["done"], axis=1).astype(bool)[:, :-1]], 1)
    for name, arr in (("reward", out["reward"]), *((f"{v} view", getattr(out["obs"], v)) for v in VIEWS)):
        mask = valid if arr.ndim == 2 else valid[..., None]
        if not np.isfinite(np.where(mask, arr, 0.0)).all():
            raise _fail(env, f"the {name} is not finite on a valid step of an expert episode")


def _check_expert(env: Environment, out: dict[str, Any], space: ActionSpace, samples: int, horizon: int) -> None:
    """The expert's actions lie in the action space; discrete probabilities are a distribution."""
    action = out["action"]
    if space.discrete:
        if action.shape != (samples, horizon) or not np.issubdtype(action.dtype, np.integer):
            raise _fail(env, f"expert_action must return an integer scalar, got shape {action.shape[2:]} and "
                             f"dtype {action.dtype}")
        if action.min() < 0 or action.max() >= space.n:
            raise _fail(env, f"expert_action returned {int(action.min())}..{int(action.max())}, "
                             f"outside 0..{space.n - 1}")
        probs = out["probs"]
        if probs is None or probs.shape != (samples, horizon, space.n):
            raise _fail(env, f"expert_probs must return [{space.n}] probabilities for a discrete action space")
        if (probs < 0).any() or not np.allclose(probs.sum(-1), 1.0, atol=1e-4):
            raise _fail(env, "expert_probs must be non-negative and sum to 1")
    else:
        if action.shape != (samples, horizon, space.n) or action.dtype != np.float32:
            raise _fail(env, f"expert_action must return a float32 [{space.n}] action, got shape "
                             f"{action.shape[2:]} and dtype {action.dtype}")
        if not np.isfinite(action).all():
            raise _fail(env, "expert_action returned a non-finite action")


def _r2(x: np.ndarray, y: np.ndarray) -> float:
    """R² of a least-squares linear fit (with intercept) of y [n] on x [n, d]."""
    design = np.concatenate([x, np.ones((len(x), 1))], axis=1).astype(np.float64)
    coef, *_ = np.linalg.lstsq(design, y.astype(np.float64), rcond=None)
    resid = y - design @ coef
    return 1.0 - float(resid @ resid) / max(float(((y - y.mean()) ** 2).sum()), 1e-12)


def _check_theta(env: Environment, out: dict[str, Any], samples: int, steps: int = 8) -> None:
    """θ varies with the reset key and no linear function of the imitator's view reproduces it."""
    theta = np.asarray(out["theta"], np.float64).reshape(samples, -1)
    if (theta.std(axis=0) == 0).all():
        raise _fail(env, "θ (env.theta(state)) is the same in every episode: sample it in reset from the key")
    views = [out["first_obs"].imitator[:, None], out["obs"].imitator[:, : steps - 1]]
    view = np.concatenate(views, axis=1)  # [samples, steps, d]
    x = view.reshape(-1, view.shape[-1])
    for i in range(theta.shape[1]):
        y = np.repeat(theta[:, i], view.shape[1])
        if y.std() > 0 and _r2(x, y) > 1.0 - 1e-6:
            raise _fail(env, f"θ is in the imitator's view: a linear read-out of obs.imitator reproduces θ"
                             f"{'' if theta.shape[1] == 1 else f'[{i}]'} exactly on {samples} episodes; the imitator "
                             "must never see θ (put it in the expert's and the oracle's views only)")


def _first_steps(out: dict[str, Any]) -> list[np.ndarray]:
    """θ, the reset observation and the first step's outputs: what a batch position could leak into."""
    first = {"theta": out["theta"], "reset": out["first_obs"],
             "step": jax.tree.map(lambda x: np.asarray(x)[:, :1], {k: out[k] for k in ("obs", "reward", "done")})}
    return [np.asarray(x) for x in jax.tree.leaves(first)]


def _check_deterministic(env: Environment, run: Any, keys: jax.Array, out: dict[str, Any]) -> None:
    """Same keys, identical outputs; permuted keys, the first step permuted alike (each episode depends on its own
    key only). The second is compared to float32 tolerance over one step: XLA need not give a batch row bit-identical
    results at another position (seen with MJX), and chaotic dynamics grow such differences over an episode."""
    again = jax.tree.map(np.asarray, run(keys))
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(again), strict=True):
        if not np.array_equal(a, b, equal_nan=True):
            raise _fail(env, "episodes are not deterministic under jit and vmap: the same keys gave different "
                             "results (hidden state or randomness not drawn from the key?)")
    order = np.arange(len(keys))[::-1].copy()
    permuted = jax.tree.map(np.asarray, run(keys[order]))
    for a, b in zip(_first_steps(out), _first_steps(permuted), strict=True):
        if not np.allclose(a[order].astype(np.float64), b.astype(np.float64), rtol=1e-4, atol=1e-5, equal_nan=True):
            raise _fail(env, "episodes depend on other episodes of the batch: permuted keys did not permute the "
                             "results (state shared across the vmapped batch?)")


def check_env(env: Environment, params: Any | None = None, samples: int = 64) -> None:
    """Check ``env`` keeps the environment contract; raise ``EnvCheckError`` naming the first problem.

    Runs ``samples`` expert episodes of the full horizon in one compiled ``jit(vmap(...))`` program (three times:
    twice on the same keys, once on permuted keys), and traces ``reset`` and ``step`` twice each without compiling.
    """
    params = env.default_params() if params is None else params
    horizon, space, sizes = _check_static(env, params)
    before = _attribute_fingerprint(env)
    _check_purity(env, params, before)
    run = jax.jit(jax.vmap(lambda k: _episode(env, params, k)))
    keys = jax.random.split(jax.random.key(20240601), samples)
    out = jax.tree.map(np.asarray, run(keys))
    _check_attributes(env, before, "step")  # Compiling and running may not change the env object either.
    _check_layout(env, params, out, space, sizes, samples, horizon)
    _check_expert(env, out, space, samples, horizon)
    _check_theta(env, out, samples)
    _check_deterministic(env, run, keys, out)
