"""The Mid Loop's SSMStack in NumPy over a window of grid points, shared by its two NumPy forms
(numpy_form.py: codes of a vector VQ-VAE; numpy_grid.py: cells of a grid frame VQ-VAE).

    blocks = [SSMBlockNumpy(tensors, f"ssm.blocks.{i}", k) for i in range(n_layers)]
    x = run_window(blocks, x [L, d], mean, last_only)      # the blocks' residual stream, before ln_f
    ahead = window_ahead(blocks, x [L - 1, d])             # a window but its last point, then
    advance(blocks, ahead, mean)                           # one stage a call (True: complete)
    x = step_last(blocks, x_last [d], ahead.states, mean)  # its last point: one step a block

The arithmetic is SSMBlock/DiagonalSSM in hope_models/components/ssm.py, float32: per block
u = LN1(x), h_t = sum_{s<=t} a^(t-s) g (B u_s) (the parallel form over the window, from a zero
state), x += C h + D u, x += GatedMLP(LN2(x)). Torch-free.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hope_models.components.numpy_layers import LN_EPS, NormMLP, fold_ln, layer_norm


class SSMBlockNumpy:
    """One SSMBlock's weights, with DiagonalSSM's constants computed as torch does (float32)."""

    def __init__(self, t: dict[str, np.ndarray], p: str, k: int):
        self.ln1_w, self.ln1_b = t[f"{p}.ln1.weight"], t[f"{p}.ln1.bias"]
        self.mlp = NormMLP.fold(t, f"{p}.ln2", f"{p}.mlp")
        log_a = -np.exp(t[f"{p}.ssm.log_rate"].astype(np.float32))  # DiagonalSSM.log_a: no clamp
        gain = np.sqrt(-np.expm1(np.float32(2.0) * log_a)).astype(np.float32)
        self.a = np.exp(log_a).astype(np.float32)
        self.bg_t = np.ascontiguousarray(t[f"{p}.ssm.B"].T * gain[None, :])  # [d, N]
        self.c_t = np.ascontiguousarray(t[f"{p}.ssm.C"].T)  # [N, d]
        self.d = t[f"{p}.ssm.D"]
        lag = np.arange(k, dtype=np.float32)[:, None] - np.arange(k, dtype=np.float32)[None, :]
        causal = lag >= 0
        # kernel[t, s] = a^(t-s) for s <= t: DiagonalSSM._chunk's, which depends on t - s only, so
        # the top-left [L, L] corner is the kernel of an L-point window
        self.kernel = (np.exp(np.where(causal, lag, 0.0)[..., None] * log_a) * causal[..., None]).astype(np.float32)
        # step_last's one point: LN1's affine folded into B (and into D, an element-wise product)
        self.bg_ln, self.bg_lb = fold_ln(self.ln1_w, self.ln1_b, self.bg_t.T, np.zeros(self.a.shape[0], np.float32))
        f64 = np.float64
        self.d_w = (self.ln1_w.astype(f64) * self.d.astype(f64)).astype(np.float32)
        self.d_b = (self.ln1_b.astype(f64) * self.d.astype(f64)).astype(np.float32)

    def ln1(self, x: np.ndarray, mean: np.ndarray) -> np.ndarray:
        u = layer_norm(x, mean)
        u *= self.ln1_w
        u += self.ln1_b
        return u


def run_window(blocks: list[SSMBlockNumpy], x: np.ndarray, mean: np.ndarray, last_only: bool = False) -> np.ndarray:
    """The blocks over a window from a zero state: x [L, d] -> [L, d] (last_only: [1, d], the last
    block's MLP run on the last point only). mean: a [d] vector of 1/d (layer_norm's)."""
    length = x.shape[0]
    for i, blk in enumerate(blocks):
        u = blk.ln1(x, mean)
        v = u.dot(blk.bg_t)  # [L, N]
        # [L, N]: sum_{s<=t} a^(t-s) v_s (einsum: 2.5x faster than a broadcast product and a sum at K=20)
        h = np.einsum("tsn,sn->tn", blk.kernel[:length, :length], v)
        y = h.dot(blk.c_t)
        y += u * blk.d
        x = x + y
        if last_only and i == len(blocks) - 1:
            x = x[-1:]
        x = x + blk.mlp(layer_norm(x, mean))
    return x


@dataclass(eq=False)
class WindowAhead:
    """The blocks' SSM states after a window's points from a zero state, computed a stage at a time
    (advance(): a block's SSM, then its MLP; the last block's SSM alone, its outputs being unread):
    what step_last() continues from, so a window's last point costs one recurrent step a block
    (the same sums as the parallel form's, up to float32 rounding)."""
    x: np.ndarray  # [L, d]: the residual stream over the points, as far as the stages done
    states: np.ndarray  # [n_layers, N]: each done block's state after the last of the points
    done: int = 0  # stages done: block i's SSM is stage 2i, its MLP 2i + 1

    def complete(self) -> bool:
        return self.done == 2 * self.states.shape[0] - 1 or not self.x.shape[0]


def window_ahead(blocks: list[SSMBlockNumpy], x: np.ndarray) -> WindowAhead:
    """A WindowAhead of a window's points x [L, d] (L may be 0: zero states), no stage done yet."""
    return WindowAhead(x, np.zeros((len(blocks), blocks[0].a.shape[0]), np.float32))


def advance(blocks: list[SSMBlockNumpy], ahead: WindowAhead, mean: np.ndarray) -> bool:
    """One more stage of `ahead` (nothing when it is complete) -> whether it is complete now."""
    if ahead.complete():
        return True
    blk, x = blocks[ahead.done // 2], ahead.x
    if ahead.done % 2:  # the block's MLP
        ahead.x = x + blk.mlp(layer_norm(x, mean))
    else:
        length = x.shape[0]
        u = blk.ln1(x, mean)
        h = np.einsum("tsn,sn->tn", blk.kernel[:length, :length], u.dot(blk.bg_t))
        ahead.states[ahead.done // 2] = h[-1]
        if ahead.done < 2 * len(blocks) - 2:  # the last block's outputs are not read: only its state
            x = x + h.dot(blk.c_t)
            x += u * blk.d
            ahead.x = x
    ahead.done += 1
    return ahead.complete()


def states_ahead(blocks: list[SSMBlockNumpy], x: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """Every block of window_ahead(blocks, x) at once -> the states [n_layers, N]."""
    ahead = window_ahead(blocks, x)
    while not advance(blocks, ahead, mean):
        pass
    return ahead.states


def step_last(blocks: list[SSMBlockNumpy], x: np.ndarray, states: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """A window's last point x [d] from states_ahead() of the points before it -> the blocks'
    residual stream [d] at that point (before ln_f), as run_window(..., last_only=True) computes it."""
    inv_d = 1.0 / x.shape[-1]
    for i, blk in enumerate(blocks):
        # one vector: LayerNorm's statistics as Python floats, LN1's affine folded at load
        n = x - float(x.dot(mean))
        n *= 1.0 / math.sqrt(float(n.dot(n)) * inv_d + LN_EPS)
        h = n.dot(blk.bg_ln)
        h += blk.bg_lb
        h += blk.a * states[i]
        x = x + h.dot(blk.c_t)
        du = n * blk.d_w
        du += blk.d_b
        x += du
        n = x - float(x.dot(mean))
        n *= 1.0 / math.sqrt(float(n.dot(n)) * inv_d + LN_EPS)
        x = x + blk.mlp(n)
    return x


__all__ = ["SSMBlockNumpy", "WindowAhead", "advance", "run_window", "states_ahead", "step_last", "window_ahead"]
