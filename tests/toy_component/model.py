"""The toy's torch model: one linear layer from the observation to the action."""
from __future__ import annotations

import torch
from torch import nn

from hope_models.components.toy.config import ToyConfig


class Toy(nn.Module):
    wants_frames = False

    def __init__(self, cfg: ToyConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.out = nn.Linear(cfg.obs_dim, cfg.act_dim)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.out(obs)
