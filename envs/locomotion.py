"""Confounded Brax locomotion on the MJX pipeline: HalfCheetah with a hidden target speed, Ant with a hidden goal.

Both wrap Brax's own environments (``brax.envs.half_cheetah.Halfcheetah`` and ``brax.envs.ant.Ant``, backend
``mjx`` by default; a pipeline changes the dynamics, so it is a static parameter recorded with every run) and add the
confounding layer: θ is sampled at reset and kept in the state, the reward is replaced by the paper's, and the three
observation views are built from the Brax observation plus a per-step cue. Actions are boxes in [-1, 1]; the env
clips what it is given, so an unbounded Gaussian policy can act directly.

half_cheetah (paper section 5.2): θ = target speed ~ U(0, 3). The imitator sees the state plus an indicator
sign(v - target) flipped with probability ``flip_prob`` (0.2); the expert sees the state plus the target; the oracle
the imitator's view plus the target. Reward -|v - target| - 0.05·‖a‖², v the torso's forward velocity over the
step (as Brax measures it). 1000 steps. The reference code's variant: ``flip_prob=0.8`` and
``expert_sees_indicator=True``.

ant_goal: θ = a goal in the disc of radius 10 (radius 10·sqrt(U), uniform angle). The state is Brax's ant
observation *with* the torso's x and y (29-d), because the goal is meaningless without the position. The imitator
sees the state plus the goal's distance and world-frame bearing atan2(Δy, Δx) from the torso, each with N(0, 1)
noise (``cue_noise``; the reference code's is 0.1), the noisy bearing b given as (cos b, sin b)
(``raw_bearing=True``: as the angle itself, which jumps by 2π where it wraps at ±π); the expert and the oracle see
the state plus the goal. Reward -‖xy - goal‖₂ (``l1_reward=True``: the reference code's L1 distance), no control
cost. 200 steps.

Termination: neither env terminates. Brax's ant ends an episode when its torso leaves z in [0.2, 1.0]; here a flipped
ant simply keeps its fixed-length episode, keeps paying its distance, and the per-step extra ``unhealthy`` records
it, so evaluation reports how often experts and imitators flip. This keeps every episode the same length (the
``valid`` mask is all ones) and does not reward an imitator for ending an episode early.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
from flax import struct
from jaxdeconf.envs.base import ActionSpace, Environment, Observation, ObsGroup, StepResult

BACKENDS = ("mjx", "generalized", "positional", "spring")


@struct.dataclass
class LocomotionState:
    """Brax's state plus the confounder θ, the last cue (indicator or noisy goal polar) and the step count."""

    brax: Any
    theta: jax.Array
    cue: jax.Array
    t: jax.Array


class BraxConfounded(Environment):
    """Shared machinery: a lazily built Brax env, clipped box actions, the shipped expert."""

    brax_name: str = ""
    #: MJX line-search steps per solver iteration, where we change Brax's model (None keeps it).
    solver_ls_iterations: int | None = None
    normalize_views = True  # MuJoCo observations mix angles with velocities of ~10: standardise from expert data.
    brax_kwargs: dict[str, Any] = {}  # noqa: RUF012 - class-level constant.

    def __init__(self) -> None:
        self._brax_envs: dict[str, Any] = {}
        self._state_sizes: dict[str, int] = {}

    def brax_env(self, params: Any) -> Any:
        """The Brax environment for ``params.backend`` (built once per backend)."""
        backend = params.backend
        if backend not in self._brax_envs:
            from brax import envs as brax_envs

            with jax.ensure_compile_time_eval():  # Built inside a trace, its arrays would be leaked tracers.
                env = brax_envs.get_environment(self.brax_name, backend=backend, **self.brax_kwargs)
            if backend == "mjx" and self.solver_ls_iterations:
                env.sys = env.sys.tree_replace({"opt.ls_iterations": self.solver_ls_iterations})
            self._brax_envs[backend] = env
        return self._brax_envs[backend]

    def validate(self, params: Any) -> None:
        """Check the backend and the horizon."""
        if params.backend not in BACKENDS:
            raise ValueError(f"{self.name} backend={params.backend!r} is not allowed; allowed: {', '.join(BACKENDS)}")
        if int(params.horizon) < 1:
            raise ValueError(f"{self.name} horizon={params.horizon} is not allowed: need a positive integer")
        self.brax_env(params)  # Build it now, outside any trace.

    def action_space(self, params: Any) -> ActionSpace:
        """Brax's actuators, each in [-1, 1]."""
        return ActionSpace("box", int(self.brax_env(params).sys.act_size()))

    def state_size(self, params: Any) -> int:
        """Size of the Brax observation (the state every view starts with), from an abstract trace of its reset
        (Brax's own ``observation_size`` runs the MJX reset op by op: minutes on a CPU)."""
        backend = params.backend
        if backend not in self._state_sizes:
            shape = jax.eval_shape(self.brax_env(params).reset, jax.random.key(0))
            self._state_sizes[backend] = int(shape.obs.shape[-1])
        return self._state_sizes[backend]

    def sample_theta(self, key: jax.Array, params: Any) -> jax.Array:
        """Draw the episode's θ."""
        raise NotImplementedError

    def cue(self, key: jax.Array, brax_state: Any, theta: jax.Array, params: Any) -> jax.Array:
        """The imitator's per-step hint about θ."""
        raise NotImplementedError

    def cue_features(self, cue: jax.Array, params: Any) -> jax.Array:
        """What the imitator's view holds of the cue (the cue itself unless an env says otherwise)."""
        del params  # Unused.
        return cue

    def reward(self, before: Any, after: Any, action: jax.Array, theta: jax.Array, params: Any) -> jax.Array:
        """The confounded task's reward for one step."""
        raise NotImplementedError

    def step_extras(self, before: Any, after: Any, theta: jax.Array, params: Any) -> dict[str, jax.Array]:
        """Per-step diagnostics summed in evaluation."""
        del before, after, theta, params  # Unused.
        return {}

    def observe(self, state: LocomotionState, params: Any) -> Observation:
        """The three views of ``state``."""
        raise NotImplementedError

    def reset(self, key: jax.Array, params: Any) -> tuple[LocomotionState, Observation]:
        """Brax's reset (its initial-state noise), θ and the first cue."""
        k_brax, k_theta, k_cue = jax.random.split(key, 3)
        brax_state = self.brax_env(params).reset(k_brax)
        theta = self.sample_theta(k_theta, params)
        state = LocomotionState(brax=brax_state, theta=theta, cue=self.cue(k_cue, brax_state, theta, params),
                                t=jnp.zeros((), jnp.int32))
        return state, self.observe(state, params)

    def step(
        self, key: jax.Array, state: LocomotionState, action: jax.Array, params: Any
    ) -> tuple[LocomotionState, StepResult]:
        """Brax's physics step with the clipped action; the confounded reward and a fresh cue."""
        action = jnp.clip(action, -1.0, 1.0)
        new_brax = self.brax_env(params).step(state.brax, action)
        new = LocomotionState(brax=new_brax, theta=state.theta, cue=self.cue(key, new_brax, state.theta, params),
                              t=state.t + 1)
        result = StepResult(
            obs=self.observe(new, params),
            reward=self.reward(state.brax, new_brax, action, state.theta, params),
            done=jnp.zeros((), jnp.bool_),
            extras=self.step_extras(state.brax, new_brax, state.theta, params),
        )
        return new, result

    @cached_property
    def expert(self) -> Any:
        """The shipped PPO expert (loaded on first use)."""
        from jaxdeconf.experts import load_expert

        return load_expert(self.name)

    def expert_action(self, key: jax.Array, obs: Observation, params: Any) -> jax.Array:
        """The shipped expert's deterministic action (the tanh of its Gaussian's mean) on the expert's view."""
        del key, params  # Unused: the expert acts deterministically.
        return self.expert.act(obs.expert)


# --------------------------------------------------------------------------------------------------- half_cheetah


def locomotion_cpu(horizon: int, prediction_steps: int, anneal: int) -> dict[str, Any]:
    """The reduced Brax preset: what a 2-core CPU trains in under an hour."""
    return {
        "env.horizon": horizon,
        "model.width": 64,
        "model.action_embed": 16,
        "model.gru": 64,
        "model.bc_gru": 64,
        "model.latent": 8,
        "train.iterations": 40,
        "train.warmup": 5,
        "train.chunk": 5,
        "train.episodes_per_iter": 8,
        "train.batch_size": 8,
        "train.buffer_episodes": 128,
        # The paper's 100 + 100 gradient steps per iteration: fewer leave dil's latent policy unable to read θ-hat.
        "train.policy_steps": 100,
        "train.encoder_steps": 100,
        "train.policy_lr": 1e-3,
        "train.encoder_lr": 1e-3,
        "train.beta": 1.0,
        "train.prediction_steps": prediction_steps,
        "train.eval_episodes": 64,
        "dagger.anneal_iterations": anneal,
    }


def locomotion_paper(latent: int, prediction_steps: int, buffer_episodes: int, anneal: int) -> dict[str, Any]:
    """The paper's configuration for the Brax envs (meant for a GPU)."""
    return {
        "model.width": 128,
        "model.action_embed": 32,
        "model.gru": 500,
        "model.bc_gru": 500,
        "model.latent": latent,
        "train.iterations": 300,
        "train.warmup": 20,
        "train.chunk": 10,
        "train.episodes_per_iter": 16,
        "train.batch_size": 16,
        "train.buffer_episodes": buffer_episodes,
        "train.policy_steps": 100,
        "train.encoder_steps": 100,
        "train.beta": 1.0,
        "train.prediction_steps": prediction_steps,
        "train.eval_episodes": 64,
        "dagger.anneal_iterations": anneal,
    }


@struct.dataclass
class HalfCheetahParams:
    """Parameters; ``backend``, ``horizon`` and ``expert_sees_indicator`` are static."""

    target_low: float = 0.0
    target_high: float = 3.0
    flip_prob: float = 0.2  # Probability that the imitator's indicator is flipped (reference code: 0.8).
    ctrl_cost: float = 0.05
    expert_sees_indicator: bool = struct.field(pytree_node=False, default=False)  # Reference code: True.
    backend: str = struct.field(pytree_node=False, default="mjx")
    horizon: int = struct.field(pytree_node=False, default=1000)


def forward_velocity(before: Any, after: Any, dt: float) -> jax.Array:
    """The torso's forward velocity over one step, as Brax's half_cheetah measures it."""
    return (after.pipeline_state.x.pos[0, 0] - before.pipeline_state.x.pos[0, 0]) / dt


class HalfCheetah(BraxConfounded):
    """Brax half_cheetah with a hidden target speed; the imitator gets a noisy faster/slower indicator."""

    name = "half_cheetah"
    brax_name = "halfcheetah"
    presets: ClassVar[dict[str, dict[str, Any]]] = {
        # Reduced for a 2-core CPU: 200-step episodes (the paper's are 1000), small nets, 40 iterations of 8 episodes.
        "cpu": locomotion_cpu(horizon=200, prediction_steps=10, anneal=8),  # 63 of 300 iterations, scaled to 40.
        # The paper's configuration (for a GPU): GRU 500, latent 64, K = 10, 2000 episodes (2e6 transitions).
        "paper": locomotion_paper(latent=64, prediction_steps=10, buffer_episodes=2000, anneal=63),
    }
    # The XML asks for Newton with 4 iterations of up to 50 line-search steps. 8 steps give the same trajectories
    # (identical max |qd| over 32 random-action episodes of 1000 steps) 3.8x faster on this CPU; Brax's ant on MJX
    # uses 1 iteration of 4, which makes the cheetah blow up (|qd| ~ 1e17, then NaN) within 1000 steps.
    solver_ls_iterations = 8
    extras_names = ("abs_speed_error",)
    diagnostic_extra = ("abs_speed_error", "mean |v − target| per step (m/s)")

    def default_params(self) -> HalfCheetahParams:
        """The paper's setting."""
        return HalfCheetahParams()

    def validate(self, params: HalfCheetahParams) -> None:
        """Check the target range and the flip probability, then the backend and horizon."""
        if not 0.0 <= float(params.flip_prob) <= 1.0:
            raise ValueError(f"half_cheetah flip_prob={params.flip_prob} is outside the allowed range [0, 1]")
        if not float(params.target_low) <= float(params.target_high):
            raise ValueError(f"half_cheetah target_low={params.target_low} exceeds target_high={params.target_high}")
        if float(params.ctrl_cost) < 0.0:
            raise ValueError(f"half_cheetah ctrl_cost={params.ctrl_cost} is not allowed: need >= 0")
        super().validate(params)

    def obs_sizes(self, params: HalfCheetahParams) -> Observation:
        """State (17) + indicator for the imitator; + target for the expert (and the oracle)."""
        s = self.state_size(params)
        return Observation(expert=s + 1 + int(params.expert_sees_indicator), imitator=s + 1, oracle=s + 2)

    def obs_groups(self, params: HalfCheetahParams) -> tuple[ObsGroup, ...]:
        """The body (Gaussian) and the ±1 indicator, whose law given the speed and θ is a sign flipped with
        probability ``flip_prob``: Bernoulli."""
        return ObsGroup("body", self.state_size(params)), ObsGroup("cue", 1, "bernoulli")

    def sample_theta(self, key: jax.Array, params: HalfCheetahParams) -> jax.Array:
        """Target speed ~ U(target_low, target_high)."""
        return jax.random.uniform(key, (), minval=params.target_low, maxval=params.target_high)

    def cue(self, key: jax.Array, brax_state: Any, theta: jax.Array, params: HalfCheetahParams) -> jax.Array:
        """sign(v - target) in {-1, +1} (v = target counts as +1), flipped w.p. ``flip_prob``."""
        v = brax_state.metrics["x_velocity"]
        sign = jnp.where(v >= theta, 1.0, -1.0)
        return jnp.where(jax.random.bernoulli(key, params.flip_prob), -sign, sign)[None]

    def reward(self, before: Any, after: Any, action: jax.Array, theta: jax.Array,
               params: HalfCheetahParams) -> jax.Array:
        """-|v - target| - ctrl_cost·‖a‖²."""
        v = forward_velocity(before, after, self.brax_env(params).dt)
        return -jnp.abs(v - theta) - params.ctrl_cost * jnp.sum(action**2)

    def step_extras(self, before: Any, after: Any, theta: jax.Array, params: HalfCheetahParams) -> dict:
        """|v - target| per step (its episode sum / horizon is the mean speed error)."""
        return {"abs_speed_error": jnp.abs(forward_velocity(before, after, self.brax_env(params).dt) - theta)}

    def observe(self, state: LocomotionState, params: HalfCheetahParams) -> Observation:
        """Expert: state, target (and indicator in the reference variant); imitator: state, indicator."""
        s = state.brax.obs
        target = state.theta[None]
        imitator = jnp.concatenate([s, self.cue_features(state.cue, params)])
        expert = jnp.concatenate([s, target, state.cue] if params.expert_sees_indicator else [s, target])
        return Observation(expert=expert, imitator=imitator, oracle=jnp.concatenate([imitator, target]))


# -------------------------------------------------------------------------------------------------------- ant_goal


@struct.dataclass
class AntGoalParams:
    """Parameters; ``backend``, ``horizon`` and ``l1_reward`` are static."""

    goal_radius: float = 10.0
    # Std of the noise on the imitator's (distance, bearing). At 1.0 one reading gives the bearing only to about a
    # radian, so the direction cannot be inferred from a single observation (what the paper's text says of its ant)
    # and naive BC is confounded. The paper's appendix and the reference code use 0.1, which gives it to 6°; there
    # our imitators all nearly match the oracle, so 0.1 is not the default.
    cue_noise: float = 1.0
    # The imitator reads the noisy bearing b as (cos b, sin b); True gives the angle itself. As an angle, a bearing
    # near ±π wraps by 2π between steps (0.4% of the expert's steps), which tripled the spread of its one-step
    # changes on expert data (0.42 against 0.155 without the wraps) and so blurred what the decoder could score.
    raw_bearing: bool = struct.field(pytree_node=False, default=False)
    l1_reward: bool = struct.field(pytree_node=False, default=False)  # Reference code: True.
    backend: str = struct.field(pytree_node=False, default="mjx")
    horizon: int = struct.field(pytree_node=False, default=200)


def torso_xy(brax_state: Any) -> jax.Array:
    """The ant torso's (x, y)."""
    return brax_state.pipeline_state.x.pos[0, :2]


class AntGoal(BraxConfounded):
    """Brax ant with a hidden goal; the imitator gets a noisy distance and bearing to it."""

    name = "ant_goal"
    brax_name = "ant"
    presets: ClassVar[dict[str, dict[str, Any]]] = {
        # Reduced for a 2-core CPU: small nets, K = 10 (the paper's is 50), 40 iterations of 8 episodes. DAgger's
        # beta anneals inside the warm-up, as in the reference code.
        "cpu": locomotion_cpu(horizon=200, prediction_steps=10, anneal=5),
        # The paper's configuration (for a GPU): latent 8, K = 50; replay capped at 2000 episodes (4e5 transitions,
        # against the reference code's 2e6) so that a seed's buffers fit next to others on one GPU.
        "paper": locomotion_paper(latent=8, prediction_steps=50, buffer_episodes=2000, anneal=20),
    }
    brax_kwargs = {"terminate_when_unhealthy": False, "exclude_current_positions_from_observation": False}  # noqa: RUF012
    extras_names = ("distance", "unhealthy")
    diagnostic_extra = ("distance", "mean distance to the goal per step")

    def default_params(self) -> AntGoalParams:
        """The paper's setting."""
        return AntGoalParams()

    def validate(self, params: AntGoalParams) -> None:
        """Check the goal radius and the cue noise, then the backend and horizon."""
        if not float(params.goal_radius) > 0.0:
            raise ValueError(f"ant_goal goal_radius={params.goal_radius} is not allowed: need > 0")
        if float(params.cue_noise) < 0.0:
            raise ValueError(f"ant_goal cue_noise={params.cue_noise} is not allowed: need >= 0")
        super().validate(params)

    def obs_sizes(self, params: AntGoalParams) -> Observation:
        """State (29, with x and y) + the goal (expert), the cue (imitator: 3, or 2 with ``raw_bearing``), or both."""
        s = self.state_size(params)
        cue = 2 if params.raw_bearing else 3
        return Observation(expert=s + 2, imitator=s + cue, oracle=s + cue + 2)

    def obs_groups(self, params: AntGoalParams) -> tuple[ObsGroup, ...]:
        """The body and the noisy cue's features, both Gaussian."""
        return ObsGroup("body", self.state_size(params)), ObsGroup("cue", 2 if params.raw_bearing else 3)

    def sample_theta(self, key: jax.Array, params: AntGoalParams) -> jax.Array:
        """A goal uniform in the disc: radius R·sqrt(U), angle U(0, 2π)."""
        k_r, k_a = jax.random.split(key)
        r = params.goal_radius * jnp.sqrt(jax.random.uniform(k_r))
        a = jax.random.uniform(k_a, minval=0.0, maxval=2 * math.pi)
        return jnp.stack([r * jnp.cos(a), r * jnp.sin(a)])

    def cue(self, key: jax.Array, brax_state: Any, theta: jax.Array, params: AntGoalParams) -> jax.Array:
        """(distance, bearing) from the torso to the goal, each plus N(0, cue_noise²)."""
        delta = theta - torso_xy(brax_state)
        polar = jnp.stack([jnp.linalg.norm(delta), jnp.arctan2(delta[1], delta[0])])
        return polar + params.cue_noise * jax.random.normal(key, (2,))

    def distance(self, brax_state: Any, theta: jax.Array, params: AntGoalParams) -> jax.Array:
        """Distance from the torso to the goal: L2, or L1 in the reference variant."""
        delta = theta - torso_xy(brax_state)
        return jnp.sum(jnp.abs(delta)) if params.l1_reward else jnp.sqrt(jnp.sum(delta**2))

    def reward(self, before: Any, after: Any, action: jax.Array, theta: jax.Array, params: AntGoalParams) -> jax.Array:
        """-distance to the goal after the step; no control cost."""
        del before, action  # Unused.
        return -self.distance(after, theta, params)

    def step_extras(self, before: Any, after: Any, theta: jax.Array, params: AntGoalParams) -> dict:
        """The L2 distance after the step and whether the torso is outside Brax's healthy z range [0.2, 1]."""
        del before  # Unused.
        z = after.pipeline_state.x.pos[0, 2]
        return {"distance": jnp.linalg.norm(theta - torso_xy(after)),
                "unhealthy": ((z < 0.2) | (z > 1.0)).astype(jnp.float32)}

    def cue_features(self, cue: jax.Array, params: AntGoalParams) -> jax.Array:
        """The imitator's reading of the noisy (distance, bearing): (distance, cos, sin), or the pair itself."""
        if params.raw_bearing:
            return cue
        return jnp.stack([cue[0], jnp.cos(cue[1]), jnp.sin(cue[1])])

    def observe(self, state: LocomotionState, params: AntGoalParams) -> Observation:
        """Expert: state and goal; imitator: state and the noisy cue's features; oracle: both."""
        s = state.brax.obs
        imitator = jnp.concatenate([s, self.cue_features(state.cue, params)])
        return Observation(expert=jnp.concatenate([s, state.theta]), imitator=imitator,
                           oracle=jnp.concatenate([imitator, state.theta]))
