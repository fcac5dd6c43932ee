"""Theorem 1's estimator (eq. 5) against hand counts and brute-force enumeration; the exact references at the edges
p = 1 and q = 1; Appendix A's grid at points whose values follow by hand."""

from __future__ import annotations

import itertools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxdeconf.envs.bandit import BanditParams
from jaxdeconf.envs.base import ActionSpace, Observation

from jaxdeconf import theory
from jaxdeconf.data import Trajectory, replay
from jaxdeconf.paper_figures import appendix_a_learned, bandit_runs, outcome_rate, success_grid
from jaxdeconf.references import ReferenceActor, belief_update, safe_log

pytestmark = pytest.mark.timeout(120)
SPACE3 = ActionSpace("discrete", 3)
SPACE5 = ActionSpace("discrete", 5)
replay_jit = jax.jit(replay, static_argnums=(0, 3))


def test_counts_by_hand():
    # One demonstration over S = 2, A = 3: 0 -a2-> 1 -a0-> 1 -a2-> 0.
    states, actions = jnp.array([0, 1, 1, 0]), jnp.array([2, 0, 2])
    log_dyn, log_pol = theory.estimate(theory.demo_counts(states, actions, 2, 3), alpha=0.0)
    dyn, pol = np.exp(log_dyn), np.exp(log_pol)
    np.testing.assert_allclose(dyn[0, 2], [0.0, 1.0])  # Seen once: 0 -> 1.
    np.testing.assert_allclose(dyn[1, 0], [0.0, 1.0])
    np.testing.assert_allclose(dyn[1, 2], [1.0, 0.0])
    np.testing.assert_allclose(dyn[0, 0], [0.5, 0.5])  # Never visited: uniform, not 0 / 0.
    np.testing.assert_allclose(pol, [[0.0, 0.0, 1.0], [0.5, 0.0, 0.5]], atol=1e-7)
    # A pseudo-count of 1 per cell: p̂(1 | 0, a2) = (1 + 1) / (1 + 2), π̂(a2 | 0) = (1 + 1) / (1 + 3).
    log_dyn, log_pol = theory.estimate(theory.demo_counts(states, actions, 2, 3), alpha=1.0)
    assert float(jnp.exp(log_dyn[0, 2, 1])) == pytest.approx(2 / 3)
    assert float(jnp.exp(log_pol[0, 2])) == pytest.approx(0.5)


def _histories(arms: int, steps: int) -> Trajectory:
    """Every bandit history of ``steps`` pulls and outcomes (s_0 = 0), as a batch [T, B]."""
    pulls, outcomes = itertools.product(range(arms), repeat=steps), itertools.product((0, 1), repeat=steps)
    rows = list(itertools.product(pulls, outcomes))
    actions = np.array([a for a, _ in rows]).T  # [T, B]
    outcomes = np.concatenate([np.zeros((1, len(rows))), np.array([s for _, s in rows]).T])  # [T+1, B]
    obs = jnp.asarray(outcomes, jnp.float32)[..., None]
    zeros = jnp.zeros(actions.shape)
    return Trajectory(obs=Observation(expert=obs, imitator=obs, oracle=obs), action=jnp.asarray(actions, jnp.int32),
                      reward=zeros, valid=zeros > -1, best_action=zeros.astype(jnp.int32), extras={})


def _eq5_by_hand(model: theory.TabularModel, actions: np.ndarray, states: np.ndarray, t: int) -> np.ndarray:
    """Eq. 5 from scratch: belief ∝ Π_{k<t} p̂_i(s_{k+1} | s_k, a_k), policy Σ_i belief_i π̂_i(· | s_t)."""
    dyn, pol = np.exp(np.asarray(model.log_dynamics, np.float64)), np.exp(np.asarray(model.log_policy, np.float64))
    weight = np.ones(model.demos)
    for k in range(t):
        weight = weight * dyn[:, states[k], actions[k], states[k + 1]]
    return (weight / weight.sum()) @ pol[:, states[t]]


def test_eq5_equals_brute_force():
    """The jitted, demo-vmapped actor equals eq. 5 evaluated by hand on every 3-step history of a 3-arm bandit."""
    params = BanditParams(p=0.7, q=0.8, arms=3)
    model = jax.jit(theory.fit_bandit, static_argnums=(2, 3))(jax.random.key(0), params, 6, 8, 0.5)
    traj = _histories(3, 3)
    log_probs = np.asarray(replay_jit(theory.TabularActor(6), model, traj, SPACE3))
    actions, states = np.asarray(traj.action), np.asarray(traj.obs.imitator[..., 0]).astype(int)
    for b in range(actions.shape[1]):
        for t in range(3):
            expected = _eq5_by_hand(model, actions[:, b], states[:, b], t)
            np.testing.assert_allclose(np.exp(log_probs[t, b]), expected, atol=1e-5)


@pytest.mark.parametrize(("p", "q"), [(0.6, 0.75), (1.0, 0.75), (0.8, 1.0)])
def test_exact_tables_give_the_interventional_policy(p, q):
    """Theorem 1's proof: with p̂_i, π̂_i exact and one demonstration per θ, eq. 5 is the interventional policy."""
    params = BanditParams(p=p, q=q, arms=3)
    traj = _histories(3, 3)
    est = replay_jit(theory.TabularActor(3), theory.exact_model(params), traj, SPACE3)
    ref = replay_jit(ReferenceActor("interventional", params), None, traj, SPACE3)
    # Histories impossible under every θ (q = 1 and an outcome no arm explains) keep the belief in both.
    np.testing.assert_allclose(np.exp(est), np.exp(ref), atol=1e-5)


def test_estimator_close_to_interventional_with_long_demos():
    """N = 200 demonstrations of 300 steps already act close to the exact interventional count (54.1 per 100)."""
    params = BanditParams()
    out = jax.jit(theory.estimator_curves, static_argnums=(1, 2, 3, 4))(jax.random.key(3), params, 200, 300, 400)
    assert float(out["count"]) == pytest.approx(54.1, abs=2.0)
    assert float(out["online"][0]) == pytest.approx(0.2, abs=0.03)  # Step 1: no evidence yet, marginal ≈ uniform.


def test_conditional_at_p1_q1_keeps_belief_after_impossible_miss():
    params = BanditParams(p=1.0, q=1.0)
    log_b = jnp.full((1, 5), -jnp.log(5.0))
    # Pull arm 2, see 0: under the conditional model every θ gives this probability 0.
    new = belief_update("conditional", log_b, jnp.array([2]), jnp.array([0.0]), params)
    np.testing.assert_allclose(new, log_b)
    # Pull arm 2, see 1: only θ = 2 explains it; the belief is one-hot and finite where possible.
    new = belief_update("conditional", log_b, jnp.array([2]), jnp.array([1.0]), params)
    np.testing.assert_allclose(jnp.exp(new), [[0, 0, 1, 0, 0]])
    # The interventional rules out arm 2 after a miss and keeps the rest uniform.
    new = belief_update("interventional", log_b, jnp.array([2]), jnp.array([0.0]), params)
    np.testing.assert_allclose(jnp.exp(new), [[0.25, 0.25, 0, 0.25, 0.25]])
    assert float(jax.grad(safe_log)(0.0)) == 0.0  # The guarded log has no NaN gradient at 0.


def test_conditional_at_p1_sticks_to_its_first_arm():
    """A deterministic expert with a stochastic env: the first pull's action evidence is infinite, outcomes finite."""
    params = BanditParams(p=1.0, q=0.75)
    log_b = jnp.full((1, 5), -jnp.log(5.0))
    for action, outcome in [(3, 0.0), (3, 0.0), (3, 1.0), (3, 0.0)]:
        log_b = belief_update("conditional", log_b, jnp.array([action]), jnp.array([outcome]), params)
        np.testing.assert_allclose(jnp.exp(log_b), [[0, 0, 0, 1, 0]])


def test_appendix_a_grid_hand_values():
    """Best-arm rate per step over 100 steps at points whose values follow by hand (comments), 2000 episodes."""
    grid = success_grid(jax.random.key(0), (1.0, 0.2), (1.0, 0.5), episodes=2000)
    for name in ("expert", "interventional", "conditional"):
        assert np.isfinite(grid[name]).all(), name
    np.testing.assert_allclose(grid["expert"], [[1.0, 1.0], [0.2, 0.2]], atol=1e-6)
    # p = 1, q = 1, interventional: pull arms without replacement until the hit, then stay; the hit comes at step
    # K ~ uniform{1..5}, so E[count] = 101 - E[K] = 98. Per-episode sd sqrt(2): s.e. 0.0003 per step.
    assert grid["interventional"][0, 0] == pytest.approx(0.98, abs=0.002)
    # p = 1, q = 1, conditional: a miss is impossible under the model and leaves the belief uniform, so it pulls
    # uniformly with replacement until the hit: P(best at step t) = 1 - 0.8^t, sum 100 - 4 (1 - 0.8^100) = 96.0.
    # Per-episode sd about 4.5 (a geometric first hit): s.e. 0.001 per step.
    assert grid["conditional"][0, 0] == pytest.approx(0.96, abs=0.005)
    # q = 0.5: outcomes carry no information, so no policy without θ beats chance: 0.2 (interventional exactly).
    assert grid["interventional"][0, 1] == pytest.approx(0.2, abs=1e-5)
    # Sticks to its first arm: count 100 or ~0, sd 40, s.e. 0.009 per step.
    assert grid["conditional"][0, 1] == pytest.approx(0.2, abs=0.04)
    # p = 0.2: the expert is uniform, so every mixture of it is uniform: 0.2 exactly.
    np.testing.assert_allclose(grid["interventional"][1], 0.2, atol=1e-5)
    np.testing.assert_allclose(grid["conditional"][1], 0.2, atol=1e-5)
    # The paper's r_t = s_{t+1}: the expert at p = 1 succeeds with probability q.
    assert outcome_rate(np.float32(1.0), np.float32(0.75)) == pytest.approx(0.75)
    assert outcome_rate(np.float32(0.2), np.float32(0.75)) == pytest.approx(0.2 * 0.75 + 0.8 * 0.25)


def test_learned_table_reads_results_folders(tmp_path):
    """``bandit_runs`` finds finished runs by their config's (p, q); the table takes each seed's last evaluation."""
    folder = tmp_path / "grid"
    for algo, returns in (("bc", (30.0, 34.0)), ("dil", (50.0, 54.0))):
        (folder / algo).mkdir(parents=True)
        (folder / algo / "DONE").write_text("{}\n")
        rows = [{"algo": algo, "seed": s, "iteration": it, "eval_return": r - (10.0 if it == 1 else 0.0)}
                for s, r in enumerate(returns) for it in (1, 2)]
        (folder / algo / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    (folder / "config.json").write_text(json.dumps({"env": "bandit", "env_params": {"p": 1.0}}))
    refs = {"expert_count": 100.0, "interventional_count": 89.6, "conditional_count": 19.7}
    (folder / "references.json").write_text(json.dumps(refs))
    runs = bandit_runs(tmp_path)
    assert list(runs) == [(1.0, 0.75)]  # q from the bandit's defaults.
    (row,) = appendix_a_learned(tmp_path / "out", runs)
    assert row["bc"]["mean"] == pytest.approx(32.0) and row["dil"]["mean"] == pytest.approx(52.0)
    assert row["dil"]["se"] == pytest.approx(2.0)  # sd of (50, 54) with ddof 1 is 2 sqrt(2); over sqrt(2) seeds.
    assert "| 1 | 0.75 | 100.0 | 89.6 | 52.0 ± 2.0 | 19.7 | 32.0 ± 2.0 | 2 | 2 |" in (
        tmp_path / "out" / "appendix_a_learned.md").read_text()


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_trained_imitators_load_for_figure1(tmp_path, tiny_config):
    """Figure 1's loader restores bc's and dil's trained parameters (not their initial ones), and ``rollout_actions``
    reports the θ the shared key draws for every policy and a best-arm count equal to the loaded actor's P(θ)
    recomputed by teacher-forcing it along the same episodes."""
    from jaxdeconf import config as cfg
    from jaxdeconf.actors import ExpertActor
    from jaxdeconf.data import rollout
    from jaxdeconf.paper_figures import learned_actor, rollout_actions
    from jaxdeconf.train import build_algorithm, train_algorithm

    config = tiny_config(seeds=1)
    (tmp_path / "config.json").write_text(cfg.dumps(config) + "\n")
    key = jax.random.key(0)
    for algo in ("bc", "dil"):
        train_algorithm(config, algo, tmp_path / algo, progress=False)
        env, env_params, actor, actor_params = learned_actor(tmp_path, algo)
        fresh = build_algorithm(config, algo)
        initial = fresh.actor_params(jax.jit(fresh.init)(jax.random.key(config.seed_start)))
        flat_loaded, flat_initial = jax.tree.leaves(actor_params), jax.tree.leaves(initial)
        assert len(flat_loaded) == len(flat_initial)
        assert any(not np.array_equal(a, b) for a, b in zip(flat_loaded, flat_initial, strict=True)), algo

        actions, theta, count = rollout_actions(key, env, env_params, actor, actor_params, episodes=3)
        assert actions.shape == (3, 10) and theta.shape == (3,)  # The tiny config's 10-step bandit.
        # The same key gives every policy the same θ (Figure 1's rows share it).
        _, expert_theta, _ = rollout_actions(key, env, env_params, ExpertActor(env, env_params), None, episodes=3)
        np.testing.assert_array_equal(theta, expert_theta)
        # The count: softmax of the teacher-forced outputs at θ, summed over the 10 steps, averaged over episodes.
        traj, _ = jax.jit(rollout, static_argnums=(0, 2, 5))(env, env_params, actor, actor_params, key, 3)
        np.testing.assert_array_equal(np.asarray(traj.action).T, actions)
        logits = np.asarray(replay_jit(actor, actor_params, traj, SPACE5), np.float64)  # [T, 3, arms]
        probs = np.exp(logits - logits.max(-1, keepdims=True))
        probs /= probs.sum(-1, keepdims=True)
        expected = probs[:, np.arange(3), theta].sum(0).mean()
        assert count == pytest.approx(expected, rel=1e-5), algo
