"""The fast_loop's building blocks in NumPy, their constants folded at load (see hope_models/components/fast_loop/numpy_form.py).

A tick at batch 1 costs what its array operations cost (each ~0.5 us of NumPy dispatch), not its
flops, so each block is as few operations as it can be: a Linear is one product and an in-place
add, a LayerNorm's affine is folded into the product after it (fold_ln), and a GatedMLP's gate and
up projections are one product. Torch-free.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

LN_EPS = 1e-5  # torch.nn.LayerNorm's default, used by every LayerNorm of the fast_loop and the VQ-VAE


class NumpyWindowState(NamedTuple):
    """Recurrent state, as WindowState in ssm.py: h [B, N], ring [B, K, N] (slot `pos` = the oldest), pos."""
    h: np.ndarray
    ring: np.ndarray
    pos: int


def mm(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """x [..., in] times w [in, out]. ndarray.dot for a vector or a matrix (for a vector it dispatches
    in about two thirds of the time of @, and a tick is a dozen of these); @ for 3-D batches, where
    dot has no BLAS path."""
    return x.dot(w) if x.ndim <= 2 else x @ w


@dataclass(frozen=True)
class Linear:
    w_t: np.ndarray  # [in, out]: transposed once at load so a tick is x.dot(w_t) + b
    b: np.ndarray

    def __call__(self, x: np.ndarray) -> np.ndarray:
        y = mm(x, self.w_t)
        y += self.b  # in place on the fresh product: a tick is bound by array-op count and temporaries
        return y


def fold_ln(ln_w: np.ndarray, ln_b: np.ndarray, w: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear(w, b) after a LayerNorm's affine (ln_w, ln_b) as one linear map of the normalised input:
    W (n * ln_w + ln_b) + b = (W diag(ln_w)) n + (W ln_b + b). Returns ([in, out] transposed, bias)."""
    w64 = w.astype(np.float64)
    return (np.ascontiguousarray((w64 * ln_w.astype(np.float64)[None, :]).T.astype(np.float32)),
            (w64 @ ln_b.astype(np.float64) + b.astype(np.float64)).astype(np.float32))


@dataclass(frozen=True)
class NormMLP:
    """GatedMLP(LayerNorm(x)) with the LayerNorm's affine folded into one [d, 2h] product for the
    gate and up projections: w_out(silu(gate) * up). The gate columns are pre-scaled by 1/2 (exact
    in binary), so silu(g) = g' (1 + tanh g') with g' = g / 2: four element-wise ops, no overflow."""
    gu_w: np.ndarray  # [d, 2h]: (w_gate * ln_w / 2 | w_up * ln_w)^T
    gu_b: np.ndarray  # [2h]
    out_w: np.ndarray  # [h, d]
    out_b: np.ndarray
    hidden: int

    @classmethod
    def fold(cls, t: dict[str, np.ndarray], ln: str, mlp: str) -> "NormMLP":
        w = np.concatenate([t[f"{mlp}.w_gate.weight"] * 0.5, t[f"{mlp}.w_up.weight"]])  # [2h, d]
        b = np.concatenate([t[f"{mlp}.w_gate.bias"] * 0.5, t[f"{mlp}.w_up.bias"]])
        gu_w, gu_b = fold_ln(t[f"{ln}.weight"], t[f"{ln}.bias"], w, b)
        return cls(gu_w, gu_b, np.ascontiguousarray(t[f"{mlp}.w_out.weight"].T), t[f"{mlp}.w_out.bias"],
                   t[f"{mlp}.w_gate.weight"].shape[0])

    def __call__(self, n: np.ndarray) -> np.ndarray:
        """n = the LayerNorm's normalised input (before its affine), [..., d]."""
        gu = mm(n, self.gu_w)
        gu += self.gu_b
        g = gu[..., :self.hidden]
        m = np.tanh(g)
        m += np.float32(1.0)
        m *= g
        m *= gu[..., self.hidden:]
        out = mm(m, self.out_w)
        out += self.out_b
        return out


def halved(layer: Linear) -> Linear:
    """The Linear whose output is exactly half of `layer`'s (weights and bias times 1/2: exact in
    binary, and so is every partial sum of its product): what silu_of_half reads."""
    return Linear(layer.w_t * np.float32(0.5), layer.b * np.float32(0.5))


def silu_of_half(g: np.ndarray) -> np.ndarray:
    """silu(x) from g = x / 2 (a halved() Linear's output): g (1 + tanh g), three ops, two of them in
    place, bit-equal to silu(x) = x (1/2 + tanh(x / 2) / 2), whose factors are the same numbers
    scaled by powers of two."""
    m = np.tanh(g)
    m += np.float32(1.0)
    m *= g
    return m


def silu(x: np.ndarray) -> np.ndarray:
    # x * sigmoid(x) through tanh: no overflow warning for large |x| (exp(-x) would overflow)
    return x * (np.float32(0.5) + np.float32(0.5) * np.tanh(np.float32(0.5) * x))


def layer_norm(x: np.ndarray, mean_vec: np.ndarray) -> np.ndarray:
    """(x - mean) / sqrt(var + eps) over the last axis of [..., d] (biased variance, as torch);
    mean_vec = a [d] vector of 1/d, so x @ mean_vec is the mean. The affine is folded elsewhere."""
    xc = x - (x @ mean_vec)[..., None]
    xc /= np.sqrt((xc * xc) @ mean_vec + np.float32(LN_EPS))[..., None]
    return xc


__all__ = ["LN_EPS", "NumpyWindowState", "Linear", "NormMLP", "fold_ln", "halved", "mm", "silu", "silu_of_half", "layer_norm"]
