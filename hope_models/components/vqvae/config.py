"""The VQ-VAE's configuration, apart from its model so that it imports no torch: the webapp, the
daemon and the CLI check a run request's model_config and estimate its memory before any process
imports torch."""
from __future__ import annotations

from dataclasses import dataclass

INPUTS = ("vector", "frame")  # what a VQ-VAE reads


@dataclass
class VQVAEConfig:
    input: str = "vector"  # "vector" (obs_dim floats) or "frame" (frame_shape uint8 image)
    obs_dim: int = 0  # vector input size (ignored for frames)
    frame_shape: tuple[int, int, int] = (64, 64, 3)
    n_codes: int = 128  # codes per group
    code_dim: int = 48  # encoder output width, cut into `groups` equal slices
    groups: int = 4  # codebooks, one code each per observation (product quantisation: vqvae.py)
    hidden: int = 128  # MLP width (vector input)
    channels: int = 32  # first conv width (frame input); then 2x, 2x, 2x
    beta: float = 0.25  # commitment weight
    ema_decay: float = 0.99
    eps: float = 1e-5  # Laplace smoothing of the EMA counts
    dead_after_steps: int = 20  # codebook updates without a single assignment before a restart

    def validate(self) -> None:
        if self.input not in INPUTS:
            raise ValueError(f"input={self.input!r} must be one of {', '.join(INPUTS)}")
        if self.input == "vector" and self.obs_dim < 1:
            raise ValueError(f"obs_dim={self.obs_dim} must be >= 1 for a vector VQ-VAE")
        if self.input == "frame":
            h, w, c = self.frame_shape
            if c != 3 or h % 16 or w % 16 or h < 16 or w < 16:
                raise ValueError(f"frame_shape={self.frame_shape} must be [H, W, 3] with H, W multiples of 16")
        if self.n_codes < 2 or self.code_dim < 1:
            raise ValueError(f"n_codes={self.n_codes} must be >= 2 and code_dim={self.code_dim} >= 1")
        if self.groups < 1 or self.code_dim % self.groups:
            raise ValueError(f"groups={self.groups} must be >= 1 and divide code_dim={self.code_dim}")
        if self.hidden < 1 or self.channels < 1:
            raise ValueError(f"hidden={self.hidden} and channels={self.channels} must be >= 1")
        if self.beta < 0 or self.eps <= 0:
            raise ValueError(f"beta={self.beta} must be >= 0 and eps={self.eps} > 0")
        if not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"ema_decay={self.ema_decay} must be within (0, 1)")
        if self.dead_after_steps < 1:
            raise ValueError(f"dead_after_steps={self.dead_after_steps} must be >= 1")
