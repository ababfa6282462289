"""The toy in NumPy, what BrainService serves: normalise the observation, one linear layer,
denormalise the action; what it accepts as a checkpoint is checked by checkpoint_checks."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hope_models.components.checkpoint_checks import CheckpointRefused, check_header, check_weights, read_component
from hope_models.data.spec_request import spec_from_json_obj


class ToyNumpyError(CheckpointRefused):
    """This checkpoint cannot be run by the NumPy toy."""


def _check_config(config: Any, where: Path):
    check_header(config, where, "toy", ToyNumpyError)
    return spec_from_json_obj(config.get("feature_spec"), f"{where}: feature_spec")


def _check_tensors(t: dict[str, np.ndarray], config: dict[str, Any], where: Path) -> None:
    mc = config["model_config"]
    want = {"out.weight": (mc["act_dim"], mc["obs_dim"]), "out.bias": (mc["act_dim"],)}
    check_weights(t, want, where, "the toy config.json describes", ToyNumpyError)


class ToyRuntime:
    name = "toy"

    def __init__(self, ck):
        self.checkpoint, self.config, self.spec, self.sha256, self.version = (
            ck.path, ck.config, ck.spec, ck.sha256, ck.version)
        self.w, self.b = ck.tensors["out.weight"].astype(np.float64), ck.tensors["out.bias"].astype(np.float64)
        self.obs_dim, self.act_dim = self.spec.obs_dim, self.spec.act_dim
        self.observation_fields = [(f.path, f.size) for f in self.spec.observation.fields]
        self.action_fields = [(f.path, f.size) for f in self.spec.action.fields]
        self.fit_fields = (self.observation_fields, self.action_fields)
        o, a = self.spec.observation, self.spec.action
        self.obs_mean, self.obs_std = np.asarray(o.mean, np.float64), np.asarray(o.std, np.float64)
        self.act_mean, self.act_std = np.asarray(a.mean, np.float64), np.asarray(a.std, np.float64)

    @classmethod
    def from_checkpoint(cls, path: str | Path, *, expected_sha256: str | None = None,
                        verify_manifest: bool = False) -> "ToyRuntime":
        return cls(read_component(path, _check_config, _check_tensors, ToyNumpyError,
                                  expected_sha256=expected_sha256, verify_manifest=verify_manifest))

    def answer(self, values: np.ndarray) -> list[float]:
        x = (np.asarray(values, np.float64) - self.obs_mean) / self.obs_std
        return [float(v) for v in (self.w @ x + self.b) * self.act_std + self.act_mean]

    def warm(self) -> None:
        self.answer(np.zeros(self.obs_dim))

    def status_fields(self) -> dict:
        return {}

    def describe_observation(self, limit: int = 12) -> str:
        return ", ".join(self.spec.observation.dim_names()[:limit])


RUNTIME = ToyRuntime
