"""How a component is built from a feature spec, or rebuilt from a checkpoint, for the training
loop (contract.Component). What each one is, its window and its loss, is in its folder
(hope_models/components/<name>/train.py); its spec says whether it reads a frozen VQ-VAE.

build_component() builds the configuration resolve.resolve() gives: the defaults of each
model's config dataclass, the dims of the feature spec, and `model_config` overrides (any config
field, plus "window": {"duration_s", "k", "horizons_s"}); an unknown key or a dim that does not fit
the spec is a ValueError naming it. It draws the initial weights from torch's global RNG: seed
before building.

A frozen VQ-VAE (for a component whose spec reads one) is loaded from `vqvae_dir`, a checkpoint
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
import logging
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from safetensors import safe_open
from safetensors.torch import load_file

from hope_models.checkpoint_format import (
    CONFIG_FILE,
    CONFIG_FORMAT,
    MODEL_FILE,
    SNIFF_BYTES,
    CheckpointError,
    looks_like_pickle,
    read_json_object,
    weights_misfit,
)
from hope_models.components import COMPONENTS, TOKENIZER, spec_of
from hope_models.components.config_fields import make_config
from hope_models.components.resolve import resolve
from hope_models.components.training_base import TrainingComponent
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.model import VQVAE
from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.spec_request import spec_from_json_obj
from hope_models.durable import file_sha256

log = logging.getLogger(__name__)


# -- building from a resolved configuration ----------------------------------------------------

def _build(name: str, spec: FeatureSpec, model_config: dict | None, vq: tuple[VQVAE, dict] | None,
           data_fingerprint: str) -> TrainingComponent:
    vqvae, ref = vq if vq is not None else (None, None)
    r = resolve(name, spec, model_config, None if vqvae is None else vqvae.cfg)
    if r.vq_cfg is None:  # a component that reads no VQ-VAE
        vqvae, ref = None, None
    return spec_of(name).part("train").build(spec, r, vqvae, data_fingerprint, ref)


# -- public API ----------------------------------------------------------------------------------

def build_component(name: str, spec: FeatureSpec, *, model_config: dict | None = None,
                    vqvae_dir: str | Path | None = None, data_fingerprint: str = "") -> TrainingComponent:
    """A fresh component for a dataset's feature spec (see the module doc)."""
    if not spec_of(name).reads_codes and vqvae_dir is not None:
        readers = [n for n, c in COMPONENTS.items() if c.reads_codes]
        raise ValueError(f"vqvae_dir is for {' and '.join(readers)} (the VQ-VAE whose codes they read); "
                         f"the {name} component itself takes none")
    vq = None if vqvae_dir is None else _load_vqvae(Path(vqvae_dir), spec)
    return _build(name, spec, model_config, vq, data_fingerprint)


def component_from_checkpoint(ckpt_dir: str | Path) -> TrainingComponent:
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


def _from_config_checked(obj: dict, cfg_path: Path) -> TrainingComponent:
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


def _from_config(obj: dict, where: Path) -> TrainingComponent:
    fmt = obj.get("format", CONFIG_FORMAT)
    if fmt != CONFIG_FORMAT:
        raise CheckpointError(f"{where}: format {fmt!r} is not {CONFIG_FORMAT!r}")
    name = obj.get("component")
    if name not in COMPONENTS:
        raise CheckpointError(f"{where}: component {name!r} is not one of {', '.join(COMPONENTS)}")
    component = spec_of(name)
    for key in ("model_config", "feature_spec", "window"):
        if not isinstance(obj.get(key), dict):
            raise CheckpointError(f"{where}: '{key}' is missing or not an object")
    spec = spec_from_json_obj(obj["feature_spec"], f"{where}: feature_spec")
    model_config = component.stored_config(obj["model_config"])
    model_config["window"] = dict(obj["window"])
    vq = None
    ref = obj.get("vqvae")
    if component.reads_codes and ref is not None:
        if not isinstance(ref, dict) or not isinstance(ref.get("model_config"), dict):
            raise CheckpointError(f"{where}: 'vqvae' must name the VQ-VAE with its model_config")
        vq_cfg = make_config(VQVAEConfig, {}, ref["model_config"], "vqvae")
        vq = (VQVAE(vq_cfg), ref)  # weights arrive with this checkpoint's model.safetensors (prefix vqvae.)
    return _build(name, spec, model_config, vq, str(obj.get("data_fingerprint", "")))


def _load_vqvae(vqvae_dir: Path, spec: FeatureSpec) -> tuple[VQVAE, dict]:
    """The trained VQ-VAE in vqvae_dir, checked against this dataset's features, and its reference."""
    comp = component_from_checkpoint(vqvae_dir)
    if comp.name != TOKENIZER:
        raise ValueError(f"vqvae_dir={str(vqvae_dir)!r} holds a {comp.name} checkpoint, not a {TOKENIZER}")
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
