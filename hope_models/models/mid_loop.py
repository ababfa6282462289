"""Mid Loop: latent dynamics. 1-10 s of codes and past actions -> the codes seconds ahead.

    codes [B, K] (frozen VQ-VAE) --Embed--+
    previous actions [B, K, act_dim] --Linear--+--> SSMStack --> Linear --> logits [B, K, H, n_codes]

At every grid point k the model predicts the code at k + s_h grid steps for each horizon h
(horizon_steps, e.g. (5, 10) = 0.5 s and 1 s on the default 2 s / K=20 window's 100 ms grid).

Actions: the input at point k is the action held at point k-1 (zeros at k=0), i.e. only actions
already taken before the point's time. The action at k itself, and so the anchor's own action
act[:, -1], is never an input: the same rule as the Fast Loop, and at inference the predictor
needs only what has happened.

Training targets (mid_loop_loss), all through the frozen VQ-VAE:
- inside the window: the code at point k + s_h, for every point k where that is still inside the
  window (and both points are real, not the masked pre-episode prefix). This is teacher forcing
  at every position, which a causal SSM gets for free: many targets per window, not one;
- beyond the window: the code of the held observation at anchor time + horizon (the window
  batch's future_obs, or future_frames when the data layer provides them), for the last point,
  where future_mask says the episode still runs.
Metrics: accuracy, and copy_last_accuracy, the baseline that predicts "the code will not change"
(the code at k for every horizon), on the same targets; anchor_* versions on the beyond-window
targets only (the prediction inference actually uses).

Two forms: forward() over a window, init_state()/step() one grid point at a time; stepping a
window's points from init_state() gives forward()'s logits at every point (tested within 1e-5).
Unlike the Fast Loop, the stepped form is NOT window-exact: the two-block SSMStack remembers
everything since init_state(), so after more than K points it no longer computes what training
saw (K-point windows). The Fast Loop's fix (one WindowSSM layer, ssm.py) does not carry over
trivially: the Mid Loop stacks two SSM layers with nonlinearities between them, and a second
layer's inputs already hold history from before the window, so no ring buffer of its inputs can
remove it. The Mid Loop is a predictor (planning, imagination), not stepped per control tick:
call forward() on the last K grid points (make_windows), or init_state() and step through them.
"""
from __future__ import annotations

import logging

import torch
import torch.nn.functional as F
from torch import nn

from hope_models.models.configs import MidLoopConfig
from hope_models.models.ssm import SSMStack, count_params
from hope_models.models.vqvae import VQVAE

log = logging.getLogger(__name__)


def previous_actions(act: torch.Tensor) -> torch.Tensor:
    """[B, K, A] held actions -> the action held one point earlier (zeros at k=0): act[:, -1] dropped."""
    return torch.cat([torch.zeros_like(act[:, :1]), act[:, :-1]], dim=1)


class MidLoop(nn.Module):
    def __init__(self, cfg: MidLoopConfig, vqvae: VQVAE):
        super().__init__()
        cfg.validate()
        if vqvae is None or vqvae.cfg.n_codes != cfg.n_codes:
            raise ValueError(f"the Mid Loop needs a VQ-VAE with n_codes={cfg.n_codes} codes")
        self.cfg = cfg
        self.code_in = nn.Embedding(cfg.n_codes, cfg.d_model)
        self.act_in = nn.Linear(cfg.act_dim, cfg.d_model)
        self.ssm = SSMStack(cfg.ssm_config())
        self.head = nn.Linear(cfg.d_model, len(cfg.horizon_steps) * cfg.n_codes)
        self.vqvae = vqvae.requires_grad_(False)  # frozen, saved with our weights (see fast_loop.py)
        log.info("%s", self.describe())

    def describe(self) -> str:
        return (f"MidLoop(codes {self.cfg.n_codes} + act {self.cfg.act_dim} -> codes at "
                f"{list(self.cfg.horizon_steps)} grid steps ahead, d_model {self.cfg.d_model}, "
                f"{self.cfg.n_layers} blocks, state {self.cfg.d_state}): "
                f"{count_params(self, trainable_only=True) / 1e6:.3f} M trainable parameters "
                f"+ frozen VQ-VAE ({count_params(self.vqvae) / 1e6:.3f} M)")

    @property
    def wants_frames(self) -> bool:
        return self.vqvae.cfg.input == "frame"

    def codes(self, obs: torch.Tensor | None, frames: torch.Tensor | None = None) -> torch.Tensor:
        """Codes of observations [..., obs_dim] or frames [..., H, W, 3] -> [...] long."""
        if self.wants_frames:
            if frames is None:
                raise ValueError("this Mid Loop's VQ-VAE reads frames: pass frames")
            return self.vqvae.encode(frames.reshape(-1, *frames.shape[-3:])).reshape(frames.shape[:-3])
        return self.vqvae.encode(obs.reshape(-1, obs.shape[-1])).reshape(obs.shape[:-1])

    def _logits(self, y: torch.Tensor) -> torch.Tensor:
        return self.head(y).unflatten(-1, (len(self.cfg.horizon_steps), self.cfg.n_codes))

    def forward(self, codes: torch.Tensor, prev_act: torch.Tensor,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        """codes [B, K], prev_act [B, K, A] (see previous_actions), mask [B, K] -> logits [B, K, H, n_codes]."""
        y, _ = self.ssm(self.code_in(codes) + self.act_in(prev_act), mask)
        return self._logits(y)

    def init_state(self, batch: int) -> torch.Tensor:
        return self.ssm.init_state(batch)

    def step(self, code_t: torch.Tensor, prev_act_t: torch.Tensor,
             state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One grid point: code_t [B], the previous point's action [B, A] -> (logits [B, H, n_codes], state)."""
        y, state = self.ssm.step(self.code_in(code_t) + self.act_in(prev_act_t), state)
        return self._logits(y), state


def mid_loop_loss(logits: torch.Tensor, codes: torch.Tensor, mask: torch.Tensor, horizon_steps: tuple[int, ...],
                  future_codes: torch.Tensor | None = None,
                  future_mask: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Cross-entropy over the in-window and beyond-window targets (see the module doc).

    logits [B, K, H, n], codes [B, K], mask [B, K] bool, future_codes/future_mask [B, H].
    """
    k = codes.shape[1]
    preds, targets, copies = [], [], []
    for h, s in enumerate(horizon_steps):
        if s < k:
            valid = mask[:, :k - s] & mask[:, s:]
            preds.append(logits[:, :k - s, h][valid])
            targets.append(codes[:, s:][valid])
            copies.append(codes[:, :k - s][valid])
    n_window = sum(int(t.numel()) for t in targets)
    metrics: dict[str, float] = {}
    if future_codes is not None:
        fmask = torch.ones_like(future_codes, dtype=torch.bool) if future_mask is None else future_mask
        anchor_logits = logits[:, -1][fmask]
        anchor_targets = future_codes[fmask]
        anchor_copy = codes[:, -1:].expand_as(future_codes)[fmask]
        preds.append(anchor_logits)
        targets.append(anchor_targets)
        copies.append(anchor_copy)
        if anchor_targets.numel():
            metrics["anchor_accuracy"] = float((anchor_logits.argmax(-1) == anchor_targets).float().mean())
            metrics["anchor_copy_last_accuracy"] = float((anchor_copy == anchor_targets).float().mean())
    if sum(int(t.numel()) for t in targets) == 0:
        # e.g. every anchor within a horizon of its episode's start and end: nothing to learn from
        # this batch, which must not stop a run. A zero loss that still has a graph (backward works).
        return logits.sum() * 0.0, {"targets": 0.0, "window_targets": 0.0}
    pred, target, copy = torch.cat(preds), torch.cat(targets), torch.cat(copies)
    loss = F.cross_entropy(pred, target)
    metrics.update({
        "accuracy": float((pred.argmax(-1) == target).float().mean()),
        "copy_last_accuracy": float((copy == target).float().mean()),
        "targets": float(target.numel()),
        "window_targets": float(n_window),
    })
    return loss, metrics
