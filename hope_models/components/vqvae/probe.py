"""A linear probe of the VQ-VAE's codes: can a position (the reacher's target, its fingertip) be read
back from a frame's codes by a linear map? Fitted on the training episodes' codes, scored on held-out
episodes' codes, in centimetres. NumPy only (no torch): the codes come in as integers.

Features: the codes alone, each cell's (group's) code one-hot, i.e. the probe is a table of one
2-d offset per (group, code), summed over the groups. It is fitted as ridge regression in its dual
form (the kernel of two frames = how many groups have the same code, at most a few thousand
frames), which needs no [N, G x n_codes] matrix. The ridge strength is picked on the training
episodes alone (the last fifth of them held back), then the probe is refitted on all of them.

    probe = fit_probe(train_codes, train_xy, train_episode)   # codes [N, G] int, xy [N, k] metres
    err_cm = probe.error_cm(test_codes, test_xy)               # mean Euclidean error per 2-d point
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LAMBDAS = (0.1, 1.0, 10.0, 100.0)  # ridge strengths tried, in units of a group's kernel weight
MAX_FIT = 4000  # frames the dual form fits on (its kernel is MAX_FIT^2 floats)


def _kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[Na, G] x [Nb, G] codes -> [Na, Nb]: how many groups agree (the one-hot features' dot product)."""
    k = np.zeros((a.shape[0], b.shape[0]), np.int32)  # counts: integer adds, a quarter of float64's time
    for g in range(a.shape[1]):
        k += a[:, g, None] == b[None, :, g]
    return k.astype(np.float64)


@dataclass
class Probe:
    codes: np.ndarray  # [n, G] the frames it was fitted on
    alpha: np.ndarray  # [n, k] dual coefficients
    mean: np.ndarray  # [k] the targets' mean (the intercept)
    lam: float

    def predict(self, codes: np.ndarray) -> np.ndarray:
        return self.mean + _kernel(np.asarray(codes), self.codes) @ self.alpha

    def error_cm(self, codes: np.ndarray, xy: np.ndarray) -> float:
        """Mean Euclidean error (cm) of the predicted 2-d positions; xy [N, 2] in metres."""
        return distance_cm(self.predict(codes), xy)


def distance_cm(pred: np.ndarray, xy: np.ndarray) -> float:
    return float(100.0 * np.linalg.norm(np.asarray(pred) - np.asarray(xy), axis=-1).mean())


def _fit(codes: np.ndarray, y: np.ndarray, lam: float, k: np.ndarray | None = None) -> Probe:
    """k: the kernel of codes with itself, if already computed (it does not depend on lam)."""
    mean = y.mean(0)
    k = _kernel(codes, codes) if k is None else k
    alpha = np.linalg.solve(k + lam * np.eye(len(codes)), y - mean)
    return Probe(codes, alpha, mean, lam)


def _subsample(n: int, at_most: int, rng: np.random.Generator) -> np.ndarray:
    return np.sort(rng.choice(n, at_most, replace=False)) if n > at_most else np.arange(n)


def fit_probe(codes: np.ndarray, xy: np.ndarray, episode: np.ndarray, seed: int = 0,
              max_fit: int = MAX_FIT) -> Probe:
    """Ridge from one-hot codes [N, G] to positions xy [N, 2] (metres); episode [N]: which episode each
    frame is from (the strength is chosen on whole held-back episodes, never on frames of a fitted one)."""
    codes, xy, episode = np.asarray(codes), np.asarray(xy, np.float64), np.asarray(episode)
    if codes.ndim != 2 or xy.ndim != 2 or len(codes) != len(xy) or len(episode) != len(codes):
        raise ValueError(f"codes [N, G], xy [N, k], episode [N] must agree, got {codes.shape}, {xy.shape}, "
                         f"{episode.shape}")
    eps = np.unique(episode)
    if len(eps) < 2:
        raise ValueError("fit_probe needs frames of at least 2 episodes (one to choose the strength on)")
    rng = np.random.default_rng(seed)
    back = np.isin(episode, eps[len(eps) - max(1, len(eps) // 5):])
    fit_i = np.flatnonzero(~back)[_subsample(int((~back).sum()), max_fit, rng)]
    val_i = np.flatnonzero(back)[_subsample(int(back.sum()), max_fit, rng)]
    g = codes.shape[1]
    k_fit, k_val = _kernel(codes[fit_i], codes[fit_i]), _kernel(codes[val_i], codes[fit_i])
    scores = {}
    for lam in LAMBDAS:
        probe = _fit(codes[fit_i], xy[fit_i], lam * g, k_fit)
        scores[lam] = distance_cm(probe.mean + k_val @ probe.alpha, xy[val_i])
    best = min(scores, key=lambda lam: scores[lam])
    every = _subsample(len(codes), max_fit, rng)
    return _fit(codes[every], xy[every], best * g)
