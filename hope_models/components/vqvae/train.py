"""The VQ-VAE as the training loop sees it: window fast, K=1 (the anchor); its frame if the spec
has one, else its obs vector -> a code; loss recon MSE + 0.25 commitment; the codebook moves (EMA,
dead-code restarts) after each optimiser step."""
from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import torch

from hope_models.components import picture
from hope_models.components.training_base import TrainingComponent, as_tensor
from hope_models.components.vqvae.model import VQVAE

log = logging.getLogger(__name__)


class VQVAEComponent(TrainingComponent):
    name = "vqvae"

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._pending: tuple[torch.Tensor, torch.Tensor] | None = None  # (z_e, codes) of the last loss()

    def _x(self, batch) -> torch.Tensor:
        frames = self._frames(batch)
        return frames[:, -1] if frames is not None else as_tensor(batch.obs[:, -1])

    def _loss(self, batch, training: bool) -> tuple[torch.Tensor, dict[str, float]]:
        model: VQVAE = self._model
        out = model(self._x(batch), init_codebook=training)
        if training:  # the codebook moves in after_step, once the optimiser step has been taken
            self._pending = (out.z_e.detach(), out.codes)
        metrics = {"recon_loss": out.recon_loss.item(), "commit_loss": out.commit_loss.item(),
                   **model.code_stats(out.codes), "codes_restarted": float(model.restarts),
                   **reconstruction_quality(model, out)}
        return model.loss_of(out), metrics

    def after_step(self, step: int) -> None:
        if self._pending is None:
            return
        z_e, codes = self._pending
        self._pending = None
        self._model.update_codebook(z_e, codes)
        n = self._model.restart_dead_codes(z_e)
        if n:
            log.debug("vqvae step %d: restarted %d dead codes", step, n)

    def held_out_picture(self, cache, episodes: np.ndarray) -> np.ndarray | None:
        """A frame model's picture of held-out `episodes` (cache episode indices): picture.FRAMES
        frames evenly spaced through them over their reconstructions, decoded from their codes
        (components/picture.py strip); None for a vector model or episodes without steps. The model's
        mode is left as it was found; no state changes (encode never updates the codebook)."""
        rows = picture.spread_rows(cache, episodes) if self.wants_frames else None
        return None if rows is None or not len(rows) else self.picture_of(np.ascontiguousarray(cache.frame_rows(rows)))

    def picture_of(self, frames: np.ndarray) -> np.ndarray:
        """uint8 [N, H, W, 3] frames -> the strip of them over their reconstructions (uint8 image)."""
        model: VQVAE = self._model
        was_training = model.training
        model.eval()
        try:
            with torch.no_grad():
                recon = model.decode(model.encode(torch.from_numpy(np.asarray(frames, dtype=np.uint8))))
        finally:
            model.train(was_training)
        return picture.strip(frames, picture.to_uint8(recon.permute(0, 2, 3, 1).numpy()))


def reconstruction_quality(model: VQVAE, out) -> dict[str, float]:
    """recon_nmse: the reconstruction's squared error over the batch's own variance, i.e. 1 - the
    share of variance kept (frames too, over pixels); frames also psnr_db, 10 log10(1 / pixel MSE)
    on [0, 1] pixels."""
    err = out.recon_loss.item()
    with torch.no_grad():
        figures = {"recon_nmse": err / max(float(out.target.var(0, unbiased=False).mean()), 1e-12)}
    if model.cfg.input == "frame":
        figures["psnr_db"] = 10.0 * math.log10(1.0 / max(err, 1e-12))
    return figures


def build(spec: Any, r: Any, vqvae: Any, data_fingerprint: str, vqvae_ref: dict | None) -> VQVAEComponent:
    """The component for a resolved configuration (components.resolve.Resolved) and a dataset's
    feature spec; vqvae: the frozen VQ-VAE module it reads codes of (None: none)."""
    return VQVAEComponent(spec, VQVAE(r.cfg), r.cfg, r.window, data_fingerprint)
