"""The environment contract shared by every confounded environment.

Environments follow gymnax's pure-function style: ``reset(key, params)`` and ``step(key, state, action, params)``
never mutate anything, state and params are ``flax.struct`` pytrees, and the latent θ is sampled at reset and kept in
the state. Every observation comes in three views (expert, imitator, oracle) so that "the imitator never sees θ" is a
property of one field. Episodes have a fixed length; early termination only clears the ``valid`` mask.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class Observation:
    """The three views of one observation: expert (sees θ), imitator (never θ), oracle (imitator's view plus θ)."""

    expert: jax.Array
    imitator: jax.Array
    oracle: jax.Array


@struct.dataclass
class StepResult:
    """What ``step`` returns besides the new state: observation, reward, termination and per-step extras."""

    obs: Observation
    reward: jax.Array
    done: jax.Array
    extras: dict[str, jax.Array]


@dataclasses.dataclass(frozen=True)
class ActionSpace:
    """A discrete space of ``n`` actions (``kind='discrete'``) or a box of ``n`` dimensions in [-1, 1]."""

    kind: str
    n: int

    @property
    def discrete(self) -> bool:
        """Whether actions are integer indices."""
        return self.kind == "discrete"

    @property
    def feature_size(self) -> int:
        """Size of the action's vector encoding (one-hot for discrete spaces)."""
        return self.n


@dataclasses.dataclass(frozen=True)
class ObsGroup:
    """A contiguous block of the imitator's view that the decoder scores with one likelihood family.

    ``"gaussian"``: unit variance on the (standardised) next value or change; ``"bernoulli"``: the sign of the next
    value, for a two-valued cue (an indicator ±1, a bit 0/1, or either standardised, whose two values straddle 0).
    """

    name: str
    size: int
    likelihood: str = "gaussian"


LIKELIHOODS = ("gaussian", "bernoulli")


class Environment:
    """Base class of confounded environments; subclasses implement the pure functions below."""

    name: ClassVar[str] = ""
    #: How the decoder should score the imitator's observation: "gaussian" (unit variance) or "bernoulli".
    obs_likelihood: ClassVar[str] = "gaussian"
    #: Whether learners see the imitator's and oracle's views standardised from expert data (``NormalizedViews``).
    normalize_views: ClassVar[bool] = False
    #: Names of the per-step extras ``step`` reports (summed per episode in evaluation).
    extras_names: ClassVar[tuple[str, ...]] = ()
    #: A per-step extra to show per θ bin in diagnostics.png, and its label (default: the episode's return).
    diagnostic_extra: ClassVar[tuple[str, str] | None] = None
    #: Config presets: preset name (``cpu``, ``paper``) -> dotted overrides (``"train.iterations"``) of the config's
    #: defaults. An env without presets cannot be trained until it declares at least one.
    presets: ClassVar[dict[str, dict[str, Any]]] = {}

    def default_params(self) -> Any:
        """The environment's default parameters."""
        raise NotImplementedError

    def validate(self, params: Any) -> None:
        """Raise ``ValueError`` naming any parameter outside its allowed range."""
        del params  # Unused.

    def horizon(self, params: Any) -> int:
        """Fixed episode length (a static Python int): every env's params carry it as the static field ``horizon``."""
        return int(params.horizon)

    def action_space(self, params: Any) -> ActionSpace:
        """The action space."""
        raise NotImplementedError

    def obs_sizes(self, params: Any) -> Observation:
        """Sizes of the three observation views, as an Observation of ints."""
        raise NotImplementedError

    def obs_groups(self, params: Any) -> tuple[ObsGroup, ...]:
        """The imitator's view as consecutive groups, in order (default: one group under ``obs_likelihood``). An env
        whose θ shows only in part of the view (a cue beside a θ-free body) declares them, so the decoder's loss can
        weigh each group (``dil.decoder_weighting``)."""
        return (ObsGroup("all", self.obs_sizes(params).imitator, self.obs_likelihood),)

    def reset(self, key: jax.Array, params: Any) -> tuple[Any, Observation]:
        """Sample θ and an initial state; return the state and its observation."""
        raise NotImplementedError

    def step(self, key: jax.Array, state: Any, action: jax.Array, params: Any) -> tuple[Any, StepResult]:
        """Advance one step."""
        raise NotImplementedError

    def expert_action(self, key: jax.Array, obs: Observation, params: Any) -> jax.Array:
        """Sample the expert's action from its view of the observation."""
        raise NotImplementedError

    def expert_probs(self, obs: Observation, params: Any) -> jax.Array | None:
        """The expert's action probabilities (discrete spaces), for DAgger labels and diagnostics."""
        del obs, params  # Unused.
        return None

    def best_action(self, state: Any, params: Any) -> jax.Array:
        """The action a θ-aware agent prefers in ``state``, or -1 where no single one exists."""
        del state, params  # Unused.
        return jnp.asarray(-1, jnp.int32)

    def theta(self, state: Any) -> jax.Array:
        """The confounder θ of ``state`` (``check_env`` and the renderer read it); by default ``state.theta``."""
        return state.theta


class NormalizedViews(Environment):
    """``env`` with the imitator's and the oracle's views standardised by fixed per-dimension statistics.

    The statistics are fitted once from expert episodes (``jaxdeconf.algos.base.fit_view_normalizer``), as the paper
    normalises observations from expert data, so every learner's inputs and the decoder's targets are on unit scale.
    The expert's view stays raw: the expert was trained on it.
    """

    def __init__(self, env: Environment, stats: dict[str, tuple[Any, Any]]):
        self.env = env
        self.stats = stats  # View name -> (mean, std), numpy arrays baked into compiled programs as constants.
        self.name = env.name
        self.obs_likelihood = env.obs_likelihood
        self.extras_names = env.extras_names

    def __getattr__(self, attr: str) -> Any:
        return getattr(self.env, attr)

    def normalize(self, obs: Observation) -> Observation:
        """Standardise the imitator's and the oracle's views."""
        views = {name: (getattr(obs, name) - mean) / std for name, (mean, std) in self.stats.items()}
        return obs.replace(**views)

    def default_params(self) -> Any:
        return self.env.default_params()

    def validate(self, params: Any) -> None:
        self.env.validate(params)

    def horizon(self, params: Any) -> int:
        return self.env.horizon(params)

    def action_space(self, params: Any) -> ActionSpace:
        return self.env.action_space(params)

    def obs_sizes(self, params: Any) -> Observation:
        return self.env.obs_sizes(params)

    def obs_groups(self, params: Any) -> tuple[ObsGroup, ...]:
        return self.env.obs_groups(params)

    def reset(self, key: jax.Array, params: Any) -> tuple[Any, Observation]:
        state, obs = self.env.reset(key, params)
        return state, self.normalize(obs)

    def step(self, key: jax.Array, state: Any, action: jax.Array, params: Any) -> tuple[Any, StepResult]:
        state, result = self.env.step(key, state, action, params)
        return state, result.replace(obs=self.normalize(result.obs))

    def expert_action(self, key: jax.Array, obs: Observation, params: Any) -> jax.Array:
        return self.env.expert_action(key, obs, params)

    def expert_probs(self, obs: Observation, params: Any) -> jax.Array | None:
        return self.env.expert_probs(obs, params)

    def best_action(self, state: Any, params: Any) -> jax.Array:
        return self.env.best_action(state, params)

    def theta(self, state: Any) -> jax.Array:
        return self.env.theta(state)
