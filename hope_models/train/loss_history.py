"""The loss curve a checkpoint carries for the convergence summary, bounded in size."""
from __future__ import annotations

from typing import Any


class LossHistory:
    """The losses the convergence summary needs, small enough to ride in every checkpoint: the
    first `head` steps, the last `tail` steps, and one point every `stride` steps in between (the
    stride doubles whenever the curve passes max_points, so a week-long job stays a few KB)."""

    def __init__(self, stride: int, head: int = 10, tail: int = 10, max_points: int = 2048):
        self.stride, self.head, self.tail, self.max_points = max(1, stride), head, tail, max_points
        self.points: list[tuple[int, float]] = []

    def add(self, step: int, loss: float) -> None:
        self.points.append((step, loss))
        if len(self.points) > self.tail:
            s = self.points[-self.tail - 1][0]
            if s > self.head and s % self.stride:
                del self.points[-self.tail - 1]
        if len(self.points) > self.max_points:
            self.stride *= 2
            keep_from = len(self.points) - self.tail
            self.points = [p for i, p in enumerate(self.points)
                           if p[0] <= self.head or p[0] % self.stride == 0 or i >= keep_from]

    def first(self) -> float | None:
        return self.points[0][1] if self.points else None

    def last(self) -> float | None:
        return self.points[-1][1] if self.points else None

    def to_json_obj(self) -> dict[str, Any]:
        return {"stride": self.stride, "points": [[s, v] for s, v in self.points]}

    @classmethod
    def from_json_obj(cls, obj: dict[str, Any]) -> "LossHistory":
        h = cls(int(obj["stride"]))
        h.points = [(int(s), float(v)) for s, v in obj["points"]]
        return h
