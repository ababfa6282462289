"""Checkpoints a job can be killed in the middle of writing, and that never load pickle.

Layout of one run:

    <run_dir>/checkpoints/<step:08d>/   one complete checkpoint per kept step
        model.safetensors               the component's state_dict (weights and buffers)
        config.json                     component.config() + {"train": ..., "checkpoint": {...}}
        training_state.safetensors      optimizer state tensors ("optim.<param>.<key>"), RNG states
        training_state.json             step, optimizer param groups, sampler state, loss history, ...
        manifest.json                   sha256 + size of every file above; written LAST
    <run_dir>/checkpoints/last          the newest complete step's dir name (atomic write + rename)

A checkpoint is written into a hidden temp dir, every file fsynced, the dir renamed to its final
name and the parent fsynced (hope_models.durable). A directory whose manifest is missing, or whose
files do not match it (a torn write, a truncated file, a disk error), is not a checkpoint: loading
walks from the newest step down and skips such dirs with a warning naming the dir and the reason.

Everything here is torch-free at import (the sequential manager and the daemon read the pointer
and manifests without loading a model); tensors are written and read with safetensors only. The
file names, the manifest check, the JSON reader and the pickle sniffing are
hope_models/checkpoint_format.py's: the runtime and the gate read checkpoints without this module's
writer.
"""
from __future__ import annotations

import json
import os
import re
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable

from hope_models.checkpoint_format import (
    CHECKPOINT_FORMAT,
    CONFIG_FILE,
    MANIFEST,
    MODEL_FILE,
    STATE_JSON,
    STATE_TENSORS,
    CheckpointError,
    NotACheckpoint,
    VerifiedCheckpoint,
    read_json_object,
    read_verified,
    refuse_non_safetensors,
    sha256_hex,
    verify,
)
from hope_models.durable import atomic_write, fsync_path

POINTER = "last"
_STEP_DIR = re.compile(r"^\d{8}$")


@dataclass
class LoadedCheckpoint:
    path: Path
    step: int
    config: dict[str, Any]
    state: dict[str, Any]  # training_state.json
    model: dict[str, Any]  # name -> torch.Tensor
    tensors: dict[str, Any]  # training_state.safetensors: name -> torch.Tensor


def checkpoints_dir(run_dir: str | Path) -> Path:
    return Path(run_dir) / "checkpoints"


def step_dir_name(step: int) -> str:
    return f"{step:08d}"


# -- writing ------------------------------------------------------------------------------------

def _write_bytes(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def _json_bytes(obj: Any) -> bytes:
    # allow_nan=False: a NaN in a config or loss history is a bug to surface, not to persist
    return (json.dumps(obj, indent=1, sort_keys=True, allow_nan=False) + "\n").encode("utf-8")


def _safetensors_bytes(tensors: dict[str, Any], metadata: dict[str, str] | None = None) -> bytes:
    import torch  # lazy: loads torch
    from safetensors.torch import save  # lazy: loads safetensors

    # safetensors refuses tensors that share storage (tied weights, views): give each its own copy
    seen: set[tuple[int, int]] = set()
    out = {}
    for name, t in tensors.items():
        t = t.detach()
        if t.device.type != "cpu":
            t = t.cpu()
        key = (t.untyped_storage().data_ptr(), t.untyped_storage().nbytes()) if t.numel() else (0, -1)
        if key in seen or not t.is_contiguous():
            t = t.clone(memory_format=torch.contiguous_format)
        elif t.numel():
            seen.add(key)
        out[name] = t
    return save(out, metadata=metadata)


def write_pointer(run_dir: str | Path, step: int) -> None:
    """checkpoints/last names the newest complete checkpoint (write a temp file, rename, fsync)."""
    # its temp file is `.last.tmp-*`, which clean_temp removes after a crash
    atomic_write(checkpoints_dir(run_dir) / POINTER, (step_dir_name(step) + "\n").encode("ascii"))


def save_checkpoint(run_dir: str | Path, step: int, *, model_state: dict[str, Any], config: dict[str, Any],
                    state_tensors: dict[str, Any], state: dict[str, Any], keep_last: int = 3) -> Path:
    """Write checkpoint `step` atomically, point `last` at it, then prune to the newest keep_last.

    Serialisation happens before anything touches the disk, so a failure there leaves no trace;
    the manifest is the last file written into the temp dir, and the rename makes it visible.
    """
    if keep_last < 1:
        raise ValueError(f"keep_last={keep_last} must be >= 1")
    ckdir = checkpoints_dir(run_dir)
    ckdir.mkdir(parents=True, exist_ok=True)
    name = step_dir_name(step)
    # One key: safetensors writes its metadata map in hash order, so two keys would make equal
    # weights into different files (and different version names); the step is in config.json.
    meta = {"format": CHECKPOINT_FORMAT}
    files = {
        MODEL_FILE: _safetensors_bytes(model_state, meta),
        CONFIG_FILE: _json_bytes({**config, "checkpoint": {"format": CHECKPOINT_FORMAT, "step": step}}),
        STATE_TENSORS: _safetensors_bytes(state_tensors, meta),
        STATE_JSON: _json_bytes({**state, "format": CHECKPOINT_FORMAT, "step": step}),
    }
    tmp = ckdir / f".tmp-{name}-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    try:
        manifest = {"format": CHECKPOINT_FORMAT, "step": step, "files": {}}
        for fname, data in files.items():
            _write_bytes(tmp / fname, data)
            manifest["files"][fname] = {"sha256": sha256_hex(data), "size": len(data)}
        _write_bytes(tmp / MANIFEST, _json_bytes(manifest))
        fsync_path(tmp)
        final = ckdir / name
        if final.exists():  # a damaged dir of the same step (skipped on load): replace it
            _discard(final)
        os.rename(tmp, final)
        fsync_path(ckdir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    write_pointer(run_dir, step)
    prune(run_dir, keep_last)
    return final


def _discard(path: Path) -> None:
    """Remove a step dir: rename it out of the step namespace first, so a crash halfway through the
    delete never leaves something that looks like a checkpoint with files missing."""
    trash = path.parent / f".del-{path.name}-{os.getpid()}-{os.urandom(3).hex()}"
    os.rename(path, trash)
    fsync_path(path.parent)
    shutil.rmtree(trash, ignore_errors=True)


def prune(run_dir: str | Path, keep_last: int) -> list[Path]:
    """Delete step dirs older than the newest keep_last complete ones (by manifest presence; the
    hashes were checked when written). Returns the removed dirs."""
    steps = list_step_dirs(run_dir)
    complete = [p for _, p in steps if (p / MANIFEST).is_file()]
    if len(complete) <= keep_last:
        return []
    oldest_kept = complete[keep_last - 1]
    removed = []
    for _, p in steps:
        if p.name < oldest_kept.name:
            _discard(p)
            removed.append(p)
    return removed


def clean_temp(run_dir: str | Path) -> None:
    """Remove temp and half-deleted dirs left by a process that was killed while writing."""
    ckdir = checkpoints_dir(run_dir)
    if not ckdir.is_dir():
        return
    for p in ckdir.iterdir():
        if p.name.startswith((".tmp-", ".del-", f".{POINTER}.tmp-")):
            if p.is_dir():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)


# -- reading ------------------------------------------------------------------------------------

def list_step_dirs(run_dir: str | Path) -> list[tuple[int, Path]]:
    """(step, dir) of every step-named dir, newest first (complete or not)."""
    ckdir = checkpoints_dir(run_dir)
    if not ckdir.is_dir():
        return []
    out = [(int(p.name), p) for p in ckdir.iterdir() if _STEP_DIR.match(p.name) and p.is_dir()]
    return sorted(out, reverse=True)


def latest_complete(run_dir: str | Path, warn: Callable[[str], None] | None = None) -> Path | None:
    """The newest step dir that verifies, warning about each newer one skipped. Torch-free."""
    for _, p in list_step_dirs(run_dir):
        reason = verify(p)
        if reason is None:
            return p
        _warn(warn, f"skipping checkpoint {p}: {reason}")
    return None


def _warn(warn: Callable[[str], None] | None, message: str) -> None:
    if warn is None:
        warnings.warn(message, RuntimeWarning, stacklevel=3)
    else:
        warn(message)


def load_tensors(path: Path) -> dict[str, Any]:
    from safetensors import SafetensorError  # lazy: loads safetensors
    from safetensors.torch import load_file  # lazy: loads safetensors

    refuse_non_safetensors(path)
    try:
        return load_file(str(path), device="cpu")
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable safetensors file: {exc}") from None


def load_checkpoint(path: str | Path) -> LoadedCheckpoint:
    """Verify and read one checkpoint dir (CheckpointError naming the dir and reason otherwise)."""
    path = Path(path)
    reason = verify(path)
    if reason is not None:
        raise CheckpointError(f"{path}: not a complete checkpoint: {reason}")
    try:
        config = read_json_object(path / CONFIG_FILE)
        state = read_json_object(path / STATE_JSON)
    except FileNotFoundError as exc:
        raise CheckpointError(f"{path}: {Path(exc.filename).name} is missing") from None
    step = state.get("step")
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise CheckpointError(f"{path / STATE_JSON}: step={step!r} is not a step number")
    model = load_tensors(path / MODEL_FILE)
    tensors = load_tensors(path / STATE_TENSORS)
    return LoadedCheckpoint(path, step, config, state, model, tensors)


def load_latest(run_dir: str | Path, warn: Callable[[str], None] | None = None) -> LoadedCheckpoint | None:
    """The newest checkpoint that verifies and loads; each one skipped is warned about."""
    for _, p in list_step_dirs(run_dir):
        try:
            return load_checkpoint(p)
        except CheckpointError as exc:
            _warn(warn, f"skipping checkpoint {p}: {exc}")
    return None


def open_checkpoint(path: str | Path, keep: Iterable[str] = (),
                    warn: Callable[[str], None] | None = None) -> VerifiedCheckpoint:
    """A checkpoint dir from a checkpoint dir, a run dir or its checkpoints/ dir (the newest that
    verifies, warning about each newer one skipped), its files checked against the manifest with
    each hashed once and the bytes of those in `keep` handed back (checkpoint_format.read_verified),
    so a loader reads what was verified. Torch-free; CheckpointError when there is none."""
    p = Path(path)
    if (p / MANIFEST).is_file() or (p / MODEL_FILE).is_file():
        return read_verified(p, keep)
    run_dir = p.parent if p.name == "checkpoints" else p
    for _, step_dir in list_step_dirs(run_dir):
        try:
            return read_verified(step_dir, keep)
        except NotACheckpoint as exc:
            _warn(warn, f"skipping checkpoint {step_dir}: {exc.reason}")
    raise CheckpointError(f"{p}: no complete checkpoint found (expected a checkpoint dir or a run dir "
                          "with checkpoints/<step>/)")


def resolve_checkpoint_dir(path: str | Path) -> Path:
    """open_checkpoint's dir (a checkpoint dir, or a run dir's newest that verifies)."""
    return open_checkpoint(path).path


# -- optimizer state <-> flat tensors + JSON ---------------------------------------------------------

def flatten_optimizer(opt_state: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """torch optimizer.state_dict() -> (tensors "optim.<param index>.<key>", JSON of the rest)."""
    import torch  # lazy: loads torch

    tensors: dict[str, Any] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for idx, pstate in opt_state["state"].items():
        for key, value in pstate.items():
            if isinstance(value, torch.Tensor):
                tensors[f"optim.{int(idx)}.{key}"] = value
            else:
                scalars.setdefault(str(int(idx)), {})[key] = value
    groups = []
    for g in opt_state["param_groups"]:
        groups.append({k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()})
    return tensors, {"param_groups": groups, "scalars": scalars, "tuples": _tuple_keys(opt_state)}


def _tuple_keys(opt_state: dict[str, Any]) -> list[str]:
    keys = set()
    for g in opt_state["param_groups"]:
        keys.update(k for k, v in g.items() if isinstance(v, tuple))
    return sorted(keys)


def unflatten_optimizer(tensors: dict[str, Any], meta: dict[str, Any]) -> dict[str, Any]:
    state: dict[int, dict[str, Any]] = {}
    for name, t in tensors.items():
        if not name.startswith("optim."):
            continue
        _, idx, key = name.split(".", 2)
        state.setdefault(int(idx), {})[key] = t
    for idx, scal in meta.get("scalars", {}).items():
        state.setdefault(int(idx), {}).update(scal)
    tuples = set(meta.get("tuples", []))
    groups = [{k: (tuple(v) if k in tuples else v) for k, v in g.items()} for g in meta["param_groups"]]
    return {"state": state, "param_groups": groups}
