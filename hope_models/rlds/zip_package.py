"""Safe extraction of a zip of an episode dir: what the XR app uploads (HttpRldsUploader).

The XR app zips its episode dir with names relative to it (`metadata.json`,
`steps/000000.jsonl`, ...). Nothing in a zip from another machine is trusted, so before anything is
written every member is checked: the member-name rules of rlds/archive.py (no absolute name, no
`..`), no symlink or device (the mode a Unix zipper keeps in `external_attr`), no encrypted
member, only stored or deflated data, no name twice, no file that is also a directory, at most
archive.MAX_DIRS directories, archive.py's name and path lengths; at most `max_members` members
(counted in the central directory itself, at most MAX_CENTRAL_DIR_BYTES, before zipfile reads it
whole and builds an object per entry: a small archive may declare millions), at most
`max_total_bytes` uncompressed (413 naming the cap). The headers can lie, so the sizes are checked
twice: as declared, and as actually inflated while writing (a member stops at its declared size and
at what is left of the cap; zipfile's CRC then fails). There is no ratio check: each member is
inflated straight to disk, so the byte cap bounds what a zip bomb (overlapping members included:
each one's declared size counts) can cost, and a ratio cap would only refuse honest members that are
mostly zeros. Files are created with O_EXCL|O_NOFOLLOW in a dir of our own, removed again when any
member is refused, so a refused zip leaves nothing.
"""
from __future__ import annotations

import os
import shutil
import stat
import struct
import zipfile
import zlib
from pathlib import Path, PurePosixPath
from typing import Any, BinaryIO

from .archive import MAX_MEMBERS, ArchiveError, check_tree, member_name_path

MAX_CENTRAL_DIR_BYTES = 16 << 20  # MAX_MEMBERS entries with long names and extras fit many times over
CHUNK = 1 << 20
METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflated"}


class ZipPackageError(ValueError):
    """The zip is unsafe, corrupt or too large; the message names the member. `status` 400 or 413."""

    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.status = status


def _count_members(fp: BinaryIO, label: str, max_members: int) -> None:
    """Walks the central directory's fixed headers, stopping past max_members."""
    endrec = zipfile._EndRecData(fp)  # noqa: SLF001 - the one EOCD reader (zip64 too) in the stdlib
    if endrec is None:
        raise ZipPackageError(f"{label}: not a zip archive (no end of central directory record)")
    size_cd = endrec[zipfile._ECD_SIZE]  # noqa: SLF001
    if size_cd > MAX_CENTRAL_DIR_BYTES:  # zipfile reads it whole into memory
        raise ZipPackageError(f"{label}: a central directory of {size_cd} bytes, more than {MAX_CENTRAL_DIR_BYTES}")
    start = endrec[zipfile._ECD_LOCATION] - size_cd  # noqa: SLF001
    if endrec[zipfile._ECD_SIGNATURE] == zipfile.stringEndArchive64:  # noqa: SLF001
        start -= zipfile.sizeEndCentDir64 + zipfile.sizeEndCentDir64Locator
    if start < 0:
        raise ZipPackageError(f"{label}: corrupt archive: the central directory starts before the file")
    fp.seek(start)
    count, left = 0, size_cd
    while left >= zipfile.sizeCentralDir:
        head = fp.read(zipfile.sizeCentralDir)
        if len(head) < zipfile.sizeCentralDir or head[:4] != zipfile.stringCentralDir:
            break  # zipfile reports the corruption with its own words
        count += 1
        if count > max_members:
            raise ZipPackageError(f"{label}: more than {max_members} members (upload_max_members={max_members})", 413)
        name_len, extra_len, comment_len = struct.unpack("<HHH", head[28:34])
        fp.seek(name_len + extra_len + comment_len, os.SEEK_CUR)
        left -= zipfile.sizeCentralDir + name_len + extra_len + comment_len


def _member_kind(label: str, info: zipfile.ZipInfo) -> str:
    name = info.filename
    mode = info.external_attr >> 16
    kind = stat.S_IFMT(mode)
    if kind == stat.S_IFLNK:
        raise ZipPackageError(f"{label}: member {name!r}: symlink refused")
    if kind not in (0, stat.S_IFREG, stat.S_IFDIR):
        raise ZipPackageError(f"{label}: member {name!r}: device, FIFO or special file refused")
    if info.flag_bits & 0x1:
        raise ZipPackageError(f"{label}: member {name!r}: encrypted members are refused")
    if info.is_dir() or kind == stat.S_IFDIR:
        return "dir"
    if info.compress_type not in METHODS:
        raise ZipPackageError(f"{label}: member {name!r}: compression method {info.compress_type} "
                              f"refused (only {', '.join(METHODS.values())})")
    return "file"


def _plan(label: str, zf: zipfile.ZipFile, max_total_bytes: int,
          cap_words: str) -> list[tuple[zipfile.ZipInfo, PurePosixPath, str]]:
    """Every member checked before anything is written; returns (info, relative path, kind)."""
    plan, seen, total = [], set(), 0
    for info in zf.infolist():
        try:
            path = member_name_path(label, info.filename)
        except ArchiveError as exc:
            raise ZipPackageError(str(exc)) from None
        kind = _member_kind(label, info)
        if path in seen:
            raise ZipPackageError(f"{label}: member {info.filename!r} appears twice")
        seen.add(path)
        if kind == "file":
            total += info.file_size
        plan.append((info, path, kind))
    try:
        check_tree(label, [(p, k == "file") for _, p, k in plan])
    except ArchiveError as exc:
        raise ZipPackageError(str(exc)) from None
    if total > max_total_bytes:
        raise ZipPackageError(f"{label}: {total} bytes uncompressed, more than {max_total_bytes} ({cap_words})", 413)
    return plan


def _write_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo, target: Path, label: str, budget: int) -> int:
    """Inflates one member, counting what actually comes out; returns the bytes written."""
    target.parent.mkdir(parents=True, exist_ok=True)
    cap = min(info.file_size, budget)
    fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    written = 0
    with os.fdopen(fd, "wb") as out, zf.open(info) as source:
        while chunk := source.read(CHUNK):
            written += len(chunk)
            if written > cap:
                raise ZipPackageError(f"{label}: member {info.filename!r}: inflates past {cap} bytes "
                                      f"(declared {info.file_size}); its header lies", 400)
            out.write(chunk)
    if written != info.file_size:
        raise ZipPackageError(f"{label}: member {info.filename!r}: {written} bytes, declared {info.file_size}")
    return written


def extract_zip(zip_path: str | os.PathLike, dest_dir: str | os.PathLike, *, label: str | None = None,
                max_members: int = MAX_MEMBERS, max_total_bytes: int = 8 << 30, budget: Any = None,
                cap_words: str | None = None, room: int | None = None, room_words: str = "") -> Path:
    """Extracts the zip into `dest_dir` (created here; it must not exist) and returns it.

    Raises ZipPackageError (nothing left behind) when the zip is unsafe, corrupt or too large;
    `budget` (rlds/inflate.Budget) is checked between members (its deadline: BudgetError). Past
    max_total_bytes (the cap `cap_words` names) 413; within it but past `room`, what may be written
    now (`room_words` says why), 507."""
    zip_path, dest = Path(zip_path), Path(dest_dir)
    label = label or str(zip_path)
    cap_words = cap_words or f"at most {max_total_bytes} bytes unpacked"
    with open(zip_path, "rb") as fp:
        try:
            _count_members(fp, label, max_members)
            zf = zipfile.ZipFile(fp)
        except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
            if isinstance(exc, ZipPackageError):
                raise
            raise ZipPackageError(f"{label}: not a readable zip archive: {exc}") from None
        with zf:
            plan = _plan(label, zf, max_total_bytes, cap_words)
            declared = sum(info.file_size for info, _, kind in plan if kind == "file")
            if room is not None and declared > room:
                raise ZipPackageError(f"{label}: unpacks to {declared} bytes, but {room_words}; send it again when "
                                      "other uploads are done", 507)
            max_total_bytes = min(max_total_bytes, room if room is not None else max_total_bytes)
            if budget is not None:
                budget.unpacking(declared)
            dest.mkdir(mode=0o700)
            try:
                total = 0
                for info, path, kind in plan:
                    if budget is not None:
                        budget.check(f"{label}: member {info.filename!r}")
                    target = dest.joinpath(*path.parts)
                    try:
                        if kind == "dir":
                            target.mkdir(parents=True, exist_ok=True)
                        else:
                            total += _write_member(zf, info, target, label, max_total_bytes - total)
                    except OSError as exc:
                        raise ZipPackageError(f"{label}: member {info.filename!r}: cannot be written: "
                                              f"{exc.strerror or exc}") from None
                    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
                        raise ZipPackageError(f"{label}: member {info.filename!r}: corrupt: {exc}") from None
            except BaseException:
                shutil.rmtree(dest, ignore_errors=True)
                raise
    return dest
