"""Diagonal linear recurrences (state-space layers): the Mid Loop's residual stack and the Fast Loop's
window-exact layer.

The recurrence, per batch row, with a real diagonal decay (the simplest stable choice):

    h_t = a * h_{t-1} + g * (B u_t)        h: [d_state], a, g: [d_state], B: [d_state, d_model]
    y_t = C h_t + D * u_t                  C: [d_model, d_state], D: [d_model]

    a = exp(-exp(log_rate)) in (0, 1)      so the recurrence is stable for any parameter value
    g = sqrt(1 - a^2)                      keeps the state's scale independent of its timescale

Two forms compute the same thing:
- forward(u [B, L, d]): the parallel form for training. Unrolled, h_t = sum_{s<=t} a^(t-s) g B u_s
  (+ a^(t+1) h0), an explicit causal decay kernel a^(t-s) over a chunk of up to `chunk` steps (our
  windows are 5-20 grid points). Longer inputs run chunk by chunk, carrying the state, so memory
  stays O(chunk^2 * d_state) whatever L is.
- step(u_t [B, d], h [B, d_state]): the recurrent form for inference, O(1) per tick.
They agree to float32 rounding (tested within 1e-5): the kernel computes a^(t-s) as
exp((t-s) log a), the step multiplies by a once per tick.

Masks: windows start with zero-filled points before an episode's first step. SSMBlock multiplies
its SSM input by the mask, so the state stays exactly zero across such a prefix, in every layer:
a window with a masked prefix gives the same output as stepping from a fresh state over its valid
points only, which is how inference starts an episode.

WindowSSM (the Fast Loop's one layer) is the same recurrence restricted to the last K inputs, so
that a policy stepped forever computes exactly what it was trained on (see its docstring).
DiagonalSSM / SSMStack (the Mid Loop) remember their whole input: stepping them past K points gives
what forward() gives on the whole stepped sequence, not on the last K points.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from hope_models.components.meta_init import initial
from hope_models.components.ssm_config import SSMConfig


class DiagonalSSM(nn.Module):
    def __init__(self, d_model: int, d_state: int, min_timescale: float = 1.0, max_timescale: float = 64.0,
                 chunk: int = 64):
        super().__init__()
        if not 0 < min_timescale <= max_timescale:
            raise ValueError(f"min_timescale={min_timescale} and max_timescale={max_timescale} must satisfy "
                             "0 < min <= max")
        self.d_model, self.d_state, self.chunk = d_model, d_state, chunk
        # rate = 1 / timescale; a = exp(-rate). Log-spaced timescales: some channels forget within a
        # grid step, others remember the whole window.
        self.log_rate = nn.Parameter(initial((d_state,), lambda: -torch.log(torch.logspace(
            math.log10(min_timescale), math.log10(max_timescale), d_state))))
        self.B = nn.Parameter(initial((d_state, d_model), lambda: torch.randn(d_state, d_model) / math.sqrt(d_model)))
        self.C = nn.Parameter(initial((d_model, d_state), lambda: torch.randn(d_model, d_state) / math.sqrt(d_state)))
        self.D = nn.Parameter(torch.ones(d_model))  # the usual S4/Mamba skip, initialised to 1

    def log_a(self) -> torch.Tensor:
        return -torch.exp(self.log_rate)  # log of the decay, < 0

    def _gain(self, log_a: torch.Tensor) -> torch.Tensor:
        # sqrt(1 - a^2) = sqrt(-expm1(2 log a)): accurate when a is close to 1
        return torch.sqrt(-torch.expm1(2.0 * log_a))

    def forward(self, u: torch.Tensor, h0: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Parallel form: u [B, L, d_model] -> (y [B, L, d_model], h_L [B, d_state])."""
        b, length, _ = u.shape
        log_a = self.log_a()
        v = (u @ self.B.t()) * self._gain(log_a)  # [B, L, N]: the input each step adds to the state
        h = u.new_zeros(b, self.d_state) if h0 is None else h0
        states = []
        for start in range(0, length, self.chunk):
            vc = v[:, start:start + self.chunk]
            hs = self._chunk(vc, log_a, h)
            states.append(hs)
            h = hs[:, -1]
        hs = torch.cat(states, dim=1) if len(states) > 1 else states[0]
        y = hs @ self.C.t() + u * self.D
        return y, h

    def _chunk(self, v: torch.Tensor, log_a: torch.Tensor, h0: torch.Tensor) -> torch.Tensor:
        """States [B, L, N] of one chunk: h_t = sum_{s<=t} a^(t-s) v_s + a^(t+1) h0."""
        length = v.shape[1]
        t = torch.arange(length, device=v.device, dtype=v.dtype)
        lag = t[:, None] - t[None, :]  # [L, L], t - s
        causal = lag >= 0
        # exponent zeroed above the diagonal before exp, so no inf * 0 reaches the gradient
        kernel = torch.exp(torch.where(causal, lag, 0.0)[..., None] * log_a) * causal[..., None]  # [L, L, N]
        hs = torch.einsum("tsn,bsn->btn", kernel, v)
        return hs + torch.exp((t[:, None] + 1.0) * log_a)[None] * h0[:, None, :]

    def step(self, u_t: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Recurrent form: u_t [B, d_model], h [B, d_state] -> (y_t [B, d_model], new h)."""
        log_a = self.log_a()
        h = torch.exp(log_a) * h + (u_t @ self.B.t()) * self._gain(log_a)
        return h @ self.C.t() + u_t * self.D, h


class GatedMLP(nn.Module):
    """w_out(silu(w_gate x) * w_up x): the per-position mixing after each SSM."""

    def __init__(self, d_model: int, hidden: int):
        super().__init__()
        self.w_gate = nn.Linear(d_model, hidden)
        self.w_up = nn.Linear(d_model, hidden)
        self.w_out = nn.Linear(hidden, d_model)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.w_out(F.silu(self.w_gate(x)) * self.w_up(x))


class SSMBlock(nn.Module):
    """Pre-norm residual block: x + SSM(norm(x) * mask), then x + MLP(norm(x))."""

    def __init__(self, cfg: SSMConfig):
        super().__init__()
        self.ln1 = nn.LayerNorm(cfg.d_model)
        self.ssm = DiagonalSSM(cfg.d_model, cfg.d_state, cfg.min_timescale, cfg.max_timescale, cfg.chunk)
        self.ln2 = nn.LayerNorm(cfg.d_model)
        self.mlp = GatedMLP(cfg.d_model, cfg.mlp_ratio * cfg.d_model)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                h0: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """x [B, L, d], mask [B, L] (True = a real point) -> (x [B, L, d], final state [B, d_state])."""
        u = self.ln1(x)
        if mask is not None:
            u = u * mask[..., None].to(u.dtype)
        y, h = self.ssm(u, h0)
        x = x + y
        return x + self.mlp(self.ln2(x)), h

    def step(self, x_t: torch.Tensor, h: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        y, h = self.ssm.step(self.ln1(x_t), h)
        x_t = x_t + y
        return x_t + self.mlp(self.ln2(x_t)), h


class SSMStack(nn.Module):
    """n_layers SSMBlocks and a final norm. The recurrent state is one tensor [n_layers, B, d_state]."""

    def __init__(self, cfg: SSMConfig):
        super().__init__()
        self.cfg = cfg
        self.blocks = nn.ModuleList(SSMBlock(cfg) for _ in range(cfg.n_layers))
        self.ln_f = nn.LayerNorm(cfg.d_model)

    def init_state(self, batch: int) -> torch.Tensor:
        ref = self.ln_f.weight
        return ref.new_zeros(self.cfg.n_layers, batch, self.cfg.d_state)

    def forward(self, x: torch.Tensor, mask: torch.Tensor | None = None,
                state: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """x [B, L, d] -> (normed outputs [B, L, d], state after the last point)."""
        finals = []
        for i, block in enumerate(self.blocks):
            x, h = block(x, mask, None if state is None else state[i])
            finals.append(h)
        return self.ln_f(x), torch.stack(finals)

    def step(self, x_t: torch.Tensor, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x_t [B, d], state [n_layers, B, d_state] -> (output [B, d], new state)."""
        new = []
        for i, block in enumerate(self.blocks):
            x_t, h = block.step(x_t, state[i])
            new.append(h)
        return self.ln_f(x_t), torch.stack(new)


class WindowState(NamedTuple):
    """Recurrent state of a WindowSSM: O(K * d_state) memory, whatever the run length."""
    h: torch.Tensor  # [B, d_state], the state over the last K inputs
    ring: torch.Tensor  # [B, K, d_state], the last K state inputs v (slot `pos` holds the oldest)
    pos: int  # the slot the next input goes to; 0 = the ring is in time order, oldest first


class WindowSSM(nn.Module):
    """A diagonal linear recurrence that sees exactly its last `window` (K) inputs.

    The state at t is the recurrence of DiagonalSSM started from zero K points back:

        h_t = sum_{j<K} a^j v_{t-j}        v_s = g * (B u_s),   y_t = C h_t + D * u_t

    which is what a window of K points (zero state at its start, masked points = zero input) gives.
    - forward(u [B, L, d]): the parallel form, this truncated kernel at every point of the input,
      each point's state from the K inputs ending there (before the input's start: zeros).
    - step(u_t, state): the recurrent form, O(d_state) per tick:

          h_t = a * h_{t-1} + v_t - a^K * v_{t-K}

      v_{t-K} comes from a ring buffer of the last K inputs. Without the last term the state
      would remember everything since init_state(), and after K ticks the stepped policy would no
      longer compute the function it was trained on (a K-point window).

    Drift: the subtraction is exact in real arithmetic but not in float32, and a rounding error
    only decays as a^n (for a channel with a close to 1 it would random-walk over a long run).
    So each time the ring wraps (every K ticks, when it is in time order) the state is recomputed
    exactly from the ring, as the parallel form computes it (O(K * d_state), once per K ticks).
    The error is then bounded by K - 1 recurrence steps' rounding, for any decay and any run
    length (tested over 2000 ticks against forward() on each trailing window within 1e-5).

    Decays: a = exp(-rate), rate = exp(log_rate) clamped to [RATE_MIN, RATE_MAX] so a is never 0 or
    1 in float32; timescales much longer than K all look alike within a window anyway. The gain
    g = sqrt((1 - a^2) / (1 - a^(2K))) gives each channel unit variance for white unit input over a
    K-point window, from g = 1 (memoryless) to 1/sqrt(K) (a near 1).
    """

    RATE_MIN = 1e-4  # timescale 10^4 steps: a = 0.9999
    RATE_MAX = 20.0  # a = 2e-9: memoryless

    def __init__(self, d_model: int, d_state: int, window: int, min_timescale: float = 1.0,
                 max_timescale: float = 16.0):
        super().__init__()
        if window < 1:
            raise ValueError(f"window={window} (grid points the layer sees) must be >= 1")
        if not 0 < min_timescale <= max_timescale:
            raise ValueError(f"min_timescale={min_timescale} and max_timescale={max_timescale} must satisfy "
                             "0 < min <= max")
        self.d_model, self.d_state, self.window = d_model, d_state, window
        self.log_rate = nn.Parameter(initial((d_state,), lambda: -torch.log(torch.logspace(
            math.log10(min_timescale), math.log10(max_timescale), d_state))))
        self.B = nn.Parameter(initial((d_state, d_model), lambda: torch.randn(d_state, d_model) / math.sqrt(d_model)))
        self.C = nn.Parameter(initial((d_model, d_state), lambda: torch.randn(d_model, d_state) / math.sqrt(d_state)))
        self.D = nn.Parameter(torch.ones(d_model))

    def log_a(self) -> torch.Tensor:
        return -torch.exp(self.log_rate.clamp(math.log(self.RATE_MIN), math.log(self.RATE_MAX)))

    def _consts(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(powers a^0..a^K [K+1, N], window kernel a^(K-1-i) [N, K] oldest first, gain [N])."""
        log_a = self.log_a()
        k = self.window
        powers = torch.exp(torch.arange(k + 1, dtype=log_a.dtype, device=log_a.device)[:, None] * log_a)
        kernel = powers[:k].flip(0).t()
        gain = torch.sqrt(torch.expm1(2.0 * log_a) / torch.expm1(2.0 * k * log_a))
        return powers, kernel, gain

    def forward(self, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Parallel form: u [B, L, d_model] -> (y [B, L, d_model], states h [B, L, d_state])."""
        _, kernel, gain = self._consts()
        v = (u @ self.B.t()) * gain
        windows = F.pad(v, (0, 0, self.window - 1, 0)).unfold(1, self.window, 1)  # [B, L, N, K], oldest first
        h = (windows * kernel).sum(-1)
        return h @ self.C.t() + u * self.D, h

    def init_state(self, batch: int) -> WindowState:
        ref = self.B
        return WindowState(ref.new_zeros(batch, self.d_state), ref.new_zeros(batch, self.window, self.d_state), 0)

    def step(self, u_t: torch.Tensor, state: WindowState) -> tuple[torch.Tensor, WindowState]:
        """Recurrent form: u_t [B, d_model], state -> (y_t [B, d_model], new state). Never mutates `state`."""
        powers, kernel, gain = self._consts()
        k = self.window
        v = (u_t @ self.B.t()) * gain
        h = powers[1] * state.h + v - powers[k] * state.ring[:, state.pos]
        ring = state.ring.clone()
        ring[:, state.pos] = v
        pos = (state.pos + 1) % k
        if pos == 0:  # the ring is in time order: recompute exactly, as forward() does (see Drift)
            h = (ring.transpose(1, 2) * kernel).sum(-1)
        return h @ self.C.t() + u_t * self.D, WindowState(h, ring, pos)


def count_params(module: nn.Module, trainable_only: bool = False) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad or not trainable_only)
