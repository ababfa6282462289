"""Per-dimension normalisation statistics merged episode by episode, in flat memory."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hope_models.data.features import FeatureSpecError


@dataclass
class RunningStats:
    """Per-dimension mean/variance merged episode by episode (Chan et al.), in float64."""

    dim: int
    count: int = 0
    mean: np.ndarray | None = None
    m2: np.ndarray | None = None

    def add(self, x: np.ndarray) -> None:
        n = x.shape[0]
        if n == 0:
            return
        mu = x.mean(axis=0, dtype=np.float64)
        m2 = ((x - mu) ** 2).sum(axis=0, dtype=np.float64)
        if self.count == 0:
            self.count, self.mean, self.m2 = n, mu, m2
            return
        total = self.count + n
        delta = mu - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + m2 + delta ** 2 * (self.count * n / total)
        self.count = total

    def result(self, std_floor: float) -> tuple[list[float], list[float]]:
        if self.count == 0:
            raise FeatureSpecError("no steps to compute normalisation statistics from")
        std = np.sqrt(self.m2 / self.count)
        return [float(v) for v in self.mean], [float(v) for v in np.maximum(std, std_floor)]
