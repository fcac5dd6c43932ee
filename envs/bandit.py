"""The confounded multi-armed bandit of Ortega et al. (2021), section 3.2 of the paper.

θ (the best arm) is uniform over the arms. The expert pulls θ with probability p and every other arm with probability
(1 - p) / (arms - 1). The binary outcome s' is 1 with probability q if the pulled arm is θ, else with probability 1 - q.
The imitator sees only the last outcome; the expert and the oracle also see θ as a one-hot vector. The reward is 1 when
the best arm is pulled, so the return is the best-arm count the paper plots; the outcome s' (the paper text's r_t) is
reported as the extra ``outcome``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import jax
import jax.numpy as jnp
from flax import struct
from jaxdeconf.envs.base import ActionSpace, Environment, Observation, StepResult


@struct.dataclass
class BanditParams:
    """Bandit parameters; ``arms`` and ``horizon`` are static (they fix shapes)."""

    p: float = 0.6  # Expert's probability of pulling the best arm.
    q: float = 0.75  # P(s' = 1) when the best arm is pulled (1 - q otherwise).
    arms: int = struct.field(pytree_node=False, default=5)
    horizon: int = struct.field(pytree_node=False, default=100)


@struct.dataclass
class BanditState:
    """θ, the last outcome and the step count."""

    theta: jax.Array  # int32 [], the best arm.
    outcome: jax.Array  # float32 [], the last outcome s_t (0 at reset).
    t: jax.Array  # int32 [].


class Bandit(Environment):
    """Confounded bandit: discrete actions, binary outcomes, fixed horizon."""

    name = "bandit"
    obs_likelihood = "bernoulli"
    extras_names = ("outcome",)
    presets: ClassVar[dict[str, dict[str, Any]]] = {
        # The paper's bandit result in minutes on a 2-core CPU: small nets, fresh expert data every iteration. A CPU
        # step costs in proportion to its arithmetic (docs/scale.md), so width 32 and 8 policy steps per iteration
        # are what make this preset fast; at width 64 and 16 steps it reaches the same tolerances 3x slower.
        "cpu": {
            "model.width": 32,
            "model.action_embed": 16,
            "model.gru": 32,
            "model.bc_gru": 32,
            "model.latent": 5,
            "train.iterations": 300,
            "train.warmup": 20,
            "train.chunk": 25,
            "train.episodes_per_iter": 32,
            "train.batch_size": 32,
            # Fresh expert data every iteration, as the paper (an "infinite-size training dataset" generated on the
            # fly) and the reference code (buffer = one iteration's 32 episodes) do.
            "train.buffer_episodes": 32,
            "train.policy_steps": 8,
            "train.encoder_steps": 4,
            "train.policy_lr": 2e-3,
            "train.encoder_lr": 3e-3,
            "train.beta": 0.001,  # The paper's appendix value; the reference code's 0.01 also learns, more slowly.
            "train.eval_episodes": 256,
            "dagger.anneal_iterations": 100,
        },
        # The reference code's bandit configuration (batch 32, 100 policy / 1 encoder step per iteration).
        "paper": {
            "model.width": 128,
            "model.action_embed": 32,
            "model.gru": 500,
            "model.bc_gru": 1000,
            "model.latent": 5,
            "train.iterations": 300,
            "train.warmup": 20,
            "train.chunk": 10,
            "train.episodes_per_iter": 32,
            "train.batch_size": 32,
            "train.buffer_episodes": 32,
            "train.policy_steps": 100,
            "train.encoder_steps": 1,
            "train.beta": 0.01,
            "train.eval_episodes": 64,
            "dagger.anneal_iterations": 125,
        },
    }

    def default_params(self) -> BanditParams:
        """The paper's bandit: 5 arms, p = 0.6, q = 0.75, 100 steps."""
        return BanditParams()

    def validate(self, params: BanditParams) -> None:
        """Check probabilities lie in (0, 1] and counts are positive."""
        for field in ("p", "q"):
            value = getattr(params, field)
            if not 0.0 < float(value) <= 1.0:
                raise ValueError(f"bandit {field}={value} is outside the allowed range (0, 1]")
        if int(params.arms) < 2:
            raise ValueError(f"bandit arms={params.arms} is not allowed: need an integer >= 2")
        if int(params.horizon) < 1:
            raise ValueError(f"bandit horizon={params.horizon} is not allowed: need a positive integer")

    def action_space(self, params: BanditParams) -> ActionSpace:
        """One action per arm."""
        return ActionSpace("discrete", int(params.arms))

    def obs_sizes(self, params: BanditParams) -> Observation:
        """Imitator: the outcome; expert and oracle: outcome plus one-hot θ."""
        return Observation(expert=1 + params.arms, imitator=1, oracle=1 + params.arms)

    def _observe(self, state: BanditState, params: BanditParams) -> Observation:
        """Build the three views of ``state``."""
        s = state.outcome[None]
        with_theta = jnp.concatenate([s, jax.nn.one_hot(state.theta, params.arms, dtype=jnp.float32)])
        return Observation(expert=with_theta, imitator=s, oracle=with_theta)

    def reset(self, key: jax.Array, params: BanditParams) -> tuple[BanditState, Observation]:
        """Draw θ uniformly; the first outcome is 0."""
        theta = jax.random.randint(key, (), 0, params.arms, dtype=jnp.int32)
        state = BanditState(theta=theta, outcome=jnp.zeros((), jnp.float32), t=jnp.zeros((), jnp.int32))
        return state, self._observe(state, params)

    def step(
        self, key: jax.Array, state: BanditState, action: jax.Array, params: BanditParams
    ) -> tuple[BanditState, StepResult]:
        """Pull ``action``: s' ~ Bernoulli(q if action == θ else 1 - q); reward 1 iff action == θ."""
        hit = action == state.theta
        p_one = jnp.where(hit, params.q, 1.0 - params.q)
        outcome = jax.random.bernoulli(key, p_one).astype(jnp.float32)
        state = BanditState(theta=state.theta, outcome=outcome, t=state.t + 1)
        result = StepResult(
            obs=self._observe(state, params),
            reward=hit.astype(jnp.float32),
            done=jnp.zeros((), jnp.bool_),
            extras={"outcome": outcome},
        )
        return state, result

    def expert_probs(self, obs: Observation, params: BanditParams) -> jax.Array:
        """p on θ (read from the expert's one-hot view), (1 - p) / (arms - 1) elsewhere."""
        theta_onehot = obs.expert[..., 1:]
        other = (1.0 - params.p) / (params.arms - 1)
        return theta_onehot * params.p + (1.0 - theta_onehot) * other

    def expert_action(self, key: jax.Array, obs: Observation, params: BanditParams) -> jax.Array:
        """Sample from ``expert_probs``."""
        return jax.random.categorical(key, jnp.log(self.expert_probs(obs, params))).astype(jnp.int32)

    def best_action(self, state: BanditState, params: BanditParams) -> jax.Array:
        """The best arm θ."""
        del params  # Unused.
        return state.theta
