"""The Mid Loop's layers from its configuration (components/layers.py), named and ordered as
model.py registers them: code embedding, action input, the SSM blocks (one description, repeated
n_layers times), the code heads, the action-conditioned world model (a vector VQ-VAE only) and the
frozen VQ-VAE."""
from __future__ import annotations

import dataclasses

from hope_models.components.layers import Layer, embedding, gated_mlp, layer_norm, linear, ssm
from hope_models.components.mid_loop.config import MidLoopConfig
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.layers import vqvae_layers


def layers(cfg: MidLoopConfig, vq: VQVAEConfig) -> list[Layer]:
    d = cfg.d_model
    hidden = cfg.mlp_ratio * d
    block = [layer_norm(d, True, "ssm.blocks.{i}.ln1"), ssm("DiagonalSSM", d, cfg.d_state, True, "ssm.blocks.{i}.ssm"),
             layer_norm(d, True, "ssm.blocks.{i}.ln2"), *gated_mlp(d, hidden, True, "ssm.blocks.{i}.mlp")]
    wm = []
    if cfg.wm_horizon > 0 and vq.input == "vector":
        w, o = cfg.wm_hidden, vq.obs_dim
        wm = [linear(d + o, w, True, "wm_enc.0"), linear(w, w, True, "wm_enc.2"),
              linear(w + cfg.act_dim, w, True, "wm_cell.0"), linear(w, w, True, "wm_cell.2"),
              linear(w, o, True, "wm_out")]
    return [embedding(cfg.n_codes * vq.groups, d, True, "code_in"), linear(cfg.act_dim, d, True, "act_in"),
            *(dataclasses.replace(layer, repeat=cfg.n_layers) for layer in block), layer_norm(d, True, "ssm.ln_f"),
            linear(d, len(cfg.horizon_steps) * cfg.n_codes * vq.groups, True, "head"), *wm,
            *vqvae_layers(vq, False, "vqvae.")]
