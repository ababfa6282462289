"""POST /api/episodes/upload on the real server (sockets) against packages built to cost far more than
their size (tests/hostile_packages.py), each sent by a client holding the token:

- decompression bombs inside members: a 241-byte zip holding an .mcap whose zstd chunk inflates to
  256 MiB (35 s of CPU and +256 MB RSS before), an lz4 chunk that states 100 bytes and holds 256 MiB,
  a gzipped .tfrecord of 58 MiB of zeros (54 s), an .npz member of 64 MiB of zeros (+904 MB RSS),
  and the same TFRecord inside a Pi runtime package with valid checksums: each answered within
  seconds, with RSS growth under 64 MB, a 4xx naming the file (or the episode rejected for it),
  and nothing left in $HOPE_HOME/tmp;
- a tar.gz of 99,991 directories (it held the upload lock 22-212 s): refused by count at once, as is
  one of more members than a long real episode has (10,000);
- the budget of time one upload's unpacking may take (upload_extract_s);
- concurrent uploads past upload_tmp_max_mb, or an upload that would take the free space below
  disk_floor_mb: refused with 507, nothing left in tmp.
"""
from __future__ import annotations

import hashlib
import json
import select
import socket
import threading
import time
from pathlib import Path

import psutil
import pytest

import hostile_packages as hp
from hostile_clients import http_request
from test_server_hardening import Served, served  # noqa: F401 - the fixture `server` builds on

MB = 1 << 20


class Server(Served):
    """Served with the upload helpers, and a 4 MB body limit the bombs stay far below."""

    def __init__(self, tmp_path: Path, **env: str):
        super().__init__(tmp_path, **{"HOPE_UPLOAD_MAX_MB": "4", **env})

    def upload(self, body: bytes, *, headers: dict | None = None, timeout: float = 120.0) -> tuple[int, dict]:
        status, raw = http_request(self.port, "POST", "/api/episodes/upload", body,
                                   {"Authorization": f"Bearer {self.token}", "Content-Type": "application/zip",
                                    **(headers or {})}, timeout=timeout)
        return status, json.loads(raw) if raw else {}

    def tmp_entries(self) -> list[str]:
        tmp = Path(self.settings.home) / "tmp"
        return sorted(p.name for p in tmp.iterdir()) if tmp.exists() else []


@pytest.fixture
def server(served):
    return lambda **env: served(cls=Server, **env)


class PeakRss:
    """The process's peak RSS above where it was when the block began, sampled every 5 ms."""

    def __enter__(self):
        self.proc = psutil.Process()
        self.base = self.peak = self.proc.memory_info().rss
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._watch, daemon=True)
        self.thread.start()
        self.t0 = time.monotonic()
        return self

    def _watch(self) -> None:
        while not self.done.wait(0.005):
            self.peak = max(self.peak, self.proc.memory_info().rss)

    def __exit__(self, *exc):
        self.seconds = time.monotonic() - self.t0
        self.done.set()
        self.thread.join()
        self.growth_mb = (self.peak - self.base) / MB


def _pi_package_holding(name: str, data: bytes, episode_id: str = "ep_bomb") -> bytes:
    """A Pi runtime package (tar.gz) whose upload_manifest.json lists `name` with its true sha256."""
    episode = json.dumps({"metadata": {"episode_id": episode_id}, "steps": []}).encode()
    sums = {"episode.json": hashlib.sha256(episode).hexdigest(), name: hashlib.sha256(data).hexdigest()}
    manifest = {"episode_id": episode_id, "file_checksums": sums, "metadata_checksum": sums["episode.json"],
                "total_size_bytes": len(episode) + len(data)}
    return hp.tar_gz_of([(episode_id, None), (f"{episode_id}/episode.json", episode), (f"{episode_id}/{name}", data),
                         (f"{episode_id}/upload_manifest.json", json.dumps(manifest).encode())])


BOMBS = {
    "mcap-zstd-chunk-of-256-mib": (lambda: hp.xr_mcap_bomb(), "episode.mcap"),
    "mcap-lz4-chunk-stating-100-bytes": (lambda: hp.xr_mcap_bomb(compression="lz4", declared=100), "episode.mcap"),
    "tfrecord-gzip-of-58-mib": (lambda: hp.xr_tfrecord_bomb(), "episode.tfrecord.gz"),
    "npz-member-of-64-mib": (lambda: hp.xr_npz_bomb(), "bomb.npz"),
    "tfrecord-bomb-in-a-pi-package": (lambda: _pi_package_holding("blobs/x.tfrecord.gz", hp.tfrecord_gzip_bomb()),
                                      "x.tfrecord.gz"),
}


@pytest.mark.parametrize("name", sorted(BOMBS))
def test_a_decompression_bomb_inside_a_member_costs_seconds_not_minutes(server, name):
    make, member = BOMBS[name]
    body = make()
    s = server()
    s.upload(hp.xr_zip_of({"warm.json": b"{}"}))  # the first request's imports and caches are not the bomb's
    with PeakRss() as cost:
        status, answer = s.upload(body)
    assert cost.seconds < 5.0, (cost.seconds, answer)
    assert cost.growth_mb < 64, (cost.growth_mb, answer)
    if status == 200:  # damage, not a bomb: the episode is rejected and says why
        (episode,) = answer["packages"][0]["episodes"]
        assert episode["action"] == "rejected" and member in " ".join(episode["errors"]), answer
    else:
        assert status == 413, answer
        assert member in answer["error"] and "tmp/package-" not in answer["error"], answer
    assert s.tmp_entries() == []


def test_a_bomb_found_after_an_episode_was_placed_leaves_it_recorded(server):
    from test_inbox import steps

    from hope_models.rlds.ingest import MANIFEST

    episode = json.dumps({"metadata": {"episode_id": "ep_before", "xr_mode": "trainer"}, "steps": steps(30)})
    s = server()
    status, answer = s.upload(hp.xr_zip_of({"a.json": episode.encode(), "z.tfrecord.gz": hp.tfrecord_gzip_bomb()}))
    assert status == 413 and "z.tfrecord.gz" in answer["error"], answer
    inbox = Path(s.settings.inbox_dir)
    manifest = json.loads((inbox / MANIFEST).read_text())
    placed = {p.name for p in inbox.iterdir() if p.is_dir() and not p.name.startswith(".")}
    assert placed == {e["episode_id"] for e in manifest["episodes"]} == {"ep_before"}, (placed, manifest)
    assert "tmp/package-" not in json.dumps(manifest)  # named by the package, as a whole ingest names it
    assert s.tmp_entries() == []


@pytest.fixture(scope="module")
def many_dirs() -> bytes:
    return hp.many_dirs_tar_gz()


def test_a_tar_of_99991_directories_is_refused_by_count_at_once(server, many_dirs):
    s = server()
    with PeakRss() as cost:
        status, answer = s.upload(many_dirs)
    assert status == 413 and "more than 1000 directories" in answer["error"], answer
    assert cost.seconds < 5.0
    assert s.tmp_entries() == []


def test_a_tar_of_more_members_than_a_long_episode_has_is_refused(server):
    files = hp.tar_gz_of([("ep", None)] + [(f"ep/step_{i:05d}_rgb.npy", b"") for i in range(10_000)])
    s = server(HOPE_UPLOAD_MAX_MEMBERS="10000")
    with PeakRss() as cost:
        status, answer = s.upload(files)
    assert status == 413 and "more than 10000 members" in answer["error"], answer
    assert "upload_max_members=10000" in answer["error"]
    assert cost.seconds < 5.0
    assert s.tmp_entries() == []


def test_unpacking_past_upload_extract_s_is_refused(server):
    s = server(HOPE_UPLOAD_EXTRACT_S="0.000001")
    status, answer = s.upload(hp.xr_zip_of({"metadata.json": b"{}", "steps/000000.jsonl": b"{}\n"}))
    assert status == 413 and "upload_extract_s" in answer["error"], answer
    assert s.tmp_entries() == []


def test_an_upload_that_would_take_the_disk_below_its_floor_is_a_507(server):
    s = server(HOPE_DISK_FLOOR_MB=str(1 << 30))  # a floor above any disk's free space
    status, answer = s.upload(hp.xr_zip_of({"metadata.json": b"{}"}))
    assert status == 507 and "below the floor" in answer["error"] and "disk_floor_mb" in answer["error"], answer
    assert s.tmp_entries() == []


def _start_upload(port: int, token: str, size: int, first: bytes) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    head = (f"POST /api/episodes/upload HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nAuthorization: Bearer {token}\r\n"
            f"Content-Type: application/zip\r\nContent-Length: {size}\r\nConnection: close\r\n\r\n")
    sock.sendall(head.encode() + first)
    return sock


def _read_answer(sock: socket.socket) -> tuple[int, bytes]:
    raw = b""
    while True:
        try:
            data = sock.recv(65536)
        except OSError:
            break
        if not data:
            break
        raw += data
    sock.close()
    if not raw.startswith(b"HTTP/"):
        return 0, raw
    return int(raw.split(b" ", 2)[1]), raw.partition(b"\r\n\r\n")[2]


def _finish_upload(sock: socket.socket, rest: bytes) -> tuple[int, bytes]:
    try:
        sock.sendall(rest)
    except OSError:
        pass  # refused while sending: its answer is already there
    return _read_answer(sock)


def _answers_of_refused(socks: list[socket.socket], within: float) -> dict[socket.socket, tuple[int, bytes]]:
    """The answers that arrive while the uploads wait for their second halves, read at once (the
    server drains a refused body for a moment only, then closes)."""
    answers: dict[socket.socket, tuple[int, bytes]] = {}
    deadline = time.monotonic() + within
    while len(answers) < len(socks) and time.monotonic() < deadline:
        readable, _, _ = select.select([s for s in socks if s not in answers], [], [], 0.5)
        if not readable and answers:
            break  # the refusals are in; the others wait for the rest of their bodies
        for sock in readable:
            answers[sock] = _read_answer(sock)
    return answers


def test_concurrent_uploads_past_upload_tmp_max_mb_are_refused_with_507(server):
    s = server(HOPE_UPLOAD_TMP_MAX_MB="4")
    size, half = 3 * MB, 3 * MB // 2
    body = (hp.xr_zip_of({"metadata.json": b"{}"}) + bytes(size))[:size]  # not a package once read whole: a 400
    socks = [_start_upload(s.port, s.token, size, body[:half]) for _ in range(6)]  # 9 MiB arriving at once
    refused = _answers_of_refused(socks, within=20)
    answers = [refused[sock] if sock in refused else _finish_upload(sock, body[half:]) for sock in socks]
    statuses = sorted(status for status, _ in answers)
    assert 507 in statuses, answers
    refused = [json.loads(raw)["error"] for status, raw in answers if status == 507]
    assert all("upload_tmp_max_mb=4" in e for e in refused), refused
    assert set(statuses) <= {400, 507}, answers
    deadline = time.monotonic() + 10
    while s.tmp_entries() and time.monotonic() < deadline:
        time.sleep(0.05)  # a handler cleans up just after its answer is sent
    assert s.tmp_entries() == []
    from webapp.uploads import TmpRoom

    assert TmpRoom.held(s.settings) == 0
