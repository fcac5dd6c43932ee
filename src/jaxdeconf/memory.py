"""A memory estimate of one algorithm's training program, from the config alone, checked before anything compiles.

XLA fails late and badly on programs that cannot fit (a traceback from deep inside the compiler, or a machine that
swaps for hours), so the CLI compares this estimate with the device's memory first. The estimate is deliberately
generous: the seed-vmapped state (replay buffers, parameters, optimiser moments) held twice, as a chunk's input and
output, plus the larger of two working sets: the largest batch of episodes in flight with the activations a gradient
step keeps for backpropagation, and the ELBO's K-step decoding (every step of its batch decoded K steps ahead, each
decoder call's activations kept for backpropagation, three times over for their gradients and XLA's temporaries).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

from jaxdeconf.algos import algorithm_class
from jaxdeconf.config import Config
from jaxdeconf.errors import ConfigError

GIB = 2**30


@dataclasses.dataclass(frozen=True)
class Estimate:
    """Bytes of one algorithm's program and what drives them."""

    algo: str
    buffers: int  # Replay buffers of all seeds.
    params: int  # Parameters and optimiser moments of all seeds.
    working: int  # Episodes in flight and their activations, all seeds.

    @property
    def total(self) -> int:
        """Bytes in all: the state twice (a chunk's input and output) plus the working set."""
        return 2 * (self.buffers + self.params) + self.working


def episode_bytes(env: Any, params: Any) -> int:
    """Bytes of one stored episode: T + 1 observations of three views and T steps of actions, rewards and flags."""
    horizon = env.horizon(params)
    obs = env.obs_sizes(params)
    per_step = env.action_space(params).feature_size + 3 + len(env.extras_names)  # Action, reward, valid, best.
    return 4 * ((horizon + 1) * (obs.expert + obs.imitator + obs.oracle) + horizon * per_step)


def estimate(config: Config, algo: str, env: Any, params: Any) -> Estimate:
    """Generous estimate of the memory ``algo`` needs to train ``config.seeds`` seeds at once."""
    m, t = config.model, config.train
    cls = algorithm_class(algo)
    horizon = env.horizon(params)
    # Dense and GRU weights of the policy and (dil) of encoder and decoder, with AdamW's two moments: x3.
    hidden = 6 * m.width**2 + 6 * (m.gru + m.width) * m.gru + 6 * (m.bc_gru + m.width) * m.bc_gru
    param_bytes = 3 * 4 * hidden
    # Per step of an episode in a gradient step or rollout: GRU gates and MLP activations kept for the backward pass,
    # and the decoder's K predictions of the next observations.
    obs = env.obs_sizes(params).imitator
    per_step = 4 * (4 * (m.gru + m.bc_gru) + 6 * m.width + 2 * m.latent + t.prediction_steps * (2 * m.width + obs))
    rollouts = cls.episodes_in_flight(config) * (episode_bytes(env, params) + horizon * per_step)
    working = max(rollouts, cls.decoded_episodes(config) * horizon * elbo_step_bytes(config, env, params))
    return Estimate(algo=algo, buffers=config.seeds * cls.stored_episodes(config) * episode_bytes(env, params),
                    params=config.seeds * param_bytes, working=config.seeds * working)


def elbo_step_bytes(config: Config, env: Any, params: Any) -> int:
    """Bytes the ELBO keeps per decoded step: K decoder calls, each with its four Dense-LayerNorm-ELU blocks (four
    arrays of the width each), the latent-action interaction, and its inputs, targets, outputs and NLLs, all three
    times over: the activations, their gradients and a margin for XLA's temporaries (with twice, the estimate of
    the cheetah's paper-preset dil program came within 2% of XLA's account of its compiled chunk on the CPU)."""
    m = config.model
    obs, action = env.obs_sizes(params).imitator, env.action_space(params).feature_size
    call = 16 * m.width + m.latent + 4 * m.action_embed + 5 * obs + action + 1
    return config.train.prediction_steps * 3 * 4 * call


def device_memory() -> tuple[int, str]:
    """Bytes of memory of the default JAX device, and its name; physical RAM for the CPU."""
    import jax

    device = jax.devices()[0]
    stats = device.memory_stats() if device.platform != "cpu" else None
    if stats and stats.get("bytes_limit"):
        return int(stats["bytes_limit"]), f"{device.platform} device"
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"), "machine's RAM (CPU)"


def _culprit(config: Config, env: Any, params: Any) -> str:
    """The size field furthest above its default: most likely the one to reduce."""
    defaults = type(config)()
    t, d = config.train, defaults.train
    horizon = env.horizon(params)
    ratios = {
        "seeds": config.seeds / defaults.seeds,
        "env.horizon": horizon / env.horizon(env.default_params()),
        "train.buffer_episodes": t.buffer_episodes / d.buffer_episodes,
        "train.batch_size": t.batch_size / d.batch_size,
        "train.episodes_per_iter": t.episodes_per_iter / d.episodes_per_iter,
        "train.eval_episodes": t.eval_episodes / d.eval_episodes,
        "train.prediction_steps": t.prediction_steps / d.prediction_steps,
    }
    name = max(ratios, key=ratios.get)
    value = horizon if name == "env.horizon" else config.seeds if name == "seeds" else getattr(t, name[6:])
    return f"{name}={value}"


def check_fits(config: Config, env: Any, params: Any, jobs: int, automatic: bool = False) -> int:
    """How many algorithms to train at once: ``jobs``, or with ``automatic`` the most up to ``jobs`` whose largest
    estimates fit together (on one GPU, the paper presets' dil programs fit one or two at a time). Raise a one-line
    ConfigError when they (with ``automatic``, the largest alone) cannot fit in memory."""
    estimates = sorted((estimate(config, a, env, params) for a in config.algos), key=lambda e: -e.total)
    have, where = device_memory()
    jobs = max(1, jobs)
    while automatic and jobs > 1 and sum(e.total for e in estimates[:jobs]) > have:
        jobs -= 1
    need = sum(e.total for e in estimates[:jobs])
    if need > have:
        raise ConfigError(
            f"{_culprit(config, env, params)} is too large: the run needs an estimated {need / GIB:.1f} GiB "
            f"({', '.join(e.algo for e in estimates[:jobs])} at once; the largest, {estimates[0].algo}, "
            f"{estimates[0].buffers / GIB:.1f} GiB of replay buffers and {estimates[0].working / GIB:.1f} GiB of "
            f"working set) but the {where} has {have / GIB:.1f} GiB"
        )
    return jobs
