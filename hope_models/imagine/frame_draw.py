"""Frames drawn from joints for imagined steps: the arm as a recorded frame showed it at the nearest
joints, over a scene (frame_goal.Scene: a target and the cells it changes).

    pool = ArmPool(arm, codes, joints, scene_cells, scene_codes)   # recorded frames, joints, their episodes' scenes
    pool.draw(joints, keep=scene_codes, where=scene_cells)   # [B, G] codes

Why not the arm model's own most probable codes: a grid tokenizer gives a thin arm crossing a cell a
code that depends on where exactly it crosses, so the model is unsure of each distal cell and its
most probable code there is the background: drawn that way, the far link of the reacher's arm went
missing (on a training play episode the drawing kept 38-55 % of the cells the real frames had off
the background). A recorded frame at nearly the same joints has them all.

What it assumes, in plain words: the arm's look is a function of the joints, and the recordings
(play) visited joints near every one an imagined step reaches. Each joint dimension is weighted by
how much the arm model's picture changes with it (a velocity, which does not move the arm in the
frame, weighs little); of the NEIGHBOURS nearest frames, the one whose arm changes the fewest of
its own episode's scene cells is drawn, and of it the cells off the background except those that
show its scene's own code (its target, not its arm).
"""
from __future__ import annotations

import numpy as np

from hope_models.imagine.frame_arm import ArmModel

NEIGHBOURS = 8
STEP = 0.05  # normalised joint units: the step each dimension's weight is measured over
SAMPLE = 512  # recorded joints the weights are measured at


def joint_weights(arm: ArmModel, joints: np.ndarray) -> np.ndarray:
    """[D]: the mean change of the arm model's P(off background) map per unit of each joint dimension."""
    q = joints[np.linspace(0, len(joints) - 1, min(SAMPLE, len(joints))).round().astype(int)].astype(np.float32)
    base = arm.off_background(q)
    out = []
    for d in range(q.shape[1]):
        moved = q.copy()
        moved[:, d] += STEP
        out.append(float(np.abs(arm.off_background(moved) - base).sum(1).mean()) / STEP)
    w = np.asarray(out)
    return w / max(float(w.max()), 1e-12)


class ArmPool:
    def __init__(self, arm: ArmModel, codes: np.ndarray, joints: np.ndarray, scene_cells: np.ndarray,
                 scene_codes: np.ndarray):
        """Recorded frames' codes [N, G], joints [N, D], and their episodes' scenes: cells [N, G], codes [N, G]."""
        self.background = arm.background
        self.weights = joint_weights(arm, joints)
        self.codes, self.joints = codes, joints.astype(np.float32) * self.weights.astype(np.float32)
        self.arm_cells = (codes != self.background) & ~(scene_cells & (codes == scene_codes))
        self.overlap = (scene_cells & (codes != scene_codes)).sum(1)  # the arm inside its own scene's cells

    def nearest(self, joints: np.ndarray, chunk: int = 64) -> np.ndarray:
        """Joints [B, D] -> the index of the recorded frame each is drawn from [B] (module doc)."""
        q = joints.astype(np.float32) * self.weights.astype(np.float32)
        out = []
        for s in range(0, len(q), chunk):
            d = ((q[s:s + chunk, None, :] - self.joints[None]) ** 2).sum(-1)  # [b, N]
            k = min(NEIGHBOURS, d.shape[1])
            near = np.argpartition(d, k - 1, axis=1)[:, :k]
            near = np.take_along_axis(near, np.argsort(np.take_along_axis(d, near, 1), axis=1, kind="stable"), 1)
            pick = np.argmin(self.overlap[near], axis=1)  # the first (nearest) of the least overlapping
            out.append(near[np.arange(len(near)), pick])
        return np.concatenate(out) if out else np.zeros(0, np.int64)

    def draw(self, joints: np.ndarray, keep: np.ndarray, where: np.ndarray) -> np.ndarray:
        """Codes [B, G] of frames showing the arm at joints [B, D]: the background, `keep` [B, G] where
        `where` [B, G] is set (a scene's target cells), and the nearest recorded arm over both."""
        n = self.nearest(joints)
        out = np.where(where, keep, self.background[None]).astype(np.int64)
        return np.where(self.arm_cells[n], self.codes[n], out)


__all__ = ["ArmPool", "NEIGHBOURS", "joint_weights"]
