"""The SSM stack's configuration and the timescale rule every SSM layer keeps, torch-free (the
configs of fast_loop and mid_loop check it before a layer is built)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SSMConfig:
    d_model: int = 128
    d_state: int = 64
    n_layers: int = 2
    mlp_ratio: int = 2  # gated MLP hidden width = mlp_ratio * d_model
    min_timescale: float = 1.0  # initial decay timescales (in grid steps), log-spaced over the state
    max_timescale: float = 64.0
    chunk: int = 64  # longest stretch the parallel form handles with one kernel


def check_timescales(lo: float, hi: float) -> None:
    # the SSM layers' own rule, here too so that a request is refused before a layer is built
    if not 0 < lo <= hi:
        raise ValueError(f"min_timescale={lo} and max_timescale={hi} must satisfy 0 < min <= max")
