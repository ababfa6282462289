"""Fast Loop: the reflex policy. The last K grid points of observations (and their codes) -> the action.

    obs [B, K, obs_dim] --Linear--+                                  per point (no mixing in time)
    codes [B, K, G] (frozen VQ-VAE, optional) --Embed, sum over G--+--> x = e + GatedMLP(LN(e))
                                                           |
                  u = LN(x) * mask --> WindowSSM (the ONLY mixing in time: exactly the last K points)
                                                           |
                  z = x + y (+ CodeKeypoints(codes): a grid VQ-VAE's cells, where things are in view)
                  z = z + GatedMLP(LN(z)) ;  action = Linear(LN(z))   per point, last point

Trained by behaviour cloning: MSE between the predicted and the recorded action at the anchor
(both normalised by the dataset's feature spec). Only observations are inputs: the window's
actions are not, so the anchor's own action (the target, act[:, -1]) can never leak in.

Window-exact by construction. Training sees K-point windows (100 ms, K=5 on the 20 ms grid, zero
state at the window's start), while the robot steps the policy once per control tick for as long
as it runs. So the recurrent form must compute the same function of the last K observations at
every tick, forever. Everything except the one SSM layer is pointwise (a function of the current
grid point only), and that layer, a WindowSSM, keeps exactly its last K inputs (a ring buffer and
a subtracted a^K term, see ssm.py). A stack of several SSM layers with nonlinearities between them
cannot be truncated this way (the second layer's inputs already carry history from before the
window), which is why there is one wide diagonal layer between a pointwise encoder and head.

Two forms, one function:
- forward(obs, mask, frames): the whole window at once (training, validation) -> the last point's
  action. actions(...) gives the action at every point of a longer sequence, each from the K
  points ending there.
- init_state(batch) / step(obs_t, state, frame_t): one control tick, O(1) work and memory per
  tick whatever the run length. After any number of ticks the action equals forward() over the
  last K observations (tested within 1e-5 over 2000 ticks). Call init_state() at an episode's
  start: its first K-1 ticks then equal forward() on windows whose points before the episode
  start are masked and zero-filled, exactly as make_windows builds them.
"""
from __future__ import annotations

import logging

import torch
from torch import nn

from hope_models.components.code_keypoints import CodeKeypoints
from hope_models.components.fast_loop.config import FastLoopConfig
from hope_models.components.meta_init import embedding
from hope_models.components.ssm import GatedMLP, WindowSSM, WindowState, count_params
from hope_models.components.vqvae.model import VQVAE

log = logging.getLogger(__name__)


class FastLoop(nn.Module):
    def __init__(self, cfg: FastLoopConfig, vqvae: VQVAE | None = None):
        super().__init__()
        cfg.validate()
        if (vqvae is None) != (cfg.n_codes == 0):
            raise ValueError(f"n_codes={cfg.n_codes} needs a VQ-VAE with that many codes (and 0 without one)")
        if vqvae is not None and vqvae.cfg.n_codes != cfg.n_codes:
            raise ValueError(f"n_codes={cfg.n_codes} but the VQ-VAE has {vqvae.cfg.n_codes} codes")
        self.cfg = cfg
        d, hidden = cfg.d_model, cfg.mlp_ratio * cfg.d_model
        self.obs_in = nn.Linear(cfg.obs_dim, d)
        # one embedding row per code of every group (the VQ-VAE's table rows); a point's code
        # embedding is the sum of its G groups' rows. A grid's cells are read as keypoints: a sum
        # would say what is in view, never where.
        self.code_in = self.keypoints = None
        if vqvae is not None and vqvae.cfg.input == "frame" and vqvae.cfg.layout == "grid":
            self.keypoints = CodeKeypoints(vqvae.cfg.n_codes, vqvae.cfg.grid_shape, cfg.keypoints, d,
                                           reader=cfg.keypoint_reader, view_frame=cfg.view_joint >= 0,
                                           draw=cfg.keypoint_draw, code_dim=vqvae.cfg.code_dim // vqvae.cfg.groups)
        elif vqvae is not None:
            self.code_in = embedding(vqvae.codebook.shape[0], d)
        self.enc_ln = nn.LayerNorm(d)
        self.enc_mlp = GatedMLP(d, hidden)
        self.ssm_ln = nn.LayerNorm(d)
        self.ssm = WindowSSM(d, cfg.d_state, cfg.window_k, cfg.min_timescale, cfg.max_timescale)
        self.head_ln = nn.LayerNorm(d)
        self.head_mlp = GatedMLP(d, hidden)
        self.out_ln = nn.LayerNorm(d)
        self.out = nn.Linear(d, cfg.act_dim)
        # The tokenizer rides along frozen: its weights are saved with ours (one self-contained
        # checkpoint for inference), it gets no gradient, and encode() never changes its codebook.
        self.vqvae = vqvae.requires_grad_(False) if vqvae is not None else None
        log.info("%s", self.describe())

    def describe(self) -> str:
        frozen = 0 if self.vqvae is None else count_params(self.vqvae)
        codes = "" if self.vqvae is None else f" + codes of a frozen VQ-VAE ({frozen / 1e6:.3f} M, not trained)"
        return (f"FastLoop(obs {self.cfg.obs_dim}{' + codes' if self.vqvae is not None else ''} -> act "
                f"{self.cfg.act_dim}, d_model {self.cfg.d_model}, one window-exact SSM layer (state "
                f"{self.cfg.d_state}, K={self.cfg.window_k})): "
                f"{count_params(self, trainable_only=True) / 1e6:.3f} M trainable parameters{codes}")

    @property
    def wants_frames(self) -> bool:
        return self.vqvae is not None and self.vqvae.cfg.input == "frame"

    def codes(self, obs: torch.Tensor, frames: torch.Tensor | None = None) -> torch.Tensor:
        """Codes of each point: obs [..., obs_dim] or frames [..., H, W, 3] -> [..., G] long."""
        if self.wants_frames:
            if frames is None:
                raise ValueError("this Fast Loop's VQ-VAE reads frames: pass frames")
            lead = frames.shape[:-3]
            return self.vqvae.encode(frames.reshape(-1, *frames.shape[-3:])).reshape(*lead, -1)
        lead = obs.shape[:-1]
        return self.vqvae.encode(obs.reshape(-1, obs.shape[-1])).reshape(*lead, -1)

    # -- pointwise parts: functions of one grid point, so the same in both forms -----------------

    def _encode(self, obs: torch.Tensor, frames: torch.Tensor | None, codes: torch.Tensor | None = None) -> torch.Tensor:
        e = self.obs_in(obs)
        if self.code_in is not None:
            if codes is None:  # precomputed codes (a dataset's code table) spare the frozen encoder
                codes = self.codes(obs, frames)
            e = e + self.code_in(self.vqvae.rows(codes)).sum(-2)
        return e + self.enc_mlp(self.enc_ln(e))

    def _head(self, z: torch.Tensor, obs: torch.Tensor, frames: torch.Tensor | None,
              codes: torch.Tensor | None, located: tuple | None = None) -> torch.Tensor:
        if self.keypoints is not None:
            # Where things are in view enters here, at the acting point only: 256 cells x K points
            # through the SSM cost 5x more per step and a static scene gains nothing from a window.
            if codes is None and located is None:  # located: the drawing has read the codes already
                codes = self.codes(obs, frames)
            z = z + self.keypoints(codes, self.view_angle(obs), located)
        z = z + self.head_mlp(self.head_ln(z))
        return self.out(self.out_ln(z))

    def view_angle(self, obs: torch.Tensor) -> torch.Tensor | None:
        """The joint angle (radians) the keypoints are turned by, from normalised obs [..., obs_dim]."""
        j = self.cfg.view_joint
        return None if j < 0 else obs[..., j] * self.cfg.view_joint_std + self.cfg.view_joint_mean

    # -- the two forms ---------------------------------------------------------------------------

    def _trunk(self, obs: torch.Tensor, mask: torch.Tensor | None, frames: torch.Tensor | None,
               codes: torch.Tensor | None = None) -> torch.Tensor:
        x = self._encode(obs, frames, codes)
        u = self.ssm_ln(x)
        if mask is not None:  # points before the episode's start add nothing to the state
            u = u * mask[..., None].to(u.dtype)
        y, _ = self.ssm(u)
        return x + y

    def forward(self, obs: torch.Tensor, mask: torch.Tensor | None = None,
                frames: torch.Tensor | None = None, codes: torch.Tensor | None = None,
                located: tuple | None = None) -> torch.Tensor:
        """obs [B, K, obs_dim], mask [B, K] (True = real point; the last must be real) -> action [B, act_dim].
        A frame tokenizer's codes come from `frames` [B, K, H, W, 3], or precomputed as `codes` [B, K, G].

        A window longer than K gives the action of its last K points. located: the last point's
        keypoints (where, there), when the drawing has located them this step."""
        last = (lambda t: None if t is None else t[:, -1])  # noqa: E731
        return self._head(self._trunk(obs, mask, frames, codes)[:, -1], obs[:, -1], last(frames), last(codes),
                          located)

    def actions(self, obs: torch.Tensor, mask: torch.Tensor | None = None,
                frames: torch.Tensor | None = None) -> torch.Tensor:
        """obs [B, L, obs_dim] -> [B, L, act_dim]: at each point, the action of the K points ending there."""
        return self._head(self._trunk(obs, mask, frames), obs, frames, None)

    def init_state(self, batch: int) -> WindowState:
        """A fresh state: the start of an episode (every earlier point masked)."""
        return self.ssm.init_state(batch)

    def step(self, obs_t: torch.Tensor, state: WindowState,
             frame_t: torch.Tensor | None = None) -> tuple[torch.Tensor, WindowState]:
        """One tick: obs_t [B, obs_dim] (normalised), state -> (action [B, act_dim] normalised, state)."""
        x = self._encode(obs_t, frame_t)
        y, state = self.ssm.step(self.ssm_ln(x), state)
        return self._head(x + y, obs_t, frame_t, None), state
