"""The Fast Loop's layers from its configuration (components/layers.py), in model.py's
registration order: obs encoder (+ code embedding), gated MLP, the window-exact SSM, the head, and
the frozen VQ-VAE it reads codes of, if any."""
from __future__ import annotations

from hope_models.components.fast_loop.config import FastLoopConfig
from hope_models.components.layers import Layer, gated_mlp, layer_norm, linear, ssm
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.layers import vqvae_layers


def layers(cfg: FastLoopConfig, vq: VQVAEConfig | None) -> list[Layer]:
    d = cfg.d_model
    hidden = cfg.mlp_ratio * d
    frozen = vqvae_layers(vq, False) if vq is not None else []
    codes = [Layer("Embedding", ((cfg.n_codes * vq.groups, d),), True)] if vq is not None else []
    return [linear(cfg.obs_dim, d, True), *codes, layer_norm(d, True), *gated_mlp(d, hidden, True),
            layer_norm(d, True), ssm("WindowSSM", d, cfg.d_state, True), layer_norm(d, True),
            *gated_mlp(d, hidden, True), layer_norm(d, True), linear(d, cfg.act_dim, True), *frozen]
