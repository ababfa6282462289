"""The toy as the training loop sees it: the window's last observation -> the action, MSE."""
from __future__ import annotations

from typing import Any

import torch
import torch.nn.functional as F

from hope_models.components.toy.model import Toy
from hope_models.components.training_base import TrainingComponent, as_tensor


class ToyComponent(TrainingComponent):
    name = "toy"

    def _loss(self, batch, training: bool) -> tuple[torch.Tensor, dict[str, float]]:
        pred = self._model(as_tensor(batch.obs[:, -1]))
        loss = F.mse_loss(pred, as_tensor(batch.target_act))
        return loss, {"mse": loss.item()}


def build(spec: Any, r: Any, vqvae: Any, data_fingerprint: str, vqvae_ref: dict | None) -> ToyComponent:
    return ToyComponent(spec, Toy(r.cfg), r.cfg, r.window, data_fingerprint)
