"""The Mid Loop as the training loop sees it: window mid, 2 s, K=20, horizons 0.5 s and 1 s; codes
(frozen VQ-VAE, required) + past actions -> codes ahead; loss cross-entropy, + the
action-conditioned world model (wm_*, vector VQ-VAE): obs of the next points given the actions to
be held, + wm_weight x its MSE. Over a grid frame VQ-VAE the model is grid_model.GridMidLoop: codes
and joints in, each cell's code and the joints at each horizon out (grid_metrics.py), + its world model
over the joints as the vector one's; its held-out
picture is a few windows' predicted frames beside the real ones (grid_picture.py)."""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from hope_models.components.mid_loop.grid_metrics import grid_loss
from hope_models.components.mid_loop.grid_model import GridMidLoop, is_grid
from hope_models.components.mid_loop.grid_picture import predicted_frames
from hope_models.components.mid_loop.metrics import mid_loop_loss, world_model_loss
from hope_models.components.mid_loop.model import MidLoop, previous_actions
from hope_models.components.training_base import TrainingComponent, as_tensor


class MidLoopComponent(TrainingComponent):
    name = "mid_loop"

    def _loss(self, batch, training: bool) -> tuple[torch.Tensor, dict[str, float]]:
        model: MidLoop | GridMidLoop = self._model
        codes = self._codes(batch)  # a dataset's code table spares the frozen encoder
        if codes is None:
            codes = model.codes(as_tensor(batch.obs), self._frames(batch))
        future_codes = None
        if self.wants_frames:
            future_codes = self._codes(batch, "future_codes")
            future_frames = self._frames(batch, "future_frames")  # only if the data layer provides them
            if future_codes is None and future_frames is not None:
                future_codes = model.codes(None, future_frames)
        elif batch.future_obs is not None:
            future_codes = model.codes(as_tensor(batch.future_obs))
        future_mask = None if future_codes is None or batch.future_mask is None else as_tensor(batch.future_mask)
        mask = as_tensor(batch.mask)
        act = as_tensor(batch.act)
        labels = tuple(f"{h:g}s" for h in self._window.horizons_s)
        if isinstance(model, GridMidLoop):
            obs = as_tensor(batch.obs)
            y = model.context(codes, previous_actions(act), obs, mask)
            loss, metrics = grid_loss(model, y, codes, obs, mask, future_codes=future_codes, future_mask=future_mask,
                                      future_obs=None if batch.future_obs is None else as_tensor(batch.future_obs),
                                      labels=labels, training=training)
            return self._with_world_model(model, loss, metrics, y, obs, act, mask)
        y = model.context(codes, previous_actions(act), mask)
        logits = model.heads(y)
        vector = not self.wants_frames
        loss, metrics = mid_loop_loss(
            model, logits, codes, mask, obs=as_tensor(batch.obs) if vector else None,
            future_codes=future_codes, future_mask=future_mask,
            future_obs=as_tensor(batch.future_obs) if vector and batch.future_obs is not None else None,
            labels=labels, training=training)
        return self._with_world_model(model, loss, metrics, y, as_tensor(batch.obs), act, mask)

    def _with_world_model(self, model, loss, metrics, y, obs, act, mask) -> tuple[torch.Tensor, dict[str, float]]:
        """+ wm_weight x the action-conditioned world model's loss (model.py), when it has one: over
        the observation vector (vector VQ-VAE) or the joints (grid)."""
        if model.has_world_model:
            wm_loss, wm_metrics = world_model_loss(model, y, obs, act, mask, self._window.grid_step_s)
            metrics.update(wm_metrics)
            loss = loss + model.cfg.wm_weight * wm_loss
        return loss, metrics

    def held_out_picture(self, cache, episodes: np.ndarray) -> np.ndarray | None:
        """A grid Mid Loop's picture of held-out `episodes` (cache episode indices): a few windows,
        the frame now beside each horizon's predicted and real frame (grid_picture.py); None for a
        Mid Loop over a vector or flat VQ-VAE, or episodes without a whole window and horizon."""
        if not isinstance(self._model, GridMidLoop):
            return None
        return predicted_frames(self._model, cache, episodes, self._window)


def build(spec: Any, r: Any, vqvae: Any, data_fingerprint: str, vqvae_ref: dict | None) -> MidLoopComponent:
    """The component for a resolved configuration (components.resolve.Resolved) and a dataset's
    feature spec; vqvae: the frozen VQ-VAE module it reads codes of (None: none)."""
    model = GridMidLoop(r.cfg, vqvae) if is_grid(vqvae.cfg) else MidLoop(r.cfg, vqvae)
    return MidLoopComponent(spec, model, r.cfg, r.window, data_fingerprint, vqvae_ref)
