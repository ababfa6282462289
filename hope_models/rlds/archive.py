"""Safe extraction of an upload package, with its checksums verified.

A package comes from another machine, so nothing in it is trusted: absolute names, `..`
components, links (an upload package holds only regular files and dirs, and a link is the usual
way out of the target dir), devices and FIFOs are refused before anything is written. Files are
created with O_EXCL|O_NOFOLLOW under a temporary dir that is renamed into place only after every
checksum in upload_manifest.json matched, so a refused package leaves nothing behind.
"""
from __future__ import annotations

import json
import os
import posixpath
import re
import shutil
import tarfile
import uuid
from pathlib import Path, PurePosixPath
from typing import Any

from ..durable import file_sha256
from .export_cloud import EPISODE_FILE, UPLOAD_MANIFEST

# The Pi runtime writes per step an rgb and a depth .npy (and a .wav with audio) beside one
# episode.json: its recorder's default of 500 steps is ~1,500 files, 3,000 steps ~9,000. The
# default of settings.upload_max_members, which the upload path passes.
MAX_MEMBERS = 20_000
MAX_DIRS = 1_000  # the recorder writes its files flat in the episode dir; the exporter adds blobs/...
MAX_TOTAL_BYTES = 8 << 30
NAME_MAX = 255  # bytes of one path component (the filesystem's limit)
MAX_PATH_BYTES = 1024  # bytes of a member's whole path: ours sit well under $HOPE_HOME's PATH_MAX
_SAFE_TOP = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,200}$")


class ArchiveError(ValueError):
    """The package is unsafe or inconsistent; the message names the package and the member."""


def _member_path(tar_path: Path, member: tarfile.TarInfo) -> PurePosixPath:
    return member_name_path(tar_path, member.name)


def member_name_path(tar_path: Path | str, name: str) -> PurePosixPath:
    """A member's name as a relative path, or ArchiveError (also the rules of rlds/zip_package.py)."""
    if not name or "\x00" in name:
        raise ArchiveError(f"{tar_path}: member {name!r}: empty or invalid name")
    if name.startswith("/") or name.startswith("\\") or re.match(r"^[A-Za-z]:", name):
        raise ArchiveError(f"{tar_path}: member {name!r}: absolute path refused")
    parts = PurePosixPath(name.replace("\\", "/")).parts
    if ".." in parts:
        raise ArchiveError(f"{tar_path}: member {name!r}: '..' component refused")
    parts = tuple(p for p in parts if p != ".")
    if not parts:
        raise ArchiveError(f"{tar_path}: member {name!r}: names no path")
    _check_lengths(tar_path, name, parts)
    return PurePosixPath(*parts)


def _check_lengths(tar_path: Path | str, name: str, parts: tuple[str, ...]) -> None:
    shown = name if len(name) <= 80 else name[:60] + f"...({len(name)} characters)"
    try:
        sizes = [len(os.fsencode(p)) for p in parts]
    except UnicodeEncodeError:
        raise ArchiveError(f"{tar_path}: member {shown!r}: the name is not valid text") from None
    if max(sizes) > NAME_MAX:
        raise ArchiveError(f"{tar_path}: member {shown!r}: a name of {max(sizes)} bytes; at most {NAME_MAX}")
    if sum(sizes) + len(sizes) - 1 > MAX_PATH_BYTES:
        raise ArchiveError(f"{tar_path}: member {shown!r}: a path of {sum(sizes) + len(sizes) - 1} bytes; "
                           f"at most {MAX_PATH_BYTES}")


def check_tree(label: Path | str, paths: list[tuple[PurePosixPath, bool]]) -> None:
    """The tree the members make, `paths` (path, is_file): no file that is also another member's
    parent, and at most MAX_DIRS directories (named or implied: each one is a mkdir and an rmdir)."""
    parents = {parent for path, _ in paths for parent in path.parents} - {PurePosixPath(".")}
    clash = sorted(path for path, is_file in paths if is_file and path in parents)
    if clash:
        raise ArchiveError(f"{label}: member {str(clash[0])!r} is both a file and a directory")
    dirs = parents | {path for path, is_file in paths if not is_file}
    if len(dirs) > MAX_DIRS:
        raise ArchiveError(f"{label}: {len(dirs)} directories, more than {MAX_DIRS}; an episode package "
                           f"keeps its files in a few")


def _check_member_type(tar_path: Path, member: tarfile.TarInfo, path: PurePosixPath) -> None:
    if member.issym() or member.islnk():
        kind = "symlink" if member.issym() else "hardlink"
        base = path.parent if member.issym() else PurePosixPath()
        target = posixpath.normpath((base / member.linkname).as_posix())
        escapes = (member.linkname.startswith("/") or target == ".." or target.startswith("../"))
        where = "leaves the target dir" if escapes else "is not allowed in an upload package"
        raise ArchiveError(f"{tar_path}: member {member.name!r}: {kind} to "
                           f"{member.linkname!r} {where}")
    if not (member.isfile() or member.isdir()):
        raise ArchiveError(f"{tar_path}: member {member.name!r}: device, FIFO or special file refused")


def _plan(tar_path: Path, members: list[tarfile.TarInfo], max_total_bytes: int, max_members: int) -> str:
    """Checks every member before anything is written; returns the package's top dir."""
    if len(members) > max_members:
        raise ArchiveError(f"{tar_path}: {len(members)} members, more than {max_members}")
    tops, seen, total, kinds = set(), set(), 0, []
    for member in members:
        path = _member_path(tar_path, member)
        _check_member_type(tar_path, member, path)
        if path in seen:
            raise ArchiveError(f"{tar_path}: member {member.name!r} appears twice")
        seen.add(path)
        kinds.append((path, member.isfile()))
        tops.add(path.parts[0])
        total += member.size if member.isfile() else 0
        if member.isfile() and len(path.parts) < 2:
            raise ArchiveError(f"{tar_path}: member {member.name!r}: file outside the episode dir")
    check_tree(tar_path, kinds)
    if total > max_total_bytes:
        raise ArchiveError(f"{tar_path}: {total} bytes uncompressed, more than {max_total_bytes}")
    if len(tops) != 1:
        raise ArchiveError(f"{tar_path}: expected one top-level episode dir, found {sorted(tops)}")
    top = tops.pop()
    if not _SAFE_TOP.match(top):
        raise ArchiveError(f"{tar_path}: top-level dir {top!r} is not a valid episode id")
    return top


def _extract_file(tar: tarfile.TarFile, member: tarfile.TarInfo, dest: Path) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    source = tar.extractfile(member)
    if source is None:
        raise ArchiveError(f"member {member.name!r}: no data")
    fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
    written = 0
    with os.fdopen(fd, "wb") as out:
        for chunk in iter(lambda: source.read(1 << 20), b""):
            written += len(chunk)
            if written > member.size:
                raise ArchiveError(f"member {member.name!r}: more data than its declared size")
            out.write(chunk)


def _os_words(exc: BaseException) -> str:
    """An extraction error without the path of our own temporary dir in it."""
    return getattr(exc, "strerror", None) or str(exc)


def verify_package_dir(episode_dir: Path, label: str | None = None) -> dict:
    """Checks an extracted package against its upload_manifest.json; returns the manifest."""
    label = label or str(episode_dir)
    manifest_path = episode_dir / UPLOAD_MANIFEST
    if not manifest_path.is_file():
        raise ArchiveError(f"{label}: missing {UPLOAD_MANIFEST}")
    try:
        manifest = json.loads(manifest_path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise ArchiveError(f"{label}: {UPLOAD_MANIFEST} is not valid JSON: {exc}") from None
    checksums = manifest.get("file_checksums") if isinstance(manifest, dict) else None
    if not isinstance(checksums, dict) or EPISODE_FILE not in checksums:
        raise ArchiveError(f"{label}: {UPLOAD_MANIFEST}: file_checksums must list {EPISODE_FILE}")
    if manifest.get("episode_id") != episode_dir.name:
        raise ArchiveError(f"{label}: {UPLOAD_MANIFEST}: episode_id {manifest.get('episode_id')!r} "
                           f"does not match the package dir {episode_dir.name!r}")
    present = {p.relative_to(episode_dir).as_posix() for p in episode_dir.rglob("*") if p.is_file()}
    present.discard(UPLOAD_MANIFEST)
    unlisted = sorted(present - set(checksums))
    if unlisted:
        raise ArchiveError(f"{label}: files not listed in file_checksums: {', '.join(unlisted)}")
    total = 0
    for name, expected in sorted(checksums.items()):
        if name not in present:
            raise ArchiveError(f"{label}: {name}: listed in file_checksums but missing")
        path = episode_dir / name
        actual = file_sha256(path)
        if actual != expected:
            raise ArchiveError(f"{label}: {name}: sha256 {actual} does not match the manifest's {expected}")
        total += path.stat().st_size
    if manifest.get("metadata_checksum") != checksums[EPISODE_FILE]:
        raise ArchiveError(f"{label}: metadata_checksum does not match the sha256 of {EPISODE_FILE}")
    if manifest.get("total_size_bytes") != total:
        raise ArchiveError(f"{label}: total_size_bytes {manifest.get('total_size_bytes')!r} but the "
                           f"files hold {total} bytes")
    return manifest


def extract_package(tar_path: str | os.PathLike, dest: str | os.PathLike,
                    max_total_bytes: int = MAX_TOTAL_BYTES, budget: Any = None,
                    max_members: int = MAX_MEMBERS) -> Path:
    """Extracts <episode_id>.tar.gz into <dest>/<episode_id>/ and returns that dir.

    Raises ArchiveError when the package is unsafe or its checksums do not match, and
    FileExistsError when <dest>/<episode_id> already exists. `budget` (rlds/inflate.Budget) is
    checked between members: its deadline raises BudgetError."""
    tar_path = Path(tar_path)
    dest = Path(dest)
    try:
        tar = tarfile.open(tar_path, "r:*")
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise ArchiveError(f"{tar_path}: not a readable tar archive: {exc}") from None
    with tar:
        try:
            members = tar.getmembers()
        except (tarfile.TarError, OSError, EOFError) as exc:
            raise ArchiveError(f"{tar_path}: corrupt archive: {exc}") from None
        top = _plan(tar_path, members, max_total_bytes, max_members)
        final = dest / top
        if final.exists():
            raise FileExistsError(f"{final}: already exists")
        dest.mkdir(parents=True, exist_ok=True)
        staging = dest / f".extract-{uuid.uuid4().hex[:12]}"
        staging.mkdir()
        try:
            for member in members:
                if budget is not None:
                    budget.check(f"{tar_path}: member {member.name!r}")
                target = staging / _member_path(tar_path, member)
                try:
                    if member.isdir():
                        target.mkdir(parents=True, exist_ok=True)
                    else:
                        _extract_file(tar, member, target)
                except ArchiveError as exc:
                    raise ArchiveError(f"{tar_path}: {exc}") from None
                except (tarfile.TarError, EOFError, OSError) as exc:
                    raise ArchiveError(f"{tar_path}: member {member.name!r}: {_os_words(exc)}") from None
            verify_package_dir(staging / top, label=str(tar_path))
            os.rename(staging / top, final)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    return final
