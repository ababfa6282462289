"""Where things are in a grid of codes: learned keypoints read from a grid VQ-VAE's cell codes.

    codes [..., G] (one code per cell of an h x w grid, one shared codebook of n_codes)
      score = Embed_s(code) [..., G, C]      how much each cell looks like keypoint c
      w = softmax over the G cells of score  (per keypoint)
      where_c = sum_cells w * cell centre                      [..., C, 2] in [-1, 1] frame units
      there_c = logsumexp_cells(score) - log G                 [..., C]   (is it in view at all)
      -> Linear(3C -> d)

A reflex needs to know where the target and the arm are, to a few centimetres. A sum of per-code
embeddings cannot say where (it is the same wherever a code sits), and a flat Linear over the
256 cells' vectors is one linear map (a linear probe of the codes reads the target to ~4 cm). A
soft argmax over the cells (spatial softmax, Levine et al. 2016) gives a position finer than a
cell: the weights spread over neighbouring cells, and each code carries a learned offset inside
its cell (a code of "ball at the cell's left edge" moves the point left). It costs G x C
multiply-adds a point, nothing beside a convolution, and needs no frame: it reads cached codes.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from hope_models.components.numpy_keypoints import cell_centres as _cell_centres


def cell_centres(grid: tuple[int, int]) -> torch.Tensor:
    """[h * w, 2] (x, y) of each cell's centre in [-1, 1], row-major like the grid's codes (the
    NumPy runtime's arithmetic, so both forms read the same centres)."""
    return torch.from_numpy(_cell_centres(grid))


class CodeKeypoints(nn.Module):
    def __init__(self, n_codes: int, grid: tuple[int, int], keypoints: int, d_out: int):
        super().__init__()
        self.n_codes, self.grid, self.keypoints = n_codes, (int(grid[0]), int(grid[1])), keypoints
        self.score = nn.Embedding(n_codes, keypoints)
        self.out = nn.Linear(3 * keypoints, d_out)
        self.centres: torch.Tensor
        self.register_buffer("centres", cell_centres(self.grid), persistent=False)
        self.cells = self.grid[0] * self.grid[1]
        self._log_g = math.log(self.cells)

    def forward(self, codes: torch.Tensor) -> torch.Tensor:
        """codes [..., G] (long, cell-local) -> [..., d_out]."""
        if codes.shape[-1] != self.cells:
            raise ValueError(f"codes have {codes.shape[-1]} cells, the grid {self.grid} has {self.cells}")
        # index_select: its backward (index_add) is half the cost of nn.Embedding's on a CPU
        s = self.score.weight.index_select(0, codes.reshape(-1).long()).view(*codes.shape, self.keypoints)
        s = s.transpose(-1, -2).contiguous()  # [..., C, G]: the reductions run along memory
        lse = torch.logsumexp(s, dim=-1, keepdim=True)
        where = torch.exp(s - lse) @ self.centres  # softmax over the cells, [..., C, 2]
        there = lse[..., 0] - self._log_g  # [..., C]
        return self.out(torch.cat([where.flatten(-2), there], -1))
