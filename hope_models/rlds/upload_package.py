"""An uploaded package of the two kinds the ecosystem produces, told apart by its bytes.

    "pi"  the Pi runtime's `<episode_id>.tar.gz` (rlds/export_cloud.py writes the same): extracted
          by rlds/archive.extract_package, which refuses unsafe members and checks every sha256 of
          its upload_manifest.json;
    "xr"  the XR app's zip of an episode dir: rlds/zip_package.extract_zip.

The kind comes from the magic bytes (gzip, a ustar header, a zip local header), never from the
file name or the Content-Type a client chose. A gzip stream is inflated once, counting, before
tarfile reads it: tarfile skips over member data by inflating it, so a small gzip of zeros would
otherwise cost minutes of CPU before any size check; the stream must stay within MAX_RATIO of
its compressed size and within the size limit. PackageError carries the HTTP status (400 unsafe
or corrupt, naming the member; 413 too large).
"""
from __future__ import annotations

import gzip
import os
import zlib
from pathlib import Path

from ..durable import file_sha256
from .archive import ArchiveError, extract_package
from .zip_package import MAX_RATIO, ZipPackageError, extract_zip, ratio_limit

GZIP_MAGIC = b"\x1f\x8b"
ZIP_MAGICS = (b"PK\x03\x04", b"PK\x05\x06")  # a local file header; an empty archive's end record
USTAR_OFFSET, USTAR_MAGIC = 257, b"ustar"
TAR_OVERHEAD = 1024  # a tar member's header and padding, at most, beyond its data
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


def check_gzip_inflation(path: Path, label: str, max_total_bytes: int) -> None:
    """Inflates the gzip stream without keeping it; PackageError past either limit."""
    by_ratio = ratio_limit(path.stat().st_size)
    inflated = 0
    try:
        with gzip.open(path, "rb") as f:
            while chunk := f.read(1 << 20):
                inflated += len(chunk)
                if inflated > max_total_bytes + TAR_OVERHEAD * 64:
                    raise PackageError(f"{label}: inflates to more than {max_total_bytes} bytes", 413)
                if inflated > by_ratio:
                    raise PackageError(f"{label}: the gzip stream inflates more than {MAX_RATIO} times "
                                       f"its size (a gzip bomb?)")
    except (OSError, EOFError, zlib.error) as exc:
        raise PackageError(f"{label}: corrupt gzip stream: {exc}") from None


def xr_dir_name(path: Path) -> str:
    """The dir an XR zip is extracted to; its name is the episode's id when metadata.json has none
    (the XR app names its dir by the clock, which the zip does not carry): derived from the
    bytes, so the same zip uploaded again is the same episode."""
    return "xr-" + file_sha256(path)[:16]


def _relabel(message: str, path: Path, label: str) -> str:
    return message.replace(str(path), label)


def extract_upload(path: str | os.PathLike, dest: str | os.PathLike, *, label: str,
                   max_total_bytes: int) -> tuple[str, Path]:
    """Extracts one package under `dest` (an empty dir of the caller's, one per package); returns
    (kind, the dir to ingest). Raises PackageError, having left nothing of this package behind."""
    path, dest = Path(path), Path(dest)
    kind = package_kind(path, label)
    if kind == "xr":
        try:
            return kind, extract_zip(path, dest / xr_dir_name(path), label=label, max_total_bytes=max_total_bytes)
        except ZipPackageError as exc:
            raise PackageError(str(exc), exc.status) from None
    with open(path, "rb") as f:
        gzipped = f.read(2) == GZIP_MAGIC
    if gzipped:
        check_gzip_inflation(path, label, max_total_bytes)
    try:
        return kind, extract_package(path, dest, max_total_bytes=max_total_bytes)
    except ArchiveError as exc:
        raise PackageError(_relabel(str(exc), path, label)) from None
