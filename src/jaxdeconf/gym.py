"""Any registered environment as a ``gymnasium.Env`` or a ``gymnasium.vector.VectorEnv``.

The observation is one view of the env (the imitator's by default; ``view="oracle"`` for the oracle's policy). Both
wrappers run one jitted JAX step over all their sub-environments. ``reset(seed=s)`` draws exactly the keys the
compiled rollout ``jaxdeconf.data.rollout(env, params, actor, actor_params, jax.random.key(s), num_envs)`` draws, so
a policy seeded with the same ``s`` (``jaxdeconf.policy.Policy.initial_state(seed=s)``) reproduces that rollout's
first episode of every sub-environment. Episodes are truncated at the env's fixed horizon and terminated when the env
says ``done``; the vector env resets a finished sub-environment on its next step (``AutoresetMode.NEXT_STEP``).
"""

from __future__ import annotations

import functools
from typing import Any

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from jaxdeconf.envs import Environment, make


@struct.dataclass
class Slots:
    """The JAX state of ``num_envs`` sub-environments between host calls."""

    state: Any  # The env states, batched on axis 0.
    elapsed: jax.Array  # int32 [N]: steps into the current episode.
    needs_reset: jax.Array  # bool [N]: the episode ended on the last step (reset on the next, NEXT_STEP).
    step: jax.Array  # int32 []: steps since ``reset(seed=)``; picks the per-step key.
    key_reset: jax.Array  # Typed key the (auto)resets derive from.
    key_steps: jax.Array  # Typed key the per-step keys derive from.


def step_key(key_steps: jax.Array, step: jax.Array, horizon: int) -> jax.Array:
    """The key of global step ``step``: ``split(key_steps, horizon)[step]`` as ``data.rollout`` draws it, and
    ``fold_in(key_steps, step)`` past the first horizon."""
    first = jax.random.key_data(jax.random.split(key_steps, horizon)[jnp.minimum(step, horizon - 1)])
    later = jax.random.key_data(jax.random.fold_in(key_steps, step))
    return jax.random.wrap_key_data(jnp.where(step < horizon, first, later))


def reset_slots(env: Environment, params: Any, num_envs: int, view: str, key: jax.Array) -> tuple[Slots, jax.Array]:
    """Reset every sub-environment with ``rollout``'s keys; return the slots and the view [N, d]."""
    key_reset, key_steps = jax.random.split(key)
    state, obs = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_envs), params)
    slots = Slots(state=state, elapsed=jnp.zeros((num_envs,), jnp.int32),
                  needs_reset=jnp.zeros((num_envs,), jnp.bool_), step=jnp.zeros((), jnp.int32),
                  key_reset=key_reset, key_steps=key_steps)
    return slots, getattr(obs, view)


def step_slots(
    env: Environment, params: Any, num_envs: int, view: str, slots: Slots, action: jax.Array
) -> tuple[Slots, jax.Array, jax.Array, jax.Array, jax.Array]:
    """Step every sub-environment, or reset those that finished on the last step (their action is ignored).

    Returns slots, the view [N, d], reward [N], terminated [N] and truncated [N].
    """
    horizon = env.horizon(params)
    _, key_env = jax.random.split(step_key(slots.key_steps, slots.step, horizon))  # The first half is the actor's.
    state, result = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
        jax.random.split(key_env, num_envs), slots.state, action, params)
    fresh_keys = jax.random.split(jax.random.fold_in(slots.key_reset, slots.step + 1), num_envs)
    fresh_state, fresh_obs = jax.vmap(env.reset, in_axes=(0, None))(fresh_keys, params)
    again = slots.needs_reset

    def pick(fresh: jax.Array, stepped: jax.Array) -> jax.Array:
        return jnp.where(again.reshape((-1,) + (1,) * (stepped.ndim - 1)), fresh, stepped)

    state = jax.tree.map(pick, fresh_state, state)
    obs = pick(getattr(fresh_obs, view), getattr(result.obs, view))
    elapsed = jnp.where(again, 0, slots.elapsed + 1)
    terminated = ~again & result.done
    truncated = ~again & ~terminated & (elapsed >= horizon)
    slots = slots.replace(state=state, elapsed=elapsed, needs_reset=terminated | truncated, step=slots.step + 1)
    return slots, obs, jnp.where(again, 0.0, result.reward), terminated, truncated


class _Core:
    """What both wrappers share: the env, its spaces and the two jitted functions."""

    def __init__(self, env: str | Environment, params: Any, num_envs: int, view: str, **overrides: Any) -> None:
        if isinstance(env, str):
            env, params = make(env, **overrides)
        elif params is None:
            params = env.default_params()
        if view not in ("imitator", "oracle", "expert"):
            raise ValueError(f"view={view!r} is not allowed; allowed: imitator, oracle, expert")
        self.env, self.params, self.num_envs, self.view = env, params, num_envs, view
        self.horizon = env.horizon(params)
        space = env.action_space(params)
        self.single_action_space = (gymnasium.spaces.Discrete(space.n) if space.discrete
                                    else gymnasium.spaces.Box(-1.0, 1.0, (space.n,), np.float32))
        size = int(getattr(env.obs_sizes(params), view))
        self.single_observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (size,), np.float32)
        self.action_dtype = np.int32 if space.discrete else np.float32
        self._reset = jax.jit(functools.partial(reset_slots, env, params, num_envs, view))
        self._step = jax.jit(functools.partial(step_slots, env, params, num_envs, view))
        self.slots: Slots | None = None

    def reset(self, seed: int) -> np.ndarray:
        """Reset all sub-environments from ``jax.random.key(seed)``."""
        self.slots, obs = self._reset(jax.random.key(seed))
        return np.array(obs)

    def step(self, action: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One step of every sub-environment."""
        if self.slots is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        action = np.asarray(action, self.action_dtype).reshape((self.num_envs, *self.single_action_space.shape))
        self.slots, obs, reward, terminated, truncated = self._step(self.slots, action)
        return np.array(obs), np.asarray(reward, np.float64), np.array(terminated), np.array(truncated)

    def theta(self) -> np.ndarray:
        """θ of each sub-environment's current episode."""
        return np.asarray(jax.vmap(self.env.theta)(self.slots.state))


def _seed(np_random: np.random.Generator) -> int:
    """A fresh integer seed for the JAX key when ``reset`` is called without one."""
    return int(np_random.integers(0, 2**31 - 1))


class GymEnv(gymnasium.Env):
    """One confounded environment as a ``gymnasium.Env``; the observation is one view (the imitator's by default).

    ``info["theta"]`` holds the episode's θ, for analysis only: an imitator must not read it.
    """

    metadata: dict[str, Any] = {"render_modes": []}  # noqa: RUF012  (gymnasium's declared class attribute)

    def __init__(self, env: str | Environment, params: Any = None, view: str = "imitator", **overrides: Any) -> None:
        self.core = _Core(env, params, 1, view, **overrides)
        self.action_space = self.core.single_action_space
        self.observation_space = self.core.single_observation_space
        self.spec = None

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """Start an episode; ``seed`` fixes every random draw of it (see the module docstring)."""
        del options  # Unused.
        super().reset(seed=seed)
        obs = self.core.reset(_seed(self.np_random) if seed is None else seed)
        return obs[0], {"theta": self.core.theta()[0]}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One step; ``truncated`` at the fixed horizon, ``terminated`` when the env ends the episode early."""
        obs, reward, terminated, truncated = self.core.step(action)
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), {"theta": self.core.theta()[0]}


class GymVectorEnv(gymnasium.vector.VectorEnv):
    """``num_envs`` confounded environments as one ``gymnasium.vector.VectorEnv`` (autoreset mode NEXT_STEP)."""

    metadata: dict[str, Any] = {"autoreset_mode": AutoresetMode.NEXT_STEP}  # noqa: RUF012

    def __init__(
        self, env: str | Environment, num_envs: int, params: Any = None, view: str = "imitator", **overrides: Any
    ) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs={num_envs} is not allowed: need a positive integer")
        self.core = _Core(env, params, num_envs, view, **overrides)
        self.num_envs = num_envs
        self.single_action_space = self.core.single_action_space
        self.single_observation_space = self.core.single_observation_space
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.observation_space = batch_space(self.single_observation_space, num_envs)

    def reset(
        self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict]:
        """Reset every sub-environment; one integer ``seed`` fixes all of them (a list is not supported)."""
        del options  # Unused.
        if isinstance(seed, list | tuple):
            raise ValueError("GymVectorEnv takes one integer seed for all sub-environments, not a list")
        if seed is not None:
            self._np_random, self._np_random_seed = gymnasium.utils.seeding.np_random(seed)
        obs = self.core.reset(_seed(self.np_random) if seed is None else seed)
        return obs, {}

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        """One step of every sub-environment (a finished one is reset instead, returning reward 0)."""
        obs, reward, terminated, truncated = self.core.step(actions)
        return obs, reward, terminated, truncated, {}


def make_env(name: str, view: str = "imitator", **overrides: Any) -> GymEnv:
    """A registered env (or ``module:Class``) with parameter ``overrides`` as a ``gymnasium.Env``."""
    return GymEnv(name, view=view, **overrides)


def make_vector_env(name: str, num_envs: int, view: str = "imitator", **overrides: Any) -> GymVectorEnv:
    """A registered env (or ``module:Class``) as a ``gymnasium.vector.VectorEnv`` of ``num_envs`` copies."""
    return GymVectorEnv(name, num_envs, view=view, **overrides)
