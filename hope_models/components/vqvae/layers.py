"""The VQ-VAE's layers from its configuration (components/layers.py): an MLP encoder/decoder for
observation vectors, a conv stack for frames; in model.py's registration order."""
from __future__ import annotations

from hope_models.components.layers import Layer, conv, linear
from hope_models.components.vqvae.config import VQVAEConfig


def vqvae_layers(cfg: VQVAEConfig, trainable: bool = True) -> list[Layer]:
    """trainable=False: the frozen VQ-VAE inside a component that reads its codes."""
    if cfg.input != "frame":
        sizes = [cfg.obs_dim, cfg.hidden, cfg.hidden, cfg.code_dim, cfg.hidden, cfg.hidden, cfg.obs_dim]
        return [linear(sizes[i], sizes[i + 1], trainable) for i in range(len(sizes) - 1)]
    h, w, _ = cfg.frame_shape
    c = cfg.channels
    flat = 2 * c * (h // 16) * (w // 16)
    return [conv("Conv2d", 3, c, trainable), conv("Conv2d", c, 2 * c, trainable),
            conv("Conv2d", 2 * c, 2 * c, trainable), conv("Conv2d", 2 * c, 2 * c, trainable),
            linear(flat, cfg.code_dim, trainable), linear(cfg.code_dim, flat, trainable),
            conv("ConvTranspose2d", 2 * c, 2 * c, trainable), conv("ConvTranspose2d", 2 * c, 2 * c, trainable),
            conv("ConvTranspose2d", 2 * c, c, trainable), conv("ConvTranspose2d", c, 3, trainable)]


def layers(cfg: VQVAEConfig, vq_cfg: None = None) -> list[Layer]:
    return vqvae_layers(cfg, True)
