"""The three HOPE seed components as the training loop sees them (contract.Component), and how they
are built from a feature spec or rebuilt from a checkpoint.

    vqvae      window fast, K=1 (the anchor)   its frame if the spec has one, else its obs vector
               -> a code; loss recon MSE + 0.25 commitment
    fast_loop  window fast, 100 ms, K=5         obs window (+ codes of a frozen VQ-VAE)
               -> the action; loss MSE on the normalised action; the model's window_k = the
               window's K (its stepped form computes exactly the last K points)
    mid_loop   window mid, 2 s, K=20,           codes (frozen VQ-VAE, required) + past actions
               horizons 0.5 s and 1 s           -> codes ahead; loss cross-entropy
                                                + the action-conditioned world model (wm_*, vector
                                                VQ-VAE): obs of the next points given the actions
                                                to be held; + wm_weight x its MSE

build_component() builds the configuration model_config.resolve() gives: the defaults of each
model's config dataclass, the dims of the feature spec, and `model_config` overrides (any config
field, plus "window": {"duration_s", "k", "horizons_s"}); an unknown key or a dim that does not fit
the spec is a ValueError naming it. It draws the initial weights from torch's global RNG: seed
before building.

A frozen VQ-VAE (fast_loop optionally, mid_loop always) is loaded from `vqvae_dir`, a checkpoint
dir, and becomes a frozen submodule of the model: its weights travel in the same
model.safetensors, so a fast/mid checkpoint is self-contained; config.json names the VQ-VAE it
came from (path, sha256 of its config and weights).

Checkpoint dir = model.safetensors (the model's state_dict, buffers included) + config.json
(config() below, plus whatever the loop adds). Weights are only ever read with safetensors, never
pickle.
"""
from __future__ import annotations

import hashlib
import json
import math
import logging
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from safetensors.torch import load_file

from hope_models.checkpoint_format import (
    CONFIG_FILE, CONFIG_FORMAT, MODEL_FILE, SNIFF_BYTES, CheckpointError, looks_like_pickle, read_json_object,
    weights_misfit,
)
from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.spec_request import spec_from_json_obj
from hope_models.data.windows import WindowSpec
from hope_models.durable import file_sha256
from hope_models.models.fast_loop import FastLoop
from hope_models.models.mid_loop import MidLoop, previous_actions
from hope_models.models.mid_loop_metrics import mid_loop_loss, world_model_loss
from hope_models.models.ssm import count_params
from hope_models.models.vqvae import VQVAE, VQVAEConfig
from hope_models.train.contract import COMPONENTS
from hope_models.train.model_config import make_config, resolve

log = logging.getLogger(__name__)


def _tensor(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.require(a, requirements=["C", "W"]))  # copies only views and read-only maps


# -- the components ------------------------------------------------------------------------------

class _Component:
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
        if frames is None and attr == "frames":
            raise ValueError(f"{self.name} reads frames: build its windows with make_windows(..., frames=True)")
        return None if frames is None else _tensor(frames)

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


class VQVAEComponent(_Component):
    name = "vqvae"

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._pending: tuple[torch.Tensor, torch.Tensor] | None = None  # (z_e, codes) of the last loss()

    def _x(self, batch) -> torch.Tensor:
        frames = self._frames(batch)
        return frames[:, -1] if frames is not None else _tensor(batch.obs[:, -1])

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


class FastLoopComponent(_Component):
    name = "fast_loop"
    clones_actions = True  # behaviour cloning: play episodes' actions are no labels (validation.anchor_sampler)

    def _loss(self, batch, training: bool) -> tuple[torch.Tensor, dict[str, float]]:
        pred = self._model(_tensor(batch.obs), _tensor(batch.mask), self._frames(batch))
        target = _tensor(batch.target_act)
        loss = F.mse_loss(pred, target)
        # baseline: always predicting the dataset's mean action (0 once normalised)
        return loss, {"mse": loss.item(), "mean_action_mse": float((target * target).mean())}


class MidLoopComponent(_Component):
    name = "mid_loop"

    def _loss(self, batch, training: bool) -> tuple[torch.Tensor, dict[str, float]]:
        model: MidLoop = self._model
        codes = model.codes(_tensor(batch.obs), self._frames(batch))
        future_codes = None
        if self.wants_frames:
            future_frames = self._frames(batch, "future_frames")  # only if the data layer provides them
            if future_frames is not None:
                future_codes = model.codes(None, future_frames)
        elif batch.future_obs is not None:
            future_codes = model.codes(_tensor(batch.future_obs))
        future_mask = None if future_codes is None or batch.future_mask is None else _tensor(batch.future_mask)
        mask = _tensor(batch.mask)
        act = _tensor(batch.act)
        y = model.context(codes, previous_actions(act), mask)
        logits = model.heads(y)
        vector = not self.wants_frames
        loss, metrics = mid_loop_loss(
            model, logits, codes, mask, obs=_tensor(batch.obs) if vector else None,
            future_codes=future_codes, future_mask=future_mask,
            future_obs=_tensor(batch.future_obs) if vector and batch.future_obs is not None else None,
            labels=tuple(f"{h:g}s" for h in self._window.horizons_s), training=training)
        if model.has_world_model:  # the action-conditioned world model (mid_loop.py), trained alongside
            wm_loss, wm_metrics = world_model_loss(model, y, _tensor(batch.obs), act, mask, self._window.grid_step_s)
            metrics.update(wm_metrics)
            loss = loss + model.cfg.wm_weight * wm_loss
        return loss, metrics


_CLASSES = {"vqvae": VQVAEComponent, "fast_loop": FastLoopComponent, "mid_loop": MidLoopComponent}


# -- building from a resolved configuration ----------------------------------------------------

def _build(name: str, spec: FeatureSpec, model_config: dict | None, vq: tuple[VQVAE, dict] | None,
           data_fingerprint: str) -> _Component:
    vqvae, ref = vq if vq is not None else (None, None)
    r = resolve(name, spec, model_config, None if vqvae is None or name == "vqvae" else vqvae.cfg)
    if name == "vqvae":
        return VQVAEComponent(spec, VQVAE(r.cfg), r.cfg, r.window, data_fingerprint)
    if name == "fast_loop":
        return FastLoopComponent(spec, FastLoop(r.cfg, vqvae), r.cfg, r.window, data_fingerprint, ref)
    return MidLoopComponent(spec, MidLoop(r.cfg, vqvae), r.cfg, r.window, data_fingerprint, ref)


# -- public API ----------------------------------------------------------------------------------

def build_component(name: str, spec: FeatureSpec, *, model_config: dict | None = None,
                    vqvae_dir: str | Path | None = None, data_fingerprint: str = "") -> _Component:
    """A fresh component for a dataset's feature spec (see the module doc)."""
    if name == "vqvae" and vqvae_dir is not None:
        raise ValueError("vqvae_dir is for fast_loop and mid_loop (the VQ-VAE whose codes they read); "
                         "the vqvae component itself takes none")
    vq = None if vqvae_dir is None else _load_vqvae(Path(vqvae_dir), spec)
    return _build(name, spec, model_config, vq, data_fingerprint)


def component_from_checkpoint(ckpt_dir: str | Path) -> _Component:
    """Rebuild a component from <ckpt_dir>/config.json and load <ckpt_dir>/model.safetensors."""
    ckpt = Path(ckpt_dir)
    cfg_path = ckpt / CONFIG_FILE
    if not cfg_path.is_file() and (ckpt / "checkpoints").is_dir():
        raise CheckpointError(f"{ckpt}: this looks like a run dir; pass one of its checkpoints/<step> dirs")
    obj = _read_json(cfg_path)
    # config.json is untrusted (a promotion names any checkpoint dir under the data roots), and its
    # dims decide how much memory building the model takes. So the model is first built on the
    # meta device, which allocates nothing, and compared with the shapes the weights file's header
    # lists: only a config describing exactly the tensors the file holds is built for real, and a
    # huge dim costs an error message instead of the Pi's memory.
    with torch.device("meta"):
        described = _from_config_checked(obj, cfg_path)
    _check_header_fits(described.model, ckpt / MODEL_FILE)
    comp = _from_config_checked(obj, cfg_path)
    load_model_weights(comp.model, ckpt / MODEL_FILE)
    return comp


def _from_config_checked(obj: dict, cfg_path: Path) -> _Component:
    try:
        return _from_config(obj, cfg_path)
    except CheckpointError:
        raise
    except (ValueError, FeatureSpecError, TypeError, KeyError, OverflowError, RuntimeError, MemoryError,
            RecursionError) as exc:
        # RuntimeError / OverflowError / MemoryError: torch refusing a tensor of the sizes the config names
        raise CheckpointError(f"{cfg_path}: does not describe a usable component: {exc}") from None


def _check_header_fits(model: torch.nn.Module, path: Path) -> None:
    """The shapes of model's state_dict against those model.safetensors's header lists (the
    header only: no tensor is read)."""
    from safetensors import safe_open

    if not path.is_file():
        raise CheckpointError(f"{path}: weights file not found")
    try:
        with safe_open(str(path), framework="pt") as f:
            found = {k: list(f.get_slice(k).get_shape()) for k in f.keys()}
    except Exception as exc:  # safetensors raises its own SafetensorError (an Exception), or OSError
        raise _not_safetensors(path, exc) from None
    _raise_unless_fits(path, {k: list(v.shape) for k, v in model.state_dict().items()}, found)


def load_model_weights(model: torch.nn.Module, path: str | Path) -> None:
    """Load a safetensors state_dict into model, refusing anything else with a clear error."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: weights file not found")
    try:
        state = load_file(str(path))
    except Exception as exc:  # safetensors raises its own SafetensorError (an Exception), or OSError
        raise _not_safetensors(path, exc) from None
    _raise_unless_fits(path, {k: f"{list(v.shape)} {v.dtype}" for k, v in model.state_dict().items()},
                       {k: f"{list(v.shape)} {v.dtype}" for k, v in state.items()})
    model.load_state_dict(state, strict=True)


def _not_safetensors(path: Path, exc: Exception) -> CheckpointError:
    try:
        with open(path, "rb") as f:
            head = f.read(SNIFF_BYTES)
    except OSError:
        head = b""
    kind = " It looks like a pickle / torch.save file;" if looks_like_pickle(head) else ""
    return CheckpointError(f"{path}: not a valid safetensors file ({exc}).{kind} pickle checkpoints are "
                           "never loaded (they can run code); only safetensors weights are accepted")


def _raise_unless_fits(path: Path, expected: dict[str, Any], found: dict[str, Any]) -> None:
    """expected / found: tensor name -> its shape (and dtype) as the model and the file have them."""
    misfit = weights_misfit(expected, found, described_by="model")
    if misfit:
        raise CheckpointError(f"{path}: weights do not fit the model its config.json describes ({misfit})")


# -- helpers -------------------------------------------------------------------------------------

def _read_json(path: Path) -> dict:
    try:
        return read_json_object(path)
    except FileNotFoundError:
        raise CheckpointError(f"{path}: not found (a checkpoint dir holds {MODEL_FILE} + {CONFIG_FILE})") from None


def _config_sha256(obj: dict) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode("utf-8")).hexdigest()


def _from_config(obj: dict, where: Path) -> _Component:
    fmt = obj.get("format", CONFIG_FORMAT)
    if fmt != CONFIG_FORMAT:
        raise CheckpointError(f"{where}: format {fmt!r} is not {CONFIG_FORMAT!r}")
    name = obj.get("component")
    if name not in COMPONENTS:
        raise CheckpointError(f"{where}: component {name!r} is not one of {', '.join(COMPONENTS)}")
    for key in ("model_config", "feature_spec", "window"):
        if not isinstance(obj.get(key), dict):
            raise CheckpointError(f"{where}: '{key}' is missing or not an object")
    spec = spec_from_json_obj(obj["feature_spec"], f"{where}: feature_spec")
    model_config = dict(obj["model_config"])
    model_config["window"] = dict(obj["window"])
    vq = None
    ref = obj.get("vqvae")
    if name != "vqvae" and ref is not None:
        if not isinstance(ref, dict) or not isinstance(ref.get("model_config"), dict):
            raise CheckpointError(f"{where}: 'vqvae' must name the VQ-VAE with its model_config")
        vq_cfg = make_config(VQVAEConfig, {}, ref["model_config"], "vqvae")
        vq = (VQVAE(vq_cfg), ref)  # weights arrive with this checkpoint's model.safetensors (prefix vqvae.)
    return _build(name, spec, model_config, vq, str(obj.get("data_fingerprint", "")))


def _load_vqvae(vqvae_dir: Path, spec: FeatureSpec) -> tuple[VQVAE, dict]:
    """The trained VQ-VAE in vqvae_dir, checked against this dataset's features, and its reference."""
    comp = component_from_checkpoint(vqvae_dir)
    if comp.name != "vqvae":
        raise ValueError(f"vqvae_dir={str(vqvae_dir)!r} holds a {comp.name} checkpoint, not a vqvae")
    vq: VQVAE = comp.model
    if vq.cfg.input == "frame":
        if spec.frame is None or tuple(spec.frame.shape) != tuple(vq.cfg.frame_shape):
            raise ValueError(f"vqvae_dir={str(vqvae_dir)!r}: that VQ-VAE reads {list(vq.cfg.frame_shape)} frames, "
                             "which this dataset's feature spec does not have")
    else:
        ours = [(f.path, f.size) for f in spec.observation.fields]
        theirs = [(f.path, f.size) for f in comp.spec.observation.fields]
        if ours != theirs:
            raise ValueError(f"vqvae_dir={str(vqvae_dir)!r}: that VQ-VAE was trained on observation fields "
                             f"{theirs}, this dataset has {ours}")
        if comp.spec.observation.mean != spec.observation.mean or comp.spec.observation.std != spec.observation.std:
            log.warning("vqvae_dir=%s was trained with other observation normalisation statistics than this "
                        "dataset's; its codes may be shifted", vqvae_dir)
    if not bool(vq.initialized):
        raise ValueError(f"vqvae_dir={str(vqvae_dir)!r}: that VQ-VAE was never trained (its codebook is not "
                         "initialised)")
    cfg_obj = _read_json(vqvae_dir / CONFIG_FILE)
    ref = {"path": str(vqvae_dir.resolve()), "config_sha256": _config_sha256(cfg_obj),
           "weights_sha256": file_sha256(vqvae_dir / MODEL_FILE), "model_config": asdict(vq.cfg)}
    return vq, json.loads(json.dumps(ref))
