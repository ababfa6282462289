"""An uploaded package of the two kinds the ecosystem produces, told apart by its bytes.

    "pi"  the Pi runtime's `<episode_id>.tar.gz` (rlds/export_cloud.py writes the same): extracted
          by rlds/archive.extract_package, which refuses unsafe members and checks every sha256 of
          its upload_manifest.json;
    "xr"  the XR app's zip of an episode dir: rlds/zip_package.extract_zip.

The kind comes from the magic bytes (gzip, a ustar header, a zip local header), never from the
file name or the Content-Type a client chose. A tar is first read once as a stream, counting,
before archive.py's extraction reads it: tarfile skips over member data by inflating it, so a
small gzip of zeros would otherwise cost minutes of CPU before any size check.

What a package may cost is judged by absolute caps, never by how well it compressed:
`max_total_bytes` unpacked (the caller's: settings.upload_unpack_max_mb, never more than the room
left in $HOPE_HOME/tmp) and `max_members` (settings.upload_max_members; a tar of ~100,000 empty
directories once held the upload lock for minutes). The scan writes nothing and stops inflating as
soon as the stream passes the cap, so a gzip of 20 GB of zeros costs at most the cap's worth of
inflating, and a member's pax or GNU long-name header (the one thing tarfile reads into memory)
may hold at most MAX_HEADER_BYTES. There is no ratio check: deflate cannot exceed ~1032:1, so a
ratio cap refuses only honest packages that are mostly zeros (the Pi's frames from a dropped or
mock camera inflate ~740x) and protects nothing the byte cap does not. PackageError carries the
HTTP status (400 unsafe or corrupt, naming the member; 413 past a cap, naming it and its value).
"""
from __future__ import annotations

import gzip
import os
import tarfile
import zlib
from pathlib import Path
from typing import BinaryIO

from ..durable import file_sha256
from .archive import MAX_DIRS, MAX_MEMBERS, ArchiveError, extract_package
from .inflate import Budget
from .zip_package import ZipPackageError, extract_zip

GZIP_MAGIC = b"\x1f\x8b"
ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header; an empty archive's end record
USTAR_OFFSET, USTAR_MAGIC = 257, b"ustar"
MAX_HEADER_BYTES = 1 << 20  # a pax or GNU long-name header: a path and a few numbers, held in memory


def tar_overhead(max_members: int) -> int:
    """What a tar stream holds beyond its members' data: a 512-byte header and up to 511 bytes of
    padding per member, and the end blocks."""
    return max_members * 1024 + (20 << 10)


KINDS = {"pi": "the Pi runtime's upload package (tar.gz)", "xr": "the XR app's episode zip"}


class PackageError(ValueError):
    def __init__(self, message: str, status: int = 400):
        super().__init__(message)
        self.message = message
        self.status = status


def package_kind(path: str | os.PathLike, label: str) -> str:
    with open(path, "rb") as f:
        head = f.read(USTAR_OFFSET + len(USTAR_MAGIC))
    if head.startswith(ZIP_MAGICS):
        return "xr"
    if head.startswith(GZIP_MAGIC) or head[USTAR_OFFSET:] == USTAR_MAGIC:
        return "pi"
    raise PackageError(f"{label}: not a package: expected the Pi runtime's <episode_id>.tar.gz or the XR "
                       f"app's episode zip (the first bytes are neither gzip, tar nor zip)")


class _Inflation:
    """The tar stream as tarfile reads it, counted: past the cap, PackageError (413)."""

    def __init__(self, source: BinaryIO, label: str, limit: int, cap_words: str, budget: Budget | None):
        self.source, self.label, self.limit, self.cap_words, self.inflated = source, label, limit, cap_words, 0
        self.budget = budget

    def read(self, size: int = -1) -> bytes:
        data = self.source.read(size if size is not None and size > 0 else 1 << 20)
        self.inflated += len(data)
        if self.inflated > self.limit:
            raise PackageError(f"{self.label}: the tar stream inflates to more than {self.limit} bytes "
                               f"({self.cap_words}); refused before it was unpacked", 413)
        if self.budget is not None:
            self.budget.check(self.label)
        return data


class _HeaderGuard(tarfile.TarInfo):
    """tarfile reads a pax or GNU long-name header's body whole into memory: its size is checked first."""

    def _check_header(self, label: str) -> None:
        if self.size > MAX_HEADER_BYTES:
            raise PackageError(f"{label}: a {self.size}-byte extended header (pax or long name), more than "
                               f"{MAX_HEADER_BYTES}", 413)

    def _proc_pax(self, tarfile):  # type: ignore[no-untyped-def]  # tarfile's own hook
        self._check_header(getattr(tarfile, "hope_label", "package"))
        return super()._proc_pax(tarfile)  # type: ignore[misc]

    def _proc_gnulong(self, tarfile):  # type: ignore[no-untyped-def]
        self._check_header(getattr(tarfile, "hope_label", "package"))
        return super()._proc_gnulong(tarfile)  # type: ignore[misc]


def scan_tar(path: Path, label: str, max_total_bytes: int, budget: Budget | None = None, *,
             max_members: int = MAX_MEMBERS, cap_words: str | None = None) -> int:
    """One streaming pass over the tar (inflated as it is read, nothing kept or written): the
    members' count against max_members, their declared sizes against max_total_bytes, the inflated
    stream against max_total_bytes plus the tar's own overhead (a lying or padded stream). 413
    naming the file and the cap (`cap_words`, e.g. "upload_unpack_max_mb=3072"). Returns the bytes
    the members hold."""
    cap_words = cap_words or f"at most {max_total_bytes} bytes unpacked"
    with open(path, "rb") as raw:
        gzipped = raw.read(2) == GZIP_MAGIC
        raw.seek(0)
        source = gzip.GzipFile(fileobj=raw, mode="rb") if gzipped else raw
        stream = _Inflation(source, label, max_total_bytes + tar_overhead(max_members), cap_words, budget)
        total = count = dirs = 0
        try:
            with tarfile.open(fileobj=stream, mode="r|", tarinfo=_HeaderGuard) as tar:  # type: ignore[call-overload]
                tar.hope_label = label
                for member in tar:
                    count += 1
                    if count > max_members:
                        raise PackageError(f"{label}: more than {max_members} members, files and directories "
                                           f"(upload_max_members={max_members})", 413)
                    dirs += member.isdir()
                    if dirs > MAX_DIRS:
                        raise PackageError(f"{label}: more than {MAX_DIRS} directories; an episode package keeps "
                                           f"its files in a few", 413)
                    if budget is not None and count % 256 == 0:
                        budget.check(label)
                    total += member.size if member.isfile() else 0
                    if total > max_total_bytes:
                        raise PackageError(f"{label}: member {member.name!r}: the members hold more than "
                                           f"{max_total_bytes} bytes uncompressed ({cap_words})", 413)
        except (tarfile.TarError, OSError, EOFError, zlib.error) as exc:
            raise PackageError(f"{label}: not a readable tar archive: {exc}") from None
    if budget is not None:
        budget.unpacking(total)
    return total


def xr_dir_name(path: Path) -> str:
    """The dir an XR zip is extracted to; its name is the episode's id when metadata.json has none
    (the XR app names its dir by the clock, which the zip does not carry): derived from the
    bytes, so the same zip uploaded again is the same episode."""
    return "xr-" + file_sha256(path)[:16]


def _relabel(message: str, path: Path, label: str) -> str:
    return message.replace(str(path), label)


def _no_room(label: str, total: int, room: int, room_words: str) -> PackageError:
    return PackageError(f"{label}: unpacks to {total} bytes, but {room_words}; send it again when other uploads "
                        "are done", 507)


def extract_upload(path: str | os.PathLike, dest: str | os.PathLike, *, label: str,
                   max_total_bytes: int, budget: Budget | None = None, max_members: int = MAX_MEMBERS,
                   cap_words: str | None = None, room: int | None = None, room_words: str = "") -> tuple[str, Path]:
    """Extracts one package under `dest` (an empty dir of the caller's, one per package); returns
    (kind, the dir to ingest). Raises PackageError (or the budget's BudgetError), having left
    nothing of this package behind: 413 past `max_total_bytes` (the cap `cap_words` names), 507
    within it but past `room`, what may be written now (`room_words` says why: a transient refusal)."""
    path, dest = Path(path), Path(dest)
    kind = package_kind(path, label)
    room = max_total_bytes if room is None else room
    if kind == "xr":
        try:
            return kind, extract_zip(path, dest / xr_dir_name(path), label=label, max_total_bytes=max_total_bytes,
                                     max_members=max_members, budget=budget, cap_words=cap_words, room=room,
                                     room_words=room_words)
        except ZipPackageError as exc:
            raise PackageError(str(exc), exc.status) from None
    total = scan_tar(path, label, max_total_bytes, budget, max_members=max_members, cap_words=cap_words)
    if total > room:
        raise _no_room(label, total, room, room_words)
    try:
        return kind, extract_package(path, dest, max_total_bytes=min(max_total_bytes, room), budget=budget,
                                     max_members=max_members)
    except ArchiveError as exc:
        raise PackageError(_relabel(str(exc), path, label)) from None
