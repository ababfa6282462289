"""Upload packages built to cost the server far more than their size, as bytes (no server needed).

Used by tests/test_upload_bombs.py (against a real server) and bench/soak.py. Each builder returns
the body a client with the token POSTs to /api/episodes/upload; the comment on each says what it
cost before the decompressors were bounded by what they produce.
"""
from __future__ import annotations

import gzip
import io
import json
import random
import stat
import struct
import tarfile
import warnings
import zipfile

import numpy as np

MCAP_MAGIC = b"\x89MCAP0\r\n"


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


def _text(value: str) -> bytes:
    raw = value.encode()
    return struct.pack("<I", len(raw)) + raw


def _chunk(compression: str, compressed: bytes, declared: int) -> bytes:
    """An MCAP Chunk record (opcode 6): start/end time, declared uncompressed size, crc 0 (unchecked)."""
    body = struct.pack("<QQQI", 0, 0, declared, 0) + _text(compression) + struct.pack("<Q", len(compressed))
    return _record(0x06, body + compressed)


def mcap_bomb(inflated: int = 256 << 20, *, compression: str = "zstd", declared: int | None = None) -> bytes:
    """A small .mcap whose one chunk inflates to `inflated` zero bytes: each 9 of them an empty
    record of an unknown type, which the mcap library walks one by one in Python (+255 MB RSS and
    60 s of CPU for 256 MiB). `declared` is the chunk's stated uncompressed size (default: the truth)."""
    zeros = bytes(1 << 20)
    if compression == "zstd":
        import zstandard

        compressor = zstandard.ZstdCompressor(level=19).compressobj(size=inflated)
        data = b"".join(compressor.compress(zeros) for _ in range(inflated >> 20)) + compressor.flush()
    else:
        import lz4.frame

        out = io.BytesIO()
        with lz4.frame.open(out, "wb", compression_level=16, content_checksum=False) as f:
            for _ in range(inflated >> 20):
                f.write(zeros)
        data = out.getvalue()
    header = _record(0x01, _text("") + _text("hostile"))
    footer = _record(0x02, struct.pack("<QQI", 0, 0, 0))
    return MCAP_MAGIC + header + _chunk(compression, data, inflated if declared is None else declared) \
        + footer + MCAP_MAGIC


def tfrecord_gzip_bomb(inflated: int = 58 << 20) -> bytes:
    """~57 KB of gzip of zeros: read_tfrecord inflated it whole, then looked for a record at
    every one of its offsets in Python (46 s of CPU)."""
    out = io.BytesIO()
    with gzip.GzipFile(fileobj=out, mode="wb", mtime=0, compresslevel=9) as gz:
        zeros = bytes(1 << 20)
        for _ in range(inflated >> 20):
            gz.write(zeros)
    return out.getvalue()


def npz_bomb(rows: int = 4096, cols: int = 4096) -> tuple[bytes, bytes]:
    """(<id>.npz, its sidecar): observations of rows x cols float32 zeros, deflated to ~1/1000:
    loaded whole (and turned into Python floats) before anything looked at the ratio."""
    buf = io.BytesIO()
    np.savez_compressed(buf, observations=np.zeros((rows, cols), np.float32),
                        actions=np.zeros((rows, 1), np.float32))
    sidecar = {"format": "hope.cloud_npz/1", "episode_id": "bomb",
               "query": {"episode_id": "bomb", "num_steps": rows},
               "arrays": {"observations": {"shape": [rows, cols], "dtype": "float32",
                                           "fields": [{"path": "observation.x", "size": cols, "offset": 0,
                                                       "kind": "vector"}]},
                          "actions": {"shape": [rows, 1], "dtype": "float32",
                                      "fields": [{"path": "action.a", "size": 1, "offset": 0, "kind": "number"}]}}}
    return buf.getvalue(), json.dumps(sidecar).encode()


def xr_zip_of(members: dict[str, bytes], *, stored: bool = False) -> bytes:
    """An XR-app style zip (names relative to the episode dir), deflated (or stored: what is
    already compressed passes the zip's own ratio check)."""
    buf = io.BytesIO()
    method = zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(buf, "w", method, compresslevel=None if stored else 9) as z:
        for name, data in members.items():
            z.writestr(name, data)
    return buf.getvalue()


def xr_mcap_bomb(**kwargs) -> bytes:
    return xr_zip_of({"episode.mcap": mcap_bomb(**kwargs)}, stored=kwargs.get("compression") == "lz4")


def xr_tfrecord_bomb(**kwargs) -> bytes:
    return xr_zip_of({"episode.tfrecord.gz": tfrecord_gzip_bomb(**kwargs)})


def xr_npz_bomb(**kwargs) -> bytes:
    npz, sidecar = npz_bomb(**kwargs)
    return xr_zip_of({"bomb.npz": npz, "bomb.npz.json": sidecar})


def tar_gz_of(entries: list[tuple[str, bytes | None]], *, fmt: int = tarfile.PAX_FORMAT) -> bytes:
    """A tar.gz of (name, data) entries; data None is a directory entry."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", format=fmt) as tar:
        for name, data in entries:
            info = tarfile.TarInfo(name)
            if data is None:
                info.type = tarfile.DIRTYPE
                tar.addfile(info)
            else:
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def many_dirs_tar_gz(count: int = 99_991) -> bytes:
    """~0.5 MB of gzip holding `count` directory entries (it held the upload lock 47-212 s)."""
    return tar_gz_of([("ep",  None)] + [(f"ep/d{i}", None) for i in range(count - 1)], fmt=tarfile.GNU_FORMAT)


def odd_entries() -> dict[str, bytes]:
    """Archives whose entries once made the upload answer 500, by what is odd about them."""
    long_name = "n" * 300
    deep = "/".join(["d" * 200] * 25)  # 5 KB of path, each part a legal name
    return {
        "tar-name-over-255-bytes": tar_gz_of([("ep", None), (f"ep/{long_name}", b"{}")]),
        "tar-path-over-4kb": tar_gz_of([("ep", None), (f"ep/{deep}/x.json", b"{}")]),
        "tar-file-then-dir-below-it": tar_gz_of([("ep", None), ("ep/a", b"{}"), ("ep/a/b", None)]),
        "tar-file-then-file-below-it": tar_gz_of([("ep", None), ("ep/a", b"{}"), ("ep/a/b", b"{}")]),
        "tar-dir-then-file-of-its-name": tar_gz_of([("ep", None), ("ep/a", None), ("ep/a", b"{}")]),
        "tar-duplicate-file": tar_gz_of([("ep", None), ("ep/a", b"{}"), ("ep/a", b"[]")]),
        "zip-name-over-255-bytes": xr_zip_of({long_name: b"{}"}),
        "zip-path-over-4kb": xr_zip_of({f"{deep}/x.json": b"{}"}),
        "zip-file-then-dir-below-it": xr_zip_of({"a": b"{}", "a/b/": b""}),
        "zip-dir-then-file-of-its-name": xr_zip_of({"a/": b"", "a": b"{}"}),
        "tar-dir-name-over-255-bytes": tar_gz_of([("ep", None), (f"ep/{long_name}", None)]),
        "tar-dir-path-over-4kb": tar_gz_of([("ep", None), (f"ep/{deep}", None)]),
        "zip-dir-name-over-255-bytes": xr_zip_of({f"{long_name}/": b""}),
        "zip-dir-path-over-4kb": xr_zip_of({f"{deep}/": b""}),
        "zip-1001-implied-directories": xr_zip_of({f"d{i}/x.json": b"{}" for i in range(1001)}),
        "tar-1001-implied-directories": tar_gz_of([("ep", None)] + [(f"ep/d{i}/x.json", b"{}") for i in range(1000)]),
    }


# -- generated archives: names, kinds and contents drawn from what has broken extractors -------------

PARTS = ["a", "b", "ep", ".", "..", "", "n" * 256, "é" * 130, "\\", "C:", " ", "a" * 255, "x.json", "metadata.json",
         "steps", "000000.jsonl", "x.mcap", "x.npz", "x.npz.json", "x.tfrecord", "episode.json",
         "upload_manifest.json", "\udcff", "blobs", "a\nb"]
DATA = [b"{}", b"", b"{", b"[]", bytes(100), b'{"metadata": {}, "steps": [{}]}\n', b"\x1f\x8b\x08\x00", b"PK\x03\x04",
        MCAP_MAGIC]


def random_name(r: random.Random, bad: float = 0.3) -> str:
    """A member name of 1-4 parts; with probability `bad` per part, an odd one."""
    safe = ["ep", "a", "b", "x.json", "metadata.json", "steps", "000000.jsonl", "blobs", "x.mcap", "x.tfrecord"]
    name = "/".join(r.choice(PARTS if r.random() < bad else safe) for _ in range(r.randint(1, 4)))
    for p, change in ((0.05, lambda n: "/" + n), (0.05, lambda n: "./" + n), (0.1, lambda n: n + "/"),
                      (0.03, lambda n: n.replace("/", "\\"))):
        if r.random() < p:
            name = change(name)
    return name


def random_tar_gz(r: random.Random) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", format=r.choice([tarfile.PAX_FORMAT, tarfile.GNU_FORMAT]),
                      encoding="utf-8", errors="surrogateescape") as tar:
        for _ in range(r.randint(1, 6)):
            info = tarfile.TarInfo(random_name(r))
            info.mode, info.mtime, kind = r.choice([0o644, 0, 0o7777]), r.choice([0, 1, 2 ** 33]), r.random()
            if kind < 0.3:
                info.type = (tarfile.DIRTYPE if kind < 0.2 else tarfile.SYMTYPE if kind < 0.25 else
                             tarfile.LNKTYPE if kind < 0.28 else tarfile.FIFOTYPE)
                info.linkname = random_name(r) if info.type in (tarfile.SYMTYPE, tarfile.LNKTYPE) else ""
                tar.addfile(info)
            else:
                data = r.choice(DATA)
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def random_zip(r: random.Random) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # zipfile warns of the duplicate names we mean to write
        for _ in range(r.randint(1, 6)):
            info = zipfile.ZipInfo(random_name(r))
            if r.random() < 0.1:
                info.create_system = 3
                info.external_attr = (r.choice([stat.S_IFLNK, stat.S_IFIFO, stat.S_IFDIR]) | 0o777) << 16
            try:
                z.writestr(info, r.choice(DATA))
            except (ValueError, UnicodeEncodeError):
                pass  # a name zipfile itself cannot write
    return buf.getvalue()


def random_archives(seed: int, count: int):
    """(index, body) of `count` generated tar.gz and zip packages, reproducible from `seed`."""
    r = random.Random(seed)
    for i in range(count):
        yield i, random_tar_gz(r) if r.random() < 0.5 else random_zip(r)
