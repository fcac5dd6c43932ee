"""check_env passes on every registered env and names the problem on broken ones; envs load from user modules."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import CARTPOLE
from jaxdeconf.envs import EnvCheckError, Observation, ObsGroup, check_env, make, register, resolve
from jaxdeconf.envs.bandit import Bandit, BanditParams, BanditState

from jaxdeconf.errors import ConfigError
from jaxdeconf.resolve import build

pytestmark = pytest.mark.timeout(900)


@pytest.mark.parametrize("name", ["bandit", "lunar_lander", CARTPOLE])
def test_check_env_passes(name):
    env, params = make(name)
    check_env(env, params)


class LeakyBandit(Bandit):
    """θ appended to the imitator's view: exactly what the imitator must never see."""

    def obs_sizes(self, params: BanditParams) -> Observation:
        return Observation(expert=1 + params.arms, imitator=2, oracle=1 + params.arms)

    def _observe(self, state: BanditState, params: BanditParams) -> Observation:
        obs = super()._observe(state, params)
        return obs.replace(imitator=jnp.concatenate([obs.imitator, state.theta.astype(jnp.float32)[None]]))


class CountingBandit(Bandit):
    """Counts its steps on the env object: state outside the state."""

    def __init__(self) -> None:
        self.calls = []

    def step(self, key, state, action, params):
        self.calls.append(1)
        return super().step(key, state, action, params)


class NumpyNoiseBandit(Bandit):
    """Draws noise with numpy inside step: a constant baked in at trace time, different on every trace."""

    def step(self, key, state, action, params):
        state, result = super().step(key, state, action, params)
        return state, result.replace(reward=result.reward + np.float32(np.random.default_rng().normal()))


class WrongSizeBandit(Bandit):
    """Declares a view size its observations do not have."""

    def obs_sizes(self, params: BanditParams) -> Observation:
        return Observation(expert=1 + params.arms, imitator=3, oracle=1 + params.arms)


class BadGroupsBandit(Bandit):
    """Declares observation groups that do not cover its one-dimensional imitator view."""

    def obs_groups(self, params: BanditParams) -> tuple[ObsGroup, ...]:
        return ObsGroup("a", 1, "bernoulli"), ObsGroup("b", 1, "poisson")


@pytest.mark.parametrize(
    ("env", "message"),
    [
        (BadGroupsBandit(), "obs_groups.params. must split the imitator's 1 dimensions"),
        (LeakyBandit(), "θ is in the imitator's view"),
        (CountingBandit(), "step is not pure: it changed the environment object's attribute"),
        (NumpyNoiseBandit(), "step is not pure: two traces with the same inputs gave different"),
        (WrongSizeBandit(), "the imitator view from reset has shape"),
    ],
)
def test_check_env_names_the_problem(env, message):
    with pytest.raises(EnvCheckError, match=message):
        check_env(env, BanditParams(horizon=10))


def test_env_from_user_module_by_name(tmp_path, monkeypatch):
    (tmp_path / "my_envs.py").write_text(
        "from jaxdeconf.envs.bandit import Bandit\n\n"
        "class SmallBandit(Bandit):\n"
        "    presets = {'cpu': {'train.iterations': 7, 'train.warmup': 1}}\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    env, params = make("my_envs:SmallBandit", horizon=10)
    assert type(env).__name__ == "SmallBandit" and params.horizon == 10
    config = build("my_envs:SmallBandit", "cpu", ("bc",), 1, {})
    assert config.train.iterations == 7 and config.env == "my_envs:SmallBandit"
    with pytest.raises(ConfigError, match=r"unknown preset 'paper' for env 'my_envs:SmallBandit'; allowed: cpu$"):
        build("my_envs:SmallBandit", "paper", ("bc",), 1, {})  # Its own presets only, never another env's.
    register("small_bandit", Bandit)
    assert resolve("small_bandit") is Bandit


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("no_such_module_xyz:Env", "cannot import env module 'no_such_module_xyz'"),
        ("jaxdeconf.envs.bandit:Nope", "has no attribute 'Nope'"),
        ("jaxdeconf.envs.bandit:BanditParams", "built a BanditParams, not a jaxdeconf.envs.Environment"),
    ],
)
def test_bad_module_env_names_are_one_line_errors(name, message):
    with pytest.raises(ValueError, match=message):
        make(name)


def test_unknown_module_env_is_a_config_error():
    with pytest.raises(ConfigError, match="cannot import env module"):
        build("no_such_module_xyz:Env", "cpu", ("bc",), 1, {})
