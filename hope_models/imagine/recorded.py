"""Recorded episodes as the world model sees them, and the goal they show: the imagination's only
contact with the robot's world (no simulator: this package never imports hope_models.sim).

    eps = read_recorded(["D/demos", "D/play"], spec)   # normalised with the checkpoint's statistics
    goal = Goal.from_rewarded(eps)                       # where the demos were rewarded
    hist_obs, hist_act, mask = grid_history(ep, step, k=20, grid_s=0.1)

Start states: any step of a recorded episode, with the K grid points of real history before it
(zero-order hold, as the data layer's windows: hope_models/data/windows.py), so the Mid Loop's
context at the start is exactly what it saw in training.

Goal: a diagonal Gaussian over the normalised observation, fitted on the steps the demos were
rewarded on (their `reward` > 0). The planner's cost is the Mahalanobis distance to its mean. The
dims that are all but constant on the target get the weight (on the reacher: the target offset
~0 and the joint velocities ~0), the dims that vary there (where the arm is) none: which is which
is read off the data, not written in the code.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from hope_models.data.cameras import read_camera
from hope_models.data.dataset_cache import is_play_episode
from hope_models.data.extract import EpisodeMismatch, group_matrix
from hope_models.data.features import FeatureSpec
from hope_models.rlds.discover import iter_reports

GOAL_STD_FLOOR = 0.1  # normalised units: no dim weighs more than 1 / floor^2 (a constant dim would be infinite)


@dataclass
class Recorded:
    episode_id: str
    metadata: dict[str, Any]
    obs: np.ndarray  # [T, D] float32, normalised with the checkpoint's spec
    act: np.ndarray  # [T, A] float32, normalised
    reward: np.ndarray  # [T] float64
    t: np.ndarray  # [T] float64, seconds since the first step
    play: bool
    codes: np.ndarray | None = None  # [T, G] int64: a camera's frames as the world model's tokenizer reads them


def _normalise(x: np.ndarray, mean, std) -> np.ndarray:
    return ((x - np.asarray(mean)) / np.asarray(std)).astype(np.float32)


def read_recorded(paths: Sequence[str | Path], spec: FeatureSpec,
                  encode: Callable[[np.ndarray], np.ndarray] | None = None) -> list[Recorded]:
    """Every non-imagined episode under paths, in the checkpoint's feature spec (a missing field
    raises: the world model cannot read an episode it has no observation for). encode: frames
    [n, H, W, 3] uint8 -> codes [n, G], for a world model that reads the spec's camera (spec.frame)."""
    out = []
    for path in paths:
        if not Path(path).exists():
            raise FileNotFoundError(f"{path}: no such file or directory")
    for report in iter_reports(paths):
        for ep in report.episodes:
            if ep.is_imagined or not ep.steps:
                continue  # start states and goals come from what was recorded, never from imaginations
            ts = [s.timestamp_ns for s in ep.steps]
            if any(v is None for v in ts):
                raise ValueError(f"{ep.episode_id}: steps without timestamp_ns; imagination needs the clock")
            t = (np.asarray(ts, dtype=np.float64) - ts[0]) / 1e9
            out.append(Recorded(
                ep.episode_id, ep.metadata,
                _normalise(group_matrix(ep.steps, spec.observation), spec.observation.mean, spec.observation.std),
                _normalise(group_matrix(ep.steps, spec.action), spec.action.mean, spec.action.std),
                np.asarray([float(s.reward or 0.0) for s in ep.steps]), t, is_play_episode(ep.metadata, ep.steps),
                None if encode is None else _codes(ep, spec, encode)))
    if not out:
        raise ValueError(f"no recorded episode under {', '.join(map(str, paths))}")
    return out


def _codes(ep, spec: FeatureSpec, encode: Callable[[np.ndarray], np.ndarray], chunk: int = 256) -> np.ndarray:
    """Every step's frame of the spec's camera, encoded chunk by chunk (an episode's frames are never all held)."""
    if spec.frame is None:
        raise ValueError("the world model reads a camera, but its feature spec names none")
    out, buf = [], []
    try:
        for img in read_camera(ep.steps, spec.frame, ep.blob_root):
            buf.append(img)
            if len(buf) == chunk:
                out.append(encode(np.stack(buf)))
                buf = []
    except EpisodeMismatch as exc:
        raise ValueError(f"{ep.episode_id}: {exc}") from None
    if buf:
        out.append(encode(np.stack(buf)))
    return np.concatenate(out).astype(np.int64)


def control_period_s(eps: Sequence[Recorded]) -> float:
    """The recordings' control period: the median step interval (20 ms on the reacher)."""
    dts = np.concatenate([np.diff(e.t) for e in eps if len(e.t) > 1])
    if dts.size == 0:
        raise ValueError("the recorded episodes have one step each: no control period to imagine at")
    return round(float(np.median(dts)), 9)  # the clock is in ns: no float dust in the metadata


def grid_points(ep: Recorded, step: int, k: int, grid_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The steps [K] held at the K grid points ending at `step` (grid_history), and the mask [K] of
    the points inside the episode."""
    times = ep.t[step] - np.arange(k - 1, -1, -1) * grid_s
    mask = times >= -1e-9
    return np.clip(np.searchsorted(ep.t, times + 1e-9, side="right") - 1, 0, step), mask


def grid_history(ep: Recorded, step: int, k: int, grid_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The K-point window ending at `step` on a grid of grid_s (each point holds the latest step at
    or before its time; points before the episode are masked and zero): obs [K, D], act [K, A], mask [K]."""
    j, mask = grid_points(ep, step, k, grid_s)
    obs, act = ep.obs[j].copy(), ep.act[j].copy()
    obs[~mask] = 0.0
    act[~mask] = 0.0
    return obs, act, mask


@dataclass
class Goal:
    mean: np.ndarray  # [D] normalised
    weight: np.ndarray  # [D] 1 / (std^2 + floor^2), scaled to a maximum of 1
    steps: int  # rewarded steps it was fitted on

    @classmethod
    def from_rewarded(cls, eps: Sequence[Recorded], floor: float = GOAL_STD_FLOOR) -> "Goal":
        rows = [e.obs[e.reward > 0] for e in eps if not e.play]
        rows = [r for r in rows if len(r)]
        if not rows:
            raise ValueError("no rewarded step in the demos: the goal is taken from where they were rewarded")
        x = np.concatenate(rows).astype(np.float64)
        w = 1.0 / (x.var(0) + floor ** 2)
        return cls(x.mean(0), w / w.max(), int(x.shape[0]))

    def distance(self, obs):
        """[..., D] normalised (torch) -> the goal's Mahalanobis distance [...] (the planner's cost)."""
        import torch  # lazy: this module stays importable without torch

        mean, w = torch.as_tensor(self.mean, dtype=torch.float32), torch.as_tensor(self.weight, dtype=torch.float32)
        return (((obs - mean) ** 2) * w).sum(-1).sqrt()

    def to_json_obj(self, names: Sequence[str] = ()) -> dict[str, Any]:
        return {"rewarded_steps": self.steps, "dims": list(names),
                "mean": [round(float(v), 4) for v in self.mean], "weight": [round(float(v), 4) for v in self.weight]}
