"""An uploaded package of the two kinds the ecosystem produces, told apart by its bytes.

    "pi"  the Pi runtime's `<episode_id>.tar.gz` (rlds/export_cloud.py writes the same): extracted
          by rlds/archive.extract_package, which refuses unsafe members and checks every sha256 of
          its upload_manifest.json;
    "xr"  the XR app's zip of an episode dir: rlds/zip_package.extract_zip.

The kind comes from the magic bytes (gzip, a ustar header, a zip local header), never from the
file name or the Content-Type a client chose. A tar is first read once as a stream, counting,
before archive.py's extraction reads it: tarfile skips over member data by inflating it, so a
small gzip of zeros would otherwise cost minutes of CPU before any size check; the stream must
stay within MAX_RATIO of its compressed size, the members' declared sizes within the limit, and
their count within archive.MAX_MEMBERS (sized for the Pi runtime's long episodes; a tar of
~100,000 empty directories once held the upload lock for minutes). PackageError carries the HTTP
status (400 unsafe or corrupt, naming the member; 413 too large).
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
from .inflate import MAX_RATIO, Budget, ratio_limit
from .zip_package import ZipPackageError, extract_zip

GZIP_MAGIC = b"\x1f\x8b"
ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header; an empty archive's end record
USTAR_OFFSET, USTAR_MAGIC = 257, b"ustar"
# a tar stream holds, beyond its members' data, a 512-byte header and up to 511 bytes of padding per
# member (at most archive.MAX_MEMBERS of them) and the end blocks
TAR_OVERHEAD = MAX_MEMBERS * 1024 + (20 << 10)
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
    """The tar stream as tarfile reads it, counted: past the ratio or the size, PackageError."""

    def __init__(self, source: BinaryIO, label: str, by_ratio: int | None, limit: int, budget: Budget | None):
        self.source, self.label, self.by_ratio, self.limit, self.inflated = source, label, by_ratio, limit, 0
        self.budget = budget

    def read(self, size: int = -1) -> bytes:
        data = self.source.read(size if size is not None and size > 0 else 1 << 20)
        self.inflated += len(data)
        if self.by_ratio is not None and self.inflated > self.by_ratio:
            raise PackageError(f"{self.label}: the gzip stream inflates more than {MAX_RATIO} times its size "
                               f"(a gzip bomb?)")
        if self.inflated > self.limit:
            raise PackageError(f"{self.label}: the tar stream is larger than {self.limit} bytes", 413)
        if self.budget is not None:
            self.budget.check(self.label)
        return data


def scan_tar(path: Path, label: str, max_total_bytes: int, budget: Budget | None = None) -> None:
    """One streaming pass over the tar (inflated as it is read, nothing kept): the members' declared
    sizes against max_total_bytes (413), the inflated stream against MAX_RATIO and the size (a bomb
    is refused after at most ratio_limit bytes of work, before tarfile's own random-access pass)."""
    with open(path, "rb") as raw:
        gzipped = raw.read(2) == GZIP_MAGIC
        raw.seek(0)
        source = gzip.GzipFile(fileobj=raw, mode="rb") if gzipped else raw
        stream = _Inflation(source, label, ratio_limit(path.stat().st_size) if gzipped else None,
                            max_total_bytes + TAR_OVERHEAD, budget)
        total = count = dirs = 0
        try:
            with tarfile.open(fileobj=stream, mode="r|") as tar:
                for member in tar:
                    count += 1
                    if count > MAX_MEMBERS:
                        raise PackageError(f"{label}: more than {MAX_MEMBERS} members (files and directories); "
                                           f"an episode package holds far fewer", 413)
                    dirs += member.isdir()
                    if dirs > MAX_DIRS:
                        raise PackageError(f"{label}: more than {MAX_DIRS} directories; an episode package keeps "
                                           f"its files in a few", 413)
                    if budget is not None and count % 256 == 0:
                        budget.check(label)
                    total += member.size if member.isfile() else 0
                    if total > max_total_bytes:
                        raise PackageError(f"{label}: member {member.name!r}: the members hold more than "
                                           f"{max_total_bytes} bytes uncompressed", 413)
        except (tarfile.TarError, OSError, EOFError, zlib.error) as exc:
            raise PackageError(f"{label}: not a readable tar archive: {exc}") from None


def xr_dir_name(path: Path) -> str:
    """The dir an XR zip is extracted to; its name is the episode's id when metadata.json has none
    (the XR app names its dir by the clock, which the zip does not carry): derived from the
    bytes, so the same zip uploaded again is the same episode."""
    return "xr-" + file_sha256(path)[:16]


def _relabel(message: str, path: Path, label: str) -> str:
    return message.replace(str(path), label)


def extract_upload(path: str | os.PathLike, dest: str | os.PathLike, *, label: str,
                   max_total_bytes: int, budget: Budget | None = None) -> tuple[str, Path]:
    """Extracts one package under `dest` (an empty dir of the caller's, one per package); returns
    (kind, the dir to ingest). Raises PackageError (or the budget's BudgetError), having left
    nothing of this package behind."""
    path, dest = Path(path), Path(dest)
    kind = package_kind(path, label)
    if kind == "xr":
        try:
            return kind, extract_zip(path, dest / xr_dir_name(path), label=label, max_total_bytes=max_total_bytes,
                                     budget=budget)
        except ZipPackageError as exc:
            raise PackageError(str(exc), exc.status) from None
    scan_tar(path, label, max_total_bytes, budget)
    try:
        return kind, extract_package(path, dest, max_total_bytes=max_total_bytes, budget=budget)
    except ArchiveError as exc:
        raise PackageError(_relabel(str(exc), path, label)) from None
