"""The models' configurations, apart from the models so that they import no torch.

The webapp, the daemon and the CLI check a run request's `model_config` and estimate its memory
(hope_models/train/model_config.py, estimate.py) before any process imports torch or builds a
model; they need these dataclasses, their defaults and their `validate()`, nothing else. The
model modules re-export them (`from hope_models.models.vqvae import VQVAEConfig` still works).
"""
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


@dataclass
class SSMConfig:
    d_model: int = 128
    d_state: int = 64
    n_layers: int = 2
    mlp_ratio: int = 2  # gated MLP hidden width = mlp_ratio * d_model
    min_timescale: float = 1.0  # initial decay timescales (in grid steps), log-spaced over the state
    max_timescale: float = 64.0
    chunk: int = 64  # longest stretch the parallel form handles with one kernel


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

    def validate(self) -> None:
        if self.obs_dim < 1 or self.act_dim < 1:
            raise ValueError(f"obs_dim={self.obs_dim} and act_dim={self.act_dim} must be >= 1")
        if self.window_k < 1:
            raise ValueError(f"window_k={self.window_k} must be >= 1")
        if self.d_model < 1 or self.d_state < 1 or self.mlp_ratio < 1:
            raise ValueError("d_model, d_state and mlp_ratio must be >= 1")
        _check_timescales(self.min_timescale, self.max_timescale)


@dataclass
class MidLoopConfig:
    act_dim: int = 0
    n_codes: int = 0  # codebook size of the frozen VQ-VAE
    horizon_steps: tuple[int, ...] = (5, 10)  # grid steps ahead, one prediction head each
    d_model: int = 128
    n_layers: int = 2
    d_state: int = 64
    mlp_ratio: int = 2
    min_timescale: float = 1.0  # grid steps (100 ms each in the default window)
    max_timescale: float = 64.0
    dropout: float = 0.1  # on the SSM's input and the head's: a few dozen episodes overfit without it
    # The action-conditioned world model (mid_loop.py, "World model"): from the context at a grid
    # point, the exact observation there and the actions held over the next wm_horizon grid steps,
    # the observation after each of them. 0 = none. A vector VQ-VAE only (it predicts vectors).
    wm_horizon: int = 4
    wm_hidden: int = 128
    wm_weight: float = 1.0  # of its MSE (normalised units) beside the codes' NLL in the loss

    def ssm_config(self) -> SSMConfig:
        return SSMConfig(self.d_model, self.d_state, self.n_layers, self.mlp_ratio, self.min_timescale,
                         self.max_timescale)

    def validate(self) -> None:
        if self.act_dim < 1 or self.n_codes < 2:
            raise ValueError(f"act_dim={self.act_dim} must be >= 1 and n_codes={self.n_codes} >= 2")
        if not self.horizon_steps or any(int(s) != s or s < 1 for s in self.horizon_steps):
            raise ValueError(f"horizon_steps={self.horizon_steps} must be positive whole grid steps")
        if self.d_model < 1 or self.n_layers < 1 or self.d_state < 1 or self.mlp_ratio < 1:
            raise ValueError("d_model, n_layers, d_state and mlp_ratio must be >= 1")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout={self.dropout} must be within [0, 1)")
        if self.wm_horizon < 0 or self.wm_hidden < 1 or not self.wm_weight >= 0:
            raise ValueError(f"wm_horizon={self.wm_horizon} must be >= 0, wm_hidden={self.wm_hidden} >= 1 and "
                             f"wm_weight={self.wm_weight} >= 0")
        _check_timescales(self.min_timescale, self.max_timescale)


def _check_timescales(lo: float, hi: float) -> None:
    # the SSM layers' own rule, here too so that a request is refused before a layer is built
    if not 0 < lo <= hi:
        raise ValueError(f"min_timescale={lo} and max_timescale={hi} must satisfy 0 < min <= max")
