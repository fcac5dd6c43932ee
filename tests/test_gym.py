"""gymnasium wrappers pass gymnasium's env checker; a trained imitator driven through them matches the compiled
rollout on the same seeds."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from conftest import CARTPOLE, TINY
from gymnasium.utils.env_checker import check_env as gymnasium_check_env
from gymnasium.vector import AutoresetMode

from jaxdeconf import config as cfg
from jaxdeconf.data import rollout
from jaxdeconf.errors import ConfigError
from jaxdeconf.gym import GymEnv, GymVectorEnv, make_env, make_vector_env
from jaxdeconf.policy import load_policy
from jaxdeconf.resolve import build
from jaxdeconf.train import train_algorithm

pytestmark = pytest.mark.timeout(1800)


@pytest.mark.parametrize("name", ["bandit", "lunar_lander", CARTPOLE])
def test_gymnasium_env_checker_passes(name):
    env = make_env(name) if name != "bandit" else make_env(name, horizon=10)
    gymnasium_check_env(env, skip_render_check=True)
    assert isinstance(env, GymEnv) and env.observation_space.shape == (env.core.single_observation_space.shape[0],)


def test_vector_env_reset_seeding_and_next_step_autoreset():
    venv = make_vector_env("bandit", 3, horizon=4)
    assert isinstance(venv, GymVectorEnv) and venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert venv.observation_space.shape == (3, 1) and venv.action_space.shape == (3,)
    first, _ = venv.reset(seed=5)
    thetas = venv.core.theta()
    rewards = []
    for t in range(4):
        obs, reward, terminated, truncated, _ = venv.step(np.full(3, 0))
        rewards.append(reward)
        assert not terminated.any() and truncated.all() == (t == 3)
    obs, reward, terminated, truncated, _ = venv.step(np.full(3, 0))  # NEXT_STEP: the reset step.
    assert (reward == 0).all() and not terminated.any() and not truncated.any()
    np.testing.assert_array_equal(obs, np.zeros((3, 1)))  # The bandit's first outcome is 0.
    np.testing.assert_array_equal(np.sum(rewards, axis=0), 4 * (thetas == 0))  # Arm 0 pays 1 iff it is θ.
    again, _ = venv.reset(seed=5)
    np.testing.assert_array_equal(first, again)
    np.testing.assert_array_equal(thetas, venv.core.theta())


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """dil trained for 4 iterations on a 10-step bandit, 2 seeds, in a results folder."""
    folder = tmp_path_factory.mktemp("results")
    config = build("bandit", "cpu", ("dil",), 2, TINY)
    (folder / "config.json").write_text(cfg.dumps(config) + "\n")
    for algo in config.algos:
        train_algorithm(config, algo, folder / algo, progress=False)
    return folder


def test_policy_through_the_wrappers_matches_the_compiled_rollout(trained):
    policy = load_policy(trained, "dil", seed=1)
    n, seed = 8, 3
    reference, _ = rollout(policy.env, policy.env_params, policy.actor, policy.params, jax.random.key(seed), n)
    expected = np.asarray(reference.reward.sum(0))

    venv = GymVectorEnv("bandit", n, view=policy.view, horizon=10)
    obs, _ = venv.reset(seed=seed)
    state = policy.initial_state(seed=seed, num_envs=n)
    total = np.zeros(n)
    for _ in range(venv.core.horizon):
        action, state = policy(obs, state)
        obs, reward, _, _, _ = venv.step(action)
        total += reward
    np.testing.assert_array_equal(total, expected)

    env = policy.gym_env()  # One env reproduces the rollout of one episode.
    assert isinstance(env, GymEnv) and env.core.horizon == 10
    single, _ = rollout(policy.env, policy.env_params, policy.actor, policy.params, jax.random.key(seed), 1)
    obs, _ = env.reset(seed=seed)
    state, done, episode = policy.initial_state(seed=seed), False, 0.0
    while not done:
        action, state = policy(obs, state)
        obs, reward, terminated, truncated, _ = env.step(action)
        episode += reward
        done = terminated or truncated
    assert episode == float(single.reward.sum())


def test_load_policy_errors_are_one_line(trained):
    with pytest.raises(ConfigError, match="seed 7 was not trained"):
        load_policy(trained, "dil", seed=7)
    with pytest.raises(ConfigError, match="holds no 'bc' run"):
        load_policy(trained, "bc", seed=0)


def test_render_bandit_raster_with_theta_and_belief(trained, tmp_path, capsys):
    from jaxdeconf.render import main

    assert main([str(trained), "--algo", "dil", "--episodes", "2", "--out", str(tmp_path)]) == 0
    path = tmp_path / "bandit_dil.png"
    assert path.exists() and path.stat().st_size > 1000 and f"wrote {path}" in capsys.readouterr().out
    assert main([str(trained), "--algo", "bc", "--out", str(tmp_path)]) == 2
    assert "holds no 'bc' run" in capsys.readouterr().err
