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

from hope_models.components.meta_init import embedding, on_meta
from hope_models.components.numpy_keypoints import READER_GAIN
from hope_models.components.numpy_keypoints import cell_centres as _cell_centres

READERS = ("policy", "frames")
DRAWINGS = ("vectors", "codes")  # fast_loop/config.py DRAWINGS, without torch
RENDER_SIGMA = 0.15  # frame units ([-1, 1] across): a point's drawing reaches about one cell either side
# Drawing "codes": its cross-entropy over G cells x n_codes is most of a training step's cost, so it
# is taken on this many frames of the batch (a probe drawing 32 frames a step put one point on the reacher's
# target to 0.9 cm, held-out, within 3000 steps: docs/reflex.md).
RENDER_BATCH = 32
# READER_GAIN: the drawing's logits and a "frames" reader's scores are used times this gain. Adam
# steps a parameter by about the learning rate whatever its gradient, so the points and their drawing
# learn at READER_GAIN x the policy's rate and have settled while the policy learns to read them.
# a point standing wholly on one code starts by adding this to that code's logit where it stands
DRAW_START = 15.0
# drawing "vectors": a point standing wholly on a cell starts with this weight against the
# background's 1 in the cell's blend
BLEND_START = 4.0


def cell_centres(grid: tuple[int, int]) -> torch.Tensor:
    """[h * w, 2] (x, y) of each cell's centre in [-1, 1], row-major like the grid's codes (the
    NumPy runtime's arithmetic, so both forms read the same centres)."""
    return torch.from_numpy(_cell_centres(grid))


class CodeKeypoints(nn.Module):
    """reader "policy": the keypoints are whatever the loss of their user makes of them.
    reader "frames": they are learned by drawing the codes back from them (draw_back), and their
    user reads them without gradient. view_frame adds each point turned into the frame of a joint."""

    def __init__(self, n_codes: int, grid: tuple[int, int], keypoints: int, d_out: int, *,
                 reader: str = "policy", view_frame: bool = False, sigma: float = RENDER_SIGMA,
                 draw: str = "codes", code_dim: int = 0):
        super().__init__()
        if reader not in READERS:
            raise ValueError(f"keypoint reader={reader!r} must be one of {', '.join(READERS)}")
        if draw not in DRAWINGS:
            raise ValueError(f"keypoint drawing={draw!r} must be one of {', '.join(DRAWINGS)}")
        if reader == "frames" and draw == "vectors" and code_dim < 1:
            raise ValueError("drawing 'vectors' needs the codebook's vector size (code_dim >= 1)")
        self.n_codes, self.grid, self.keypoints = n_codes, (int(grid[0]), int(grid[1])), keypoints
        self.reader, self.sigma, self.draw = reader, float(sigma), draw
        self.score = embedding(n_codes, keypoints)
        self.gain = READER_GAIN if reader == "frames" else 1.0
        if reader == "frames" and not on_meta():  # the scores in use start as a policy reader's (N(0, 1))
            nn.init.normal_(self.score.weight, std=1.0 / self.gain)
        self.out = nn.Linear(feature_count(keypoints, view_frame), d_out)
        self.centres: torch.Tensor
        self.register_buffer("centres", cell_centres(self.grid), persistent=False)
        self.cells = self.grid[0] * self.grid[1]
        self._log_g = math.log(self.cells)
        self.view = JointView() if view_frame else None
        self.render = None
        if reader == "frames" and draw == "codes":
            self.render = KeypointRender(self.cells, keypoints, n_codes, DRAW_START / self.gain)
        elif reader == "frames":
            self.render = KeypointRender(self.cells, keypoints, code_dim, math.log(BLEND_START) / self.gain)

    def _scores(self, codes: torch.Tensor) -> torch.Tensor:
        """codes [..., G] (long, cell-local) -> each keypoint's score of each cell [..., C, G]."""
        if codes.shape[-1] != self.cells:
            raise ValueError(f"codes have {codes.shape[-1]} cells, the grid {self.grid} has {self.cells}")
        # index_select: its backward (index_add) is half the cost of nn.Embedding's on a CPU; the
        # gain scales the [n_codes, C] table, not the [..., G, C] scores
        table = self.score.weight * self.gain if self.gain != 1.0 else self.score.weight
        s = table.index_select(0, codes.reshape(-1).long()).view(*codes.shape, self.keypoints)
        return s.transpose(-1, -2).contiguous()  # the reductions over the cells run along memory

    def locate(self, codes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """codes [..., G] (long, cell-local) -> where [..., C, 2], there [..., C]."""
        return self._located(self._scores(codes))[1:]

    def _located(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Scores [..., C, G] -> (softmax over the cells, where [..., C, 2], there [..., C])."""
        log_w = torch.log_softmax(s, -1)
        w = log_w.exp()
        where = (w.reshape(-1, self.cells) @ self.centres).view(*w.shape[:-1], 2)  # one 2-D product
        # logsumexp over the cells = s - log_softmax(s) at any cell, without a second pass
        return w, where, s[..., 0] - log_w[..., 0] - self._log_g

    def forward(self, codes: torch.Tensor | None, angle: torch.Tensor | None = None,
                located: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """codes [..., G] (long, cell-local), angle [...] (radians; view_frame only) -> [..., d_out].
        located: these codes' (where, there) when already computed (draw_back's, the same step)."""
        if located is None:
            if codes is None:
                raise ValueError("pass the codes, or the points located from them")
            located = self.locate(codes)
        where, there = located
        if self.reader == "frames":
            where, there = where.detach(), there.detach()
        feats = [where.flatten(-2), there]
        if self.view is not None:
            if angle is None:
                raise ValueError("this keypoint reader turns its points into a joint's frame: pass the joint angle")
            feats += turned(where - self.view.pivot, angle)
        return self.out(torch.cat(feats, -1))

    def draw_back(self, codes: torch.Tensor, vectors: torch.Tensor | None = None
                  ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor] | None]:
        """The cells drawn back from the keypoints alone (reader "frames"), as a loss. Each point
        draws, around where it stands, what it stands on (the softmax-weighted mix of the cells
        under it), so a point pays off only on something the cells' usual content does not
        explain: the arm, which moves, and the target, which differs between scenes. No label
        (Transporter / KeyNet, on codes rather than pixels). A point with its own fixed drawing
        instead finds its way to a lone target only when it starts near one (tests).
        draw "vectors" (vectors: the codebook [n_codes, D]): each cell's code vector, the
        background and the points' drawings blended, MSE. draw "codes": each cell's code as one
        of n_codes classes, background and drawings added as logits, cross-entropy (~30x the work).
        -> (the loss, and for "vectors", which draws every row of codes [N, G], where and there of
        each row (detached): the points the policy reads this step, located once)."""
        assert self.render is not None, "reader 'policy' has no drawing"
        if self.draw == "codes":
            codes = codes.reshape(-1, self.cells)[:RENDER_BATCH].long()
        else:
            if vectors is None:
                raise ValueError("drawing 'vectors' needs the codebook's vectors")
            codes = codes.reshape(-1, self.cells).long()
        w, where, there = self._located(self._scores(codes))  # [N, C, G], [N, C, 2], [N, C]
        if self.draw == "vectors":
            return self._blend_loss(codes, w, where, vectors), (where.detach(), there.detach())
        heat = self._log_near(where, torch.zeros_like(self.render.strength)).exp()  # [N, G, C]
        under = torch.zeros(codes.shape[0], self.keypoints, self.n_codes, dtype=w.dtype)
        under.scatter_add_(2, codes[:, None, :].expand(-1, self.keypoints, -1), w)  # [N, C, n_codes]
        drawn = under * self.render.strength[None, :, None]
        logits = (self.render.background + torch.einsum("ngc,nck->ngk", heat, drawn)) * self.gain
        return nn.functional.cross_entropy(logits.reshape(-1, self.n_codes), codes.reshape(-1)), None

    def _log_near(self, where: torch.Tensor, log_strength: torch.Tensor) -> torch.Tensor:
        """log(strength_c x exp(-|cell g - point c|^2 / sigma^2)) [N, G, C] for points where [N, C, 2]:
        |c - p|^2 expanded, k |c|^2 + (k |p|^2 + log strength) - 2k c.p, one broadcast add and one
        product instead of a [N, C, G, 2] difference."""
        k = -1.0 / (self.sigma * self.sigma)
        near = (self.centres.pow(2).sum(-1) * k)[None, :, None] + (where.pow(2).sum(-1) * k + log_strength)[:, None, :]
        return torch.baddbmm(near, self.centres.expand(where.shape[0], -1, -1), where.transpose(1, 2), alpha=-2.0 * k)

    def _blend_loss(self, codes: torch.Tensor, w: torch.Tensor, where: torch.Tensor,
                    vectors: torch.Tensor) -> torch.Tensor:
        """Each cell's code vector as the blend of its background (weight 1) and every point's drawing
        (weight a = exp(strength) x exp(-|cell - point|^2 / sigma^2)): a blend, not a sum, so two
        points on one thing agree. Laid out [N, G, C] so that both products run along memory."""
        assert self.render is not None
        n = codes.shape[0]
        # [N, G, D]: what each cell holds (the frozen codebook's rows); index_select, not [codes]: 1/4 the time
        held = vectors.detach().index_select(0, codes.reshape(-1)).view(n, self.cells, -1)
        drawn = w @ held  # [N, C, D]
        a = self._log_near(where, self.render.strength * self.gain).exp()  # [N, G, C]
        num = torch.baddbmm(self.render.background * self.gain, a, drawn)  # [N, G, D]
        pred = num / (1.0 + a.sum(-1, keepdim=True))
        return nn.functional.mse_loss(pred, held)


class JointView(nn.Module):
    """Where the joint turns, in frame units: learned (the camera need not look straight at it)."""

    def __init__(self):
        super().__init__()
        self.pivot = nn.Parameter(torch.zeros(2))


class KeypointRender(nn.Module):
    """The drawing a "frames" reader learns from: each cell's content with no point near it
    (background [G, width]: code logits, or a code vector) and how strongly each point draws what it
    stands on (strength [C])."""

    def __init__(self, cells: int, keypoints: int, width: int, strength: float):
        super().__init__()
        self.background = nn.Parameter(torch.zeros(cells, width))
        self.strength = nn.Parameter(torch.full((keypoints,), float(strength)))
        self.estimate_per_sample = cells  # train/estimate.py: G cells x width values per sample, once


def turned(r: torch.Tensor, angle: torch.Tensor) -> list[torch.Tensor]:
    """r [..., C, 2] turned by -angle and by +angle ([..., 2C] each): a camera's image may be the
    world mirrored, so which way the joint turns the view is learned, not assumed."""
    c, s = torch.cos(angle)[..., None], torch.sin(angle)[..., None]
    x, y = r[..., 0], r[..., 1]
    back = torch.stack([c * x + s * y, c * y - s * x], -1).flatten(-2)
    ahead = torch.stack([c * x - s * y, c * y + s * x], -1).flatten(-2)
    return [back, ahead]


def feature_count(keypoints: int, view_frame: bool) -> int:
    """The values out() reads: where (2C), there (C), and with view_frame both turnings (4C)."""
    return keypoints * (7 if view_frame else 3)
