"""The Fast Loop as the training loop sees it: window fast, 100 ms, K=5; obs window (+ codes of a
frozen VQ-VAE) -> the action; loss MSE on the normalised action. The model's window_k is the
window's K (its stepped form computes exactly the last K points)."""
from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from hope_models.components.fast_loop.model import FastLoop
from hope_models.components.training_base import TrainingComponent, as_tensor


class FastLoopComponent(TrainingComponent):
    name = "fast_loop"
    clones_actions = True  # behaviour cloning: play episodes' actions are no labels (validation.anchor_sampler)

    def _loss(self, batch, training: bool) -> tuple[torch.Tensor, dict[str, float]]:
        frames, codes, obs = self._frames(batch), self._codes(batch), as_tensor(batch.obs)
        kp, vq = self._model.keypoints, self._model.vqvae
        render = located = None
        if kp is not None and kp.render is not None:  # the points learn from the frames (reader "frames")
            # the acting point's codes: the ones the keypoints are read from
            last = codes[:, -1] if codes is not None else self._model.codes(
                obs[:, -1], frames[:, -1] if frames is not None else None)
            # the drawing locates the points the policy reads: one softmax over the cells, not two
            render, located = kp.draw_back(last, vq.codebook[:vq.cfg.n_codes])  # keypoints read a VQ-VAE's grid
        pred = self._model(obs, as_tensor(batch.mask), frames, codes, located)
        target = as_tensor(batch.target_act)
        mse = F.mse_loss(pred, target)
        # baseline: always predicting the dataset's mean action (0 once normalised)
        metrics = {"mse": mse.item(), "mean_action_mse": float((target * target).mean())}
        if render is None:  # no keypoints, or placed by this loss alone
            return mse, metrics
        metrics["render_ce" if kp.draw == "codes" else "render_mse"] = render.item()
        # validation's loss stays the action's MSE: the figure the gate compares between policies
        return (mse + self._model.cfg.render_weight * render if training else mse), metrics


def build(spec: Any, r: Any, vqvae: Any, data_fingerprint: str, vqvae_ref: dict | None) -> FastLoopComponent:
    """The component for a resolved configuration (components.resolve.Resolved) and a dataset's
    feature spec; vqvae: the frozen VQ-VAE module it reads codes of (None: none)."""
    return FastLoopComponent(spec, FastLoop(r.cfg, vqvae), r.cfg, r.window, data_fingerprint, vqvae_ref)
