"""The reacher env (reach and track), the expert, the random policy and the scoring rules."""
from __future__ import annotations

import math

import numpy as np
import pytest

from hope_models.sim.evaluate import (
    ON_TARGET_FRACTION, REACH_DEADLINE_S, evaluate_policy, expert_factory, random_factory, score_rewards,
)
from hope_models.sim.expert import ExpertController, RandomPolicy
from hope_models.sim.reacher import (
    CONTROL_PERIOD_S, EPISODE_STEPS, OBS_DIM, from_arm_frame, TOLERANCE_M, TRACK_OMEGA_RAD_S, TRACK_RADIUS_M, make_env,
    observation_vector,
)


def _rollout(task: str, seed: int, policy, steps: int) -> tuple[list[np.ndarray], list[float]]:
    env = make_env(task, seed)
    obs = env.reset()
    policy.reset()
    vecs, rewards = [observation_vector(obs)], []
    for _ in range(steps):
        obs, r, _ = env.step(policy.act(obs))
        vecs.append(observation_vector(obs))
        rewards.append(r)
    return vecs, rewards


def test_observation_layout_and_constants():
    env = make_env("reach", 3)
    obs = env.reset()
    assert set(obs) == {"robot_state", "target_offset"}
    assert set(obs["robot_state"]) == {"joint_positions", "joint_velocities"}
    v = observation_vector(obs)
    assert v.shape == (OBS_DIM,) and np.isfinite(v).all()
    assert -math.pi <= v[0] < math.pi  # the continuous shoulder is wrapped
    # target_offset is target minus fingertip, in the upper arm's frame
    np.testing.assert_allclose(from_arm_frame(v[0], v[4:]), env.target_xy() - env.fingertip_xy(), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(v[4:]), env.distance(), atol=1e-12)
    assert env.physics.model.opt.timestep == pytest.approx(CONTROL_PERIOD_S)
    assert env._env.control_timestep() == pytest.approx(CONTROL_PERIOD_S)


def test_episode_is_1000_steps_and_then_over():
    env = make_env("reach", 0)
    env.reset()
    done = False
    n = 0
    while not done:
        _, _, done = env.step([0.0, 0.0])
        n += 1
    assert n == EPISODE_STEPS
    with pytest.raises(RuntimeError, match="episode is over"):
        env.step([0.0, 0.0])


@pytest.mark.parametrize("task", ["reach", "track"])
def test_same_seed_same_episode_other_seed_differs(task):
    a, ra = _rollout(task, 11, RandomPolicy(5), 50)
    b, rb = _rollout(task, 11, RandomPolicy(5), 50)
    c, _ = _rollout(task, 12, RandomPolicy(5), 50)
    assert all(np.array_equal(x, y) for x, y in zip(a, b)) and ra == rb
    assert not np.array_equal(a[0], c[0])


def test_reward_is_one_exactly_within_tolerance():
    env = make_env("reach", 4)
    obs = env.reset()
    expert = ExpertController()
    seen = set()
    for _ in range(200):
        obs, r, _ = env.step(expert.act(obs))
        d = env.distance()
        assert r == (1.0 if d <= TOLERANCE_M else 0.0)
        seen.add(r)
    assert seen == {0.0, 1.0}


def test_track_target_moves_along_a_reachable_circle():
    env = make_env("track", 21)
    env.reset()
    task = env.task
    lo, hi = TRACK_RADIUS_M
    assert lo <= task.circle_radius <= hi
    positions = [env.target_xy()]
    for _ in range(100):
        env.step([0.0, 0.0])
        positions.append(env.target_xy())
    p = np.array(positions)
    radii = np.linalg.norm(p, axis=1)
    np.testing.assert_allclose(radii, task.circle_radius, atol=1e-9)
    angles = np.unwrap(np.arctan2(p[:, 1], p[:, 0]))
    np.testing.assert_allclose(np.diff(angles), task.direction * TRACK_OMEGA_RAD_S * CONTROL_PERIOD_S, atol=1e-9)
    # the observation's offset follows the moving target
    v = observation_vector(env.observation)
    np.testing.assert_allclose(from_arm_frame(v[0], v[4:]), env.target_xy() - env.fingertip_xy(), atol=1e-12)


def test_reach_target_does_not_move():
    env = make_env("reach", 21)
    env.reset()
    t0 = env.target_xy()
    for _ in range(20):
        env.step([1.0, -1.0])
    np.testing.assert_array_equal(env.target_xy(), t0)


def test_expert_is_deterministic_and_in_bounds():
    env = make_env("reach", 2)
    obs = env.reset()
    e = ExpertController()
    a = e.act(obs)
    assert np.array_equal(a, ExpertController().act(obs))
    assert np.array_equal(a, e.act(observation_vector(obs)))
    assert np.array_equal(a, e.act(env))  # an env: its current observation
    assert np.all(a >= -1) and np.all(a <= 1)
    with pytest.raises(ValueError, match="6 values"):
        e.act([0.0, 1.0])


@pytest.mark.parametrize("task", ["reach", "track"])
def test_expert_beats_random(task):
    seeds = [0, 1, 2]
    expert = evaluate_policy(expert_factory, seeds, task)
    rand = evaluate_policy(random_factory, seeds, task)
    assert expert.mean_return > 900, expert.summary()
    assert expert.success_rate == 1.0
    assert expert.mean_return > 5 * max(rand.mean_return, 1.0), (expert.summary(), rand.summary())
    assert all(e > r for e, r in zip(expert.returns, rand.returns))


def test_evaluation_is_deterministic_for_a_seed():
    a = evaluate_policy(random_factory, [3, 4], "track")
    b = evaluate_policy(random_factory, [3, 4], "track")
    assert a.returns == b.returns
    assert [e.to_json_obj() for e in a.episodes] == [e.to_json_obj() for e in b.episodes]


def test_success_definition():
    n = EPISODE_STEPS
    deadline = int(round(REACH_DEADLINE_S / CONTROL_PERIOD_S))
    never = np.zeros(n)
    s = score_rewards(0, never)
    assert (s.ret, s.success, s.time_to_reach_s) == (0.0, False, None)
    on_early = np.zeros(n)
    on_early[9:] = 1
    s = score_rewards(0, on_early)
    assert s.success and s.time_to_reach_s == pytest.approx(0.2) and s.on_target_after_reach == 1.0
    late = np.zeros(n)
    late[deadline:] = 1  # first on target at (deadline + 1) steps: after the 2 s deadline
    assert not score_rewards(0, late).success
    just_in = np.zeros(n)
    just_in[deadline - 1:] = 1  # on target at exactly 2.0 s
    assert score_rewards(0, just_in).success
    leaves = np.zeros(n)
    leaves[10:] = 1
    off = int((1 - ON_TARGET_FRACTION) * (n - 10)) + 2  # just over 20 % of the remaining steps off target
    leaves[n - off:] = 0
    s = score_rewards(0, leaves)
    assert s.on_target_after_reach < ON_TARGET_FRACTION and not s.success


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="task"):
        make_env("juggle", 0)
    with pytest.raises(ValueError, match="seed"):
        make_env("reach", -1)
    env = make_env("reach", 0)
    with pytest.raises(RuntimeError, match="reset"):
        env.step([0, 0])
    env.reset()
    with pytest.raises(ValueError, match="2 values"):
        env.step([0, 0, 0])
    with pytest.raises(ValueError, match="not finite"):
        env.step([float("nan"), 0])
    with pytest.raises(ValueError, match="seeds is empty"):
        evaluate_policy(expert_factory, [], "reach")
