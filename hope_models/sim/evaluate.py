"""Closed-loop evaluation of a policy in the reacher: one act() per 20 ms control step, seeded.

    result = evaluate_policy(lambda seed: policy, seeds=range(0, 20), task="reach")
    result.mean_return, result.success_rate, result.time_to_reach_s, result.episodes

Each seed is one episode of the task with that seed (reacher.make_env(task, seed)); the policy's
reset() is called before its first step, then act(observation) once per control step for the
1000 steps. A policy with a `frame_size` (a camera reflex) is shown the joints and the top-down
camera frame rendered at that size, never the target's position. The same policy and seeds give the same returns, bit for bit (the env is seeded, the
expert and the fast loop are deterministic, the random policy is seeded per episode).

Success (docs/reflex.md): the fingertip is within the reward tolerance (TOLERANCE_M = 0.06 m of the
target centre: reward 1) for the first time within REACH_DEADLINE_S = 2 s, and stays within it for
at least ON_TARGET_FRACTION = 80 % of the steps from then to the end of the episode. The same rule
serves reach and track (on track the target moves, so staying is the hard part).
time_to_reach_s = (index of the first rewarded step + 1) x 20 ms, i.e. the time at which the
fingertip is first on target; the aggregate is the mean over the episodes that reached at all
(null when none did), and `reached` says how many that was.

Held-out seeds: evaluation uses seeds S .. S+N-1 (eval-reflex --seed S, default 0); sim-demos
records from seed 100000 up (recorder.DEFAULT_SEED_BASE), so a policy is never scored on an episode
it was trained on unless asked to.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Iterable

import numpy as np

from hope_models.sim.expert import ExpertController, RandomPolicy
from hope_models.sim.reacher import CAMERA_KEY, CONTROL_PERIOD_S, EPISODE_STEPS, RENDER_STYLE, TASKS, make_env

REACH_DEADLINE_S = 2.0
ON_TARGET_FRACTION = 0.8


@dataclass
class EpisodeScore:
    seed: int
    ret: float
    success: bool
    time_to_reach_s: float | None
    on_target_after_reach: float  # fraction of steps on target from the first reach to the end (0 if never)

    def to_json_obj(self) -> dict[str, Any]:
        d = asdict(self)
        d["return"] = d.pop("ret")
        return d


@dataclass
class EvalResult:
    task: str
    policy: str
    episodes: list[EpisodeScore] = field(default_factory=list)

    @property
    def returns(self) -> list[float]:
        return [e.ret for e in self.episodes]

    @property
    def mean_return(self) -> float:
        return float(np.mean(self.returns)) if self.episodes else float("nan")

    @property
    def success_rate(self) -> float:
        return float(np.mean([e.success for e in self.episodes])) if self.episodes else float("nan")

    @property
    def reached(self) -> int:
        return sum(e.time_to_reach_s is not None for e in self.episodes)

    @property
    def time_to_reach_s(self) -> float | None:
        times = [e.time_to_reach_s for e in self.episodes if e.time_to_reach_s is not None]
        return float(np.mean(times)) if times else None

    def summary(self) -> dict[str, Any]:
        return {"task": self.task, "policy": self.policy, "mean_return": self.mean_return,
                "success_rate": self.success_rate, "time_to_reach_s": self.time_to_reach_s,
                "reached": self.reached, "episodes": len(self.episodes)}


def score_rewards(seed: int, rewards: np.ndarray) -> EpisodeScore:
    """Return, success and time to reach of one episode from its per-step rewards."""
    on = np.asarray(rewards) > 0.5
    ret = float(np.sum(rewards))
    hits = np.flatnonzero(on)
    if hits.size == 0:
        return EpisodeScore(seed, ret, False, None, 0.0)
    first = int(hits[0])
    t_reach = round((first + 1) * CONTROL_PERIOD_S, 6)
    frac = float(on[first:].mean())
    success = t_reach <= REACH_DEADLINE_S + 1e-9 and frac >= ON_TARGET_FRACTION
    return EpisodeScore(seed, ret, bool(success), t_reach, frac)


PolicyFactory = Callable[[int], Any]


def _policy_for(policy_factory: Any, seed: int):
    if hasattr(policy_factory, "act"):
        return policy_factory
    return policy_factory(seed)


TickHook = Callable[[int, dict, np.ndarray], None]


def run_episode(policy, task: str, seed: int, steps: int = EPISODE_STEPS, frames=None,
                episode: int = 0, target_jump_s: float | None = None, on_tick: TickHook | None = None) -> np.ndarray:
    """Per-step rewards of one closed-loop episode. `frames` (a hope_models.sim.frames.FrameStream)
    is shown the env after reset and after every step, and renders the frames it wants; the episode
    is the same with or without it (rendering does not touch the physics). `on_tick(step, observation,
    action)` sees every control step's observation and the action the policy answered to it (clipped
    to the range the env applies), before the env steps: what a model watching the robot would be
    sent (eval-reflex's Mid Loop surprise), without this module knowing any model. target_jump_s:
    reacher.make_env's target jump."""
    # A policy with a frame_size sees what a robot has: the joints and the camera, nothing else.
    frame_size = getattr(policy, "frame_size", None)
    env = make_env(task, seed, frames=frames is not None or frame_size is not None, target_jump_s=target_jump_s,
                   render_style=getattr(policy, "render_style", RENDER_STYLE))
    obs = env.reset()
    reset = getattr(policy, "reset", None)
    if reset is not None:
        reset()
    rewards = np.zeros(steps)
    ret = 0.0
    if frames is not None:
        frames.on_step(env, episode=episode, seed=seed, step=0, return_so_far=0.0, last=False)
    for t in range(steps):
        seen = obs if frame_size is None else {"robot_state": obs["robot_state"], CAMERA_KEY: env.render(frame_size)}
        action = np.asarray(policy.act(seen), dtype=np.float64)
        if not np.isfinite(action).all():
            raise ValueError(f"{task} seed {seed} step {t}: the policy gave a non-finite action {action.tolist()}")
        if on_tick is not None:
            on_tick(t, obs, np.clip(action, env.action_low, env.action_high))
        obs, rewards[t], done = env.step(action)
        ret += rewards[t]
        if frames is not None:
            frames.on_step(env, episode=episode, seed=seed, step=t + 1, return_so_far=ret,
                           last=done or t + 1 == steps)
        if done:
            break
    return rewards


def evaluate_policy(policy_factory: PolicyFactory | Any, seeds: Iterable[int], task: str = "reach",
                    name: str | None = None, steps: int = EPISODE_STEPS, frames=None,
                    target_jump_s: float | None = None, on_tick: TickHook | None = None) -> EvalResult:
    """Score a policy on each seed. `policy_factory` is a callable seed -> policy, or a policy
    (anything with act(observation) and optionally reset(), which is called per episode).
    `frames` (a hope_models.sim.frames.FrameStream) streams the first episode's frames and
    `on_tick` (run_episode's) sees the first episode's steps; target_jump_s applies to every episode."""
    if task not in TASKS:
        raise ValueError(f"task {task!r} is not one of {', '.join(TASKS)}")
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("seeds is empty: evaluate at least one episode")
    if steps < 1 or steps > EPISODE_STEPS:
        raise ValueError(f"steps={steps} must be within 1-{EPISODE_STEPS}")
    label = name
    out = EvalResult(task, "")
    for i, seed in enumerate(seeds):
        policy = _policy_for(policy_factory, seed)
        if label is None:
            label = str(getattr(policy, "version", None) or getattr(policy, "name", type(policy).__name__))
        first = i == 0
        rewards = run_episode(policy, task, seed, steps, frames=frames if first else None, episode=i,
                              target_jump_s=target_jump_s, on_tick=on_tick if first else None)
        out.episodes.append(score_rewards(seed, rewards))
    out.policy = label or ""
    return out


def expert_factory(seed: int):
    return ExpertController()


def random_factory(seed: int):
    return RandomPolicy(seed)


def json_number(v: float | None) -> float | None:
    """Rounded for printing; NaN becomes null (JSON has no NaN)."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return None
    return round(float(v), 4)
