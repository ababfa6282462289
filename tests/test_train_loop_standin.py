"""A tiny stand-in Component for the loop tests (no tests here): an MLP from the last observation
and the previous action to the anchor's action, with dropout and an RNG-drawing after_step hook,
so a resume that lost any RNG state would not come out bitwise identical."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from hope_models.data.windows import window_spec


class StandIn:
    name = "fast_loop"

    def __init__(self, spec, nan_at_call: int | None = None, hidden: int = 16):
        self.spec = spec
        self.k = 3
        self._window = window_spec("fast", duration_s=0.06, k=self.k)
        d_in = self.k * spec.obs_dim
        self._model = torch.nn.Sequential(torch.nn.Linear(d_in, hidden), torch.nn.Tanh(), torch.nn.Dropout(0.1),
                                          torch.nn.Linear(hidden, spec.act_dim))
        self._model.register_buffer("noise", torch.zeros(spec.act_dim))
        self.nan_at_call = nan_at_call
        self.calls = 0

    @property
    def model(self):
        return self._model

    @property
    def window(self):
        return self._window

    @property
    def wants_frames(self) -> bool:
        return False

    def _forward(self, batch):
        x = torch.from_numpy(np.ascontiguousarray(batch.obs)).reshape(len(batch.obs), -1)
        return self._model(x) + self._model.noise

    def loss(self, batch):
        self.calls += 1
        pred = self._forward(batch)
        loss = torch.nn.functional.mse_loss(pred, torch.from_numpy(np.ascontiguousarray(batch.target_act)))
        if self.nan_at_call is not None and self.calls >= self.nan_at_call:
            loss = loss * float("nan")
        return loss, {"pred_std": float(pred.detach().std())}

    def evaluate(self, batch):
        with torch.no_grad():
            pred = self._forward(batch)
            return {"loss": float(torch.nn.functional.mse_loss(pred, torch.from_numpy(batch.target_act)))}

    def after_step(self, step: int) -> None:
        if step % 7 == 0:  # like a dead-code restart: draws from torch's global RNG
            with torch.no_grad():
                self._model.noise.copy_(torch.randn(self.spec.act_dim) * 1e-3)

    def config(self):
        return {"component": self.name, "model": {"hidden": 16}, "window": self._window.to_json_obj(),
                "feature_spec": self.spec.to_json_obj()}


def factory(**overrides):
    def build(name, spec, *, model_config=None, vqvae_dir=None, data_fingerprint=""):
        return StandIn(spec, **overrides)
    return build


def weights(run_dir: Path) -> dict[str, torch.Tensor]:
    """The final weights of a run, read through the checkpoint module (safetensors)."""
    from hope_models import checkpoints as ckpt
    return ckpt.load_latest(run_dir).model


def assert_bitwise_equal(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), f"{k} differs"
