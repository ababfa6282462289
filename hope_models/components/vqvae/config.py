"""The VQ-VAE's configuration, apart from its model so that it imports no torch: the webapp, the
daemon and the CLI check a run request's model_config and estimate its memory before any process
imports torch."""
from __future__ import annotations

from dataclasses import dataclass

INPUTS = ("vector", "frame")  # what a VQ-VAE reads
LAYOUTS = ("flat", "grid")  # how a frame's codes are laid out (model.py)
GRID_CELL_DIM = 8  # a grid cell's code width when model_config does not set code_dim


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
    # Frames: "flat" = the whole frame -> one code_dim vector cut into `groups` codes; "grid" = one
    # code per patch x patch cell of the frame (groups = the cells, row-major; code_dim = cells x
    # a cell's width). Checkpoints from before the grid have no layout: flat.
    layout: str = "flat"
    patch: int = 4  # grid: pixels per cell side, a power of 2 (64x64 / 4 = a 16x16 grid, 256 codes)
    fg_weight: float = 0.0  # frames: extra loss weight of the pixels that differ from the background
    decoder_channels: int = 0  # grid: the decoder's first width (0: `channels`); the encoder stays as cheap

    @property
    def grid_shape(self) -> tuple[int, int]:
        """The grid's cells (rows, columns): (H / patch, W / patch)."""
        return self.frame_shape[0] // self.patch, self.frame_shape[1] // self.patch

    def validate(self) -> None:
        if self.input not in INPUTS:
            raise ValueError(f"input={self.input!r} must be one of {', '.join(INPUTS)}")
        if self.input == "vector" and self.obs_dim < 1:
            raise ValueError(f"obs_dim={self.obs_dim} must be >= 1 for a vector VQ-VAE")
        if self.input == "frame":
            h, w, c = self.frame_shape
            if c != 3 or h % 16 or w % 16 or h < 16 or w < 16:
                raise ValueError(f"frame_shape={self.frame_shape} must be [H, W, 3] with H, W multiples of 16")
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout={self.layout!r} must be one of {', '.join(LAYOUTS)}")
        if self.layout == "grid":
            self._validate_grid()
        elif self.decoder_channels:
            raise ValueError(f"decoder_channels={self.decoder_channels} is the grid layout's; layout is {self.layout!r}")
        if self.fg_weight < 0:
            raise ValueError(f"fg_weight={self.fg_weight} must be >= 0")
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

    def _validate_grid(self) -> None:
        if self.input != "frame":
            raise ValueError("layout='grid' needs input='frame': a vector has no cells")
        h, w, _ = self.frame_shape
        p = self.patch
        if p < 2 or p & (p - 1) or h % p or w % p:
            raise ValueError(f"patch={p} must be a power of 2 >= 2 that divides the frame {h}x{w}")
        cells = (h // p) * (w // p)
        if self.groups != cells:
            raise ValueError(f"groups={self.groups} must be the grid's {h // p}x{w // p}={cells} cells "
                             f"(layout='grid', patch={p})")
        if self.decoder_channels < 0:
            raise ValueError(f"decoder_channels={self.decoder_channels} must be >= 0 (0: channels)")


def grid_widths(cfg: VQVAEConfig, decoder: bool = False) -> list[int]:
    """The channels of the grid encoder's stride-2 convs, input first: 3, c, 2c, 2c, ... (log2(patch)
    convs); the decoder runs its own widths backwards (c = decoder_channels when set: a wider
    decoder costs training time, never the robot's encode)."""
    n = cfg.patch.bit_length() - 1
    c = (cfg.decoder_channels or cfg.channels) if decoder else cfg.channels
    return [3] + [c * (1 if i == 0 else 2) for i in range(n)]
