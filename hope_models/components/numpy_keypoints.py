"""CodeKeypoints (components/code_keypoints.py) in NumPy: a grid VQ-VAE's cell codes -> learned
keypoints -> the Fast Loop's embedding, for the torch-free runtime.

    kp = KeypointsNumpy(tensors, "keypoints", grid=(16, 16), out=centred)   # at load
    kp(codes)                    # codes [..., G] (cell-local ints) -> [..., d]

Per keypoint c: w = softmax over the cells of score[code]; where = sum_cells w * cell centre (x, y);
there = logsumexp_cells(score) - log G; out = Linear(3C -> d) of
[where_0x, where_0y, ..., where_Cx, where_Cy, there_0, ..., there_C] (torch's order). `out` may be
given in another form (the Fast Loop's flat path centres it: numpy_form._prepare_flat). float32
throughout. Torch-free.
"""
from __future__ import annotations

import math

import numpy as np


def cell_centres(grid: tuple[int, int]) -> np.ndarray:
    """[h * w, 2] (x, y) of each cell's centre in [-1, 1], row-major (code_keypoints.cell_centres)."""
    h, w = grid
    ys = (np.arange(h, dtype=np.float32) + np.float32(0.5)) / np.float32(h) * np.float32(2) - np.float32(1)
    xs = (np.arange(w, dtype=np.float32) + np.float32(0.5)) / np.float32(w) * np.float32(2) - np.float32(1)
    yy, xx = np.meshgrid(ys, xs, indexing="ij")
    return np.stack([xx.reshape(-1), yy.reshape(-1)], -1).astype(np.float32)


class KeypointsNumpy:
    """One CodeKeypoints' arithmetic (its tensors under `prefix`). Immutable."""

    def __init__(self, tensors: dict[str, np.ndarray], prefix: str, grid: tuple[int, int]):
        score = tensors[f"{prefix}.score.weight"]
        self.n_codes, self.keypoints = score.shape
        self.cells = int(grid[0]) * int(grid[1])
        c = self.keypoints
        self._score = np.ascontiguousarray(score, dtype=np.float32)  # [n, C]
        self._centres = cell_centres(grid)  # [G, 2]
        self._log_g = np.float32(math.log(self.cells))
        self._c = c
        self.w_t = np.ascontiguousarray(tensors[f"{prefix}.out.weight"].T)  # [3C, d]
        self.b = tensors[f"{prefix}.out.bias"]

    def features(self, codes: np.ndarray) -> np.ndarray:
        """codes [..., G] -> the 3C values out() reads: where (x, y per keypoint) then there."""
        c = self._c
        s = self._score[codes]  # [..., G, C]
        top = s.max(-2, keepdims=True)  # [..., 1, C]
        e = np.exp(s - top)
        total = e.sum(-2, keepdims=True)
        w = e / total  # [..., G, C]: softmax over the cells
        wt = np.swapaxes(w, -1, -2)  # [..., C, G]
        where = wt @ self._centres  # [..., C, 2]
        there = np.log(total[..., 0, :]) + top[..., 0, :] - self._log_g  # [..., C]
        return np.concatenate([where.reshape(*where.shape[:-2], 2 * c), there], -1)

    def __call__(self, codes: np.ndarray, w_t: np.ndarray | None = None, b: np.ndarray | None = None) -> np.ndarray:
        """codes [..., G] -> out(features) [..., d]; w_t, b: another form of out (e.g. centred)."""
        y = self.features(codes).dot(self.w_t if w_t is None else w_t)
        y += self.b if b is None else b
        return y


__all__ = ["KeypointsNumpy", "cell_centres"]
