"""What the three components share as the training loop sees them (train/contract.Component):
the model, its window, the frames it reads, evaluate() in eval mode without grad, and the
config.json a checkpoint holds. Each component's loss is in its folder's train.py."""
from __future__ import annotations

import json
from dataclasses import asdict
from typing import Any

import numpy as np
import torch

from hope_models.checkpoint_format import CONFIG_FORMAT
from hope_models.components.code_table import frame_code_table
from hope_models.components.ssm import count_params
from hope_models.data.features import FeatureSpec
from hope_models.data.windows import WindowSpec


def as_tensor(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.require(a, requirements=["C", "W"]))  # copies only views and read-only maps


class TrainingComponent:
    name = ""

    def __init__(self, spec: FeatureSpec, model: torch.nn.Module, cfg: Any, window: WindowSpec,
                 data_fingerprint: str, vqvae_ref: dict | None = None):
        self.spec, self._model, self.model_config = spec, model, cfg
        self._window, self.data_fingerprint, self.vqvae_ref = window, data_fingerprint, vqvae_ref

    @property
    def model(self) -> torch.nn.Module:
        return self._model

    @property
    def window(self) -> WindowSpec:
        return self._window

    @property
    def wants_frames(self) -> bool:
        return bool(self._model.wants_frames)

    def _frames(self, batch, attr: str = "frames") -> torch.Tensor | None:
        if not self.wants_frames:
            return None
        frames = getattr(batch, attr, None)
        if frames is None and attr == "frames" and getattr(batch, "codes", None) is None:
            raise ValueError(f"{self.name} reads frames: build its windows with make_windows(..., frames=True)")
        return None if frames is None else as_tensor(frames)

    def _codes(self, batch, attr: str = "codes") -> torch.Tensor | None:
        """The batch's precomputed tokenizer codes (make_windows with a code table), long, or None."""
        codes = getattr(batch, attr, None) if self.wants_frames else None
        return None if codes is None else torch.from_numpy(np.asarray(codes, dtype=np.int64))

    def code_table(self, cache, log=None) -> np.ndarray | None:
        """The frozen tokenizer's codes of every frame of `cache`, computed once per (cache, tokenizer
        weights) and kept in the cache dir (components/code_table.py); None for a component that
        reads no frames or whose tokenizer has no recorded weights."""
        vqvae = getattr(self._model, "vqvae", None)
        key = (self.vqvae_ref or {}).get("weights_sha256")
        if not self.wants_frames or vqvae is None or not isinstance(key, str):
            return None
        return frame_code_table(cache, vqvae, key, log)

    def _loss(self, batch, training: bool) -> tuple[torch.Tensor, dict[str, float]]:
        raise NotImplementedError

    def loss(self, batch) -> tuple[torch.Tensor, dict[str, float]]:
        return self._loss(batch, training=True)

    def evaluate(self, batch) -> dict[str, float]:
        """The metrics of one batch in eval mode (no dropout), the model back in its mode after."""
        was_training = self._model.training
        self._model.eval()
        try:
            with torch.no_grad():
                loss, metrics = self._loss(batch, training=False)
        finally:
            self._model.train(was_training)
        return {"loss": float(loss), **metrics}

    def after_step(self, step: int) -> None:
        pass

    def config(self) -> dict[str, Any]:
        obj = {
            "format": CONFIG_FORMAT,
            "component": self.name,
            "model_config": asdict(self.model_config),
            "window": self._window.to_json_obj(),
            "feature_spec": self.spec.to_json_obj(),
            "data_fingerprint": self.data_fingerprint,
            "vqvae": self.vqvae_ref,
            "params": {"trainable": count_params(self._model, trainable_only=True),
                       "total": count_params(self._model)},
        }
        return json.loads(json.dumps(obj))  # tuples -> lists: exactly what config.json will hold
