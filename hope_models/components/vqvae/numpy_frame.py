"""The frame VQ-VAE's encoder in NumPy: a camera frame -> its codes, as VQVAE.encode computes them.

    cfg = frame_config(config["model_config"], where, SomeError)        # an untrusted config, checked
    enc = FrameEncoder(tensors, cfg, prefix="vqvae.")
    enc.encode(frames)           # uint8 [..., H, W, 3] -> z_e [..., G, code_dim / G]
    enc.fingerprint              # sha256 of what the codes depend on: equal encoders share codes

Both layouts of model.py, their convolutions read off the layer description (layers.py: kernel,
stride, padding per conv, so the two cannot drift apart) and run channels-last
(components/numpy_conv.py):

- "flat": four stride-2 convs, each followed by SiLU, then Linear over the flattened map and a
  LayerNorm without parameters. torch flattens [C, h, w]; the map here is [h, w, C], so the
  Linear's columns are permuted once at load instead of the map at every frame.
- "grid": stride-2 convs with SiLU down to the H/patch x W/patch map, a 3x3 conv + SiLU and a 1x1
  conv to a cell's width, then each cell's vector LayerNorm'd (no parameters): a channels-last
  map is already the cells in row-major order (_ToCells).

Pixels are float32 x / 255 as VQVAE.prepare computes them. The nearest code is VQVAENumpy's
(numpy_form.py); a grid's codebook is shared, so only its first block is read. Torch-free.
"""
from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from hope_models.components.layers import Layer
from hope_models.components.numpy_conv import Conv2d
from hope_models.components.numpy_layers import LN_EPS, silu
from hope_models.components.vqvae.config import LAYOUTS, VQVAEConfig
from hope_models.components.vqvae.layers import vqvae_layers

MAX_FRAME_SIDE = 512  # bounds what an untrusted config sizes (64 is the default camera, 96 allowed)
MAX_FRAME_CODES = 1 << 16  # a grid's cells: (MAX_FRAME_SIDE / 2) ** 2 at the smallest patch


def _positive_int(v: Any, hi: int) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= hi


def frame_config(vq_cfg: Any, where: Any, error: type[Exception], max_width: int) -> VQVAEConfig:
    """The VQVAEConfig of a frame VQ-VAE's model_config (untrusted JSON), every size bounded and the
    whole validated as the model validates it; `error` naming `where` and the field otherwise."""
    if not isinstance(vq_cfg, dict):
        raise error(f"{where}: the VQ-VAE's model_config is missing or not an object")
    shape = vq_cfg.get("frame_shape")
    if (not isinstance(shape, (list, tuple)) or len(shape) != 3
            or not all(_positive_int(v, MAX_FRAME_SIDE) for v in shape)):
        raise error(f"{where}: vqvae model_config.frame_shape={shape!r} must be [H, W, 3], each side 1-{MAX_FRAME_SIDE}")
    layout = vq_cfg.get("layout", "flat")  # checkpoints from before the grid have no layout: flat
    if layout not in LAYOUTS:
        raise error(f"{where}: vqvae model_config.layout={layout!r} must be one of {', '.join(LAYOUTS)}")
    sizes = {"n_codes": max_width, "code_dim": max_width * MAX_FRAME_CODES, "groups": MAX_FRAME_CODES,
             "channels": max_width, "patch": MAX_FRAME_SIDE}
    defaults = VQVAEConfig()
    values = {}
    for key, hi in sizes.items():
        v = vq_cfg.get(key, getattr(defaults, key))
        if not _positive_int(v, hi):
            raise error(f"{where}: vqvae model_config.{key}={v!r} must be an integer in 1-{hi}")
        values[key] = v
    # the decoder's width (0: channels) shapes a served tokenizer's decoder tensors
    dec = vq_cfg.get("decoder_channels", 0)
    if dec != 0 and not _positive_int(dec, max_width):
        raise error(f"{where}: vqvae model_config.decoder_channels={dec!r} must be 0 or an integer in 1-{max_width}")
    cfg = VQVAEConfig(input="frame", obs_dim=0, frame_shape=(shape[0], shape[1], shape[2]), layout=layout,
                      decoder_channels=dec, **values)
    try:
        cfg.validate()
    except ValueError as exc:
        raise error(f"{where}: vqvae model_config: {exc}") from None
    if layout == "flat" and cfg.groups > 64:  # a flat frame's groups are product codebooks, like a vector's
        raise error(f"{where}: vqvae model_config.groups={cfg.groups} must be at most 64 for layout 'flat'")
    return cfg


def encoder_layers(cfg: VQVAEConfig, prefix: str = "") -> list[Layer]:
    """The encoder's layers (convs, and the flat layout's Linear), in order."""
    return [layer for layer in vqvae_layers(cfg, prefix=prefix) if layer.name.startswith(f"{prefix}encoder.")]


class FrameEncoder:
    """A frame VQ-VAE's encoder (its tensors under `prefix`). Immutable."""

    def __init__(self, tensors: dict[str, np.ndarray], cfg: VQVAEConfig, prefix: str = ""):
        self.cfg, self.frame_shape = cfg, tuple(cfg.frame_shape)
        self.layout, self.groups = cfg.layout, cfg.groups
        self.cell_dim = cfg.code_dim // cfg.groups
        layers = encoder_layers(cfg, prefix)
        self._convs = []
        for layer in layers:
            if layer.kind == "Conv2d" and layer.conv is not None:
                _, _, _, stride, padding, _, _ = layer.conv
                self._convs.append(Conv2d.from_torch(tensors[f"{layer.name}.weight"], tensors[f"{layer.name}.bias"],
                                                     stride, int(padding)))
        self._linear = None
        if cfg.layout == "flat":  # the Linear after Flatten: columns from torch's (C, h, w) order to (h, w, C)
            name = layers[-1].name
            w = tensors[f"{name}.weight"]
            c, h, wd = 2 * cfg.channels, cfg.frame_shape[0] // 16, cfg.frame_shape[1] // 16
            w_hwc = w.reshape(w.shape[0], c, h, wd).transpose(0, 2, 3, 1).reshape(w.shape[0], -1)
            self._linear = (np.ascontiguousarray(w_hwc.T, dtype=np.float32), tensors[f"{name}.bias"].astype(np.float32))
        digest = hashlib.sha256(repr((cfg.layout, self.frame_shape, cfg.groups, cfg.code_dim)).encode())
        for layer in layers:
            for param in ("weight", "bias"):
                digest.update(np.ascontiguousarray(tensors[f"{layer.name}.{param}"]).tobytes())
        self._digest = digest

    def fingerprint_with(self, codebook: np.ndarray) -> str:
        """sha256 of the encoder's weights and the codebook the codes are read from."""
        d = self._digest.copy()
        d.update(np.ascontiguousarray(codebook).tobytes())
        return d.hexdigest()

    def encode(self, frames: np.ndarray) -> np.ndarray:
        """uint8 frames [..., H, W, 3] -> z_e [..., G, code_dim / G] (after the parameter-free LayerNorm:
        of the whole vector for flat, of each cell's for grid)."""
        lead = frames.shape[:-3]
        x = frames.reshape(-1, *self.frame_shape).astype(np.float32)
        x /= np.float32(255.0)
        last = len(self._convs) - 1
        for i, conv in enumerate(self._convs):
            x = conv(x)
            if self._linear is not None or i < last:  # the grid's final 1x1 conv has no SiLU
                x = silu(x)
        if self._linear is not None:
            w, b = self._linear
            z = x.reshape(x.shape[0], -1).dot(w)
            z += b
        else:
            z = x.reshape(x.shape[0], self.groups, self.cell_dim)
        z = z - z.mean(-1, keepdims=True)
        z /= np.sqrt((z * z).mean(-1, keepdims=True) + np.float32(LN_EPS))
        return z.reshape(*lead, self.groups, self.cell_dim)


__all__ = ["FrameEncoder", "MAX_FRAME_CODES", "MAX_FRAME_SIDE", "encoder_layers", "frame_config"]
