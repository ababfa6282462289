"""VQ-VAE: one observation frame (a 64x64 RGB image or a state vector) to a few discrete codes.

    x -> encoder -> z_e [B, code_dim] -> G groups of code_dim/G -> nearest row of each group's
         codebook -> codes [B, G] -> z_q (the G rows side by side) -> decoder -> x_hat

- Groups (product quantisation): z_e is cut into `groups` slices, each quantised against its own
  codebook of `n_codes` rows, so one observation is G codes and the code space has n_codes ** G
  cells. One codebook of 1024 codes keeps only ~90 % of the variance of the reacher's normalised
  6-d observation (k-means bound, measured: docs/training.md); three groups of 128 keep ~95 %+ and
  each group stays a small categorical the Mid Loop can predict. The G codebooks are stored as one
  [G * n_codes, code_dim / G] table: group g owns rows g * n_codes .. (g + 1) * n_codes - 1, and
  a code is the group-local index 0 .. n_codes - 1 (`rows()` turns codes into table rows).

- Inputs: "frame" = uint8 images [B, H, W, 3] (H, W multiples of 16; 64x64 here), a small conv
  encoder/decoder; "vector" = normalised observation vectors [B, obs_dim], an MLP encoder/decoder.
- Frame layouts: "flat" squeezes the whole frame through one Linear into code_dim, cut into the
  groups; "grid" keeps the conv encoder's H/patch x W/patch map and quantises every cell (one group
  per cell, row-major, each with its own codebook), and the decoder is all convs from that grid.
  Flat lost the thin arm of the reacher (a few pixels that cost little squared error); a cell's
  code only has to say what is in its patch, and the grid keeps where (docs/training.md).
- Loss = reconstruction MSE + beta * commitment MSE(z_e, sg(z_q)); gradients reach the encoder
  through the straight-through estimator. With fg_weight > 0 (frames) the reconstruction term
  weighs each pixel 1 + fg_weight where it differs from the batch's background (its mean
  frame) by more than FG_THRESHOLD: the arm and the target, a few % of the pixels. The codebook itself gets no gradient: it is an
  exponential moving average of the encoder outputs assigned to each code (decay ~0.99), with
  Laplace-smoothed counts so a rarely used code never divides by ~0.
- Data-driven init: the first training batch's encoder outputs become the codebook (a random
  choice of them; with fewer outputs than codes, repeats get a little noise so all rows differ).
- Dead-code restart: a code unused for `dead_after_steps` codebook updates is re-seeded from a
  random current encoder output. All randomness comes from torch's global RNG, which the trainer
  checkpoints, so a resumed run restarts the same codes with the same values.
- Every piece of codebook state (rows, EMA counts and sums, unused-step counters, the init flag)
  is a registered buffer: state_dict() / safetensors capture it, and resume is exact.

encode(x) -> codes is pure (no statistics change), so a frozen VQ-VAE inside the Fast and Mid
Loops can run in any train/eval mode. The model has no dropout or batch norm at all: train() and
eval() compute the same function.
"""
from __future__ import annotations

import logging
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from hope_models.components.vqvae.config import INPUTS, VQVAEConfig, grid_widths  # noqa: F401 - re-exported

log = logging.getLogger(__name__)


FG_THRESHOLD = 0.1  # a pixel is foreground where a channel differs from the background by this ([0, 1] scale)


class VQOutput(NamedTuple):
    recon: torch.Tensor  # decoder output, in the space of target()
    z_e: torch.Tensor  # [B, code_dim] encoder outputs (with grad)
    codes: torch.Tensor  # [B, G] long, group-local
    recon_loss: torch.Tensor  # plain MSE: what the figures (recon_nmse, psnr_db) report
    commit_loss: torch.Tensor
    target: torch.Tensor  # what recon reconstructs: prepare(x)
    fit_loss: torch.Tensor  # the reconstruction term trained on (recon_loss, or weighted: fg_weight)


class _ToCells(nn.Module):
    """[B, D, h, w] conv map -> [B, h * w * D]: each cell's D values, LayerNorm'd (no parameters,
    see VQVAE.__init__), cells row-major: the slice group g quantises is cell g."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = x.permute(0, 2, 3, 1)
        return F.layer_norm(z, z.shape[-1:]).flatten(1)


class _FromCells(nn.Module):
    """[B, h * w * D] -> [B, D + 2, h, w]: the inverse of _ToCells' layout, plus each cell's row and
    column (-1 .. 1) as two more channels. The shared codes say what is in a cell, not where; the
    coordinates let the decoder draw what belongs to the place (the arena's shading, its border)."""

    def __init__(self, h: int, w: int):
        super().__init__()
        self.h, self.w = h, w

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = z.unflatten(1, (self.h, self.w, -1)).permute(0, 3, 1, 2)
        rows = torch.linspace(-1.0, 1.0, self.h, dtype=x.dtype).view(1, 1, self.h, 1).expand(x.shape[0], 1, self.h, self.w)
        cols = torch.linspace(-1.0, 1.0, self.w, dtype=x.dtype).view(1, 1, 1, self.w).expand(x.shape[0], 1, self.h, self.w)
        return torch.cat([x, rows, cols], dim=1)


class AddBackground(nn.Module):
    """x + a learned [3, H, W] image: the static scene (the arena's shading, its border) is drawn
    once, here, and the codes and convs only draw what differs from it. The first training batch's
    mean frame seeds it (VQVAE.forward). Without it the small decoder rendered the shading as grain
    across the whole frame (40 % of the held-out error of an 8x8 grid at 1000 steps)."""

    def __init__(self, h: int, w: int):
        super().__init__()
        self.image = nn.Parameter(torch.zeros(3, h, w))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.image


def _grid_encoder(cfg: VQVAEConfig) -> nn.Module:
    w = grid_widths(cfg)
    layers: list[nn.Module] = []
    for a, b in zip(w[:-1], w[1:], strict=True):
        layers += [nn.Conv2d(a, b, 4, 2, 1), nn.SiLU()]
    cell = cfg.code_dim // cfg.groups
    return nn.Sequential(*layers, nn.Conv2d(w[-1], w[-1], 3, 1, 1), nn.SiLU(), nn.Conv2d(w[-1], cell, 1), _ToCells())


def _grid_decoder(cfg: VQVAEConfig) -> nn.Module:
    w = grid_widths(cfg, decoder=True)
    cell = cfg.code_dim // cfg.groups
    layers: list[nn.Module] = [_FromCells(*cfg.grid_shape), nn.Conv2d(cell + 2, w[-1], 3, 1, 1), nn.SiLU()]
    ups = list(zip(w[:0:-1], w[-2::-1], strict=True))  # (2c -> 2c), ..., (c -> 3)
    for i, (a, b) in enumerate(ups):
        layers.append(nn.ConvTranspose2d(a, b, 4, 2, 1))
        if i < len(ups) - 1:
            layers.append(nn.SiLU())
    return nn.Sequential(*layers, AddBackground(*cfg.frame_shape[:2]))


def background_weights(x: torch.Tensor, fg_weight: float) -> torch.Tensor:
    """Per-pixel loss weights [B, 1, H, W] for frames x [B, 3, H, W] in [0, 1]: 1 + fg_weight where
    a pixel differs from the batch's mean frame (the static scene, when the batch comes from many
    moments and the objects are small) by more than FG_THRESHOLD in some channel, 1 elsewhere. The
    mean, not the median: the median cost a third of a training step."""
    background = x.mean(dim=0, keepdim=True)
    fg = ((x - background).abs().amax(dim=1, keepdim=True) > FG_THRESHOLD).to(x.dtype)
    return 1.0 + fg_weight * fg


def _conv_encoder(cfg: VQVAEConfig) -> nn.Module:
    h, w, _ = cfg.frame_shape
    c = cfg.channels
    return nn.Sequential(  # four stride-2 convs: 64x64 -> 4x4
        nn.Conv2d(3, c, 4, 2, 1), nn.SiLU(),
        nn.Conv2d(c, 2 * c, 4, 2, 1), nn.SiLU(),
        nn.Conv2d(2 * c, 2 * c, 4, 2, 1), nn.SiLU(),
        nn.Conv2d(2 * c, 2 * c, 4, 2, 1), nn.SiLU(),
        nn.Flatten(), nn.Linear(2 * c * (h // 16) * (w // 16), cfg.code_dim),
        nn.LayerNorm(cfg.code_dim, elementwise_affine=False),  # see VQVAE.__init__
    )


def _conv_decoder(cfg: VQVAEConfig) -> nn.Module:
    h, w, _ = cfg.frame_shape
    c = cfg.channels
    return nn.Sequential(
        nn.Linear(cfg.code_dim, 2 * c * (h // 16) * (w // 16)), nn.SiLU(),
        nn.Unflatten(1, (2 * c, h // 16, w // 16)),
        nn.ConvTranspose2d(2 * c, 2 * c, 4, 2, 1), nn.SiLU(),
        nn.ConvTranspose2d(2 * c, 2 * c, 4, 2, 1), nn.SiLU(),
        nn.ConvTranspose2d(2 * c, c, 4, 2, 1), nn.SiLU(),
        nn.ConvTranspose2d(c, 3, 4, 2, 1),
    )


def _mlp(sizes: list[int]) -> nn.Module:
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(nn.SiLU())
    return nn.Sequential(*layers)


class VQVAE(nn.Module):
    def __init__(self, cfg: VQVAEConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        if cfg.input == "frame" and cfg.layout == "grid":
            self.encoder, self.decoder = _grid_encoder(cfg), _grid_decoder(cfg)
        elif cfg.input == "frame":
            self.encoder, self.decoder = _conv_encoder(cfg), _conv_decoder(cfg)
        else:
            self.encoder = nn.Sequential(_mlp([cfg.obs_dim, cfg.hidden, cfg.hidden, cfg.code_dim]),
                                         nn.LayerNorm(cfg.code_dim, elementwise_affine=False))
        # Both encoders end in a LayerNorm without parameters: z_e keeps a fixed scale. Without it
        # the outputs grow early in training faster than the EMA codebook follows, and nearly
        # everything lands on the few outermost codes (perplexity ~5 of 128 in our tests).
            self.decoder = _mlp([cfg.code_dim, cfg.hidden, cfg.hidden, cfg.obs_dim])
        k, d = cfg.groups * cfg.n_codes, cfg.code_dim // cfg.groups  # every group's rows in one table
        self.register_buffer("codebook", torch.zeros(k, d))
        self.register_buffer("ema_count", torch.zeros(k))  # EMA of assignments per code
        self.register_buffer("ema_sum", torch.zeros(k, d))  # EMA of the encoder outputs assigned
        self.register_buffer("unused_steps", torch.zeros(k, dtype=torch.int64))  # since used or restarted
        self.register_buffer("idle_steps", torch.zeros(k, dtype=torch.int64))  # since really used (metric)
        self.register_buffer("_offsets", torch.arange(0, cfg.groups * cfg.n_codes, cfg.n_codes), persistent=False)
        self.register_buffer("initialized", torch.zeros((), dtype=torch.int64))  # 0/1
        self.register_buffer("restarts", torch.zeros((), dtype=torch.int64))  # dead codes re-seeded so far
        log.info("%s", self.describe())

    def describe(self) -> str:
        n = sum(p.numel() for p in self.parameters())
        what = (f"{self.cfg.frame_shape[0]}x{self.cfg.frame_shape[1]} frame" if self.cfg.input == "frame"
                else f"{self.cfg.obs_dim}-d vector")
        g = self.cfg.groups
        groups = (f"a {'x'.join(map(str, self.cfg.grid_shape))} grid of cells" if self.cfg.layout == "grid"
                  else f"{g} group{'s' * (g > 1)}")
        return (f"VQVAE({what} -> {groups} of {self.cfg.n_codes} codes x {self.cfg.code_dim // g}): "
                f"{n / 1e6:.3f} M parameters (+ {self.codebook.numel()} codebook values as EMA buffers)")

    @property
    def wants_frames(self) -> bool:
        return self.cfg.input == "frame"

    # -- inputs and targets ---------------------------------------------------------------------
    def prepare(self, x: torch.Tensor) -> torch.Tensor:
        """Raw input -> encoder input: uint8 [B, H, W, 3] -> float [B, 3, H, W] in [0, 1]; vectors as is."""
        if self.cfg.input == "frame":
            if x.dim() != 4 or tuple(x.shape[1:]) != tuple(self.cfg.frame_shape):
                shape = ", ".join(map(str, self.cfg.frame_shape))
                raise ValueError(f"frames must be [B, {shape}] uint8, got {list(x.shape)}")
            return x.permute(0, 3, 1, 2).to(torch.float32) / 255.0
        if x.dim() != 2 or x.shape[1] != self.cfg.obs_dim:
            raise ValueError(f"observations must be [B, {self.cfg.obs_dim}], got {list(x.shape)}")
        return x.to(torch.float32)

    # -- the quantiser --------------------------------------------------------------------------
    def groups_of(self, z: torch.Tensor) -> torch.Tensor:
        """[B, code_dim] -> [B, G, code_dim / G]: the slice each group quantises."""
        return z.unflatten(-1, (self.cfg.groups, self.cfg.code_dim // self.cfg.groups))

    def rows(self, codes: torch.Tensor) -> torch.Tensor:
        """Group-local codes [..., G] -> rows of the codebook table [..., G]."""
        return codes + self._offsets

    @property
    def shared(self) -> bool:
        """One codebook for every group (the grid: a ball or a piece of arm looks the same in every
        cell, and a cell's own codebook would know it only where training episodes put it). It is
        stored once per group, so the table keeps the [G * n_codes, d] layout every reader of
        `codebook` and `rows()` expects; maintenance learns the first block and copies it."""
        return self.cfg.layout == "grid"

    def _learned(self) -> int:
        """How many codebooks training learns: 1 when shared, else G (the first that many blocks)."""
        return 1 if self.shared else self.cfg.groups

    def _points(self, z: torch.Tensor, codes: torch.Tensor | None = None):
        """[B, code_dim] (and codes [B, G]) -> [N, learned, d] (and [N, learned]): every slice next
        to the codebook it is quantised by (shared: all B * G slices as one group's points)."""
        zg = self.groups_of(z)
        if not self.shared:
            return zg if codes is None else (zg, codes)
        zg = zg.flatten(0, 1)[:, None]
        return zg if codes is None else (zg, codes.reshape(-1, 1))

    def _tile(self) -> None:
        """Shared: copy the learned block of every piece of codebook state into the other groups'."""
        if not self.shared:
            return
        g, n = self.cfg.groups, self.cfg.n_codes
        for buf in (self.codebook, self.ema_count, self.ema_sum, self.unused_steps, self.idle_steps):
            blocks = buf.view(g, n, *buf.shape[1:])
            blocks[1:] = blocks[:1]

    def nearest(self, z: torch.Tensor) -> torch.Tensor:
        """The closest row of each group's codebook for each z [B, code_dim] -> codes [B, G] (ties:
        the lowest index)."""
        zg = self.groups_of(z)  # [B, G, d]
        book = self.codebook.view(self.cfg.groups, self.cfg.n_codes, -1)  # [G, K, d]
        if self.shared:  # one block for all: G copies of the same distances would cost G times as much
            b0 = book[0]
            d = (zg * zg).sum(-1, keepdim=True) - 2.0 * zg @ b0.t() + (b0 ** 2).sum(-1)
            return d.argmin(dim=-1)
        d = ((zg * zg).sum(-1, keepdim=True) - 2.0 * torch.einsum("bgd,gkd->bgk", zg, book)
             + (book ** 2).sum(-1)[None])
        return d.argmin(dim=-1)

    def quantised(self, codes: torch.Tensor) -> torch.Tensor:
        """codes [B, G] -> z_q [B, code_dim]: each group's row, side by side."""
        return self.codebook[self.rows(codes)].flatten(-2)

    @torch.no_grad()
    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """Raw frames or normalised vectors [B, ...] -> codes [B, G] (long). Never changes any state."""
        return self.nearest(self.encoder(self.prepare(x)))

    def decode(self, codes: torch.Tensor) -> torch.Tensor:
        """codes [B, G] -> reconstructions: [B, 3, H, W] in ~[0, 1] for frames, [B, obs_dim] for vectors."""
        return self.decoder(self.quantised(codes))

    def decode_expected(self, probs: torch.Tensor) -> torch.Tensor:
        """Per-group code probabilities [B, G, n_codes] -> the decoder's output at the expected z_q
        (each group's probability-weighted row): the Mid Loop's predicted observation."""
        book = self.codebook.view(self.cfg.groups, self.cfg.n_codes, -1)
        return self.decoder(torch.einsum("bgk,gkd->bgd", probs, book).flatten(-2))

    def forward(self, x: torch.Tensor, *, init_codebook: bool = False) -> VQOutput:
        """One training/validation pass. init_codebook=True seeds an uninitialised codebook from
        this batch's encoder outputs first (the training path passes it; evaluation does not)."""
        xin = self.prepare(x)
        z_e = self.encoder(xin)
        if init_codebook and not bool(self.initialized):
            if self.cfg.layout == "grid":
                with torch.no_grad():
                    self.decoder[-1].image.copy_(xin.mean(0))
            self._init_codebook(z_e.detach())
        codes = self.nearest(z_e.detach())
        z_q = self.quantised(codes)  # a gathered copy: later in-place codebook updates do not touch it
        commit = F.mse_loss(z_e, z_q)
        z_st = z_e + (z_q - z_e).detach()  # straight-through: decoder gradient flows to the encoder
        recon = self.decoder(z_st)
        mse = F.mse_loss(recon, xin)
        fit = mse
        if self.cfg.input == "frame" and self.cfg.fg_weight > 0:
            fit = (background_weights(xin, self.cfg.fg_weight) * (recon - xin) ** 2).mean()
        return VQOutput(recon, z_e, codes, mse, commit, xin, fit)

    def loss_of(self, out: VQOutput) -> torch.Tensor:
        return out.fit_loss + self.cfg.beta * out.commit_loss

    # -- codebook maintenance (training only; call after the optimiser step) -------------------
    @torch.no_grad()
    def _init_codebook(self, z: torch.Tensor) -> None:
        k = self.cfg.n_codes
        books = []
        for zg in self._points(z).unbind(1):  # [N, d] each
            if zg.shape[0] >= k:
                rows = zg[torch.randperm(zg.shape[0])[:k]]
            else:  # too few outputs: repeat them, jittered so no two rows are identical
                rows = zg[torch.randint(0, zg.shape[0], (k,))]
                rows = rows + 0.01 * (zg.std() + 1e-6) * torch.randn_like(rows)
            books.append(rows)
        rows = torch.cat(books)
        m = rows.shape[0]
        self.codebook[:m] = rows
        self.ema_sum[:m] = rows
        self.ema_count.fill_(1.0)
        self.unused_steps.zero_()
        self.idle_steps.fill_(self.cfg.dead_after_steps)  # "in use" only once a code wins a point
        self._tile()
        self.initialized.fill_(1)

    @torch.no_grad()
    def update_codebook(self, z_e: torch.Tensor, codes: torch.Tensor) -> None:
        """EMA step with one batch's encoder outputs [B, code_dim] and their codes [B, G]."""
        decay, eps = self.cfg.ema_decay, self.cfg.eps
        zg, cg = self._points(z_e, codes)
        k = self._learned() * self.cfg.n_codes  # the learned rows: the table's first k
        # One matmul per codebook (not index_add: deterministic); a [B * G, G * n_codes] one-hot
        # over all groups at once would be G times larger, 130 MB a step for a 64-cell grid.
        onehot = F.one_hot(cg.t(), self.cfg.n_codes).to(z_e.dtype)  # [learned, N, n_codes]
        counts = onehot.sum(1).flatten()  # [k], in table order
        count, total = self.ema_count[:k], self.ema_sum[:k]
        count.mul_(decay).add_(counts, alpha=1 - decay)
        total.mul_(decay).add_(torch.bmm(onehot.transpose(1, 2), zg.transpose(0, 1)).flatten(0, 1), alpha=1 - decay)
        n = count.sum()
        smoothed = (count + eps) / (n + k * eps) * n  # Laplace: never ~0
        self.codebook[:k] = total / smoothed[:, None]
        self.unused_steps[:k].add_(1).masked_fill_(counts > 0, 0)
        self.idle_steps[:k].add_(1).masked_fill_(counts > 0, 0)
        self._tile()

    @torch.no_grad()
    def restart_dead_codes(self, z_e: torch.Tensor) -> int:
        """Re-seed codes unused for dead_after_steps updates from random encoder outputs of z_e (the
        slice of the code's own group); returns how many."""
        k = self._learned() * self.cfg.n_codes
        dead = torch.nonzero(self.unused_steps[:k] >= self.cfg.dead_after_steps).flatten()
        if dead.numel() == 0:
            return 0
        zg = self._points(z_e)  # [N, learned, d]
        rows = zg[torch.randint(0, zg.shape[0], (dead.numel(),)), dead // self.cfg.n_codes]
        self.codebook[dead] = rows
        self.ema_sum[dead] = rows  # with ema_count 1 the next update starts from exactly this row
        self.ema_count[dead] = 1.0
        self.unused_steps[dead] = 0
        self.restarts.add_(dead.numel())
        self._tile()
        return int(dead.numel())

    # -- metrics --------------------------------------------------------------------------------
    def code_stats(self, codes: torch.Tensor) -> dict[str, float]:
        """perplexity of this batch's codes (per group, averaged over the groups: out of n_codes),
        batch_code_usage (fraction of the codes it uses) and code_usage (fraction that won at least
        one point within the last dead_after_steps updates or in this batch; a restarted code
        counts only once it is actually used)."""
        g, k = self.cfg.groups, self.cfg.n_codes
        counts = torch.bincount(self.rows(codes).flatten(), minlength=g * k).to(torch.float32).view(g, k)
        p = counts / counts.sum(1, keepdim=True).clamp(min=1.0)
        entropy = -torch.where(p > 0, p * p.clamp(min=1e-30).log(), torch.zeros_like(p)).sum(1)
        return {"perplexity": float(torch.exp(entropy).mean()),
                "batch_code_usage": float((counts > 0).float().mean()),
                "code_usage": float(((self.idle_steps.view(g, k) < self.cfg.dead_after_steps) | (counts > 0))
                                    .float().mean())}
