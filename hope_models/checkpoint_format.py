"""What a checkpoint dir is on disk, for every reader and the one writer.

    <checkpoint dir>/                    e.g. <run_dir>/checkpoints/00002500/
        model.safetensors                the component's weights (safetensors; pickle is never loaded)
        config.json                      what the component is (format hope.component_config/1)
        training_state.safetensors       optimizer state, RNG states
        training_state.json              step, sampler state, loss history, ...
        manifest.json                    sha256 + size of the four files above; written last

This module holds the file names, the format versions, the bounded reader of a checkpoint's
(untrusted) JSON, the pickle sniffing that refuses anything but safetensors, the manifest check
(`read_verified`: each file read and hashed once, the bytes a loader needs handed back, so what is
loaded is what was verified), the version string that names a set of weights
(`<run>@<step>:<sha12>`) and the comparison of the weights' shapes with those a config describes.

Why here, at the top of the package with durable.py and paths.py: the trainer writes checkpoints
(train/checkpoint.py), the gate and the pointers name them (promote/, promoted.py), the torch-free
runtime serves them (runtime/) and the daemon and the webapp record their versions. This module
imports none of them (only the standard library and durable.py), so each can use it without
importing another, and it never imports torch.
"""
from __future__ import annotations

import hashlib
import json
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Mapping

from hope_models.durable import file_sha256

CHECKPOINT_FORMAT = "hope.checkpoint/1"  # manifest.json, training_state.json, the safetensors metadata
CONFIG_FORMAT = "hope.component_config/1"  # config.json: the component a checkpoint holds
MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
# The key of config.json, of a run's provenance and of the API's answers about a run that names the
# frozen VQ-VAE a component read codes of (null or absent: it read none).
VQVAE_REF = "vqvae"
STATE_TENSORS = "training_state.safetensors"
STATE_JSON = "training_state.json"
MANIFEST = "manifest.json"
CHECKPOINT_FILES = (MODEL_FILE, CONFIG_FILE, STATE_TENSORS, STATE_JSON)  # what a manifest must list
# config.json, training_state.json and manifest.json are a few kB to a few MB (the feature spec's
# statistics, the loss history); a bigger one is not something the trainer wrote.
MAX_JSON_BYTES = 64 << 20
# A safetensors file starts with an 8-byte little-endian header length, then a JSON object; a
# pickle starts with 0x80 and its protocol byte, which read as a length is far past the limit.
_PICKLE_PROTOCOL_BYTE = 0x80
_ZIP_MAGIC = b"PK\x03\x04"  # torch.save's default format: a zip of pickles
_MAX_HEADER = 100_000_000  # safetensors' own limit on the JSON header
SNIFF_BYTES = 9  # what safetensors_problem needs to see


class CheckpointError(ValueError):
    """A checkpoint cannot be written, read or used (the one such error, whichever layer finds it);
    the message names the dir or file and why."""


# -- hashing: the one function every checkpoint file is hashed with ------------------------------------

def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def file_digest(path: Path, keep: bool = False) -> tuple[str, bytes | None]:
    """(sha256, the bytes if keep) of a file, read once. Every hash of a checkpoint file goes
    through here, so a test can count them."""
    if keep:
        data = path.read_bytes()
        return sha256_hex(data), data
    return file_sha256(path), None


# -- JSON --------------------------------------------------------------------------------------------

def _no_constant(name: str):
    raise ValueError(f"{name} is not JSON (JSON has no NaN or Infinity)")


def parse_json_object(data: bytes, path: str | Path) -> dict[str, Any]:
    """Strict JSON (no NaN/Infinity: the trainer writes none), not nested deeper than the parser's
    recursion limit, and an object; CheckpointError naming `path` otherwise."""
    try:
        obj = json.loads(data.decode("utf-8"), parse_constant=_no_constant)
    except UnicodeDecodeError as exc:
        raise CheckpointError(f"{path}: not UTF-8 text: {exc.reason} at byte {exc.start}") from None
    except ValueError as exc:  # JSONDecodeError, NaN / Infinity
        raise CheckpointError(f"{path}: not readable JSON: {exc}") from None
    except RecursionError:
        raise CheckpointError(f"{path}: not readable JSON: nested too deeply") from None
    if not isinstance(obj, dict):
        raise CheckpointError(f"{path}: must be a JSON object, not {type(obj).__name__}")
    return obj


def read_json_object(path: str | Path, max_bytes: int = MAX_JSON_BYTES) -> dict[str, Any]:
    """A checkpoint's JSON file (config.json, training_state.json, manifest.json) as a dict.

    A checkpoint dir may come from anyone who can write one (a promotion names any dir under the
    data roots), so its JSON is untrusted: only a regular file (not a FIFO or a device, whose read
    would never end), at most max_bytes, then parse_json_object. CheckpointError names the file and
    the reason; FileNotFoundError passes through for callers that say what is missing."""
    path = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO for reading would otherwise wait for a writer, forever
        with open(os.open(path, os.O_RDONLY | os.O_NONBLOCK), "rb") as f:
            st = os.fstat(f.fileno())
            if not stat.S_ISREG(st.st_mode):
                raise CheckpointError(f"{path}: not a regular file")
            if st.st_size > max_bytes:
                raise CheckpointError(f"{path}: {st.st_size} bytes, more than the {max_bytes} a checkpoint's JSON "
                                      "may have")
            data = f.read(max_bytes + 1)
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if len(data) > max_bytes:  # grew while we looked
        raise CheckpointError(f"{path}: more than the {max_bytes} bytes a checkpoint's JSON may have")
    return parse_json_object(data, path)


# -- weights -----------------------------------------------------------------------------------------

def looks_like_pickle(head: bytes) -> bool:
    """Whether a file's first bytes are those of a pickle or of torch.save's zip of pickles."""
    return head[:4] == _ZIP_MAGIC or head[:1] == bytes([_PICKLE_PROTOCOL_BYTE])


def safetensors_problem(head: bytes) -> str | None:
    """None when `head` (a file's first SNIFF_BYTES bytes) starts like a safetensors file, else what
    it is instead. torch.save output (a zip of pickles) or a raw pickle is never handed to a loader:
    unpickling runs code."""
    n = int.from_bytes(head[:8], "little") if len(head) >= 8 else -1
    if 2 <= n <= _MAX_HEADER and head[8:9] == b"{":
        return None  # safetensors' own parser checks the rest
    if looks_like_pickle(head):
        return "is a pickle (torch.save) file, not safetensors; pickle is never loaded"
    return "not a safetensors file (bad header)"


def refuse_non_safetensors(path: Path) -> None:
    """CheckpointError unless the file starts like a safetensors file (safetensors_problem)."""
    try:
        with open(path, "rb") as f:
            head = f.read(SNIFF_BYTES)
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read: {exc.strerror}") from None
    problem = safetensors_problem(head)
    if problem is not None:
        raise CheckpointError(f"{path}: {problem}")


def _listing(items: list[str]) -> str:
    return f"{'; '.join(items[:5])}{' ...' if len(items) > 5 else ''}"


def weights_misfit(expected: Mapping[str, Any], found: Mapping[str, Any], *, ignore: Iterable[str] = (),
                   described_by: str = "config") -> str | None:
    """None when the file's tensors are exactly those expected, else what differs. expected /
    found: tensor name -> a comparable description (shape, or shape and dtype) as `described_by`
    (the config, the model built from it) has it and as the file holds it; names in `ignore` may
    be in the file without being expected."""
    ignored = set(ignore)
    missing = sorted(set(expected) - set(found))
    unexpected = sorted(set(found) - set(expected) - ignored)
    wrong = [f"{k}: file {found[k]}, {described_by} {v}" for k, v in expected.items() if k in found and found[k] != v]
    parts = []
    if wrong:
        parts.append(f"shape/dtype mismatch: {_listing(wrong)}")
    if missing:
        parts.append(f"missing: {missing[:5]}{' ...' if len(missing) > 5 else ''}")
    if unexpected:
        parts.append(f"unexpected: {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}")
    return ", ".join(parts) or None


# -- the manifest ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class VerifiedCheckpoint:
    """A checkpoint dir whose files matched its manifest when read: their sha256 (each hashed
    once) and the bytes of those asked for (the bytes that were hashed)."""
    path: Path
    sha256: dict[str, str]
    data: dict[str, bytes] = field(default_factory=dict)

    def json(self, name: str = CONFIG_FILE) -> dict[str, Any]:
        """A kept JSON file, parsed as read_json_object parses it."""
        data = self.data[name]
        if len(data) > MAX_JSON_BYTES:
            raise CheckpointError(f"{self.path / name}: more than the {MAX_JSON_BYTES} bytes a checkpoint's JSON "
                                  "may have")
        return parse_json_object(data, self.path / name)


class NotACheckpoint(CheckpointError):
    """read_verified's refusal; `.reason` is what verify() returns for the dir."""

    def __init__(self, path: Path, reason: str):
        super().__init__(f"{path}: not a complete checkpoint: {reason}")
        self.reason = reason


def _manifest_files(path: Path) -> dict[str, Any]:
    try:
        manifest = read_json_object(path / MANIFEST)
    except FileNotFoundError:
        raise NotACheckpoint(path, "no manifest.json (the write never finished)") from None
    except CheckpointError as exc:
        raise NotACheckpoint(path, f"manifest.json unreadable: {exc}") from None
    if manifest.get("format") != CHECKPOINT_FORMAT:
        raise NotACheckpoint(path, f"manifest.json is not a {CHECKPOINT_FORMAT} manifest")
    files = manifest.get("files")
    if not isinstance(files, dict) or not set(CHECKPOINT_FILES) <= set(files):
        raise NotACheckpoint(path, "manifest.json does not list the four checkpoint files")
    return files


def read_verified(path: str | Path, keep: Iterable[str] = ()) -> VerifiedCheckpoint:
    """Check every file of a checkpoint dir against its manifest (size, then sha256), hashing each
    once, and keep the bytes of the files named in `keep`. NotACheckpoint with the reason otherwise."""
    path = Path(path)
    keep = set(keep)
    files = _manifest_files(path)
    sha: dict[str, str] = {}
    data: dict[str, bytes] = {}
    for fname, entry in files.items():
        # Only plain files of this dir: a name like "../../x" or a symlink would have the
        # hash below read any file (or /dev/zero, forever) on the word of the manifest.
        if not isinstance(entry, dict) or fname in (".", "..") or "/" in fname or "\\" in fname or "\x00" in fname:
            raise NotACheckpoint(path, f"manifest.json lists {fname!r}, which is not a file of a checkpoint dir")
        f = path / fname
        try:
            st = f.lstat()
        except (OSError, ValueError):
            raise NotACheckpoint(path, f"{fname} is missing") from None
        if not stat.S_ISREG(st.st_mode):
            raise NotACheckpoint(path, f"{fname} is not a regular file")
        if st.st_size != entry.get("size"):
            raise NotACheckpoint(path, f"{fname} is {st.st_size} bytes, the manifest says {entry.get('size')} "
                                       "(truncated or overwritten)")
        if fname in keep and fname.endswith(".json") and st.st_size > MAX_JSON_BYTES:
            # kept means read whole: the JSON bound read_json_object applies, before the read
            raise CheckpointError(f"{f}: {st.st_size} bytes, more than the {MAX_JSON_BYTES} a checkpoint's JSON "
                                  "may have")
        try:
            digest, content = file_digest(f, keep=fname in keep)
        except OSError as exc:
            raise NotACheckpoint(path, f"{fname} cannot be read: {exc.strerror or exc}") from None
        if digest != entry.get("sha256") or (content is not None and len(content) != st.st_size):
            raise NotACheckpoint(path, f"{fname} does not match its sha256 in the manifest")
        sha[fname] = digest
        if content is not None:
            data[fname] = content
    return VerifiedCheckpoint(path, sha, data)


def verify(path: str | Path) -> str | None:
    """None when the dir is a complete checkpoint, else the reason it is not."""
    try:
        read_verified(path)
    except NotACheckpoint as exc:
        return exc.reason
    return None


# -- the version string ------------------------------------------------------------------------------

def version_name(ckpt_dir: str | Path, sha256: str, config: Any = None) -> str:
    """The name of a set of weights: "<run name>@<step>:<first 12 hex of the sha256>".

    The run name is the run dir's name (checkpoints/<step> sits in <run dir>/checkpoints), a bare
    checkpoint dir gives its own name; the step comes from config.json's "checkpoint"."step" (the
    parsed object, untrusted: any other shape only loses the step), else from a numeric dir name,
    else 0. ReflexPolicy, BrainService and the promotion records all name weights with this, so a
    response's version always matches the pointer's."""
    ckpt = Path(ckpt_dir)
    info = config.get("checkpoint") if isinstance(config, dict) else None
    step = info.get("step") if isinstance(info, dict) else None
    if not isinstance(step, int) or isinstance(step, bool):
        step = int(ckpt.name) if ckpt.name.isdigit() else 0
    run_name = ckpt.parent.parent.name if ckpt.parent.name == "checkpoints" else ckpt.name
    return f"{run_name}@{int(step)}:{sha256[:12]}"


def checkpoint_version(ckpt_dir: str | Path) -> tuple[str, str]:
    """(version, sha256 of model.safetensors) of a checkpoint dir; CheckpointError when the
    weights cannot be read."""
    ckpt = Path(ckpt_dir)
    weights = ckpt / MODEL_FILE
    try:
        sha, _ = file_digest(weights)
    except FileNotFoundError:
        raise CheckpointError(f"{weights}: not found (a checkpoint dir holds {MODEL_FILE})") from None
    except OSError as exc:
        raise CheckpointError(f"{weights}: cannot read: {exc.strerror or exc}") from None
    try:  # the config is untrusted: read bounded, and any shape of it only loses the step
        config = read_json_object(ckpt / CONFIG_FILE)
    except (OSError, CheckpointError):
        config = None
    return version_name(ckpt, sha, config), sha


__all__ = ["CHECKPOINT_FORMAT", "CONFIG_FORMAT", "MODEL_FILE", "CONFIG_FILE", "STATE_TENSORS", "STATE_JSON",
           "MANIFEST", "CHECKPOINT_FILES", "MAX_JSON_BYTES", "CheckpointError", "NotACheckpoint",
           "VerifiedCheckpoint", "sha256_hex", "file_digest", "parse_json_object", "read_json_object",
           "looks_like_pickle", "safetensors_problem", "refuse_non_safetensors", "weights_misfit", "read_verified", "verify",
           "version_name", "checkpoint_version"]
