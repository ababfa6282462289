"""The Mid Loop's layers from its configuration (components/layers.py), named and ordered as
model.py registers them: code embedding, action input, the SSM blocks (one description, repeated
n_layers times), the code heads, the action-conditioned world model (a vector VQ-VAE only) and the
frozen VQ-VAE. Over a grid frame VQ-VAE, grid_model.py's: keypoints and the shared code embedding
in, the shared cell decoder (run only on the cells it decodes: decoded_cells), the joints out and its
world model over the joints (grid_world_model)."""
from __future__ import annotations

import dataclasses

from hope_models.components.layers import Layer, embedding, gated_mlp, layer_norm, linear, ssm
from hope_models.components.mid_loop.config import MidLoopConfig
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.layers import vqvae_layers

# The fraction of a frame's cells whose code changes over a horizon, for the estimate of how many
# cells training decodes (grid_metrics.py: every changed one, stay_sample of the others): 11 % on
# 50 reacher camera episodes with the 16x16 grid, at 0.5 s and at 1 s alike (held-out copy-last
# accuracy 0.888 and 0.887).
CHANGED_AT_HORIZON = 0.11


def decoded_cells(cfg: MidLoopConfig, groups: int) -> int:
    """The cells a training step decodes per sample (expected): score_points targets per horizon,
    each every changed cell and stay_sample of the others."""
    fraction = min(1.0, cfg.stay_sample + (1.0 - cfg.stay_sample) * CHANGED_AT_HORIZON)
    return max(1, round(len(cfg.horizon_steps) * cfg.score_points * groups * fraction))


def _grid(cfg: MidLoopConfig, vq: VQVAEConfig, block: list[Layer]) -> list[Layer]:
    d, r, n, g, h = cfg.d_model, cfg.cell_rank, cfg.n_codes, vq.groups, len(cfg.horizon_steps)
    m = decoded_cells(cfg, g)
    score = dataclasses.replace(embedding(n, cfg.keypoints, True, "keypoints.score"), per_point=g)
    cell = [embedding(n, r, True, "cell_code"), layer_norm(r, True, "cell_ln"),
            *gated_mlp(r, 2 * r, True, "cell_mlp"), linear(r, n, True, "cell_out")]
    return [score, linear(3 * cfg.keypoints, d, True, "keypoints.out"), embedding(n, d, True, "code_in"),
            linear(cfg.act_dim, d, True, "act_in"), linear(cfg.obs_dim, d, True, "obs_in"),
            *(dataclasses.replace(layer, repeat=cfg.n_layers) for layer in block), layer_norm(d, True, "ssm.ln_f"),
            linear(d, h * r, True, "cell_ctx"), embedding(g, r, True, "cell_pos"),
            *(dataclasses.replace(layer, per_sample=m) for layer in cell), linear(d, h * cfg.obs_dim, True, "joint_out"),
            *(_wm(cfg, cfg.obs_dim) if cfg.grid_world_model else []), *vqvae_layers(vq, False, "vqvae.")]


def _wm(cfg: MidLoopConfig, obs_dim: int) -> list[Layer]:
    """The action-conditioned world model over obs_dim observed values (none at wm_horizon 0)."""
    if cfg.wm_horizon <= 0:
        return []
    d, w = cfg.d_model, cfg.wm_hidden
    return [linear(d + obs_dim, w, True, "wm_enc.0"), linear(w, w, True, "wm_enc.2"),
            linear(w + cfg.act_dim, w, True, "wm_cell.0"), linear(w, w, True, "wm_cell.2"),
            linear(w, obs_dim, True, "wm_out")]


def layers(cfg: MidLoopConfig, vq: VQVAEConfig) -> list[Layer]:
    d = cfg.d_model
    hidden = cfg.mlp_ratio * d
    block = [layer_norm(d, True, "ssm.blocks.{i}.ln1"), ssm("DiagonalSSM", d, cfg.d_state, True, "ssm.blocks.{i}.ssm"),
             layer_norm(d, True, "ssm.blocks.{i}.ln2"), *gated_mlp(d, hidden, True, "ssm.blocks.{i}.mlp")]
    if vq.input == "frame" and vq.layout == "grid":
        return _grid(cfg, vq, block)
    wm = _wm(cfg, vq.obs_dim) if vq.input == "vector" else []
    return [embedding(cfg.n_codes * vq.groups, d, True, "code_in"), linear(cfg.act_dim, d, True, "act_in"),
            *(dataclasses.replace(layer, repeat=cfg.n_layers) for layer in block), layer_norm(d, True, "ssm.ln_f"),
            linear(d, len(cfg.horizon_steps) * cfg.n_codes * vq.groups, True, "head"), *wm,
            *vqvae_layers(vq, False, "vqvae.")]
