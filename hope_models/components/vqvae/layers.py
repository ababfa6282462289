"""The VQ-VAE's layers from its configuration (components/layers.py): an MLP encoder/decoder for
observation vectors, a conv stack for frames; named and ordered as model.py registers them."""
from __future__ import annotations

from hope_models.components.layers import Layer, conv, linear
from hope_models.components.vqvae.config import VQVAEConfig, grid_widths


def vqvae_layers(cfg: VQVAEConfig, trainable: bool = True, prefix: str = "") -> list[Layer]:
    """trainable=False, prefix "vqvae.": the frozen VQ-VAE inside a component that reads its codes."""
    if cfg.input != "frame":
        sizes = [cfg.obs_dim, cfg.hidden, cfg.hidden, cfg.code_dim, cfg.hidden, cfg.hidden, cfg.obs_dim]
        names = ["encoder.0.0", "encoder.0.2", "encoder.0.4", "decoder.0", "decoder.2", "decoder.4"]
        return [linear(sizes[i], sizes[i + 1], trainable, prefix + names[i]) for i in range(len(sizes) - 1)]
    if cfg.layout == "grid":
        return _grid_layers(cfg, trainable, prefix)
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


def _grid_layers(cfg: VQVAEConfig, trainable: bool, prefix: str) -> list[Layer]:
    """model.py's _grid_encoder / _grid_decoder: stride-2 convs down to the grid, a 3x3 and a 1x1
    conv to a cell's width; a 3x3 conv from it, stride-2 transposed convs back up."""
    w = grid_widths(cfg)
    n, top, cell = len(w) - 1, w[-1], cfg.code_dim // cfg.groups
    enc = [conv("Conv2d", w[i], w[i + 1], trainable, f"{prefix}encoder.{2 * i}") for i in range(n)]
    enc += [conv("Conv2d", top, top, trainable, f"{prefix}encoder.{2 * n}", 3, 1, 1),
            conv("Conv2d", top, cell, trainable, f"{prefix}encoder.{2 * n + 2}", 1, 1, 0)]
    d = grid_widths(cfg, decoder=True)
    dec = [conv("Conv2d", cell + 2, d[-1], trainable, f"{prefix}decoder.1", 3, 1, 1)]  # + a cell's row, column
    dec += [conv("ConvTranspose2d", d[n - i], d[n - i - 1], trainable, f"{prefix}decoder.{3 + 2 * i}") for i in range(n)]
    h, wd, _ = cfg.frame_shape
    return enc + dec + [Layer("AddBackground", ((3, h, wd),), trainable, name=f"{prefix}decoder.{2 + 2 * n}")]


def layers(cfg: VQVAEConfig, vq_cfg: None = None) -> list[Layer]:
    return vqvae_layers(cfg, True)
