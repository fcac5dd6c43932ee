"""The confounded Brax envs (half_cheetah, ant_goal on MJX): θ never in the imitator's view, the indicator's flip
rate and the goal cue's noise statistically, rewards on constructed states, shapes, no NaN, determinism, the view
normaliser and the expert loader's round trip.

The default tier checks the confounding layer on constructed states (no Brax compile). The slow tier compiles each
env's rollout once (module fixture, one small shape: a Brax compile takes 1-3 minutes on CI's CPU) and checks the
same properties on recorded episodes.
"""

from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxdeconf.envs import make

B, T = 32, 30


def _within(rate: float, p: float, n: int, sigmas: float = 4.5) -> bool:
    return abs(rate - p) <= sigmas * np.sqrt(p * (1 - p) / n)


def _record(env, params):
    """Compiled: B episodes of T uniformly random actions in [-1.5, 1.5] (beyond the box: the env clips)."""
    act_size = env.action_space(params).n

    @jax.jit
    def run(key):
        k_reset, k_run = jax.random.split(key)
        state, obs = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(k_reset, B), params)

        def body(state, k):
            k_act, k_step = jax.random.split(k)
            action = jax.random.uniform(k_act, (B, act_size), minval=-1.5, maxval=1.5)
            new, res = jax.vmap(env.step, in_axes=(0, 0, 0, None))(jax.random.split(k_step, B), state, action, params)
            return new, {"obs": res.obs, "reward": res.reward, "done": res.done, "extras": res.extras,
                         "state_obs": new.brax.obs, "cue": new.cue, "v": new.brax.metrics["x_velocity"],
                         "xy": new.brax.pipeline_state.x.pos[:, 0, :2], "action": action}

        _, rec = jax.lax.scan(body, state, jax.random.split(k_run, T))
        return state.theta, obs, rec

    return run


@pytest.fixture(scope="module")
def cheetah():
    env, params = make("half_cheetah")
    run = _record(env, params)
    return env, params, run, jax.device_get(run(jax.random.key(0)))


@pytest.fixture(scope="module")
def ant():
    env, params = make("ant_goal")
    run = _record(env, params)
    return env, params, run, jax.device_get(run(jax.random.key(0)))


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.parametrize("name", ["cheetah", "ant"])
def test_shapes_finite_and_deterministic(name, request):
    env, params, run, (_, obs0, rec) = request.getfixturevalue(name)
    sizes = env.obs_sizes(params)
    for view in ("expert", "imitator", "oracle"):
        assert getattr(rec["obs"], view).shape == (T, B, getattr(sizes, view))
        assert getattr(obs0, view).shape == (B, getattr(sizes, view))
        assert np.isfinite(getattr(rec["obs"], view)).all()
    assert rec["reward"].shape == (T, B) and np.isfinite(rec["reward"]).all()
    assert not rec["done"].any()  # Fixed-length episodes: nothing terminates.
    assert env.action_space(params).n == (6 if name == "cheetah" else 8)
    again = jax.device_get(run(jax.random.key(0)))
    np.testing.assert_array_equal(again[2]["obs"].imitator, rec["obs"].imitator)
    np.testing.assert_array_equal(again[2]["reward"], rec["reward"])
    other = jax.device_get(run(jax.random.key(1)))
    assert not np.array_equal(other[2]["reward"], rec["reward"])


@pytest.mark.slow
@pytest.mark.timeout(600)
@pytest.mark.parametrize("name", ["cheetah", "ant"])
def test_imitator_view_is_state_plus_cue_only(name, request):
    """The imitator's view is exactly Brax's state and the cue's features (the ant's bearing as cos and sin); θ enters
    only through the cue, the oracle's view is the imitator's plus θ, and the expert's the state plus θ (the cheetah's
    reference variant adds the indicator)."""
    env, params, _, (theta, _, rec) = request.getfixturevalue(name)
    imitator, oracle, expert = rec["obs"].imitator, rec["obs"].oracle, rec["obs"].expert
    cue = np.asarray(jax.vmap(jax.vmap(lambda c: env.cue_features(c, params)))(rec["cue"]))
    np.testing.assert_allclose(imitator, np.concatenate([rec["state_obs"], cue], -1), rtol=1e-6, atol=1e-6)
    theta_t = np.broadcast_to(theta.reshape(1, B, -1), (T, B, theta.reshape(B, -1).shape[1]))
    np.testing.assert_array_equal(oracle, np.concatenate([imitator, theta_t], -1))
    np.testing.assert_array_equal(expert, np.concatenate([rec["state_obs"], theta_t], -1))
    # No column of the imitator's view is θ (or a fixed multiple of it) across episodes.
    flat_theta = theta.reshape(B, -1)
    for col in range(imitator.shape[-1]):
        for j in range(flat_theta.shape[1]):
            assert abs(np.corrcoef(imitator[-1, :, col], flat_theta[:, j])[0, 1]) < 0.999


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_cheetah_indicator_flip_rate_on_episodes(cheetah):
    _, _, _, (theta, _, rec) = cheetah
    assert (theta >= 0).all() and (theta <= 3).all()
    true_sign = np.where(rec["v"] >= theta[None], 1.0, -1.0)
    flipped = rec["cue"][..., 0] != true_sign
    assert set(np.unique(rec["cue"])) <= {-1.0, 1.0}
    assert _within(flipped.mean(), 0.2, flipped.size)


@pytest.mark.parametrize("flip_prob", [0.2, 0.8, 0.0])
def test_cheetah_target_and_indicator_flip_rate(flip_prob):
    """θ ~ U(0, 3); the indicator is sign(v - target), flipped w.p. flip_prob (0.2; the reference code's 0.8)."""
    env, params = make("half_cheetah", flip_prob=flip_prob)
    n = 20000
    theta = np.asarray(jax.vmap(env.sample_theta, in_axes=(0, None))(jax.random.split(jax.random.key(2), n), params))
    assert theta.min() >= 0 and theta.max() <= 3 and _within(float(np.mean(theta < 1.0)), 1 / 3, n)
    v = jnp.asarray(np.random.default_rng(0).uniform(0, 3, n), jnp.float32)
    cue = np.asarray(jax.vmap(lambda k, v, t: env.cue(k, types.SimpleNamespace(metrics={"x_velocity": v}), t,
                                                      params))(jax.random.split(jax.random.key(3), n), v, theta))
    true_sign = np.where(np.asarray(v) >= theta, 1.0, -1.0)
    assert set(np.unique(cue)) <= {-1.0, 1.0}
    assert _within(float(np.mean(cue[:, 0] != true_sign)), flip_prob, n) if 0 < flip_prob < 1 else \
        np.array_equal(cue[:, 0] != true_sign, np.full(n, flip_prob == 1.0))


def test_views_on_constructed_states():
    """θ reaches the imitator's view only through the cue: the views of a constructed state, for both envs and the
    cheetah's reference variant (whose expert also sees the indicator)."""
    from jaxdeconf.envs.locomotion import LocomotionState

    ant_cue = jnp.array([5.1, -0.9])
    for name, theta, overrides, cue, seen in [
        ("half_cheetah", jnp.array(2.5), {}, jnp.array([-1.0]), jnp.array([-1.0])),
        ("half_cheetah", jnp.array(2.5), {"expert_sees_indicator": True}, jnp.array([-1.0]), jnp.array([-1.0])),
        ("ant_goal", jnp.array([3.0, -4.0]), {}, ant_cue, jnp.array([5.1, np.cos(-0.9), np.sin(-0.9)])),
        ("ant_goal", jnp.array([3.0, -4.0]), {"raw_bearing": True}, ant_cue, ant_cue),
    ]:
        env, params = make(name, **overrides)
        size = env.state_size(params)
        s = jnp.arange(size, dtype=jnp.float32) / 7.0
        state = LocomotionState(brax=types.SimpleNamespace(obs=s), theta=theta, cue=cue, t=jnp.zeros((), jnp.int32))
        obs = env.observe(state, params)
        sizes = env.obs_sizes(params)
        assert obs.imitator.shape == (sizes.imitator,) and obs.expert.shape == (sizes.expert,)
        assert obs.oracle.shape == (sizes.oracle,)
        np.testing.assert_allclose(obs.imitator, jnp.concatenate([s, seen]), rtol=1e-6)
        np.testing.assert_allclose(obs.oracle, jnp.concatenate([s, seen, theta.reshape(-1)]), rtol=1e-6)
        expected = [s, theta.reshape(-1), cue] if overrides.get("expert_sees_indicator") else [s, theta.reshape(-1)]
        np.testing.assert_array_equal(obs.expert, jnp.concatenate(expected))
        # Changing θ alone changes the expert's and oracle's views and leaves the imitator's untouched.
        other = env.observe(state.replace(theta=theta + 0.5), params)
        np.testing.assert_array_equal(other.imitator, obs.imitator)
        assert not np.array_equal(other.expert, obs.expert) and not np.array_equal(other.oracle, obs.oracle)


def test_ant_goal_distribution_and_cue_noise():
    env, params = make("ant_goal")
    goals = np.asarray(jax.vmap(env.sample_theta, in_axes=(0, None))(jax.random.split(jax.random.key(2), 20000),
                                                                    params))
    r = np.linalg.norm(goals, axis=-1)
    assert r.max() <= 10.0
    # Uniform in the disc: P(r < 5) = 1/4, and the angle is uniform.
    assert _within(float(np.mean(r < 5.0)), 0.25, 20000)
    assert _within(float(np.mean(goals[:, 0] > 0)), 0.5, 20000)
    # The cue is (distance, bearing) plus N(0, cue_noise²) on each (the reference code's 0.1 here).
    params = params.replace(cue_noise=0.1)
    brax_state = types.SimpleNamespace(pipeline_state=types.SimpleNamespace(
        x=types.SimpleNamespace(pos=jnp.array([[1.0, 2.0, 0.5]]))))
    goal = jnp.array([4.0, 6.0])
    cue = np.asarray(jax.vmap(lambda k: env.cue(k, brax_state, goal, params))(jax.random.split(jax.random.key(4),
                                                                                                20000)))
    noise = cue - np.array([5.0, np.arctan2(4.0, 3.0)])
    np.testing.assert_allclose(noise.mean(0), 0.0, atol=4.5 * 0.1 / np.sqrt(20000))
    np.testing.assert_allclose(noise.std(0), 0.1, rtol=0.03)


def test_ant_bearing_features_are_continuous_across_the_wrap():
    """The torso straddling the line behind its goal (true bearing ±π, alternating sides): the imitator's (cos, sin)
    of the noisy bearing moves by about the noise from one step to the next, where the raw angle jumps by about 2π.
    At the reference code's cue noise 0.1, where a step's change is small enough to tell from a wrap."""
    y = jnp.where(jnp.arange(4000) % 2 == 0, 0.01, -0.01)
    goal = jnp.array([5.0, 0.0])
    keys = jax.random.split(jax.random.key(5), 4000)
    for raw in (False, True):
        env, params = make("ant_goal", raw_bearing=raw, cue_noise=0.1)

        def features(key, y_torso, env=env, params=params):
            state = _body_at(10.0, y_torso)
            return env.cue_features(env.cue(key, state, goal, params), params)

        jumps = np.abs(np.diff(np.asarray(jax.vmap(features)(keys, y))[:, 1:], axis=0)).max(-1)
        if raw:
            assert np.median(jumps) > 2 * np.pi - 0.5
        else:
            assert jumps.max() < 0.8  # |Δ(cos, sin)| <= |Δ noise|, about 0.14 std.


def _body_at(x, y=0.0, z=0.5):
    """A stand-in Brax state with the torso at (x, y, z): what the reward functions read."""
    return types.SimpleNamespace(pipeline_state=types.SimpleNamespace(x=types.SimpleNamespace(
        pos=jnp.array([[x, y, z]]))))


def test_cheetah_reward_on_constructed_states():
    env, params = make("half_cheetah")
    dt = env.brax_env(params).dt
    assert dt == pytest.approx(0.05)
    action = jnp.full((6,), 0.5)
    # v = 0.1 / 0.05 = 2 m/s against a 1.5 m/s target: -|0.5| - 0.05 * 6 * 0.25.
    r = env.reward(_body_at(0.0), _body_at(0.1), action, jnp.asarray(1.5), params)
    assert float(r) == pytest.approx(-0.575, abs=1e-6)
    r = env.reward(_body_at(1.0), _body_at(1.0), jnp.zeros(6), jnp.asarray(2.0), params.replace(ctrl_cost=0.0))
    assert float(r) == pytest.approx(-2.0, abs=1e-6)


def test_ant_reward_on_constructed_states():
    env, params = make("ant_goal")
    goal = jnp.array([3.0, 4.0])
    assert float(env.reward(None, _body_at(0.0), jnp.ones(8), goal, params)) == pytest.approx(-5.0)  # No ctrl cost.
    l1 = params.replace(l1_reward=True)
    assert float(env.reward(None, _body_at(0.0), jnp.ones(8), goal, l1)) == pytest.approx(-7.0)
    extras = env.step_extras(None, _body_at(3.0, 0.0, 0.1), goal, params)
    assert float(extras["distance"]) == pytest.approx(4.0) and float(extras["unhealthy"]) == 1.0


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_actions_are_clipped(cheetah):
    """Rewards charge the clipped action: a step's control cost never exceeds ctrl_cost · 6."""
    _, _, _, (theta, _, rec) = cheetah
    speed_term = np.abs(rec["v"] - theta[None])
    ctrl = -(rec["reward"] + speed_term)
    np.testing.assert_allclose(ctrl, 0.05 * np.sum(np.clip(rec["action"], -1, 1) ** 2, -1), rtol=1e-4, atol=1e-5)


def test_bad_parameters_are_one_line_errors():
    with pytest.raises(ValueError, match=r"flip_prob=1.5 is outside the allowed range \[0, 1\]"):
        make("half_cheetah", flip_prob=1.5)
    with pytest.raises(ValueError, match=r"backend='bullet' is not allowed; allowed: mjx"):
        make("ant_goal", backend="bullet")
    with pytest.raises(ValueError, match=r"goal_radius=-1\.0"):
        make("ant_goal", goal_radius=-1)


def test_expert_loader_round_trip(tmp_path):
    from jaxdeconf.brax_experts import PolicyExpert, policy_template
    from jaxdeconf.experts import load_expert, save_expert

    meta = {"kind": "brax_ppo", "env": "ant_goal", "obs_size": 31, "action_size": 8, "policy_layers": [16, 16],
            "value_layers": [16]}
    params = policy_template(meta)
    params["policy"] = jax.tree.map(lambda a: a + 0.1 * jnp.arange(a.size).reshape(a.shape) / a.size,
                                    params["policy"])
    save_expert("ant_goal", params, meta, tmp_path)
    with pytest.raises(FileExistsError):
        save_expert("ant_goal", params, meta, tmp_path)
    loaded = load_expert("ant_goal", tmp_path)
    assert isinstance(loaded, PolicyExpert)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(loaded.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    obs = jax.random.normal(jax.random.key(0), (5, 31))
    act = np.asarray(loaded.act(obs))
    assert act.shape == (5, 8) and (np.abs(act) <= 1).all()
    np.testing.assert_array_equal(act, np.asarray(PolicyExpert(params, meta).act(obs)))
    (tmp_path / "ant_goal.msgpack").write_bytes(b"not msgpack")
    with pytest.raises(ValueError, match="corrupt"):
        load_expert("ant_goal", tmp_path)
