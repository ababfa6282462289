"""The Mid Loop's layers from its configuration (components/layers.py), in model.py's
registration order: code embedding, action input, the SSM blocks (counted n_layers times), the
code heads, the action-conditioned world model (a vector VQ-VAE only) and the frozen VQ-VAE."""
from __future__ import annotations

import dataclasses

from hope_models.components.layers import Layer, gated_mlp, layer_norm, linear, ssm
from hope_models.components.mid_loop.config import MidLoopConfig
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.layers import vqvae_layers


def layers(cfg: MidLoopConfig, vq: VQVAEConfig) -> list[Layer]:
    d = cfg.d_model
    hidden = cfg.mlp_ratio * d
    block = [layer_norm(d, True), ssm("DiagonalSSM", d, cfg.d_state, True), layer_norm(d, True),
             *gated_mlp(d, hidden, True)]
    wm = []
    if cfg.wm_horizon > 0 and vq.input == "vector":
        w, o = cfg.wm_hidden, vq.obs_dim
        wm = [linear(d + o, w, True), linear(w, w, True), linear(w + cfg.act_dim, w, True), linear(w, w, True),
              linear(w, o, True)]
    return [Layer("Embedding", ((cfg.n_codes * vq.groups, d),), True), linear(cfg.act_dim, d, True),
            *(dataclasses.replace(layer, repeat=cfg.n_layers) for layer in block), layer_norm(d, True),
            linear(d, len(cfg.horizon_steps) * cfg.n_codes * vq.groups, True), *wm, *vqvae_layers(vq, False)]
