"""Request bodies larger than the app-wide 1 MiB: episodes and their media coming in.

    @bp.post("/api/episodes/upload")
    @large_body
    def upload():
        with received(settings) as got:       # after the token check (a before_request)
            got.fields["manifest"], got.files, got.body ...

`large_body` marks a view whose body may be up to `settings.upload_max_mb` MiB; errors.py checks
the declared Content-Length against that limit before the token check and before anything is
read, and sets it as the request's own limit, so a chunked body (no length) is cut there too.

`received` streams the body to files under `$HOPE_HOME/tmp/upload-<random>/` (not /tmp: on Pi OS
that is RAM, and an upload may be hundreds of MB): a multipart body part by part (`.fields` the
form fields, text; `.files` (field, filename as sent, path, size) of the file parts, stored under
names of our own), any other body whole as `.body`. The size limit is counted while reading. A
file part goes straight to its own file (one open at a time, nothing of it held in memory), so the
number of parts is bounded by what a real session sends, `settings.upload_max_parts` (20,000: the
app's 2,000-tap session with depth is 8,002), not by descriptors or memory; past it, or past
MAX_FIELD_BYTES in one form field or MAX_FIELDS_BYTES in all of them (the fields are held in
memory), 413 naming the limit and its value. The directory is removed when the block ends,
whatever happens in it. The filename a client sends is only reported, never used as a path.

`TmpRoom` is what every upload in progress holds in `$HOPE_HOME/tmp` together (bodies as they are
read, and what a package unpacks to): at most `upload_tmp_max_mb`, and never so much that the free
space under $HOPE_HOME drops below `disk_floor_mb` (else FLOOR_MARGIN_MB); past either, 507 with
a message, and the upload's files are removed. Six concurrent uploads once held 594 MiB there.
"""
from __future__ import annotations

import shutil
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, BinaryIO, Callable, Iterator

from flask import request
from werkzeug.exceptions import RequestEntityTooLarge
from werkzeug.sansio.multipart import Data, Epilogue, Field, File, MultipartDecoder, NeedData

from hope_models.disk import FLOOR_MARGIN_MB, MB, free_mb
from webapp.errors import LARGE_BODY_ATTR, ApiError

MAX_FIELD_BYTES = 16 << 20  # a form field is held in memory (and parsed): a long episode's manifest fits
MAX_FIELDS_BYTES = 32 << 20  # all fields together: the manifest and the assets list of a long session
CHUNK = 1 << 16
TMP_DIR = "tmp"


def large_body(view: Callable) -> Callable:
    """Mark a view as taking bodies up to settings.upload_max_mb (errors.py reads the mark)."""
    setattr(view, LARGE_BODY_ATTR, True)
    return view


def upload_limit(settings: Any) -> int:
    return int(settings.upload_max_mb) << 20


@dataclass
class Received:
    dir: Path
    room: TmpRoom
    fields: dict[str, str] = field(default_factory=dict)
    files: list[tuple[str, str, Path, int]] = field(default_factory=list)  # (field, filename, path, size)
    body: Path | None = None
    size: int = 0  # bytes of body read


class TmpRoom:
    """The bytes all uploads in progress hold under one $HOPE_HOME/tmp (one per home, per process:
    only the webapp receives uploads)."""

    _lock = threading.Lock()
    _held: dict[str, int] = {}

    def __init__(self, settings: Any):
        self.root = Path(settings.home) / TMP_DIR
        self.key = str(self.root)
        self.cap = int(settings.upload_tmp_max_mb) * MB
        self.floor_mb = float(settings.disk_floor_mb) if settings.disk_floor_mb > 0 else FLOOR_MARGIN_MB
        self.taken = 0  # by this upload

    def available(self) -> int:
        """What one more upload may still write: the cap's remainder and the free space above the floor."""
        with self._lock:
            room = self.cap - self._held.get(self.key, 0)
        free = free_mb(self.root)
        if free is not None:
            room = min(room, int((free - self.floor_mb) * MB))
        return max(room, 0)

    def take(self, n: int, what: str) -> None:
        with self._lock:
            held = self._held.get(self.key, 0)
            if held + n > self.cap:
                raise ApiError(f"{what}: $HOPE_HOME/tmp would hold more than upload_tmp_max_mb="
                               f"{self.cap // MB} MB of uploads in progress ({held // MB} MB now); try again "
                               f"when they are done", 507)
            self._held[self.key] = held + n
            self.taken += n
        free = free_mb(self.root)
        if free is not None and free < self.floor_mb:
            raise ApiError(f"{what}: {free:.0f} MB free under $HOPE_HOME, below the floor of "
                           f"{self.floor_mb:.0f} MB (disk_floor_mb) an upload must leave", 507)

    def release(self) -> None:
        with self._lock:
            self._held[self.key] = max(self._held.get(self.key, 0) - self.taken, 0)
            self.taken = 0

    @classmethod
    def held(cls, settings: Any) -> int:
        with cls._lock:
            return cls._held.get(str(Path(settings.home) / TMP_DIR), 0)


class _Counter:
    """Reads the request body in chunks, refusing it once past the limit or the room in tmp."""

    def __init__(self, stream: IO[bytes], limit: int, room: TmpRoom):
        self.stream, self.limit, self.room, self.read_bytes = stream, limit, room, 0

    def read(self) -> bytes:
        try:
            chunk = self.stream.read(CHUNK)
        except RequestEntityTooLarge:
            chunk = b""
            self.read_bytes = self.limit + 1
        self.read_bytes += len(chunk)
        if self.read_bytes > self.limit:
            raise ApiError(f"request body too large: more than {self.limit} bytes; the limit for this "
                           f"endpoint is {self.limit} bytes (upload_max_mb)", 413)
        self.room.take(len(chunk), "request body")
        return chunk


def _read_raw(got: Received, body: _Counter) -> None:
    got.body = got.dir / "body"
    with open(got.body, "wb") as out:
        while chunk := body.read():
            out.write(chunk)
    got.size = body.read_bytes


class _Parts:
    """Where the multipart events go: the current part's name, and its file or its bytes."""

    def __init__(self, got: Received, max_parts: int, limit_name: str):
        self.got, self.max_parts, self.limit_name, self.count, self.field_bytes = got, max_parts, limit_name, 0, 0
        self.name: str | None = None
        self.filename: str | None = None
        self.out: BinaryIO | None = None
        self.path: Path | None = None
        self.buf = bytearray()

    def start(self, event: Field | File) -> None:
        self.count += 1
        if self.count > self.max_parts:
            raise ApiError(f"multipart body: more than {self.max_parts} parts ({self.limit_name})", 413)
        self.name = event.name
        if isinstance(event, File):
            self.filename = event.filename or ""
            self.path = self.got.dir / f"part-{self.count:05d}"
            self.out = open(self.path, "wb")
        else:
            self.filename, self.out, self.path = None, None, None
            self.buf = bytearray()

    def data(self, event: Data) -> None:
        if self.name is None:
            raise ApiError("multipart body: data before any part header", 400)
        if self.out is not None:
            self.out.write(event.data)
        else:
            self.buf += event.data
            self.field_bytes += len(event.data)
            if len(self.buf) > MAX_FIELD_BYTES:
                raise ApiError(f"{self.name}: form field larger than {MAX_FIELD_BYTES} bytes", 413)
            if self.field_bytes > MAX_FIELDS_BYTES:
                raise ApiError(f"{self.name}: the form fields together hold more than {MAX_FIELDS_BYTES} "
                               "bytes (they are held in memory)", 413)
        if not event.more_data:
            self.end()

    def end(self) -> None:
        if self.out is not None:
            self.out.close()
            assert self.path is not None  # start() sets path together with out
            self.got.files.append((self.name or "", self.filename or "", self.path, self.path.stat().st_size))
        else:
            try:
                # surrogatepass: a lone UTF-16 surrogate as raw bytes (older Dart) is text the episode keeps
                self.got.fields[self.name or ""] = bytes(self.buf).decode("utf-8", "surrogatepass")
            except UnicodeDecodeError as exc:
                raise ApiError(f"{self.name}: form field is not UTF-8 text (byte {exc.start})", 400) from None
        self.name, self.out = None, None

    def close(self) -> None:
        if self.out is not None:
            self.out.close()


def _read_multipart(got: Received, body: _Counter, max_parts: int, limit_name: str) -> None:
    boundary = request.mimetype_params.get("boundary")
    if not boundary:
        raise ApiError("multipart/form-data body without a boundary parameter", 400)
    decoder = MultipartDecoder(boundary.encode("latin-1"), max_form_memory_size=MAX_FIELD_BYTES)
    parts = _Parts(got, max_parts, limit_name)
    try:
        while True:
            chunk = body.read()
            decoder.receive_data(chunk or None)
            try:
                event = decoder.next_event()
                while not isinstance(event, (NeedData, Epilogue)):
                    if isinstance(event, (Field, File)):
                        parts.start(event)
                    elif isinstance(event, Data):
                        parts.data(event)
                    event = decoder.next_event()
            except ValueError as exc:  # werkzeug's parse errors
                raise ApiError(f"multipart body: {exc}", 400) from None
            if isinstance(event, Epilogue):
                break
            if not chunk:
                raise ApiError("multipart body ends before its closing boundary", 400)
    except RequestEntityTooLarge:
        raise ApiError(f"multipart body: a part larger than {MAX_FIELD_BYTES} bytes held in memory", 413) from None
    finally:
        parts.close()
    got.size = body.read_bytes


@contextmanager
def received(settings: Any, *, max_parts: int | None = None) -> Iterator[Received]:
    """The current request's body on disk (see the module doc); removed on exit. `max_parts`
    (default settings.upload_max_parts) bounds a multipart body's parts."""
    limit_name = "this endpoint's limit"
    if max_parts is None:
        max_parts = int(settings.upload_max_parts)
        limit_name = f"upload_max_parts={max_parts}"
    root = Path(settings.home) / TMP_DIR
    root.mkdir(mode=0o700, parents=True, exist_ok=True)
    got = Received(Path(tempfile.mkdtemp(prefix="upload-", dir=root)), TmpRoom(settings))
    try:
        body = _Counter(request.stream, upload_limit(settings), got.room)
        if request.mimetype == "multipart/form-data":
            _read_multipart(got, body, max_parts, limit_name)
        else:
            _read_raw(got, body)
        yield got
    finally:
        shutil.rmtree(got.dir, ignore_errors=True)
        got.room.release()


__all__ = ["MAX_FIELDS_BYTES", "Received", "TmpRoom", "large_body", "received", "upload_limit"]
