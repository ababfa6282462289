"""The Mid Loop over a grid frame tokenizer: G cells of a frame, each one code of ONE shared codebook
of n_codes (VQ-VAE layout "grid", e.g. 16x16 = 256 cells of 256 codes per 64x64 frame).

    codes_k [B, K, G] --CodeKeypoints-----------------------+   where things are in view
                      --mean over cells of Embed(code)-------+   what is in view
    previous action [B, K, A] --Linear-----------------------+--> SSMStack --> y [B, K, d]
    joints_k [B, K, obs_dim] (normalised) --Linear-----------+
    y --Linear--> per horizon: the joints' change (joints at k + s_h = joints_k + delta)
    y, horizon h, current codes c [G] --shared cell decoder--> logits [G, n_codes]:
        z_g = ctx_h(y) + pos[g] + code[c_g]     (width cell_rank r)
        u_g = z_g + GatedMLP(LN(z_g));  logits_g = u_g @ V^T + b,  V [n_codes, r]

The vector Mid Loop's head, one Linear(d, H * G * n_codes), is ~17 M weights at 256 x 256 codes and
its logits at every point of a window are [B, K, H, G, n_codes] (~335 MB at batch 32). Here one
small decoder is shared by every cell (the codebook is shared: a piece of arm looks the same in
every cell), told which cell it is (pos) and what the cell holds now (code[c_g]: "it stays the
same" is then the easy answer, and a change is what the context must explain). Its cost is per
scored target, so only targets that are scored are decoded (grid_metrics.py: the anchor's and the
last few in-window points per horizon), never the whole [B, K, H, G, n_codes] tensor.
The loss and the metrics read each cell's distribution mixed with copy-last's (copy_mix,
grid_metrics.py): the decoder alone is too sure of changes on episodes it was not trained on.

The joints are the robot's own measurement, an input at every point and a target per horizon: a
camera world model that forgets where its arm is cannot plan with it. The code heads, like the
vector Mid Loop's, are not conditioned on actions still to be taken (only on the past ones).

Two forms: context() over a window, init_state()/step() one grid point at a time (the same
context at every point from a zero state, tested).

World model (wm_*, when wm_horizon > 0 and grid_world_model): model.py's action-conditioned heads over
the joints, h = wm_enc(context y detached, joints_k); h <- h + wm_cell(h, act_{k+i}); joints_{k+i+1} =
joints_k + wm_out(h): what `imagine --method model` plans in (hope_models/imagine/). The frame of an
imagined step is not predicted here: imagine/frame_goal.py draws it from the joints.
Its torch-free form is numpy_grid.py (GridMidLoopNumpy, equal to this one in eval mode: what
BrainService serves, the joints ahead and each cell's code distribution mixed with copy-last).
"""
from __future__ import annotations

import logging

import torch
from torch import nn

from hope_models.components.code_keypoints import CodeKeypoints
from hope_models.components.meta_init import embedding
from hope_models.components.mid_loop.config import MidLoopConfig
from hope_models.components.mid_loop.layers import decoded_cells
from hope_models.components.mid_loop.model import MidLoop
from hope_models.components.ssm import GatedMLP, SSMStack, count_params
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.model import VQVAE

log = logging.getLogger(__name__)


def is_grid(vq: VQVAEConfig | None) -> bool:
    """A frame tokenizer whose codes are cells of one shared codebook: the Mid Loop reads it per cell."""
    return vq is not None and vq.input == "frame" and vq.layout == "grid"


class GridMidLoop(nn.Module):
    grid = True  # the Mid Loop's grid form (train.py, held_out.py read it)

    def __init__(self, cfg: MidLoopConfig, vqvae: VQVAE):
        super().__init__()
        cfg.validate()
        if not is_grid(vqvae.cfg) or vqvae.cfg.n_codes != cfg.n_codes:
            raise ValueError(f"the grid Mid Loop needs a grid frame VQ-VAE with n_codes={cfg.n_codes} codes")
        if cfg.obs_dim < 1:
            raise ValueError("model_config.obs_dim must be the joints' size (the observation vector), >= 1")
        self.cfg = cfg
        self.groups = g = vqvae.cfg.groups
        h, n, d, r = len(cfg.horizon_steps), cfg.n_codes, cfg.d_model, cfg.cell_rank
        self.keypoints = CodeKeypoints(n, vqvae.cfg.grid_shape, cfg.keypoints, d)
        self.code_in = embedding(n, d)  # shared by every cell: its mean over the cells says what is in view
        self.act_in = nn.Linear(cfg.act_dim, d)
        self.obs_in = nn.Linear(cfg.obs_dim, d)
        self.ssm = SSMStack(cfg.ssm_config())
        self.drop = nn.Dropout(cfg.dropout)
        self.cell_ctx = nn.Linear(d, h * r)
        self.cell_pos = embedding(g, r)
        self.cell_code = embedding(n, r)
        self.cell_ln = nn.LayerNorm(r)
        self.cell_mlp = GatedMLP(r, 2 * r)
        self.cell_out = nn.Linear(r, n)  # V and a bias: one row per code of the shared codebook
        self.joint_out = nn.Linear(d, h * cfg.obs_dim)
        self.wm_enc = self.wm_cell = self.wm_out = None
        if cfg.wm_horizon > 0 and cfg.grid_world_model:  # model.py's world model, over the joints
            o, w = cfg.obs_dim, cfg.wm_hidden
            self.wm_enc = nn.Sequential(nn.Linear(d + o, w), nn.SiLU(), nn.Linear(w, w))
            self.wm_cell = nn.Sequential(nn.Linear(w + cfg.act_dim, w), nn.SiLU(), nn.Linear(w, w))
            self.wm_out = nn.Linear(w, o)
        self.vqvae = vqvae.requires_grad_(False)  # frozen, saved with our weights (see model.py)
        # what the memory estimate must know of these layers (layers.py): how often each runs
        # (setattr: nn.Module's typed __setattr__ takes only tensors and modules)
        setattr(self.keypoints.score, "estimate_per_point", g)  # noqa: B010
        for m in (self.cell_code, self.cell_ln, *self.cell_mlp.children(), self.cell_out):
            setattr(m, "estimate_per_sample", decoded_cells(cfg, g))  # noqa: B010
        self.register_buffer("code_counts", torch.zeros(g, n, dtype=torch.float64))
        self.register_buffer("stay_counts", torch.zeros(h, g, 2, dtype=torch.float64))  # [changed, stayed]
        log.info("%s", self.describe())

    def describe(self) -> str:
        return (f"GridMidLoop({'x'.join(map(str, self.vqvae.cfg.grid_shape))} cells x {self.cfg.n_codes} codes + "
                f"joints {self.cfg.obs_dim} + act {self.cfg.act_dim} -> cell codes and joints at "
                f"{list(self.cfg.horizon_steps)} grid steps ahead, d_model {self.cfg.d_model}, cell decoder rank "
                f"{self.cfg.cell_rank}): {count_params(self, trainable_only=True) / 1e6:.3f} M trainable "
                f"parameters + frozen VQ-VAE ({count_params(self.vqvae) / 1e6:.3f} M)")

    @property
    def wants_frames(self) -> bool:
        return True

    @property
    def has_world_model(self) -> bool:
        return self.wm_enc is not None

    # the same heads and arithmetic as the vector Mid Loop's (they read only wm_enc, wm_cell, wm_out)
    wm_predict = MidLoop.wm_predict
    wm_encode = MidLoop.wm_encode
    wm_unroll = MidLoop.wm_unroll

    def codes(self, obs: torch.Tensor | None, frames: torch.Tensor | None = None) -> torch.Tensor:
        """Codes of frames [..., H, W, 3] -> [..., G] long (obs is not read: the codes are the frame's)."""
        if frames is None:
            raise ValueError("this Mid Loop's VQ-VAE reads frames: pass frames")
        return self.vqvae.encode(frames.reshape(-1, *frames.shape[-3:])).reshape(*frames.shape[:-3], -1)

    def _inputs(self, codes: torch.Tensor, prev_act: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        # the mean of the cells' embeddings as a histogram of codes times the table: [.., n] not [.., G, d]
        hist = torch.zeros(*codes.shape[:-1], self.cfg.n_codes, dtype=torch.float32, device=codes.device)
        hist.scatter_add_(-1, codes, torch.full(codes.shape, 1.0 / self.groups, device=codes.device))
        return self.keypoints(codes) + hist @ self.code_in.weight + self.act_in(prev_act) + self.obs_in(obs)

    def context(self, codes: torch.Tensor, prev_act: torch.Tensor, obs: torch.Tensor,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        """codes [B, K, G], prev_act [B, K, A] (model.previous_actions), obs [B, K, obs_dim]
        normalised, mask [B, K] -> the SSM's output at every point [B, K, d_model]."""
        y, _ = self.ssm(self.drop(self._inputs(codes, prev_act, obs)), mask)
        return y

    def init_state(self, batch: int) -> torch.Tensor:
        return self.ssm.init_state(batch)

    def step(self, code_t: torch.Tensor, prev_act_t: torch.Tensor, obs_t: torch.Tensor,
             state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One grid point: codes [B, G], the previous point's action [B, A], joints [B, obs_dim] ->
        (context [B, d_model], state)."""
        return self.ssm.step(self._inputs(code_t, prev_act_t, obs_t), state)

    def cell_logits(self, y: torch.Tensor, h: int, now: torch.Tensor,
                    cells: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
        """Context [N, d] at N scored points, horizon index h, the points' codes now [N, G] ->
        logits [N, G, n_codes] of each cell's code s_h grid steps later; with cells = (target
        index [M], cell index [M]) only those M cells' logits [M, n_codes]."""
        r = self.cfg.cell_rank
        ctx = self.cell_ctx(self.drop(y))[:, h * r:(h + 1) * r]  # [N, r]
        if cells is None:
            code = self.cell_code.weight.index_select(0, now.reshape(-1)).view(*now.shape, r)
            z = ctx[:, None] + self.cell_pos.weight + code
        else:
            n, g = cells
            z = ctx[n] + self.cell_pos.weight[g] + self.cell_code.weight.index_select(0, now[n, g])
        return self.cell_out(z + self.cell_mlp(self.cell_ln(z)))

    def joints(self, y: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """Context [..., d], joints now [..., obs_dim] -> the joints at each horizon [..., H, obs_dim] (normalised)."""
        delta = self.joint_out(self.drop(y)).unflatten(-1, (len(self.cfg.horizon_steps), self.cfg.obs_dim))
        return obs.unsqueeze(-2) + delta
