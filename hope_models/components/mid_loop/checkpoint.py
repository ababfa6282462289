"""What the NumPy runtime accepts as a mid_loop checkpoint (read with each file hashed once).

    ck = read_mid_loop(path, expected_sha256=pointer["sha256"], verify_manifest=True)

config.json must describe a mid_loop (format hope.component_config/1): integer dims in range,
horizon_steps positive whole grid steps, a window {"k", "duration_s"} of at most MAX_K points, a
feature spec with the model's action size, and under "vqvae" the VQ-VAE it reads: a vector one
(its model_config: groups, n_codes equal to the Mid Loop's, obs_dim equal to the spec's), or a
grid frame one (grid_model.GridMidLoop: vqvae/numpy_frame.frame_config's checks, its frame the
feature spec's, and the Mid Loop's obs_dim, keypoints, cell_rank and copy_mix in range). The
weights must be exactly the float32 tensors of those shapes, finite, with the frozen VQ-VAE under
vqvae.* trained (a grid's encoder and codebook only: its decoder is not served). Not read, so not
refused: the baselines' buffers (code_counts; stay_counts of a vector Mid Loop), the VQ-VAE's EMA
buffers, and any tensor named wm_* (a world model's action-conditioned heads, which another model
may add). A grid Mid Loop reads stay_counts (copy-last, mixed into each cell's distribution): it
must be [H, G, 2] float64, finite and >= 0. A flat frame VQ-VAE is refused. Anything else is
MidLoopNumpyError naming the file and the reason. Torch-free.
"""
from __future__ import annotations

import math
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.components.checkpoint_checks import (
    CheckedCheckpoint,
    CheckpointRefused,
    check_header,
    check_weights,
    read_component,
)
from hope_models.components.layers import tensors
from hope_models.components.mid_loop.config import MidLoopConfig
from hope_models.components.mid_loop.layers import layers
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.numpy_form import MAX_WIDTH, check_vqvae_ref, check_vqvae_tensors, frame_of
from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.spec_request import spec_from_json_obj
from hope_models.data.windows import MAX_K

MAX_LAYERS = 64
MAX_HORIZONS = 16
IGNORED = ("code_counts", "stay_counts")  # baseline statistics, not read at inference


class MidLoopNumpyError(CheckpointRefused):
    """This checkpoint cannot be run by the NumPy Mid Loop; the message names the file and why."""


def _int(mc: dict[str, Any], key: str, where: Path, lo: int, hi: int) -> int:
    v = mc.get(key)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise MidLoopNumpyError(f"{where}: model_config.{key}={v!r} must be an integer in {lo}-{hi}")
    return v


def _check_model(mc: Any, window: Any, where: Path) -> None:
    if not isinstance(mc, dict):
        raise MidLoopNumpyError(f"{where}: 'model_config' is missing or not an object")
    for key in ("act_dim", "d_model", "d_state", "mlp_ratio"):
        _int(mc, key, where, 1, MAX_WIDTH)
    _int(mc, "n_codes", where, 2, MAX_WIDTH)
    _int(mc, "n_layers", where, 1, MAX_LAYERS)
    hs = mc.get("horizon_steps")
    if (not isinstance(hs, list) or not 1 <= len(hs) <= MAX_HORIZONS
            or any(isinstance(s, bool) or not isinstance(s, int) or not 1 <= s <= MAX_K for s in hs)):
        raise MidLoopNumpyError(f"{where}: model_config.horizon_steps={hs!r} must be 1-{MAX_HORIZONS} whole grid "
                                f"steps in 1-{MAX_K}")
    if not isinstance(window, dict):
        raise MidLoopNumpyError(f"{where}: 'window' is missing (its k and duration_s give the grid step)")
    k, dur = window.get("k"), window.get("duration_s")
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= MAX_K:
        raise MidLoopNumpyError(f"{where}: window.k={k!r} must be an integer in 1-{MAX_K}")
    if isinstance(dur, bool) or not isinstance(dur, (int, float)) or not math.isfinite(dur) or dur <= 0:
        raise MidLoopNumpyError(f"{where}: window.duration_s={dur!r} must be a positive number of seconds")


def check_config(config: Any, where: Path) -> FeatureSpec:
    """The feature spec of a mid_loop config.json this runtime can run (see the module doc)."""
    check_header(config, where, "mid_loop", MidLoopNumpyError)
    mc = config.get("model_config")
    _check_model(mc, config.get("window"), where)
    try:
        spec = spec_from_json_obj(config.get("feature_spec"), f"{where}: feature_spec")
    except FeatureSpecError as exc:
        raise MidLoopNumpyError(str(exc)) from None
    if spec.act_dim != mc["act_dim"]:
        raise MidLoopNumpyError(f"{where}: the feature spec has {spec.act_dim} action values, model_config says "
                                f"act_dim={mc['act_dim']}")
    ref = config.get("vqvae")
    if not isinstance(ref, dict):
        raise MidLoopNumpyError(f"{where}: 'vqvae' does not describe the VQ-VAE the Mid Loop reads")
    vq_cfg = ref.get("model_config")
    frames = isinstance(vq_cfg, dict) and vq_cfg.get("input") == "frame"
    check_vqvae_ref(vq_cfg, spec.obs_dim, where, MidLoopNumpyError, n_codes=mc["n_codes"], frames=frames)
    if frames:
        _check_grid(mc, spec, grid_frame(config), where)
    return spec


def _check_grid(mc: dict[str, Any], spec: FeatureSpec, frame: VQVAEConfig | None, where: Path) -> None:
    """A Mid Loop over a frame VQ-VAE: a grid one (grid_model.py), reading the spec's frame and joints."""
    if frame is None:
        raise MidLoopNumpyError(f"{where}: vqvae model_config.layout is 'flat'; the NumPy Mid Loop reads the codes "
                                "of a vector VQ-VAE or the cells of a grid frame VQ-VAE")
    if spec.frame is None or tuple(spec.frame.shape) != frame.frame_shape:
        raise MidLoopNumpyError(f"{where}: the VQ-VAE reads {list(frame.frame_shape)} camera frames, the feature "
                                f"spec's frame is {None if spec.frame is None else list(spec.frame.shape)}")
    if _int(mc, "obs_dim", where, 1, MAX_WIDTH) != spec.obs_dim:
        raise MidLoopNumpyError(f"{where}: model_config.obs_dim={mc['obs_dim']} is not the feature spec's "
                                f"{spec.obs_dim} joint values")
    _int(mc, "keypoints", where, 1, MAX_WIDTH)
    _int(mc, "cell_rank", where, 1, MAX_WIDTH)
    mix = mc.get("copy_mix", MidLoopConfig.copy_mix)
    if isinstance(mix, bool) or not isinstance(mix, (int, float)) or not 0.0 <= mix < 1.0:
        raise MidLoopNumpyError(f"{where}: model_config.copy_mix={mix!r} must be a number within [0, 1)")


def grid_frame(config: dict[str, Any]) -> VQVAEConfig | None:
    """The grid frame VQ-VAE a checked mid_loop config reads, or None (a vector or flat one)."""
    vq = frame_of(config["vqvae"]["model_config"])
    return vq if vq is not None and vq.layout == "grid" else None


def expected_shapes(mc: dict[str, Any], groups: int, frame: VQVAEConfig | None = None) -> dict[str, tuple[int, ...]]:
    """Tensor name -> shape of every Mid Loop weight the NumPy form reads (the VQ-VAE's and the world
    model's apart), from the same layer description the memory estimate reads (layers.py). frame:
    the grid frame VQ-VAE of a grid Mid Loop."""
    cfg = MidLoopConfig(**{f.name: mc[f.name] for f in fields(MidLoopConfig) if f.name in mc})
    cfg.horizon_steps = tuple(mc["horizon_steps"])
    vq = frame if frame is not None else VQVAEConfig(n_codes=mc["n_codes"], groups=groups)
    return tensors([layer for layer in layers(cfg, vq) if not layer.name.startswith(("vqvae.", "wm_"))])


def check_tensors(t: dict[str, np.ndarray], config: dict[str, Any], where: Path) -> None:
    """The weights are exactly the float32 tensors config.json describes, finite, the VQ-VAE trained."""
    mc, vq_cfg = config["model_config"], config["vqvae"]["model_config"]
    frame = grid_frame(config)
    want = expected_shapes(mc, int(vq_cfg.get("groups", 1)), frame)
    ignore = [k for k in t if k.startswith(("vqvae.", "wm_")) or k in IGNORED]
    check_weights(t, want, where, "the mid_loop config.json describes", MidLoopNumpyError, ignore)
    check_vqvae_tensors(t, vq_cfg, where, "vqvae.", MidLoopNumpyError, encoder_only=frame is not None)
    if frame is not None:
        _check_stay_counts(t.get("stay_counts"), (len(mc["horizon_steps"]), frame.groups, 2), where)


def _check_stay_counts(stay: np.ndarray | None, shape: tuple[int, ...], where: Path) -> None:
    """copy-last's counts, which a grid Mid Loop mixes into each cell's distribution (grid_metrics.py)."""
    if stay is None or stay.shape != shape or stay.dtype != np.float64:
        got = "missing" if stay is None else f"{list(stay.shape)} {stay.dtype}"
        raise MidLoopNumpyError(f"{where}: stay_counts (copy-last's counts, mixed into each cell's distribution) "
                                f"must be {list(shape)} float64, got {got}")
    if not np.isfinite(stay).all() or (stay < 0).any():
        raise MidLoopNumpyError(f"{where}: stay_counts holds non-finite or negative counts")


def read_mid_loop(path: str | Path, *, expected_sha256: str | None = None,
                  verify_manifest: bool = False) -> CheckedCheckpoint:
    """Read and check <path>/config.json + model.safetensors (fast_loop_checkpoint.read_component:
    the manifest, the sha256 against the pointer's)."""
    return read_component(path, check_config, check_tensors, MidLoopNumpyError, expected_sha256=expected_sha256,
                          verify_manifest=verify_manifest)


__all__ = ["MidLoopNumpyError", "read_mid_loop", "check_config", "check_tensors", "expected_shapes", "grid_frame"]
