"""OpenMP's waiting threads sleep instead of spinning, in every process that may train with torch.

torch's CPU kernels run on an OpenMP team; between parallel regions libgomp's idle threads spin
for a while by default. With a 2-thread job and any other busy process on 2 cores (the robot's own
work, an evaluation, a second job), one team thread is descheduled while its partner spins at the
barrier in the core it needs: the grid VQ-VAE (2 threads) fell from ~9.7 to 0.4-1.0 steps/s beside
other work, and held 1.8-2.1 steps/s under the same load with passive waits (2026-12-07, docs/
benchmarks.md). libgomp reads the setting once, when torch loads it, so it is set in the processes
that start the training children and never import torch themselves: the command line and the
worker parent. A value the user exported wins.
"""
from __future__ import annotations

import os
from typing import MutableMapping

WAIT_POLICY = "OMP_WAIT_POLICY"


def passive_waits(environ: MutableMapping[str, str] = os.environ) -> str:
    """Set OMP_WAIT_POLICY=PASSIVE unless it is set; the value in force."""
    return environ.setdefault(WAIT_POLICY, "PASSIVE")
