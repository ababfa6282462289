"""CodeKeypoints (components/code_keypoints.py) in NumPy: a grid VQ-VAE's cell codes -> learned
keypoints -> the Fast Loop's embedding, for the torch-free runtime.

    kp = KeypointsNumpy(tensors, "keypoints", grid=(16, 16), out=centred)   # at load
    kp(codes)                    # codes [..., G] (cell-local ints) -> [..., d]

Per keypoint c: w = softmax over the cells of score[code]; where = sum_cells w * cell centre (x, y);
there = logsumexp_cells(score) - log G; out = Linear(3C -> d) of
[where_0x, where_0y, ..., where_Cx, where_Cy, there_0, ..., there_C] (torch's order), and with a
view joint, (where - pivot) turned by -angle then by +angle (4C more: code_keypoints.turned). The
scores are used times `gain` (code_keypoints.READER_GAIN for reader "frames"). `out` may be
given in another form (the Fast Loop's flat path centres it: numpy_form._prepare_flat). float32
throughout. Torch-free.
"""
from __future__ import annotations

import math

import numpy as np

# code_keypoints.READER_GAIN: a "frames" reader's scores are used times this (why: code_keypoints.py)
READER_GAIN = 10.0


def keypoint_gain(model_config: dict) -> float:
    """The gain a Fast Loop's keypoint scores are used with, from its (stored) model_config."""
    return READER_GAIN if model_config["keypoint_reader"] == "frames" else 1.0


def cell_centres(grid: tuple[int, int]) -> np.ndarray:
    """[h * w, 2] (x, y) of each cell's centre in [-1, 1], row-major (code_keypoints.cell_centres)."""
    h, w = grid
    ys = (np.arange(h, dtype=np.float32) + np.float32(0.5)) / np.float32(h) * np.float32(2) - np.float32(1)
    xs = (np.arange(w, dtype=np.float32) + np.float32(0.5)) / np.float32(w) * np.float32(2) - np.float32(1)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return np.stack([xx.reshape(-1), yy.reshape(-1)], -1).astype(np.float32)


class KeypointsNumpy:
    """One CodeKeypoints' arithmetic (its tensors under `prefix`). Immutable."""

    def __init__(self, tensors: dict[str, np.ndarray], prefix: str, grid: tuple[int, int], gain: float = 1.0):
        score = tensors[f"{prefix}.score.weight"] * np.float32(gain)
        self.n_codes, self.keypoints = score.shape
        self.cells = int(grid[0]) * int(grid[1])
        c = self.keypoints
        self._score = np.ascontiguousarray(score, dtype=np.float32)  # [n, C]
        self._centres = cell_centres(grid)  # [G, 2]
        self._log_g = np.float32(math.log(self.cells))
        self._c = c
        self.w_t = np.ascontiguousarray(tensors[f"{prefix}.out.weight"].T)  # [3C or 7C, d]
        self.b = tensors[f"{prefix}.out.bias"]
        pivot = tensors.get(f"{prefix}.view.pivot")
        self.pivot = None if pivot is None else np.asarray(pivot, np.float32)  # present: it reads an angle

    def features(self, codes: np.ndarray, angle: np.ndarray | None = None) -> np.ndarray:
        """codes [..., G] (angle [...] radians, with a view joint) -> the values out() reads: where
        (x, y per keypoint), there, then where turned into the joint's frame both ways."""
        c = self._c
        s = self._score[codes]  # [..., G, C]
        top = s.max(-2, keepdims=True)  # [..., 1, C]
        e = np.exp(s - top)
        total = e.sum(-2, keepdims=True)
        w = e / total  # [..., G, C]: softmax over the cells
        wt = np.swapaxes(w, -1, -2)  # [..., C, G]
        where = wt @ self._centres  # [..., C, 2]
        there = np.log(total[..., 0, :]) + top[..., 0, :] - self._log_g  # [..., C]
        parts = [where.reshape(*where.shape[:-2], 2 * c), there]
        if self.pivot is not None:
            if angle is None:
                raise ValueError("these keypoints are also read in a joint's frame: pass the joint angle")
            r = where - self.pivot
            cos = np.cos(np.asarray(angle, np.float32))[..., None]
            sin = np.sin(np.asarray(angle, np.float32))[..., None]
            x, y = r[..., 0], r[..., 1]
            parts += [np.stack([cos * x + sin * y, cos * y - sin * x], -1).reshape(*r.shape[:-2], 2 * c),
                      np.stack([cos * x - sin * y, cos * y + sin * x], -1).reshape(*r.shape[:-2], 2 * c)]
        return np.concatenate(parts, -1).astype(np.float32, copy=False)

    def __call__(self, codes: np.ndarray, w_t: np.ndarray | None = None, b: np.ndarray | None = None,
                 angle: np.ndarray | None = None) -> np.ndarray:
        """codes [..., G] -> out(features) [..., d]; w_t, b: another form of out (e.g. centred)."""
        y = self.features(codes, angle).dot(self.w_t if w_t is None else w_t)
        y += self.b if b is None else b
        return y


__all__ = ["READER_GAIN", "KeypointsNumpy", "cell_centres", "keypoint_gain"]
