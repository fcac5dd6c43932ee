"""PPO for θ-aware experts on discrete-action environments, on the expert's view (θ visible).

Brax's PPO trainer (``brax.training.agents.ppo``) only has continuous (tanh-normal) action distributions, so the
discrete experts (LunarLander) are trained here: the standard clipped-surrogate PPO with GAE, separate actor and critic
MLPs, advantage normalisation, a linearly annealed learning rate and global-norm clipping. Rollouts and updates of a
chunk of iterations are one compiled program; episodes reset automatically when they terminate or reach the horizon.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxdeconf.envs.base import Environment
from jaxdeconf.losses import masked_mean


class ExpertNetwork(nn.Module):
    """Actor (logits) and critic (value) MLPs with tanh activations and orthogonal initialisation."""

    actions: int
    width: int = 64
    depth: int = 2

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Logits [..., actions] and value [...]."""
        def mlp(x: jax.Array, out: int, scale: float, name: str) -> jax.Array:
            for i in range(self.depth):
                x = nn.tanh(nn.Dense(self.width, kernel_init=nn.initializers.orthogonal(np.sqrt(2)),
                                     name=f"{name}_{i}")(x))
            return nn.Dense(out, kernel_init=nn.initializers.orthogonal(scale), name=f"{name}_out")(x)

        logits = mlp(obs, self.actions, 0.01, "actor")
        value = mlp(obs, 1, 1.0, "critic")[..., 0]
        return logits, value


def gae(
    rewards: jax.Array, values: jax.Array, next_values: jax.Array, continues: jax.Array, gamma: float, lam: float
) -> jax.Array:
    """Generalised advantage estimates [T, ...] by a reverse scan over time (axis 0).

    delta_t = r_t + gamma c_t V'_t - V_t and A_t = delta_t + gamma lam c_t A_{t+1}, where V'_t (``next_values``) is
    the value of the state after step t and c_t (``continues``, 0 or 1) says whether the episode goes on after it.
    """

    def body(next_adv: jax.Array, step: tuple) -> tuple[jax.Array, jax.Array]:
        reward, value, next_value, cont = step
        delta = reward + gamma * next_value * cont - value
        adv = delta + gamma * lam * cont * next_adv
        return adv, adv

    _, adv = jax.lax.scan(body, jnp.zeros_like(values[0]), (rewards, values, next_values, continues), reverse=True)
    return adv


def _mean(x: jax.Array, mask: jax.Array | None) -> jax.Array:
    """Mean of ``x``, over the entries where ``mask`` holds when one is given."""
    return x.mean() if mask is None else masked_mean(x, mask)


def normalize_advantages(adv: jax.Array, mask: jax.Array | None = None) -> jax.Array:
    """Advantages standardised to mean 0 and standard deviation 1 (over the masked entries)."""
    mean = _mean(adv, mask)
    if mask is None:
        return (adv - mean) / (adv.std() + 1e-8)
    std = jnp.sqrt(_mean((adv - mean) ** 2, mask))
    return (adv - mean) / (std + 1e-8)


def clipped_surrogate(
    log_prob: jax.Array, old_log_prob: jax.Array, adv: jax.Array, clip: float, mask: jax.Array | None = None
) -> jax.Array:
    """PPO's clipped surrogate loss -mean(min(r A, clip(r, 1 - eps, 1 + eps) A)), r = exp(log_prob - old)."""
    ratio = jnp.exp(log_prob - old_log_prob)
    return -_mean(jnp.minimum(ratio * adv, jnp.clip(ratio, 1 - clip, 1 + clip) * adv), mask)


def squared_value_error(value: jax.Array, target: jax.Array, mask: jax.Array | None = None) -> jax.Array:
    """The critic's loss 0.5 mean((V - target)^2)."""
    return 0.5 * _mean((value - target) ** 2, mask)


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyperparameters (defaults: the rl-zoo LunarLander settings, with more parallel envs)."""

    total_steps: int = 3_000_000
    num_envs: int = 64
    rollout: int = 256  # Steps per env per iteration.
    epochs: int = 4
    minibatches: int = 64
    lr: float = 3e-4
    gamma: float = 0.999
    gae_lambda: float = 0.98
    clip: float = 0.2
    entropy: float = 0.01
    value_coef: float = 0.5
    max_grad_norm: float = 0.5
    width: int = 64
    depth: int = 2
    chunk: int = 10  # Iterations per compiled call.

    @property
    def iterations(self) -> int:
        """Number of rollout/update iterations, rounded up to whole chunks."""
        iters = max(1, self.total_steps // (self.num_envs * self.rollout))
        return -(-iters // self.chunk) * self.chunk


def train_ppo(
    env: Environment,
    env_params: Any,
    config: PPOConfig,
    seed: int,
    log: Callable[[dict[str, float]], None] | None = None,
) -> tuple[Any, list[dict[str, float]]]:
    """Train an expert on ``env``'s expert view; return its network params and the per-chunk log."""
    space = env.action_space(env_params)
    if not space.discrete:
        raise ValueError(f"PPO here trains discrete experts; env {env.name} has a {space.kind} action space")
    horizon = env.horizon(env_params)
    net = ExpertNetwork(space.n, config.width, config.depth)
    key = jax.random.key(seed)
    key, k_init, k_reset = jax.random.split(key, 3)
    obs_size = env.obs_sizes(env_params).expert
    params = net.init(k_init, jnp.zeros((obs_size,)))
    steps_per_update = config.iterations * config.epochs * config.minibatches
    schedule = optax.linear_schedule(config.lr, 0.0, steps_per_update)
    tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.adam(schedule, eps=1e-5))
    opt_state = tx.init(params)
    reset = jax.vmap(env.reset, in_axes=(0, None))
    step = jax.vmap(env.step, in_axes=(0, 0, 0, None))
    state, obs = reset(jax.random.split(k_reset, config.num_envs), env_params)
    ep_return = jnp.zeros((config.num_envs,))

    def env_step(carry: tuple, key: jax.Array) -> tuple[tuple, dict]:
        params, state, obs, ep_return = carry
        k_act, k_step, k_reset = jax.random.split(key, 3)
        logits, value = net.apply(params, obs.expert)
        action = jax.random.categorical(k_act, logits)
        log_prob = jax.nn.log_softmax(logits)[jnp.arange(config.num_envs), action]
        next_state, result = step(jax.random.split(k_step, config.num_envs), state, action, env_params)
        done = result.done | (next_state.t >= horizon)
        fresh_state, fresh_obs = reset(jax.random.split(k_reset, config.num_envs), env_params)
        pick = lambda a, b: jnp.where(done.reshape(done.shape + (1,) * (a.ndim - 1)), a, b)  # noqa: E731
        next_state = jax.tree.map(pick, fresh_state, next_state)
        next_obs = jax.tree.map(pick, fresh_obs, result.obs)
        ep_return = ep_return + result.reward
        record = {"obs": obs.expert, "action": action, "log_prob": log_prob, "value": value,
                  "reward": result.reward, "done": done, "finished_return": jnp.where(done, ep_return, jnp.nan)}
        return (params, next_state, next_obs, jnp.where(done, 0.0, ep_return)), record

    def loss_fn(params: Any, batch: dict) -> tuple[jax.Array, dict]:
        logits, value = net.apply(params, batch["obs"])
        log_probs = jax.nn.log_softmax(logits)
        log_prob = jnp.take_along_axis(log_probs, batch["action"][:, None], -1)[:, 0]
        adv = normalize_advantages(batch["adv"])
        policy_loss = clipped_surrogate(log_prob, batch["log_prob"], adv, config.clip)
        # No value clipping (SB3's default): returns here are in the hundreds; a clip of 0.2 would freeze the critic.
        value_loss = squared_value_error(value, batch["target"])
        entropy = -(jnp.exp(log_probs) * log_probs).sum(-1).mean()
        total = policy_loss + config.value_coef * value_loss - config.entropy * entropy
        return total, {"policy_loss": policy_loss, "value_loss": value_loss, "entropy": entropy}

    def iteration(carry: tuple, key: jax.Array) -> tuple[tuple, dict]:
        params, opt_state, state, obs, ep_return = carry
        k_roll, k_perm = jax.random.split(key)
        (_, state, obs, ep_return), traj = jax.lax.scan(
            env_step, (params, state, obs, ep_return), jax.random.split(k_roll, config.rollout))
        _, last_value = net.apply(params, obs.expert)
        next_values = jnp.concatenate([traj["value"][1:], last_value[None]], axis=0)
        continues = 1.0 - traj["done"].astype(jnp.float32)
        adv = gae(traj["reward"], traj["value"], next_values, continues, config.gamma, config.gae_lambda)
        flat = jax.tree.map(lambda x: x.reshape((-1, *x.shape[2:])),
                            {"obs": traj["obs"], "action": traj["action"], "log_prob": traj["log_prob"],
                             "value": traj["value"], "adv": adv, "target": adv + traj["value"]})
        n = config.num_envs * config.rollout

        def epoch(carry: tuple, key: jax.Array) -> tuple[tuple, dict]:
            params, opt_state = carry
            perm = jax.random.permutation(key, n).reshape(config.minibatches, -1)

            def minibatch(carry: tuple, idx: jax.Array) -> tuple[tuple, dict]:
                params, opt_state = carry
                (_, info), grads = jax.value_and_grad(loss_fn, has_aux=True)(
                    params, jax.tree.map(lambda x: x[idx], flat))
                updates, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), info

            return jax.lax.scan(minibatch, (params, opt_state), perm)

        (params, opt_state), info = jax.lax.scan(epoch, (params, opt_state), jax.random.split(k_perm, config.epochs))
        finished = traj["finished_return"]
        metrics = {k: v.mean() for k, v in info.items()}
        metrics["episodes"] = jnp.sum(~jnp.isnan(finished))
        metrics["return_sum"] = jnp.nansum(finished)
        return (params, opt_state, state, obs, ep_return), metrics

    @jax.jit
    def chunk(carry: tuple, key: jax.Array) -> tuple[tuple, dict]:
        return jax.lax.scan(iteration, carry, jax.random.split(key, config.chunk))

    carry = (params, opt_state, state, obs, ep_return)
    history = []
    start = time.time()
    done_iters = 0
    while done_iters < config.iterations:
        key, k = jax.random.split(key)
        carry, metrics = chunk(carry, k)
        done_iters += config.chunk
        metrics = jax.device_get(metrics)
        episodes = float(metrics["episodes"].sum())
        row = {
            "iteration": done_iters,
            "steps": done_iters * config.num_envs * config.rollout,
            "mean_return": float(metrics["return_sum"].sum()) / max(episodes, 1.0),
            "episodes": episodes,
            "entropy": float(metrics["entropy"].mean()),
            "value_loss": float(metrics["value_loss"].mean()),
            "seconds": time.time() - start,
        }
        history.append(row)
        if log is not None:
            log(row)
    return carry[0], history
