"""What every component's NumPy form shares in reading a checkpoint: the manifest, the sha256
against the promotion pointer's, the safetensors bytes read once (pickle refused by its first
bytes), the config.json header and the weights' names, shapes, dtype and finiteness. Each
component's own checks (its config.json's dims, the tensors its form reads) are in its folder's
checkpoint.py (fast_loop, mid_loop) or numpy_form.py (vqvae). Torch-free.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from hope_models.checkpoint_format import (
    CONFIG_FILE,
    CONFIG_FORMAT,
    MODEL_FILE,
    CheckpointError,
    read_json_object,
    safetensors_problem,
    sha256_hex,
    version_name,
    weights_misfit,
)
from hope_models.checkpoints import open_checkpoint
from hope_models.data.features import FeatureSpec


class CheckpointRefused(ValueError):
    """A checkpoint the NumPy runtime cannot run (any component); the message names the file and why."""

@dataclass(frozen=True)
class CheckedCheckpoint:
    """A fast_loop checkpoint the NumPy runtime can run: its config (checked), the feature spec,
    the weights (checked), their sha256 and the version that names them."""
    path: Path
    config: dict[str, Any]
    spec: FeatureSpec
    tensors: dict[str, np.ndarray]
    sha256: str
    version: str

def read_component(path: str | Path, config_check: Callable[[Any, Path], FeatureSpec],
                   tensors_check: Callable[[dict[str, np.ndarray], dict[str, Any], Path], None],
                   error: type[CheckpointRefused], *, expected_sha256: str | None = None,
                   verify_manifest: bool = False) -> CheckedCheckpoint:
    """A component's checkpoint as the NumPy runtime reads it: config_check(config, where) -> its feature spec and
    tensors_check(tensors, config, where) raise `error` (a CheckpointRefused) naming the file; the
    manifest, the sha256 against the pointer's and the safetensors reading are the same for all."""
    ckpt = Path(path)
    cfg_path, weights_path = ckpt / CONFIG_FILE, ckpt / MODEL_FILE
    if verify_manifest:

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
        config = read_config(cfg_path, error)
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
    return CheckedCheckpoint(ckpt, config, spec, tensors, sha, version_name(ckpt, sha, config))


def read_config(cfg_path: Path, error: type[CheckpointRefused]) -> dict[str, Any]:
    try:
        return read_json_object(cfg_path)  # untrusted: size, depth and type bounded there
    except FileNotFoundError:
        raise error(f"{cfg_path}: not found (a checkpoint dir holds {MODEL_FILE} + "
                                 f"{CONFIG_FILE})") from None
    except CheckpointError as exc:
        raise error(str(exc)) from None

MAX_GROUPS = 64  # far above any useful product of codebooks; bounds what an untrusted config sizes

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

def load_tensors(data: bytes, where: Path,
                 error: type[CheckpointRefused]) -> dict[str, np.ndarray]:
    """The tensors of a safetensors file's bytes (pickle refused by its first bytes, never parsed)."""
    from safetensors import SafetensorError  # lazy: loads safetensors
    from safetensors.numpy import load  # lazy: loads safetensors

    problem = safetensors_problem(data[:9])
    if problem is not None:
        raise error(f"{where}: {problem}")
    try:
        return load(data)
    except (SafetensorError, ValueError, TypeError) as exc:
        raise error(f"{where}: not a readable safetensors file: {exc}") from None

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


__all__ = ["CheckedCheckpoint", "CheckpointRefused", "MAX_GROUPS", "check_header", "check_trained", "check_weights",
           "load_tensors", "read_component", "read_config"]
