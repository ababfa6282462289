"""The toy's configuration (torch-free)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class ToyConfig:
    obs_dim: int = 0
    act_dim: int = 0

    def validate(self) -> None:
        if self.obs_dim < 1 or self.act_dim < 1:
            raise ValueError(f"obs_dim={self.obs_dim} and act_dim={self.act_dim} must be >= 1")
