"""The camera side of imagining from a camera world model (a grid mid_loop's wm_* heads predict the
joints; nothing predicts a frame): each imagined step's cell codes are drawn from the joints, and the
planner's goal is the start episode's target.

    scene = CameraScene(goal, eps, starts, k=20, grid_s=0.1)
    scene.history_codes          # [B, K, G] the start windows' recorded codes (the Mid Loop's context)
    scene.goal                   # goal.bind(the start episodes' targets): the planner's cost
    scene.draw(joints)           # [B, G] codes of the frames the joints [B, D] make
    scene.bounds                 # (low, high) [D]: the recorded joints' range, which a predicted step is kept in

A drawn frame is the start episode's scene (its target's cells and their codes, frame_goal.Scene) over
the background, with the arm where the joints put it: the arm of the recorded frame at the nearest
joints (frame_draw.ArmPool). In codes (the Mid Loop's context) the arm is drawn over the scene. A
written frame is composed in pixels (write.py): the arm layer decoded, and over it the pixels where
the decoded scene differs from the decoded background (the target in front of the arm, as the
recordings show it; composing in codes let the cells around the arm, which a grid tokenizer also
changes, blot the target out). The codes are decoded into pixels by the tokenizer's frozen decoder when an
episode is written (write.py), so a Fast Loop reading frames re-encodes what it would have seen.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from hope_models.imagine.frame_goal import FrameGoal
from hope_models.imagine.recorded import Recorded, grid_points


class CameraScene:
    def __init__(self, goal: FrameGoal, eps: Sequence[Recorded], starts: list[tuple[int, int]], k: int, grid_s: float):
        missing = [eps[e].episode_id for e, _ in starts if goal.targets[e] is None]
        if missing:
            raise ValueError(f"{missing[0]}: no target located in its frames (nothing the arm model does not "
                             f"explain); {len(missing)} start state(s) affected")
        windows = [grid_points(eps[e], s, k, grid_s) for e, s in starts]
        codes = []
        for (e, _), (j, mask) in zip(starts, windows, strict=True):
            c = _codes_of(eps[e])[j].copy()
            c[~mask] = 0
            codes.append(c)
        self.history_codes = np.stack(codes)
        self.scene_codes = np.stack([goal.scenes[e].codes for e, _ in starts])
        self.scene_cells = np.stack([goal.scenes[e].cells for e, _ in starts])
        self.targets = np.stack([t for t in (goal.targets[e] for e, _ in starts) if t is not None])
        self.goal = goal.bind(self.targets)
        self._pool = goal.pool
        # The joints an imagined step may reach: the range recorded (normalised). Left free, a predicted
        # wrap of a joint that turns without end (+-pi) can go the wrong way, and the world model then
        # reads joints it never saw: 2 of 50 reacher rollouts ran off to |shoulder| > 10^4 rad
        every = np.concatenate([e.obs for e in eps])
        self.bounds = (every.min(0), every.max(0))

    def draw(self, joints: np.ndarray) -> np.ndarray:
        """Joints [B, D] (normalised) -> the codes [B, G] of the frames they make in each start's scene
        (the arm over the scene: what the Mid Loop's context reads)."""
        return self._pool.draw(joints, keep=self.scene_codes, where=self.scene_cells)

    def arm(self, joints: np.ndarray) -> np.ndarray:
        """Joints [B, D] -> the arm alone over the background [B, G]: the layer a written frame's arm comes
        from (write.py lays the scene's target over it in pixels)."""
        return self._pool.draw(joints, keep=self._pool.background, where=np.zeros(self.scene_cells.shape, bool))

    def layers(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Start i's scene layer (its target's cells and codes over the background) and the background [G]."""
        bg = self._pool.background
        return np.where(self.scene_cells[i], self.scene_codes[i], bg), bg


def _codes_of(ep: Recorded) -> np.ndarray:
    if ep.codes is None:
        raise ValueError(f"{ep.episode_id}: read without its frames; a camera world model needs them")
    return ep.codes


__all__ = ["CameraScene"]
