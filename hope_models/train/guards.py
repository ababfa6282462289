"""The memory guard: the training process's RSS against its job's budget, checked between steps.

A job has a memory budget (default 3 GiB, Settings.memory_budget_mb). The loop calls check()
between steps; once RSS reaches the soft limit (soft_fraction x budget) the loop checkpoints and
stops with outcome "paused_memory", so the job pauses with a clear reason and resumes later,
instead of growing into the OS OOM killer. RSS is what the daemon compares with the budget too.

No torch here: the guard is imported by processes that never hold a model.
"""
from __future__ import annotations

import math
import resource
import sys
from dataclasses import dataclass
from typing import Callable

import psutil

MB = 1024 * 1024


def validate_budget_mb(budget_mb, name: str = "memory budget") -> float:
    """A budget in MB must be a positive finite number; the error names the parameter."""
    if isinstance(budget_mb, bool) or not isinstance(budget_mb, (int, float)) \
            or not math.isfinite(budget_mb) or budget_mb <= 0:
        raise ValueError(f"{name} (memory_budget_mb) = {budget_mb!r} must be a positive number of MB")
    return float(budget_mb)


@dataclass(frozen=True)
class MemoryVerdict:
    rss_mb: float  # resident set size now
    peak_mb: float  # highest RSS seen (with the default rss_fn also the kernel's high-water mark)
    over_soft: bool  # True: checkpoint and pause for memory
    message: str


def _process_rss_bytes() -> int:
    return psutil.Process().memory_info().rss


def _high_water_bytes() -> int:
    """The kernel's peak RSS of this process (VmHWM): catches a spike between two checks."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak if sys.platform == "darwin" else peak * 1024  # Linux reports KiB, macOS bytes


class MemoryGuard:
    """check() -> MemoryVerdict. rss_fn() returns bytes (default: this process's RSS via psutil)."""

    def __init__(self, budget_mb: float, soft_fraction: float = 0.9,
                 rss_fn: Callable[[], int] | None = None):
        self.budget_mb = validate_budget_mb(budget_mb)
        if isinstance(soft_fraction, bool) or not isinstance(soft_fraction, (int, float)) \
                or not 0 < soft_fraction <= 1:
            raise ValueError(f"soft_fraction = {soft_fraction!r} must be a number in (0, 1]")
        self.soft_fraction = float(soft_fraction)
        self.soft_limit_mb = self.budget_mb * self.soft_fraction
        self._rss_fn = rss_fn or _process_rss_bytes
        self._own_process = rss_fn is None
        self.peak_mb = 0.0

    def check(self) -> MemoryVerdict:
        rss_mb = self._rss_fn() / MB
        peak = max(self.peak_mb, rss_mb)
        if self._own_process:
            peak = max(peak, _high_water_bytes() / MB)
        self.peak_mb = peak
        over = rss_mb >= self.soft_limit_mb
        limits = (f"the soft limit of {self.soft_limit_mb:.0f} MB "
                  f"({self.soft_fraction:.0%} of the {self.budget_mb:.0f} MB memory budget)")
        if over:
            message = (f"RSS {rss_mb:.0f} MB reached {limits}: checkpointing and pausing for memory. "
                       f"Re-run the same command to resume, or raise the budget "
                       f"(--memory-budget-mb / HOPE_MEMORY_BUDGET_MB) or lower --batch-size.")
        else:
            message = f"RSS {rss_mb:.0f} MB (peak {peak:.0f} MB) is under {limits}"
        return MemoryVerdict(rss_mb=rss_mb, peak_mb=peak, over_soft=over, message=message)
