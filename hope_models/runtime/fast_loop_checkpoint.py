"""What the NumPy runtime accepts as a fast_loop checkpoint, and reading one with each file hashed once.

    ck = read_fast_loop(path, expected_sha256=pointer["sha256"], verify_manifest=True)
    ck.config, ck.spec, ck.tensors, ck.sha256, ck.version

config.json must describe a fast_loop (format hope.component_config/1) whose dims are integers in
range, whose window K is the model's, whose feature spec has the model's observation and action
sizes, and, when it reads VQ-VAE codes, a VQ-VAE of observation vectors (one that reads camera
frames is refused: a conv stack is not worth re-implementing for a runtime that receives
observation vectors). model.safetensors must be a safetensors file (pickle is refused unread)
holding exactly the float32 tensors of those shapes (the comparison is
checkpoint_format.weights_misfit, which the torch loader uses too), all finite, with a trained
codebook when there is one. Anything else is FastLoopNumpyError naming the file and the reason.

The weights' bytes are read once: the sha256 (checked against the manifest and the promotion
pointer), the version string (checkpoint_format.version_name) and the tensors all come from the
same bytes. Torch-free.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Callable

import numpy as np

from hope_models.checkpoint_format import (
    CONFIG_FILE, CONFIG_FORMAT, MODEL_FILE, CheckpointError, read_json_object, safetensors_problem, sha256_hex,
    version_name, weights_misfit,
)
from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.spec_request import spec_from_json_obj
from hope_models.data.windows import MAX_K

MODEL_CONFIG_KEYS = ("obs_dim", "act_dim", "window_k", "d_model", "d_state", "mlp_ratio", "min_timescale",
                     "max_timescale", "n_codes")


class CheckpointRefused(ValueError):
    """A checkpoint the NumPy runtime cannot run (any component); the message names the file and why."""


class FastLoopNumpyError(CheckpointRefused):
    """This checkpoint cannot be run by the NumPy fast_loop; the message names the file and why."""


@dataclass(frozen=True)
class FastLoopCheckpoint:
    """A fast_loop checkpoint the NumPy runtime can run: its config (checked), the feature spec,
    the weights (checked), their sha256 and the version that names them."""
    path: Path
    config: dict[str, Any]
    spec: FeatureSpec
    tensors: dict[str, np.ndarray]
    sha256: str
    version: str


def read_fast_loop(path: str | Path, *, expected_sha256: str | None = None,
                   verify_manifest: bool = False) -> FastLoopCheckpoint:
    """Read and check <path>/config.json + model.safetensors. expected_sha256: refuse weights whose
    sha256 differs (the promotion pointer's record of what was promoted). verify_manifest: a run
    dir is resolved to its newest complete checkpoint and every file is checked against the
    manifest (train/checkpoint.open_checkpoint), the bytes loaded being those hashed; without it,
    a bare checkpoint dir needs no manifest (what a test or a tool wrote by hand)."""
    def tensors_ok(t: dict[str, np.ndarray], config: dict[str, Any], where: Path) -> None:
        check_tensors(t, config["model_config"], where, groups=vqvae_groups(config))

    return read_component(path, check_config, tensors_ok, FastLoopNumpyError, expected_sha256=expected_sha256,
                          verify_manifest=verify_manifest)


def read_component(path: str | Path, config_check: Callable[[Any, Path], FeatureSpec],
                   tensors_check: Callable[[dict[str, np.ndarray], dict[str, Any], Path], None],
                   error: type[CheckpointRefused], *, expected_sha256: str | None = None,
                   verify_manifest: bool = False) -> FastLoopCheckpoint:
    """read_fast_loop for any component: config_check(config, where) -> its feature spec and
    tensors_check(tensors, config, where) raise `error` (a CheckpointRefused) naming the file; the
    manifest, the sha256 against the pointer's and the safetensors reading are the same for all."""
    ckpt = Path(path)
    cfg_path, weights_path = ckpt / CONFIG_FILE, ckpt / MODEL_FILE
    if verify_manifest:
        from hope_models.train.checkpoint import open_checkpoint

        try:
            verified = open_checkpoint(ckpt, keep=(CONFIG_FILE, MODEL_FILE))
            ckpt, cfg_path, weights_path = verified.path, verified.path / CONFIG_FILE, verified.path / MODEL_FILE
            config = verified.json(CONFIG_FILE)
        except CheckpointError as exc:
            raise error(str(exc)) from None
        spec = config_check(config, cfg_path)
        data, sha = verified.data[MODEL_FILE], verified.sha256[MODEL_FILE]
    else:
        if not ckpt.is_dir():
            raise error(f"{ckpt}: checkpoint dir not found")
        config = _read_config(cfg_path, error)
        spec = config_check(config, cfg_path)
        try:
            data = weights_path.read_bytes()
        except FileNotFoundError:
            raise error(f"{weights_path}: weights file not found") from None
        except OSError as exc:
            raise error(f"{weights_path}: cannot read: {exc.strerror or exc}") from None
        sha = sha256_hex(data)
    if expected_sha256 is not None and sha != expected_sha256:
        raise error(f"{weights_path}: sha256 {sha[:12]}... does not match the promoted "
                    f"{expected_sha256[:12]}... (the file changed after promotion)")
    tensors = load_tensors(data, weights_path, error)
    tensors_check(tensors, config, weights_path)
    return FastLoopCheckpoint(ckpt, config, spec, tensors, sha, version_name(ckpt, sha, config))


def _read_config(cfg_path: Path, error: type[CheckpointRefused] = FastLoopNumpyError) -> dict[str, Any]:
    try:
        return read_json_object(cfg_path)  # untrusted: size, depth and type bounded there
    except FileNotFoundError:
        raise error(f"{cfg_path}: not found (a checkpoint dir holds {MODEL_FILE} + "
                                 f"{CONFIG_FILE})") from None
    except CheckpointError as exc:
        raise error(str(exc)) from None


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


MAX_GROUPS = 64  # far above any useful product of codebooks; bounds what an untrusted config sizes


def _check_vqvae(config: dict[str, Any], mc: dict[str, Any], where: Path) -> None:
    vq = config.get("vqvae")
    vq_cfg = vq.get("model_config") if isinstance(vq, dict) else None
    if not isinstance(vq_cfg, dict):
        raise FastLoopNumpyError(f"{where}: n_codes={mc['n_codes']} but 'vqvae' does not describe the VQ-VAE")
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


def check_header(config: Any, where: Path, component: str, error: type[Exception]) -> None:
    """config.json is an object of this checkpoint format for `component`; else `error` naming the file."""
    if not isinstance(config, dict):
        raise error(f"{where}: must be a JSON object")
    fmt = config.get("format")
    if fmt != CONFIG_FORMAT:
        raise error(f"{where}: format {fmt!r} is not {CONFIG_FORMAT!r}")
    comp = config.get("component")
    if comp != component:
        raise error(f"{where}: component is {comp!r}; this runtime serves {component} checkpoints here")


def check_config(config: Any, where: Path) -> FeatureSpec:
    """The feature spec of a config.json this runtime can run (see the module doc)."""
    check_header(config, where, "fast_loop", FastLoopNumpyError)
    mc = config.get("model_config")
    _check_model_config(mc, where)
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
        _check_vqvae(config, mc, where)
    return spec


def load_tensors(data: bytes, where: Path,
                 error: type[CheckpointRefused] = FastLoopNumpyError) -> dict[str, np.ndarray]:
    """The tensors of a safetensors file's bytes (pickle refused by its first bytes, never parsed)."""
    from safetensors import SafetensorError
    from safetensors.numpy import load

    problem = safetensors_problem(data[:9])
    if problem is not None:
        raise error(f"{where}: {problem}")
    try:
        return load(data)
    except (SafetensorError, ValueError, TypeError) as exc:
        raise error(f"{where}: not a readable safetensors file: {exc}") from None


def expected_shapes(mc: dict[str, Any], groups: int = 1) -> dict[str, tuple[int, ...]]:
    """Tensor name -> shape of every weight the NumPy form reads."""
    d, n, hidden = mc["d_model"], mc["d_state"], mc["mlp_ratio"] * mc["d_model"]
    shapes: dict[str, tuple[int, ...]] = {
        "obs_in.weight": (d, mc["obs_dim"]), "obs_in.bias": (d,),
        "ssm.B": (n, d), "ssm.C": (d, n), "ssm.D": (d,), "ssm.log_rate": (n,),
        "out.weight": (mc["act_dim"], d), "out.bias": (mc["act_dim"],),
    }
    for name in ("enc_ln", "ssm_ln", "head_ln", "out_ln"):
        shapes[f"{name}.weight"] = shapes[f"{name}.bias"] = (d,)
    for name in ("enc_mlp", "head_mlp"):
        shapes.update({f"{name}.w_gate.weight": (hidden, d), f"{name}.w_gate.bias": (hidden,),
                       f"{name}.w_up.weight": (hidden, d), f"{name}.w_up.bias": (hidden,),
                       f"{name}.w_out.weight": (d, hidden), f"{name}.w_out.bias": (d,)})
    if mc["n_codes"]:
        shapes["code_in.weight"] = (mc["n_codes"] * groups, d)  # one row per code of every group
    return shapes


def vqvae_groups(config: dict[str, Any]) -> int:
    """The code groups of a checkpoint's VQ-VAE (1 without one, or one saved before groups existed);
    check_config has checked the value."""
    vq = config.get("vqvae")
    return int(vq["model_config"].get("groups", 1)) if isinstance(vq, dict) else 1


def _vqvae_shapes(t: dict[str, np.ndarray], mc: dict[str, Any], groups: int) -> dict[str, tuple[int, ...]]:
    """The vector VQ-VAE encoder and codebook the codes need; its widths are the file's own."""
    w0 = t.get("vqvae.encoder.0.0.weight")
    w4 = t.get("vqvae.encoder.0.4.weight")
    hidden = w0.shape[0] if w0 is not None and w0.ndim == 2 else -1
    code_dim = w4.shape[0] if w4 is not None and w4.ndim == 2 else -1
    return {"vqvae.encoder.0.0.weight": (hidden, mc["obs_dim"]), "vqvae.encoder.0.0.bias": (hidden,),
            "vqvae.encoder.0.2.weight": (hidden, hidden), "vqvae.encoder.0.2.bias": (hidden,),
            "vqvae.encoder.0.4.weight": (code_dim, hidden), "vqvae.encoder.0.4.bias": (code_dim,),
            "vqvae.codebook": (mc["n_codes"] * groups, code_dim // groups if code_dim % groups == 0 else -1)}


def check_weights(t: dict[str, np.ndarray], want: dict[str, tuple[int, ...]], where: Path, what: str,
                  error: type[Exception], ignore: Iterable[str] = ()) -> None:
    """t holds exactly the float32 tensors `want` names with those shapes (besides the `ignore`d
    names), every one finite; else `error` naming the file and the tensors."""
    misfit = weights_misfit({k: f"{list(s)} float32" for k, s in want.items()},
                            {k: f"{list(v.shape)} {v.dtype}" for k, v in t.items()}, ignore=list(ignore))
    if misfit:
        raise error(f"{where}: weights do not fit {what} ({misfit})")
    bad = [k for k in want if not np.isfinite(t[k]).all()]
    if bad:
        raise error(f"{where}: non-finite weights (NaN/Inf) in {', '.join(bad[:5])}{' ...' if len(bad) > 5 else ''}")


def check_trained(t: dict[str, np.ndarray], prefix: str, where: Path, whose: str, error: type[Exception]) -> None:
    """The VQ-VAE under prefix was trained (its codebook initialised)."""
    init = t.get(f"{prefix}initialized")
    if init is None or int(np.asarray(init).reshape(-1)[0]) != 1:
        raise error(f"{where}: {whose} was never trained (codebook not initialised)")


def check_tensors(t: dict[str, np.ndarray], mc: dict[str, Any], where: Path, groups: int = 1) -> None:
    """The weights are exactly the float32 tensors config.json describes, finite, and a VQ-VAE
    they read codes of was trained."""
    want = expected_shapes(mc, groups)
    n_codes = mc["n_codes"]
    if n_codes:
        want.update(_vqvae_shapes(t, mc, groups))
    # names the runtime does not read: the VQ-VAE's decoder and EMA buffers are fine, anything else
    # means the file describes another model than config.json does
    ignore = [k for k in t if n_codes and k.startswith("vqvae.")]
    check_weights(t, want, where, "the fast_loop config.json describes", FastLoopNumpyError, ignore)
    if n_codes:
        check_trained(t, "vqvae.", where, "the fast_loop's VQ-VAE", FastLoopNumpyError)


__all__ = ["CheckpointRefused", "FastLoopNumpyError", "FastLoopCheckpoint", "read_fast_loop", "read_component",
           "check_config", "check_tensors",
           "expected_shapes", "load_tensors", "MODEL_CONFIG_KEYS"]
