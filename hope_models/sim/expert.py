"""The reacher expert: task-space PD through the Jacobian transpose, a pure function of the observation.

    u = clip(J^T (KP * target_offset - KD * J qdot) + wrist limit term, -1, 1)

All in the upper arm's frame, the frame the observation's target_offset is in (reacher.py): there
J = J(0, q2) is the fingertip Jacobian of the two-link arm (links of 0.12 m) with the shoulder
rotation removed (world J(q1, q2) = R(q1) J(0, q2), and R(q1) cancels in J^T F), target_offset is
target minus fingertip (m) and J qdot the fingertip velocity. The force-like term is mapped to the two
motor commands by J^T; when the wrist is folded past WRIST_SOFT_LIMIT (2.2 rad; its hard limit is
2.79) a term K_LIMIT x (excess) pushes it back out instead of into the hard limit; the result is
clipped to the action bounds. It reads nothing but the observation a policy sees (no privileged
target velocity on the track task), so it is exactly what behaviour cloning can imitate, and it is
deterministic: the same observation always gives the same action.

KP = 300, KD = 15: measured on the reacher's 20 ms Euler step; KD = 40 already chatters (the
derivative term is unstable for the light arm at this step), KD = 15 keeps a 2.5x margin. It
converges from any joint state we tried (200 random angles and velocities, 0 failures). Mean returns
on seeds 0-19 (docs/reflex.md has the table): reach 985.7, track 982.6 (uniform random 27.6 / 54.8).

A policy here is anything with reset() (called at an episode's start) and act(observation) ->
action; ExpertController, RandomPolicy and PlayPolicy (smooth random exploration, see its doc) are.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from hope_models.sim.reacher import (
    ACT_DIM,
    ACTION_HIGH,
    ACTION_LOW,
    CONTROL_PERIOD_S,
    LINK_LENGTHS_M,
    OBS_DIM,
    observation_vector,
)

KP = 300.0
KD = 15.0
WRIST_SOFT_LIMIT = 2.2  # rad; the wrist's hard limit is +-2.79 (160 deg)
K_LIMIT = 10.0  # command per rad beyond the soft limit, away from the hard limit

# PlayPolicy (measured in test_sim_play: joint-position spread well above the expert's, which parks
# the arm on the target within ~1 s)
PLAY_TAU_S = 0.3  # correlation time of the random command
PLAY_STD = 0.8  # its stationary std before the [-1, 1] clip: often saturated, so the links swing far
PLAY_SEGMENT_STEPS = (25, 100)  # 0.5-2 s segments, each pure noise or blended toward the expert
PLAY_BLEND_P = 0.3  # share of blended segments
PLAY_BLEND_WEIGHT = (0.4, 0.9)  # expert weight of a blended segment


def fingertip_jacobian(q1: float, q2: float) -> np.ndarray:
    l1, l2 = LINK_LENGTHS_M
    s1, c1 = np.sin(q1), np.cos(q1)
    s12, c12 = np.sin(q1 + q2), np.cos(q1 + q2)
    return np.array([[-l1 * s1 - l2 * s12, -l2 * s12],
                     [l1 * c1 + l2 * c12, l2 * c12]])


def _as_vector(obs: Any) -> np.ndarray:
    """An env (its current observation), an observation dict or a raw OBS_FIELDS vector -> vector."""
    if hasattr(obs, "observation") and not isinstance(obs, dict):
        obs = obs.observation
    if isinstance(obs, dict):
        return observation_vector(obs)
    v = np.asarray(obs, dtype=np.float64).reshape(-1)
    if v.shape != (OBS_DIM,):
        raise ValueError(f"observation vector must have {OBS_DIM} values (joint_positions, joint_velocities, "
                         f"target_offset), got shape {np.shape(obs)}")
    return v


class ExpertController:
    """Deterministic state-feedback expert toward the target (see the module doc)."""

    name = "expert"

    def __init__(self, kp: float = KP, kd: float = KD, wrist_soft_limit: float = WRIST_SOFT_LIMIT,
                 k_limit: float = K_LIMIT):
        if not (np.isfinite(kp) and np.isfinite(kd) and kp > 0 and kd >= 0):
            raise ValueError(f"kp={kp} must be > 0 and kd={kd} >= 0")
        if not (np.isfinite(wrist_soft_limit) and wrist_soft_limit > 0 and np.isfinite(k_limit) and k_limit >= 0):
            raise ValueError(f"wrist_soft_limit={wrist_soft_limit} must be > 0 and k_limit={k_limit} >= 0")
        self.kp, self.kd = float(kp), float(kd)
        self.wrist_soft_limit, self.k_limit = float(wrist_soft_limit), float(k_limit)

    def config(self) -> dict[str, float]:
        return {"kp": self.kp, "kd": self.kd, "wrist_soft_limit": self.wrist_soft_limit, "k_limit": self.k_limit}

    def reset(self) -> None:
        pass  # stateless

    def act(self, obs: Any) -> np.ndarray:
        v = _as_vector(obs)
        q1, q2, qd1, qd2, dx, dy = v
        jac = fingertip_jacobian(0.0, q2)  # the arm frame: J(q) = R(q1) J(0, q2), and R(q1) cancels
        force = self.kp * np.array([dx, dy]) - self.kd * (jac @ np.array([qd1, qd2]))
        u = jac.T @ force
        beyond = abs(q2) - self.wrist_soft_limit
        if beyond > 0:  # folded: push the wrist back out instead of into its hard limit
            u[1] -= np.sign(q2) * self.k_limit * beyond
        return np.clip(u, ACTION_LOW, ACTION_HIGH)


class RandomPolicy:
    """Uniform random commands in the action bounds; seeded, re-seeded by reset(seed)."""

    name = "random"

    def __init__(self, seed: int = 0):
        self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)

    def act(self, obs: Any) -> np.ndarray:
        return self._rng.uniform(ACTION_LOW, ACTION_HIGH, ACT_DIM)


class PlayPolicy:
    """Play: smooth random exploration, no expert label (`sim-demos --policy play`).

    Each joint's command is an AR(1) (discretised Ornstein-Uhlenbeck) process around 0 with
    stationary std PLAY_STD and correlation time PLAY_TAU_S. Smooth rather than white noise because
    the light arm low-pass filters white commands into a jitter around its start pose, while a
    command held for ~0.3 s swings a link through a large angle: the arm sweeps its workspace.
    The episode is cut into segments of PLAY_SEGMENT_STEPS; in a share PLAY_BLEND_P of them the
    command is blended toward the expert's action with a weight drawn in PLAY_BLEND_WEIGHT. Pure
    noise almost never puts the fingertip on the small target (uniform random scores ~28 of 1000),
    so a world model would never see the on-target states and rewards it must predict; the blend
    visits them without making the episode a demonstration (the executed command is still mostly
    noise, and it is recorded as such). Seeded from the episode seed: deterministic.
    """

    name = "play"

    def __init__(self, seed: int = 0, tau_s: float = PLAY_TAU_S, std: float = PLAY_STD,
                 blend_p: float = PLAY_BLEND_P):
        if not (np.isfinite(tau_s) and tau_s > 0 and np.isfinite(std) and std > 0):
            raise ValueError(f"tau_s={tau_s} and std={std} must be > 0")
        if not 0.0 <= blend_p <= 1.0:
            raise ValueError(f"blend_p={blend_p} must be within [0, 1]")
        self.seed, self.tau_s, self.std, self.blend_p = int(seed), float(tau_s), float(std), float(blend_p)
        self._expert = ExpertController()
        self.reset()

    def config(self) -> dict[str, Any]:
        return {"tau_s": self.tau_s, "std": self.std, "blend_p": self.blend_p,
                "segment_steps": list(PLAY_SEGMENT_STEPS), "blend_weight": list(PLAY_BLEND_WEIGHT)}

    def reset(self, seed: int | None = None) -> None:
        if seed is not None:
            self.seed = int(seed)
        self._rng = np.random.default_rng([self.seed, 0x91A7])
        self._x = self._rng.normal(0.0, self.std, ACT_DIM)  # start in the stationary distribution
        self._left, self._weight = 0, 0.0

    def act(self, obs: Any) -> np.ndarray:
        rng = self._rng
        if self._left == 0:
            self._left = int(rng.integers(PLAY_SEGMENT_STEPS[0], PLAY_SEGMENT_STEPS[1] + 1))
            self._weight = float(rng.uniform(*PLAY_BLEND_WEIGHT)) if rng.random() < self.blend_p else 0.0
        self._left -= 1
        a = np.exp(-CONTROL_PERIOD_S / self.tau_s)
        self._x = a * self._x + np.sqrt(1.0 - a * a) * self.std * rng.normal(0.0, 1.0, ACT_DIM)
        u = self._x
        if self._weight > 0:
            u = (1.0 - self._weight) * u + self._weight * self._expert.act(obs)
        return np.clip(u, ACTION_LOW, ACTION_HIGH)
