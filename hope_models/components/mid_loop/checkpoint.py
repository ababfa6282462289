"""What the NumPy runtime accepts as a mid_loop checkpoint (read with each file hashed once).

    ck = read_mid_loop(path, expected_sha256=pointer["sha256"], verify_manifest=True)

config.json must describe a mid_loop (format hope.component_config/1): integer dims in range,
horizon_steps positive whole grid steps, a window {"k", "duration_s"} of at most MAX_K points, a
feature spec with the model's action size, and under "vqvae" the vector VQ-VAE it reads (its
model_config: groups, n_codes equal to the Mid Loop's, obs_dim equal to the spec's). The weights
must be exactly the float32 tensors of those shapes, finite, with the frozen VQ-VAE under vqvae.*
trained. Not read, so not refused: the baselines' buffers (code_counts, stay_counts), the VQ-VAE's
EMA buffers, and any tensor named wm_* (a world model's action-conditioned heads, which another
model may add). Anything else is MidLoopNumpyError naming the file and the reason. Torch-free.
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
from hope_models.components.vqvae.numpy_form import MAX_WIDTH, check_vqvae_ref, check_vqvae_tensors
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
    check_vqvae_ref(ref.get("model_config"), spec.obs_dim, where, MidLoopNumpyError, n_codes=mc["n_codes"])
    return spec


def expected_shapes(mc: dict[str, Any], groups: int) -> dict[str, tuple[int, ...]]:
    """Tensor name -> shape of every Mid Loop weight the NumPy form reads (the VQ-VAE's and the world
    model's apart), from the same layer description the memory estimate reads (layers.py)."""
    cfg = MidLoopConfig(**{f.name: mc[f.name] for f in fields(MidLoopConfig) if f.name in mc})
    cfg.horizon_steps = tuple(mc["horizon_steps"])
    vq = VQVAEConfig(n_codes=mc["n_codes"], groups=groups)
    return tensors([layer for layer in layers(cfg, vq) if not layer.name.startswith(("vqvae.", "wm_"))])


def check_tensors(t: dict[str, np.ndarray], config: dict[str, Any], where: Path) -> None:
    """The weights are exactly the float32 tensors config.json describes, finite, the VQ-VAE trained."""
    mc, vq_cfg = config["model_config"], config["vqvae"]["model_config"]
    want = expected_shapes(mc, int(vq_cfg.get("groups", 1)))
    ignore = [k for k in t if k.startswith(("vqvae.", "wm_")) or k in IGNORED]
    check_weights(t, want, where, "the mid_loop config.json describes", MidLoopNumpyError, ignore)
    check_vqvae_tensors(t, vq_cfg, where, "vqvae.", MidLoopNumpyError)


def read_mid_loop(path: str | Path, *, expected_sha256: str | None = None,
                  verify_manifest: bool = False) -> CheckedCheckpoint:
    """Read and check <path>/config.json + model.safetensors (fast_loop_checkpoint.read_component:
    the manifest, the sha256 against the pointer's)."""
    return read_component(path, check_config, check_tensors, MidLoopNumpyError, expected_sha256=expected_sha256,
                          verify_manifest=verify_manifest)


__all__ = ["MidLoopNumpyError", "read_mid_loop", "check_config", "check_tensors", "expected_shapes"]
