"""The files of a run dir a client may download, and how they are read safely (GET
/api/runs/<id>/artifacts in webapp/api/run_artifacts.py).

An artifact's name is one this module finds in the run dir (`candidates`), never a path taken
from the request; `list_artifacts` is those that pass `is_safe`. Every file is resolved and
refused when its real path leaves the run dir (a symlink escape) or it is not a regular file; it is opened by that real path with O_NOFOLLOW, and its
size is the opened file's, so what is checked is what is sent.

A checkpoint is sent as an uncompressed tar of its dir, members "checkpoint-<step>/<file>": the
files are opened (and checked) before the first byte goes out, so a prune that deletes the dir
mid-download does not cut the tar short, and the tar is generated block by block (headers, file
data, padding, the two zero blocks at the end), never built in memory or on disk. Its length is
known up front (Content-Length).
"""
from __future__ import annotations

import os
import stat
import tarfile
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Iterator

from hope_models.checkpoints import list_step_dirs
from hope_models.train.held_out_picture import HELD_OUT_PICTURE, PREDICTED_PICTURE

CHUNK = 256 * 1024
BLOCK = tarfile.BLOCKSIZE

JSONL_TYPE = "application/x-ndjson"
MCAP_TYPE = "application/octet-stream"
JSON_TYPE = "application/json"
TAR_TYPE = "application/x-tar"
PNG_TYPE = "image/png"

# (file name, kind, media type, description) of the single files a run dir may hold
SINGLE_FILES = (
    ("metrics.jsonl", "metrics", JSONL_TYPE, "every metric and event record, one JSON object per line"),
    ("result.json", "result", JSON_TYPE, "how the run ended: outcome, losses, peak memory, validation figures"),
    ("provenance.json", "provenance", JSON_TYPE, "what the run was made from: config, dataset, VQ-VAE, code"),
    ("gate.json", "gate", JSON_TYPE, "the promotion gate's report"),
    (HELD_OUT_PICTURE, "picture", PNG_TYPE, "held-out frames (top row) over the VQ-VAE's reconstructions of them "
     "(bottom row), drawn at the end of training"),
    (PREDICTED_PICTURE, "picture", PNG_TYPE, "held-out windows, one a row: the frame now, then at each horizon "
     "(0.5 s, 1 s) the frame decoded from the Mid Loop's predicted codes beside the recorded one, drawn at the "
     "end of training"),
)


class UnsafeFile(Exception):
    """The file's real path is outside the run dir, or it is not a regular file."""


@dataclass
class Artifact:
    name: str
    kind: str
    media_type: str
    description: str
    path: Path  # a file, or for a checkpoint its dir
    step: int | None = None


def confined(run_dir: Path, path: Path) -> Path:
    """path's real path, when it is inside the run dir's real path; UnsafeFile otherwise."""
    root = os.path.realpath(run_dir)
    real = os.path.realpath(path)
    if os.path.commonpath([root, real]) != root:
        raise UnsafeFile(f"{path.name} resolves outside the run dir")
    return Path(real)


def open_confined(run_dir: Path, path: Path) -> tuple[IO[bytes], os.stat_result]:
    """A regular file inside the run dir, opened for reading, and its stat."""
    real = confined(run_dir, path)
    try:
        fd = os.open(real, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError as exc:
        raise UnsafeFile(f"{path.name}: cannot open: {exc.strerror or exc}") from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise UnsafeFile(f"{path.name} is not a regular file")
    return os.fdopen(fd, "rb"), st


def checkpoint_files(run_dir: Path, ckdir: Path) -> list[Path]:
    """The regular files of a checkpoint dir, sorted; UnsafeFile when the dir or one of them
    resolves outside the run dir."""
    confined(run_dir, ckdir)
    out = []
    for entry in sorted(os.scandir(ckdir), key=lambda e: e.name):
        path = Path(entry.path)
        confined(run_dir, path)
        if entry.is_file():
            out.append(path)
    return out


def candidates(run_dir: Path) -> list[Artifact]:
    """Every artifact the run dir seems to hold, in a fixed order, before the confinement check
    (`is_safe`): names a client may ask for, some of which may be refused."""
    from hope_models.train.metrics import mcap_segments  # lazy: loads mcap

    if not run_dir.is_dir():
        return []

    def single(name, kind, media, text):
        path = run_dir / name
        return [Artifact(name, kind, media, text, path)] if path.exists() or path.is_symlink() else []

    out = single(*SINGLE_FILES[0])
    out += [Artifact(seg.name, "mcap", MCAP_TYPE, f"{seg.name} opens in Foxglove: the metrics and events "
                     "as MCAP (plot /metrics.loss against time)", seg) for seg in mcap_segments(run_dir)]
    for spec in SINGLE_FILES[1:]:
        out += single(*spec)
    out += [Artifact(f"checkpoint-{step}.tar", "checkpoint", TAR_TYPE,
                     f"the checkpoint of step {step} (weights, config, optimizer state) as a tar", ckdir, step)
            for step, ckdir in sorted(list_step_dirs(run_dir))]
    return out


def is_safe(run_dir: Path, art: Artifact) -> bool:
    """The artifact's file (or every file of its checkpoint dir) is a regular file whose real path
    is inside the run dir."""
    try:
        if art.kind == "checkpoint":
            checkpoint_files(run_dir, art.path)
            return True
        return confined(run_dir, art.path).is_file()
    except (UnsafeFile, OSError):
        return False


def list_artifacts(run_dir: Path) -> list[Artifact]:
    """What the run dir holds for download, in a fixed order; files that resolve outside it are
    left out."""
    return [a for a in candidates(run_dir) if is_safe(run_dir, a)]


def artifact_size(run_dir: Path, art: Artifact) -> int:
    if art.kind == "checkpoint":
        return sum(p.stat().st_size for p in checkpoint_files(run_dir, art.path))
    return art.path.stat().st_size


# -- the checkpoint tar ------------------------------------------------------------------------

def _pad(size: int) -> int:
    return -size % BLOCK


def open_checkpoint_tar(run_dir: Path, art: Artifact) -> tuple[Iterator[bytes], int]:
    """(the tar's blocks, its length in bytes) for a checkpoint artifact; every file is opened
    (and checked) here, before the first block."""
    prefix = f"checkpoint-{art.step}"
    members: list[tuple[bytes, IO[bytes], int]] = []
    try:
        dir_info = tarfile.TarInfo(prefix)
        dir_info.type, dir_info.mode = tarfile.DIRTYPE, 0o755
        dir_info.mtime = int(art.path.stat().st_mtime)
        head = dir_info.tobuf(format=tarfile.PAX_FORMAT)
        for path in checkpoint_files(run_dir, art.path):
            f, st = open_confined(run_dir, path)
            info = tarfile.TarInfo(f"{prefix}/{path.name}")
            info.size, info.mode, info.mtime = st.st_size, 0o644, int(st.st_mtime)
            members.append((info.tobuf(format=tarfile.PAX_FORMAT), f, st.st_size))
    except BaseException:
        for _, f, _ in members:
            f.close()
        raise
    length = len(head) + sum(len(h) + size + _pad(size) for h, _, size in members) + 2 * BLOCK

    def blocks() -> Iterator[bytes]:
        try:
            yield head
            for header, f, size in members:
                yield header
                left = size
                while left > 0:
                    data = f.read(min(CHUNK, left))
                    if not data:  # the file shrank after it was opened: the tar must keep its length
                        data = b"\0" * min(CHUNK, left)
                    left -= len(data)
                    yield data
                if _pad(size):
                    yield b"\0" * _pad(size)
            yield b"\0" * (2 * BLOCK)
        finally:
            for _, f, _ in members:
                f.close()

    return blocks(), length
