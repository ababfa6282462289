"""The Fast Loop's layers from its configuration (components/layers.py), named and ordered as
model.py registers them: obs encoder (+ code embedding), gated MLP, the window-exact SSM, the
head, and the frozen VQ-VAE it reads codes of, if any."""
from __future__ import annotations

from hope_models.components.fast_loop.config import FastLoopConfig
from hope_models.components.layers import Layer, embedding, gated_mlp, layer_norm, linear, ssm
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.layers import vqvae_layers


def layers(cfg: FastLoopConfig, vq: VQVAEConfig | None) -> list[Layer]:
    d = cfg.d_model
    hidden = cfg.mlp_ratio * d
    frozen = vqvae_layers(vq, False, "vqvae.") if vq is not None else []
    codes = []
    if vq is not None and vq.input == "frame" and vq.layout == "grid":  # model.py's CodeKeypoints
        c = cfg.keypoints
        view = cfg.view_joint >= 0
        codes = [embedding(cfg.n_codes, c, True, "keypoints.score"),
                 linear(c * (7 if view else 3), d, True, "keypoints.out")]  # code_keypoints.feature_count
        if view:
            codes.append(Layer("JointView", ((2,),), True, name="keypoints.view"))
        if cfg.keypoint_reader == "frames":
            # drawn at the acting point only: per window, G cells x (n_codes logits or a code vector) once
            cells = vq.grid_shape[0] * vq.grid_shape[1]
            width = cfg.n_codes if cfg.keypoint_draw == "codes" else vq.code_dim // vq.groups
            codes.append(Layer("KeypointRender", ((cells, width), (c,)), True, name="keypoints.render",
                               per_sample=cells))
    elif vq is not None:
        codes = [embedding(cfg.n_codes * vq.groups, d, True, "code_in")]
    return [linear(cfg.obs_dim, d, True, "obs_in"), *codes, layer_norm(d, True, "enc_ln"),
            *gated_mlp(d, hidden, True, "enc_mlp"), layer_norm(d, True, "ssm_ln"),
            ssm("WindowSSM", d, cfg.d_state, True, "ssm"), layer_norm(d, True, "head_ln"),
            *gated_mlp(d, hidden, True, "head_mlp"), layer_norm(d, True, "out_ln"), linear(d, cfg.act_dim, True, "out"),
            *frozen]
