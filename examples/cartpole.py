"""A confounded cart-pole, written outside the package: the sign of the cart's actuator is θ.

With probability 1/2 (θ = 1) the motor is wired backwards, so "push right" pushes left. The expert sees θ and
balances the pole with a scripted linear controller; the imitator sees only the cart-pole state (position, velocity,
pole angle, angular velocity) and must find out which way the motor pushes from what happens. The dynamics, limits
and reward (+1 per step until the pole falls past 12° or the cart leaves ±2.4) are gymnasium's CartPole-v1.

Train it from the repository root, without editing the package:

    python -m jaxdeconf.run --env examples.cartpole:ConfoundedCartPole --algo bc,dil,oracle --seeds 3
"""

from __future__ import annotations

from typing import Any, ClassVar

import jax
import jax.numpy as jnp
from flax import struct
from jaxdeconf.envs import ActionSpace, Environment, Observation, StepResult

GRAVITY, MASS_CART, MASS_POLE, HALF_LENGTH, FORCE, TAU = 9.8, 1.0, 0.1, 0.5, 10.0, 0.02
ANGLE_LIMIT, X_LIMIT = 12 * 2 * jnp.pi / 360, 2.4
GAINS = (0.5, 1.0, 20.0, 3.0)  # The expert's controller: push right when GAINS · (x, ẋ, angle, angle') > 0.


@struct.dataclass
class CartPoleParams:
    """Parameters; ``horizon`` is static (it fixes shapes)."""

    noise: float = 0.1  # Probability the expert's action is replaced by a uniformly random one.
    horizon: int = struct.field(pytree_node=False, default=100)


@struct.dataclass
class CartPoleState:
    """The physical state, θ and whether the episode has ended."""

    physics: jax.Array  # float32 [4]: x, ẋ, pole angle, angular velocity.
    theta: jax.Array  # int32 []: 1 if the actuator is reversed.
    done: jax.Array  # bool [].


class ConfoundedCartPole(Environment):
    """Cart-pole with a hidden actuator sign; two actions (push left, push right)."""

    name = "cartpole"
    normalize_views = True
    presets: ClassVar[dict[str, dict[str, Any]]] = {
        "cpu": {
            "model.width": 64, "model.action_embed": 16, "model.gru": 64, "model.bc_gru": 64, "model.latent": 4,
            "train.iterations": 40, "train.warmup": 5, "train.chunk": 5, "train.episodes_per_iter": 16,
            "train.batch_size": 16, "train.buffer_episodes": 256, "train.policy_steps": 16,
            "train.encoder_steps": 16, "train.policy_lr": 1e-3, "train.encoder_lr": 1e-3, "train.beta": 1.0,
            "train.prediction_steps": 5, "train.eval_episodes": 64,
        },
    }

    def default_params(self) -> CartPoleParams:
        """100-step episodes, 10% random expert actions."""
        return CartPoleParams()

    def validate(self, params: CartPoleParams) -> None:
        """Check the noise is a probability and the horizon positive."""
        if not 0.0 <= float(params.noise) <= 1.0:
            raise ValueError(f"cartpole noise={params.noise} is outside [0, 1]")
        if int(params.horizon) < 1:
            raise ValueError(f"cartpole horizon={params.horizon} is not allowed: need a positive integer")

    def action_space(self, params: CartPoleParams) -> ActionSpace:
        """Push left (0) or right (1), as wired when θ = 0."""
        del params  # Unused.
        return ActionSpace("discrete", 2)

    def obs_sizes(self, params: CartPoleParams) -> Observation:
        """Imitator: the 4-d state; expert and oracle: the state and θ."""
        del params  # Unused.
        return Observation(expert=5, imitator=4, oracle=5)

    def _observe(self, state: CartPoleState) -> Observation:
        """The three views of ``state``."""
        with_theta = jnp.concatenate([state.physics, state.theta.astype(jnp.float32)[None]])
        return Observation(expert=with_theta, imitator=state.physics, oracle=with_theta)

    def reset(self, key: jax.Array, params: CartPoleParams) -> tuple[CartPoleState, Observation]:
        """A state uniform in ±0.05 per dimension (gymnasium's) and θ ~ Bernoulli(1/2)."""
        del params  # Unused.
        k_state, k_theta = jax.random.split(key)
        state = CartPoleState(
            physics=jax.random.uniform(k_state, (4,), jnp.float32, -0.05, 0.05),
            theta=jax.random.bernoulli(k_theta).astype(jnp.int32),
            done=jnp.zeros((), jnp.bool_),
        )
        return state, self._observe(state)

    def step(
        self, key: jax.Array, state: CartPoleState, action: jax.Array, params: CartPoleParams
    ) -> tuple[CartPoleState, StepResult]:
        """One Euler step of gymnasium's cart-pole with the force's sign flipped when θ = 1; frozen once done."""
        del key, params  # Unused: the dynamics are deterministic.
        x, x_dot, angle, angle_dot = state.physics
        force = FORCE * (2.0 * action - 1.0) * (1.0 - 2.0 * state.theta)
        total = MASS_CART + MASS_POLE
        temp = (force + MASS_POLE * HALF_LENGTH * angle_dot**2 * jnp.sin(angle)) / total
        angle_acc = (GRAVITY * jnp.sin(angle) - jnp.cos(angle) * temp) / (
            HALF_LENGTH * (4.0 / 3.0 - MASS_POLE * jnp.cos(angle) ** 2 / total))
        x_acc = temp - MASS_POLE * HALF_LENGTH * angle_acc * jnp.cos(angle) / total
        moved = jnp.stack([x + TAU * x_dot, x_dot + TAU * x_acc, angle + TAU * angle_dot, angle_dot + TAU * angle_acc])
        physics = jnp.where(state.done, state.physics, moved).astype(jnp.float32)
        fallen = (jnp.abs(physics[2]) > ANGLE_LIMIT) | (jnp.abs(physics[0]) > X_LIMIT)
        reward = jnp.where(state.done, 0.0, 1.0).astype(jnp.float32)
        state = CartPoleState(physics=physics, theta=state.theta, done=state.done | fallen)
        return state, StepResult(obs=self._observe(state), reward=reward, done=state.done, extras={})

    def expert_probs(self, obs: Observation, params: CartPoleParams) -> jax.Array:
        """The controller's push direction through the actuator's sign θ, mixed with uniform noise."""
        physics, theta = obs.expert[..., :4], obs.expert[..., 4]
        right = (physics @ jnp.asarray(GAINS, jnp.float32)) > 0
        wired = jnp.where(theta > 0.5, ~right, right)  # The action that pushes the way the controller wants.
        greedy = jax.nn.one_hot(wired.astype(jnp.int32), 2, dtype=jnp.float32)
        return (1.0 - params.noise) * greedy + params.noise / 2.0

    def expert_action(self, key: jax.Array, obs: Observation, params: CartPoleParams) -> jax.Array:
        """Sample from ``expert_probs``."""
        return jax.random.categorical(key, jnp.log(self.expert_probs(obs, params))).astype(jnp.int32)

    def best_action(self, state: CartPoleState, params: CartPoleParams) -> jax.Array:
        """The noiseless expert's action."""
        return jnp.argmax(self.expert_probs(self._observe(state), params.replace(noise=0.0))).astype(jnp.int32)
