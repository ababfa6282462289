"""2-D convolutions in NumPy, equal to torch.nn.Conv2d / ConvTranspose2d, for the frame tokenizer
the torch-free runtime runs (encode a camera frame) and decodes (pictures for the Robot Editor).

Activations are channels-last, [B, H, W, C]: a convolution is then one gather of the input's
windows ([B * Ho * Wo, kh * kw * Cin], a strided view copied once) and one matrix product with the
kernel reshaped at load; a transposed convolution is one product followed by kh * kw strided adds.
Torch's layouts (weight [Cout, Cin, kh, kw] for a convolution, [Cin, Cout, kh, kw] for a transposed
one; NCHW activations) are converted once, at load (`from_torch`). Torch-free.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import as_strided


@dataclass(frozen=True)
class Conv2d:
    w: np.ndarray  # [kh * kw * Cin, Cout], rows in (ki, kj, cin) order
    b: np.ndarray  # [Cout]
    kernel: tuple[int, int]
    stride: int
    padding: int

    @classmethod
    def from_torch(cls, weight: np.ndarray, bias: np.ndarray, stride: int, padding: int) -> "Conv2d":
        cout, cin, kh, kw = weight.shape
        w = np.ascontiguousarray(weight.transpose(2, 3, 1, 0).reshape(kh * kw * cin, cout), dtype=np.float32)
        return cls(w, np.asarray(bias, dtype=np.float32), (kh, kw), stride, padding)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """x [B, H, W, Cin] float32 -> [B, Ho, Wo, Cout]."""
        b, h, w, c = x.shape
        kh, kw = self.kernel
        s, p = self.stride, self.padding
        xp = np.pad(x, ((0, 0), (p, p), (p, p), (0, 0))) if p else x
        xp = np.ascontiguousarray(xp, dtype=np.float32)
        ho, wo = (h + 2 * p - kh) // s + 1, (w + 2 * p - kw) // s + 1
        sb, sh, sw, sc = xp.strides
        windows = as_strided(xp, (b, ho, wo, kh, kw, c), (sb, sh * s, sw * s, sh, sw, sc), writeable=False)
        y = windows.reshape(b * ho * wo, kh * kw * c) @ self.w
        y += self.b
        return y.reshape(b, ho, wo, -1)


@dataclass(frozen=True)
class ConvTranspose2d:
    w: np.ndarray  # [Cin, kh * kw * Cout], columns in (ki, kj, cout) order
    b: np.ndarray  # [Cout]
    kernel: tuple[int, int]
    stride: int
    padding: int

    @classmethod
    def from_torch(cls, weight: np.ndarray, bias: np.ndarray, stride: int, padding: int) -> "ConvTranspose2d":
        cin, cout, kh, kw = weight.shape
        w = np.ascontiguousarray(weight.transpose(0, 2, 3, 1).reshape(cin, kh * kw * cout), dtype=np.float32)
        return cls(w, np.asarray(bias, dtype=np.float32), (kh, kw), stride, padding)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """x [B, H, W, Cin] float32 -> [B, (H - 1) * s - 2p + kh, ..., Cout]: each input pixel adds
        its kernel-sized patch to the output at stride s."""
        b, h, w, _ = x.shape
        kh, kw = self.kernel
        s, p = self.stride, self.padding
        cout = self.b.shape[0]
        cols = (x.reshape(b * h * w, -1) @ self.w).reshape(b, h, w, kh, kw, cout)
        full = np.zeros((b, (h - 1) * s + kh, (w - 1) * s + kw, cout), dtype=np.float32)
        for ki in range(kh):
            for kj in range(kw):
                full[:, ki:ki + (h - 1) * s + 1:s, kj:kj + (w - 1) * s + 1:s] += cols[:, :, :, ki, kj]
        out = full[:, p:full.shape[1] - p, p:full.shape[2] - p] if p else full
        out = np.ascontiguousarray(out)
        out += self.b
        return out
