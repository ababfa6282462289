"""The VQ-VAE's layers from its configuration (components/layers.py): an MLP encoder/decoder for
observation vectors, a conv stack for frames; named and ordered as model.py registers them."""
from __future__ import annotations

from hope_models.components.layers import Layer, conv, linear
from hope_models.components.vqvae.config import VQVAEConfig


def vqvae_layers(cfg: VQVAEConfig, trainable: bool = True, prefix: str = "") -> list[Layer]:
    """trainable=False, prefix "vqvae.": the frozen VQ-VAE inside a component that reads its codes."""
    if cfg.input != "frame":
        sizes = [cfg.obs_dim, cfg.hidden, cfg.hidden, cfg.code_dim, cfg.hidden, cfg.hidden, cfg.obs_dim]
        names = ["encoder.0.0", "encoder.0.2", "encoder.0.4", "decoder.0", "decoder.2", "decoder.4"]
        return [linear(sizes[i], sizes[i + 1], trainable, prefix + names[i]) for i in range(len(sizes) - 1)]
    h, w, _ = cfg.frame_shape
    c = cfg.channels
    flat = 2 * c * (h // 16) * (w // 16)
    return [conv("Conv2d", 3, c, trainable, f"{prefix}encoder.0"), conv("Conv2d", c, 2 * c, trainable, f"{prefix}encoder.2"),
            conv("Conv2d", 2 * c, 2 * c, trainable, f"{prefix}encoder.4"),
            conv("Conv2d", 2 * c, 2 * c, trainable, f"{prefix}encoder.6"),
            linear(flat, cfg.code_dim, trainable, f"{prefix}encoder.9"),
            linear(cfg.code_dim, flat, trainable, f"{prefix}decoder.0"),
            conv("ConvTranspose2d", 2 * c, 2 * c, trainable, f"{prefix}decoder.3"),
            conv("ConvTranspose2d", 2 * c, 2 * c, trainable, f"{prefix}decoder.5"),
            conv("ConvTranspose2d", 2 * c, c, trainable, f"{prefix}decoder.7"),
            conv("ConvTranspose2d", c, 3, trainable, f"{prefix}decoder.9")]


def layers(cfg: VQVAEConfig, vq_cfg: None = None) -> list[Layer]:
    return vqvae_layers(cfg, True)
