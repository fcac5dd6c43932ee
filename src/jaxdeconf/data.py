"""Trajectories of whole fixed-length episodes, on-device replay buffers, and rollouts by ``lax.scan``.

Every Trajectory leaf is time-major with the episode (batch) axis at position 1, so buffers index axis 1 throughout.
"""

from __future__ import annotations

from typing import Any, Protocol

import jax
import jax.numpy as jnp
from flax import struct

from jaxdeconf.envs.base import Environment, Observation
from jaxdeconf.models import action_features, sample


@struct.dataclass
class Trajectory:
    """A batch of B episodes of T steps."""

    obs: Observation  # Each view [T+1, B, d]: s_0 .. s_T.
    action: jax.Array  # [T, B] int32 or [T, B, A] float32.
    reward: jax.Array  # [T, B], zero where invalid.
    valid: jax.Array  # [T, B] bool: the episode had not terminated before step t.
    best_action: jax.Array  # [T, B] int32: the θ-aware preferred action, -1 where undefined.
    extras: dict[str, jax.Array]  # Env-specific per-step scalars, each [T, B], zero where invalid.

    @property
    def horizon(self) -> int:
        """T."""
        return self.valid.shape[0]


class Actor(Protocol):
    """Anything that acts: ``init_carry(batch)`` and ``__call__(params, carry, obs, prev_action)``."""

    def init_carry(self, batch: int) -> Any:
        """Recurrent state at the start of an episode."""

    def __call__(self, params: Any, carry: Any, obs: Observation, prev_action: jax.Array) -> tuple[Any, jax.Array]:
        """New carry and the policy head output (logits, or mean and log-std) for a batch."""


def rollout(
    env: Environment, env_params: Any, actor: Actor, actor_params: Any, key: jax.Array, num_episodes: int
) -> tuple[Trajectory, jax.Array]:
    """Run ``num_episodes`` episodes of the env's fixed horizon with vmapped envs inside one ``lax.scan``.

    Returns the trajectory and the actor's probability of the best action per step [T, B] (NaN where undefined or
    for continuous actions).
    """
    traj, p_best, _ = rollout_with_outputs(env, env_params, actor, actor_params, key, num_episodes)
    return traj, p_best


def rollout_with_outputs(
    env: Environment, env_params: Any, actor: Actor, actor_params: Any, key: jax.Array, num_episodes: int
) -> tuple[Trajectory, jax.Array, jax.Array]:
    """``rollout`` that also returns the actor's head outputs [T, B, ...] as it acted (PPO's behaviour policy)."""
    space = env.action_space(env_params)
    T = env.horizon(env_params)
    key_reset, key_steps = jax.random.split(key)
    state, obs = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key_reset, num_episodes), env_params)
    prev = jnp.zeros((num_episodes, space.feature_size), jnp.float32)
    alive = jnp.ones((num_episodes,), jnp.bool_)

    def body(carry: tuple, step_key: jax.Array) -> tuple[tuple, dict[str, Any]]:
        state, obs, actor_carry, prev, alive = carry
        key_act, key_env = jax.random.split(step_key)
        actor_carry, out = actor(actor_params, actor_carry, obs, prev)
        action = sample(space, key_act, out)
        best = jax.vmap(env.best_action, in_axes=(0, None))(state, env_params)
        next_state, result = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            jax.random.split(key_env, num_episodes), state, action, env_params
        )
        p_best = best_action_prob(out, best) if space.discrete else jnp.full((num_episodes,), jnp.nan)
        mask = alive.astype(jnp.float32)
        record = {
            "obs": obs,
            "action": action,
            "reward": result.reward * mask,
            "valid": alive,
            "best_action": best.astype(jnp.int32),
            "extras": {name: value * mask for name, value in result.extras.items()},
            "p_best": p_best,
            "out": out,
        }
        alive = alive & ~result.done
        return (next_state, result.obs, actor_carry, action_features(space, action), alive), record

    init = (state, obs, actor.init_carry(num_episodes), prev, alive)
    (_, last_obs, _, _, _), rec = jax.lax.scan(body, init, jax.random.split(key_steps, T))
    all_obs = jax.tree.map(lambda seq, last: jnp.concatenate([seq, last[None]], axis=0), rec["obs"], last_obs)
    traj = Trajectory(
        obs=all_obs,
        action=rec["action"],
        reward=rec["reward"],
        valid=rec["valid"],
        best_action=rec["best_action"],
        extras=rec["extras"],
    )
    return traj, rec["p_best"], rec["out"]


@struct.dataclass
class Tagged:
    """Episodes with per-step annotations that a buffer keeps beside them (DAgger's labels, PPO's log-probs)."""

    traj: Trajectory
    tags: dict[str, jax.Array]  # Each [T, B, ...].

    @property
    def valid(self) -> jax.Array:
        """The episodes' valid mask [T, B] (what the buffer functions read)."""
        return self.traj.valid


@struct.dataclass
class Buffer:
    """A circular buffer of whole episodes: ``data`` leaves have the capacity on axis 1."""

    data: Trajectory
    pos: jax.Array  # int32: where the next episode goes.
    size: jax.Array  # int32: episodes stored so far (<= capacity).

    @property
    def capacity(self) -> int:
        """Maximum number of episodes."""
        return self.data.valid.shape[1]


def buffer_init(example: Trajectory, capacity: int) -> Buffer:
    """An empty buffer shaped like ``example`` (any batch size) with room for ``capacity`` episodes."""
    data = jax.tree.map(lambda x: jnp.zeros((x.shape[0], capacity, *x.shape[2:]), x.dtype), example)
    return Buffer(data=data, pos=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32))


def buffer_add(buffer: Buffer, traj: Trajectory) -> Buffer:
    """Insert the episodes of ``traj``, overwriting the oldest once full."""
    # Written as gather + select rather than a scatter (``.at[:, idx].set``): under the seed vmap, XLA's CPU runtime
    # (jaxlib 0.10.2) deadlocked reproducibly on that batched scatter at 4 seeds, every thread idle.
    n = traj.valid.shape[1]
    offset = (jnp.arange(buffer.capacity) - buffer.pos) % buffer.capacity  # Slot j receives episode offset[j].
    written = offset < n
    src = jnp.minimum(offset, n - 1)

    def insert(d: jax.Array, x: jax.Array) -> jax.Array:
        mask = written.reshape((1, -1) + (1,) * (d.ndim - 2))
        return jnp.where(mask, jnp.take(x, src, axis=1), d)

    data = jax.tree.map(insert, buffer.data, traj)
    return Buffer(
        data=data, pos=(buffer.pos + n) % buffer.capacity, size=jnp.minimum(buffer.size + n, buffer.capacity)
    )


def buffer_indices(buffer: Buffer, key: jax.Array, batch: int) -> jax.Array:
    """Indices of ``batch`` distinct stored episodes, drawn uniformly (without replacement)."""
    scores = jax.random.uniform(key, (buffer.capacity,))
    scores = jnp.where(jnp.arange(buffer.capacity) < buffer.size, scores, 2.0)
    return jnp.argsort(scores)[:batch]


def buffer_sample(buffer: Buffer, key: jax.Array, batch: int) -> Trajectory:
    """Sample ``batch`` distinct stored episodes uniformly (without replacement)."""
    idx = buffer_indices(buffer, key, batch)
    return jax.tree.map(lambda d: d[:, idx], buffer.data)


def replay(actor: Actor, actor_params: Any, traj: Trajectory, space: Any) -> jax.Array:
    """Teacher-force ``actor`` along ``traj`` (its own observations and actions): head outputs [T, B, ...]."""
    T = traj.horizon
    obs = jax.tree.map(lambda x: x[:T], traj.obs)
    feats = action_features(space, traj.action)
    prev = jnp.concatenate([jnp.zeros_like(feats[:1]), feats[:-1]], axis=0)

    def body(carry: Any, xs: tuple) -> tuple[Any, jax.Array]:
        obs_t, prev_t = xs
        return actor(actor_params, carry, obs_t, prev_t)

    _, out = jax.lax.scan(body, actor.init_carry(traj.valid.shape[1]), (obs, prev))
    return out


def best_action_prob(out: jax.Array, best: jax.Array) -> jax.Array:
    """Probability a categorical head output [..., n] gives the best action [...] (NaN where best < 0)."""
    probs = jax.nn.softmax(out, axis=-1)
    p = jnp.take_along_axis(probs, jnp.maximum(best, 0)[..., None], axis=-1)[..., 0]
    return jnp.where(best >= 0, p, jnp.nan)
