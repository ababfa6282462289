"""What the NumPy runtime accepts as a fast_loop checkpoint, and reading one with each file hashed once.

    ck = read_fast_loop(path, expected_sha256=pointer["sha256"], verify_manifest=True)
    ck.config, ck.spec, ck.tensors, ck.sha256, ck.version

config.json must describe a fast_loop (format hope.component_config/1) whose dims are integers in
range, whose window K is the model's, whose feature spec has the model's observation and action
sizes, and, when it reads VQ-VAE codes, a VQ-VAE of observation vectors or of camera frames
(vqvae/numpy_frame.frame_config: layout flat or grid, sizes bounded; its frame the feature spec's
frame). model.safetensors must be a safetensors file (pickle is refused unread)
holding exactly the float32 tensors of those shapes (the comparison is
checkpoint_format.weights_misfit, which the torch loader uses too), all finite, with a trained
codebook when there is one. Anything else is FastLoopNumpyError naming the file and the reason.

The weights' bytes are read once: the sha256 (checked against the manifest and the promotion
pointer), the version string (checkpoint_format.version_name) and the tensors all come from the
same bytes. Torch-free.
"""
from __future__ import annotations

import math
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.components.checkpoint_checks import (
    MAX_GROUPS,
    CheckedCheckpoint,
    CheckpointRefused,
    check_header,
    check_trained,
    check_weights,
    read_component,
)
from hope_models.components.fast_loop import SPEC
from hope_models.components.fast_loop.config import FastLoopConfig
from hope_models.components.fast_loop.layers import layers
from hope_models.components.layers import tensors
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.layers import vqvae_layers
from hope_models.components.vqvae.numpy_form import MAX_WIDTH, check_vqvae_tensors, frame_of
from hope_models.components.vqvae.numpy_frame import frame_config
from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.spec_request import spec_from_json_obj
from hope_models.data.windows import MAX_K

VQVAE_PREFIX = "vqvae."  # the frozen VQ-VAE's tensors in a fast_loop's state_dict
MODEL_CONFIG_KEYS = ("obs_dim", "act_dim", "window_k", "d_model", "d_state", "mlp_ratio", "min_timescale",
                     "max_timescale", "n_codes")


class FastLoopNumpyError(CheckpointRefused):
    """This checkpoint cannot be run by the NumPy fast_loop; the message names the file and why."""


def read_fast_loop(path: str | Path, *, expected_sha256: str | None = None,
                   verify_manifest: bool = False) -> CheckedCheckpoint:
    """Read and check <path>/config.json + model.safetensors. expected_sha256: refuse weights whose
    sha256 differs (the promotion pointer's record of what was promoted). verify_manifest: a run
    dir is resolved to its newest complete checkpoint and every file is checked against the
    manifest (train/checkpoint.open_checkpoint), the bytes loaded being those hashed; without it,
    a bare checkpoint dir needs no manifest (what a test or a tool wrote by hand)."""
    def tensors_ok(t: dict[str, np.ndarray], config: dict[str, Any], where: Path) -> None:
        check_tensors(t, config["model_config"], where, groups=vqvae_groups(config), frame=vqvae_frame(config))

    return read_component(path, check_config, tensors_ok, FastLoopNumpyError, expected_sha256=expected_sha256,
                          verify_manifest=verify_manifest)


def _check_model_config(mc: Any, where: Path) -> None:
    if not isinstance(mc, dict):
        raise FastLoopNumpyError(f"{where}: 'model_config' is missing or not an object")
    for key in MODEL_CONFIG_KEYS:
        value = mc.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise FastLoopNumpyError(f"{where}: model_config.{key}={value!r} is missing or not a number")
    for key in ("obs_dim", "act_dim", "window_k", "d_model", "d_state", "mlp_ratio"):
        if not isinstance(mc[key], int) or mc[key] < 1:
            raise FastLoopNumpyError(f"{where}: model_config.{key}={mc[key]!r} must be an integer >= 1")
    if not isinstance(mc["n_codes"], int) or mc["n_codes"] < 0:
        raise FastLoopNumpyError(f"{where}: model_config.n_codes={mc['n_codes']!r} must be an integer >= 0")
    # Every other dim is the shape of a weight (checked against the file); window_k only sizes the
    # recurrent state's ring, which init_state allocates per session, so it is bounded here.
    if mc["window_k"] > MAX_K:
        raise FastLoopNumpyError(f"{where}: model_config.window_k={mc['window_k']} is more than a window's "
                                 f"{MAX_K} points")


def _check_vqvae(config: dict[str, Any], mc: dict[str, Any], where: Path, spec: FeatureSpec) -> None:
    vq = config.get("vqvae")
    vq_cfg = vq.get("model_config") if isinstance(vq, dict) else None
    if not isinstance(vq_cfg, dict):
        raise FastLoopNumpyError(f"{where}: n_codes={mc['n_codes']} but 'vqvae' does not describe the VQ-VAE")
    if vq_cfg.get("input") == "frame":  # a camera reflex: the frame is the feature spec's camera
        frame = frame_config(vq_cfg, where, FastLoopNumpyError, MAX_WIDTH)
        if frame.n_codes != mc["n_codes"]:
            raise FastLoopNumpyError(f"{where}: the VQ-VAE's n_codes ({frame.n_codes}) does not fit the fast_loop's "
                                     f"({mc['n_codes']})")
        if spec.frame is None or tuple(spec.frame.shape) != frame.frame_shape:
            raise FastLoopNumpyError(f"{where}: the VQ-VAE reads {list(frame.frame_shape)} camera frames, the feature "
                                     f"spec's frame is {None if spec.frame is None else list(spec.frame.shape)}")
        return
    if vq_cfg.get("input") != "vector":
        raise FastLoopNumpyError(f"{where}: this fast_loop reads codes of a VQ-VAE with input "
                                 f"{vq_cfg.get('input')!r} (camera frames); the inference runtime runs "
                                 "state-only fast_loops (observation vectors)")
    groups = vq_cfg.get("groups", 1)
    if isinstance(groups, bool) or not isinstance(groups, int) or not 1 <= groups <= MAX_GROUPS:
        raise FastLoopNumpyError(f"{where}: vqvae.model_config.groups={groups!r} must be an integer in 1-{MAX_GROUPS}")
    if vq_cfg.get("obs_dim") != mc["obs_dim"] or vq_cfg.get("n_codes") != mc["n_codes"]:
        raise FastLoopNumpyError(f"{where}: the VQ-VAE's obs_dim/n_codes ({vq_cfg.get('obs_dim')}/"
                                 f"{vq_cfg.get('n_codes')}) do not fit the fast_loop's "
                                 f"({mc['obs_dim']}/{mc['n_codes']})")


def check_config(config: Any, where: Path) -> FeatureSpec:
    """The feature spec of a config.json this runtime can run (see the module doc)."""
    check_header(config, where, "fast_loop", FastLoopNumpyError)
    mc = config.get("model_config")
    _check_model_config(mc, where)
    # what a checkpoint from before a field was trained with (the torch loader fills in the same);
    # the config dict is the one the runtime is then built from
    mc = config["model_config"] = SPEC.stored_config(mc)
    window = config.get("window")
    if isinstance(window, dict) and window.get("k") != mc["window_k"]:
        raise FastLoopNumpyError(f"{where}: window.k={window.get('k')!r} differs from model_config.window_k="
                                 f"{mc['window_k']} (the stepped form must see the training window's K points)")
    try:
        spec = spec_from_json_obj(config.get("feature_spec"), f"{where}: feature_spec")
    except FeatureSpecError as exc:
        raise FastLoopNumpyError(str(exc)) from None
    if spec.obs_dim != mc["obs_dim"] or spec.act_dim != mc["act_dim"]:
        raise FastLoopNumpyError(f"{where}: the feature spec has {spec.obs_dim} observation / {spec.act_dim} action "
                                 f"values, model_config says obs_dim={mc['obs_dim']}, act_dim={mc['act_dim']}")
    if mc["n_codes"]:
        _check_vqvae(config, mc, where, spec)
    return spec


def expected_shapes(mc: dict[str, Any], groups: int = 1, frame: VQVAEConfig | None = None) -> dict[str, tuple[int, ...]]:
    """Tensor name -> shape of every weight of the fast_loop itself (its frozen VQ-VAE's apart), from
    the same layer description the memory estimate reads (layers.py). frame: its frame VQ-VAE's
    config (a grid's codes are read as keypoints, not summed)."""
    cfg = FastLoopConfig(**{f.name: mc[f.name] for f in fields(FastLoopConfig) if f.name in mc})
    vq = frame if frame is not None else VQVAEConfig(n_codes=mc["n_codes"], groups=groups) if mc["n_codes"] else None
    return tensors([layer for layer in layers(cfg, vq) if not layer.name.startswith(VQVAE_PREFIX)])


def vqvae_frame(config: dict[str, Any]) -> VQVAEConfig | None:
    """The frame VQ-VAE config of a checkpoint whose codes come from camera frames (check_config has
    checked it), else None."""
    vq = config.get("vqvae")
    return frame_of(vq["model_config"]) if config["model_config"]["n_codes"] and isinstance(vq, dict) else None


def vqvae_groups(config: dict[str, Any]) -> int:
    """The code groups of a checkpoint's VQ-VAE (1 without one, or one saved before groups existed);
    check_config has checked the value."""
    vq = config.get("vqvae")
    return int(vq["model_config"].get("groups", 1)) if isinstance(vq, dict) else 1


def _vqvae_shapes(t: dict[str, np.ndarray], mc: dict[str, Any], groups: int) -> dict[str, tuple[int, ...]]:
    """The vector VQ-VAE encoder and codebook the codes need; its widths are the file's own, its
    layers the VQ-VAE's description (vqvae/layers.py)."""
    w0 = t.get("vqvae.encoder.0.0.weight")
    w4 = t.get("vqvae.encoder.0.4.weight")
    hidden = w0.shape[0] if w0 is not None and w0.ndim == 2 else -1
    code_dim = w4.shape[0] if w4 is not None and w4.ndim == 2 else -1
    cfg = VQVAEConfig(input="vector", obs_dim=mc["obs_dim"], hidden=hidden, code_dim=code_dim, n_codes=mc["n_codes"],
                      groups=groups)
    want = {k: v for k, v in tensors(vqvae_layers(cfg, prefix=VQVAE_PREFIX)).items()
            if k.startswith(VQVAE_PREFIX + "encoder.")}
    want[VQVAE_PREFIX + "codebook"] = (mc["n_codes"] * groups, code_dim // groups if code_dim % groups == 0 else -1)
    return want


def check_tensors(t: dict[str, np.ndarray], mc: dict[str, Any], where: Path, groups: int = 1,
                  frame: VQVAEConfig | None = None) -> None:
    """The weights are exactly the float32 tensors config.json describes, finite, and a VQ-VAE
    they read codes of was trained."""
    want = expected_shapes(mc, groups, frame)
    n_codes = mc["n_codes"]
    if frame is not None:  # the frame VQ-VAE's encoder and codebook (its own checks)
        want.update(check_vqvae_tensors(t, asdict(frame), where, VQVAE_PREFIX, FastLoopNumpyError, encoder_only=True))
    elif n_codes:
        want.update(_vqvae_shapes(t, mc, groups))
    # names the runtime does not read: the VQ-VAE's decoder and EMA buffers are fine, anything else
    # means the file describes another model than config.json does
    ignore = [k for k in t if n_codes and k.startswith("vqvae.")]
    check_weights(t, want, where, "the fast_loop config.json describes", FastLoopNumpyError, ignore)
    if n_codes:
        check_trained(t, "vqvae.", where, "the fast_loop's VQ-VAE", FastLoopNumpyError)


__all__ = ["FastLoopNumpyError", "MODEL_CONFIG_KEYS", "check_config", "check_tensors", "expected_shapes",
           "read_fast_loop", "vqvae_frame", "vqvae_groups"]
