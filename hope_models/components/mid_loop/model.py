"""Mid Loop: latent dynamics. 1-10 s of codes and past actions -> the codes seconds ahead.

    codes [B, K, G] (frozen VQ-VAE) --Embed, sum over G--+
    previous actions [B, K, act_dim] --Linear-------------+--> SSMStack --> Linear
                                                                --> logits [B, K, H, G, n_codes]

G is the VQ-VAE's code groups: each group's code is a categorical of n_codes, predicted
independently given the history (the log-likelihood of an observation's code is the sum over its
groups). The predicted observation at a horizon is the VQ-VAE's decoder at the expected z_q under
those distributions (VQVAE.decode_expected): one small matrix product, cheap enough per tick.

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
Metrics (mid_loop_metrics.py) compare the model with two baselines on the same targets, both
fitted on the training targets only (counts kept as buffers, so they travel with the weights and
the gate reads the same numbers): copy-last ("the code will not change": the current code with
the training split's probability that a group's code stays the same over that horizon, the rest
spread evenly) and code frequency (each group's code drawn from its training frequencies).

World model (wm_*, when cfg.wm_horizon > 0 and the VQ-VAE reads vectors): the same model
conditioned on the actions still to be taken. At grid point k,

    h = enc(context y_k (the SSM's output, detached), obs_k); then for i = 0 .. M-1:
    h <- h + cell(h, act_{k+i});  obs_{k+i+1} = obs_k + out(h)

with M = wm_horizon and act_j the action held at point j (normalised units throughout). The context
is detached so the world model never changes what the unconditional heads learn (their metrics and
the gate's baselines stay exactly as they were); the exact observation is an input because the
codes keep only ~95 % of its variance and a planner needs the target offset to the centimetre.
Multi-step prediction in a latent (not a one-step model fed its own outputs): trained on all M
steps at once, a planner scores a held action sequence in one pass and no error compounds
through the tokenizer; causal in the actions (see wm_predict). Targets: every point
of the window with M real points after it (world_model_loss, mid_loop_metrics.py). Its parameters
are all named wm_*: the torch-free inference runtime ignores them.

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
from torch import nn

from hope_models.components.meta_init import embedding
from hope_models.components.mid_loop.config import MidLoopConfig
from hope_models.components.ssm import SSMStack, count_params
from hope_models.components.vqvae.model import VQVAE

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
        self.groups = vqvae.cfg.groups
        h, g, n = len(cfg.horizon_steps), self.groups, cfg.n_codes
        self.code_in = embedding(g * n, cfg.d_model)  # one row per code of every group (vqvae.rows)
        self.act_in = nn.Linear(cfg.act_dim, cfg.d_model)
        self.ssm = SSMStack(cfg.ssm_config())
        self.drop = nn.Dropout(cfg.dropout)
        self.head = nn.Linear(cfg.d_model, h * g * n)
        self.obs_dim = vqvae.cfg.obs_dim if vqvae.cfg.input == "vector" else 0
        self.wm_enc = self.wm_cell = self.wm_out = None
        if cfg.wm_horizon > 0 and self.obs_dim > 0:
            d, w = self.obs_dim, cfg.wm_hidden
            self.wm_enc = nn.Sequential(nn.Linear(cfg.d_model + d, w), nn.SiLU(), nn.Linear(w, w))
            self.wm_cell = nn.Sequential(nn.Linear(w + cfg.act_dim, w), nn.SiLU(), nn.Linear(w, w))
            self.wm_out = nn.Linear(w, d)
        self.vqvae = vqvae.requires_grad_(False)  # frozen, saved with our weights (see fast_loop.py)
        # The baselines' statistics, counted on training targets (mid_loop_metrics.count_targets).
        self.register_buffer("code_counts", torch.zeros(g, n, dtype=torch.float64))
        self.register_buffer("stay_counts", torch.zeros(h, g, 2, dtype=torch.float64))  # [changed, stayed]
        log.info("%s", self.describe())

    def describe(self) -> str:
        return (f"MidLoop({self.groups} x {self.cfg.n_codes} codes + act {self.cfg.act_dim} -> codes at "
                f"{list(self.cfg.horizon_steps)} grid steps ahead, d_model {self.cfg.d_model}, "
                f"{self.cfg.n_layers} blocks, state {self.cfg.d_state}): "
                f"{count_params(self, trainable_only=True) / 1e6:.3f} M trainable parameters "
                f"+ frozen VQ-VAE ({count_params(self.vqvae) / 1e6:.3f} M)")

    @property
    def wants_frames(self) -> bool:
        return self.vqvae.cfg.input == "frame"

    def codes(self, obs: torch.Tensor | None, frames: torch.Tensor | None = None) -> torch.Tensor:
        """Codes of observations [..., obs_dim] or frames [..., H, W, 3] -> [..., G] long."""
        if self.wants_frames:
            if frames is None:
                raise ValueError("this Mid Loop's VQ-VAE reads frames: pass frames")
            return self.vqvae.encode(frames.reshape(-1, *frames.shape[-3:])).reshape(*frames.shape[:-3], -1)
        return self.vqvae.encode(obs.reshape(-1, obs.shape[-1])).reshape(*obs.shape[:-1], -1)

    def _inputs(self, codes: torch.Tensor, prev_act: torch.Tensor) -> torch.Tensor:
        return self.code_in(self.vqvae.rows(codes)).sum(-2) + self.act_in(prev_act)

    def _logits(self, y: torch.Tensor) -> torch.Tensor:
        return self.head(self.drop(y)).unflatten(-1, (len(self.cfg.horizon_steps), self.groups, self.cfg.n_codes))

    def forward(self, codes: torch.Tensor, prev_act: torch.Tensor,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        """codes [B, K, G], prev_act [B, K, A] (see previous_actions), mask [B, K] -> logits [B, K, H, G, n_codes]."""
        return self._logits(self.context(codes, prev_act, mask))

    def context(self, codes: torch.Tensor, prev_act: torch.Tensor,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        """The SSM's output at every point [B, K, d_model]: what the heads read."""
        y, _ = self.ssm(self.drop(self._inputs(codes, prev_act)), mask)
        return y

    def heads(self, y: torch.Tensor) -> torch.Tensor:
        """context [..., d_model] -> the unconditional heads' logits [..., H, G, n_codes]."""
        return self._logits(y)

    @property
    def has_world_model(self) -> bool:
        return self.wm_enc is not None

    def wm_predict(self, y: torch.Tensor, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """World model: context [..., d_model], observation [..., D], the actions held at the next
        j <= wm_horizon points [..., j, A] -> the observations after each [..., j, D] (normalised).

        Causal in the actions: the observation after step i reads actions 0..i only. A head fed
        the whole sequence at once would learn, from demos whose actions are the expert's reply
        to the state, to read the next state off the next action, and a planner would exploit it."""
        return self.wm_unroll(self.wm_encode(y, obs), obs, actions)

    def wm_encode(self, y: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """The world model's latent of a state [..., wm_hidden] (a planner encodes once per state)."""
        if self.wm_enc is None:
            raise ValueError("this Mid Loop has no world model (wm_horizon 0, or a frame VQ-VAE)")
        return self.wm_enc(torch.cat([y.detach(), obs], dim=-1))

    def wm_unroll(self, h: torch.Tensor, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Latent h [..., w] of obs [..., D] (both broadcast against actions' leading dims), held
        actions [..., j, A] -> the observations after each [..., j, D]."""
        h = h.expand(*actions.shape[:-2], h.shape[-1])
        out = []
        for a in actions.unbind(-2):
            h = h + self.wm_cell(torch.cat([h, a], dim=-1))  # residual: a held action nudges the state
            out.append(obs + self.wm_out(h))
        return torch.stack(out, dim=-2)

    def init_state(self, batch: int) -> torch.Tensor:
        return self.ssm.init_state(batch)

    def step(self, code_t: torch.Tensor, prev_act_t: torch.Tensor,
             state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One grid point: code_t [B, G], the previous point's action [B, A] -> (logits [B, H, G, n_codes], state)."""
        y, state = self.ssm.step(self._inputs(code_t, prev_act_t), state)
        return self._logits(y), state

    def predicted_observation(self, logits: torch.Tensor) -> torch.Tensor:
        """logits [..., G, n_codes] -> the expected observation (normalised vector, or frame) [..., ...]."""
        probs = logits.softmax(-1)
        lead = probs.shape[:-2]
        out = self.vqvae.decode_expected(probs.reshape(-1, *probs.shape[-2:]))
        return out.reshape(*lead, *out.shape[1:])
