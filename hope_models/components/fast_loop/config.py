"""The Fast Loop's configuration, apart from its model so that it imports no torch."""
from __future__ import annotations

from dataclasses import dataclass

from hope_models.components.ssm_config import check_timescales


@dataclass
class FastLoopConfig:
    obs_dim: int = 0
    act_dim: int = 0
    window_k: int = 5  # grid points the policy sees: the training window's K (set from the window spec)
    d_model: int = 128
    d_state: int = 256  # one SSM layer, so a wide state
    mlp_ratio: int = 2  # encoder / head gated MLP hidden width = mlp_ratio * d_model
    min_timescale: float = 1.0  # grid steps (20 ms each in the default window)
    max_timescale: float = 16.0
    n_codes: int = 0  # codebook size of the frozen VQ-VAE whose codes are inputs; 0 = none
    keypoints: int = 16  # a grid VQ-VAE's codes are read as this many learned keypoints (code_keypoints.py)

    def validate(self) -> None:
        if self.obs_dim < 1 or self.act_dim < 1:
            raise ValueError(f"obs_dim={self.obs_dim} and act_dim={self.act_dim} must be >= 1")
        if self.window_k < 1:
            raise ValueError(f"window_k={self.window_k} must be >= 1")
        if self.d_model < 1 or self.d_state < 1 or self.mlp_ratio < 1:
            raise ValueError("d_model, d_state and mlp_ratio must be >= 1")
        if self.keypoints < 1:
            raise ValueError(f"keypoints={self.keypoints} must be >= 1")
        check_timescales(self.min_timescale, self.max_timescale)
