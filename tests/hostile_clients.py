"""What a hostile neighbour on the same machine does to the webapp, as plain socket code.

Used by tests/test_server_hardening.py (against a real `serve`) and bench/soak.py. Every pattern
needs no token (but run_flood, a token holder's); each returns once its own bounded work is done,
leaving whatever sockets it opened in `held` so the caller decides when they end.
"""
from __future__ import annotations

import base64
import json
import os
import socket
import threading
import time
from dataclasses import dataclass, field

# The bodies that once pinned a thread for ever (python-engineio's close() waiting on the queue).
BAD_POLL_BODIES = (b"6", b"0", b"2probe", b"9zzz", b"4" + b"x" * 1_100_000)


def http_request(port: int, method: str, path: str, body: bytes = b"", headers: dict | None = None,
                 timeout: float = 5.0, host: str = "127.0.0.1", source: str | None = None) -> tuple[int, bytes]:
    """One request on its own connection (from the loopback address `source`, as another client, if
    given); (status, body). Status 0 when the server closed without answering."""
    head = {"Host": f"127.0.0.1:{port}", "Connection": "close", "Content-Length": str(len(body))}
    head.update(headers or {})
    lines = [f"{method} {path} HTTP/1.1"] + [f"{k}: {v}" for k, v in head.items()]
    with socket.create_connection((host, port), timeout=timeout,
                                  source_address=None if source is None else (source, 0)) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode() + body)
        raw = b""
        while not _complete(raw):
            try:
                data = s.recv(65536)
            except (ConnectionResetError, socket.timeout):
                break
            if not data:
                break
            raw += data
    if not raw.startswith(b"HTTP/"):
        return 0, raw
    head_end = raw.find(b"\r\n\r\n")
    status = int(raw.split(b" ", 2)[1])
    payload = raw[head_end + 4:] if head_end >= 0 else b""
    if b"transfer-encoding: chunked" in raw[:head_end].lower():
        payload = _dechunk(payload)
    return status, payload


def _complete(raw: bytes) -> bool:
    """A whole response with a Content-Length has arrived (a client then hangs up, as curl does)."""
    end = raw.find(b"\r\n\r\n")
    if end < 0:
        return False
    if raw.endswith(b"\r\n0\r\n\r\n") or raw[end + 4:].startswith(b"0\r\n\r\n"):
        return True  # the last chunk of a chunked body
    for line in raw[:end].split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"content-length":
            return len(raw) - end - 4 >= int(value)
    return False


def _dechunk(data: bytes) -> bytes:
    out, i = [], 0
    while i < len(data):
        end = data.find(b"\r\n", i)
        if end < 0:
            break
        size = int(data[i:end].split(b";")[0] or b"0", 16)
        if size == 0:
            break
        out.append(data[end + 2:end + 2 + size])
        i = end + 2 + size + 2
    return b"".join(out)


def polling_handshake(port: int, timeout: float = 5.0, source: str | None = None) -> str | None:
    status, body = http_request(port, "GET", "/socket.io/?EIO=4&transport=polling", timeout=timeout, source=source)
    if status != 200 or not body.startswith(b"0"):
        return None
    return json.loads(body[1:])["sid"]


def bad_poll_pair(port: int, body: bytes, timeout: float = 2.0, source: str | None = None) -> int:
    """An Engine.IO polling handshake, then one POST of a bad packet; the POST's status (0 = no answer)."""
    sid = polling_handshake(port, source=source)
    if sid is None:
        return -1
    try:
        status, _ = http_request(port, "POST", f"/socket.io/?EIO=4&transport=polling&sid={sid}", body=body,
                                 headers={"Content-Type": "text/plain;charset=UTF-8"}, timeout=timeout, source=source)
    except (socket.timeout, OSError):
        return 0
    return status


def _connect(port: int, source: str | None, timeout: float = 5.0) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=timeout,
                                    source_address=None if source is None else (source, 0))


def half_header_socket(port: int, source: str | None = None) -> socket.socket:
    """A connection that sends half a request and then nothing."""
    s = _connect(port, source)
    s.sendall(b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
    return s


def silent_websocket(port: int, source: str | None = None) -> socket.socket | None:
    """A completed WebSocket handshake on the Socket.IO endpoint that never sends CONNECT. None if refused."""
    s = _connect(port, source)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET /socket.io/?EIO=4&transport=websocket HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
               f"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
               "Sec-WebSocket-Version: 13\r\n\r\n").encode())
    try:
        head = s.recv(4096)
    except (socket.timeout, OSError):
        head = b""
    if not head.startswith(b"HTTP/1.1 101"):
        s.close()
        return None
    return s


@dataclass
class HostileRound:
    """One round of every pattern; the sockets it keeps open are in `held` until `release()`."""

    port: int
    pairs_per_body: int = 60
    half_headers: int = 50
    silent_websockets: int = 100
    source: str | None = None  # a loopback address of its own (127.0.0.3: another host), else the default
    held: list = field(default_factory=list)
    statuses: dict = field(default_factory=dict)
    refused: int = 0

    def run(self) -> "HostileRound":
        for body in BAD_POLL_BODIES:
            for _ in range(self.pairs_per_body):
                status = bad_poll_pair(self.port, body, source=self.source)
                self.statuses[status] = self.statuses.get(status, 0) + 1
        for _ in range(self.half_headers):
            try:
                self.held.append(half_header_socket(self.port, self.source))
            except OSError:
                self.refused += 1
        for _ in range(self.silent_websockets):
            try:
                ws = silent_websocket(self.port, self.source)
            except OSError:
                ws = None
            if ws is None:
                self.refused += 1
            else:
                self.held.append(ws)
        return self

    def release(self) -> None:
        for s in self.held:
            try:
                s.close()
            except OSError:
                pass
        self.held.clear()


def run_flood(port: int, token: str, data: str, *, runs: int = 21, queue: str = "nobody",
              component: str = "fast_loop", steps: int = 10, cancel: bool = True) -> dict:
    """A token holder's create-and-cancel burst: `runs` runs POSTed to a queue no worker serves, each
    cancelled at once (they never start). Once made retention delete a trained run's files. With
    cancel=False it fills the queue instead (429 past max_queued_runs).
    Returns the statuses of the creations and of the cancels ({status: count}) and the run ids made."""
    auth = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    body = json.dumps({"component": component, "data": data, "steps": steps, "queue": queue}).encode()
    out: dict = {"created": {}, "cancelled": {}, "ids": []}
    for _ in range(runs):
        status, raw = http_request(port, "POST", "/api/runs", body=body, headers=auth, timeout=30.0)
        out["created"][status] = out["created"].get(status, 0) + 1
        if status != 201:
            continue
        run_id = json.loads(raw)["run"]["id"]
        out["ids"].append(run_id)
        if not cancel:
            continue
        status, _ = http_request(port, "POST", f"/api/runs/{run_id}/cancel", headers=auth, timeout=30.0)
        out["cancelled"][status] = out["cancelled"].get(status, 0) + 1
    return out


def process_counts(pid: int) -> tuple[int, int]:
    """(threads, open file descriptors) of a process, from /proc."""
    return len(os.listdir(f"/proc/{pid}/task")), len(os.listdir(f"/proc/{pid}/fd"))


def fd_kinds(pid: int) -> dict[str, int]:
    """What a process's descriptors point at, counted by kind (a file's name, or socket/pipe/anon
    without its inode): says what grew when a count did."""
    kinds: dict[str, int] = {}
    for fd in os.listdir(f"/proc/{pid}/fd"):
        try:
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
        except OSError:
            continue  # closed meanwhile
        kind = target.split(":", 1)[0] if ":[" in target else os.path.basename(target)
        kinds[kind] = kinds.get(kind, 0) + 1
    return dict(sorted(kinds.items()))


def wait_until(predicate, timeout: float, step: float = 0.25):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value or time.monotonic() >= deadline:
            return value
        time.sleep(step)


class SocketIOClient:
    """A legitimate Socket.IO client over a raw WebSocket (Engine.IO v4 framing by hand): logs in with
    the token and answers pings, so it stays connected as the Robot Editor does."""

    def __init__(self, port: int, token: str | None, host: str = "127.0.0.1", timeout: float = 20.0):
        import simple_websocket

        # timeout: socket.io-client's default connection timeout (20 s)
        self.ws = simple_websocket.Client(f"ws://{host}:{port}/socket.io/?EIO=4&transport=websocket")
        opened = self.ws.receive(timeout=0.5)
        if opened is None:
            # simple-websocket's client (1.1) takes only the first event of the handshake's read: when
            # the server's OPEN came in the same segment as its 101 (a loaded box), the OPEN waits in
            # wsproto's buffer until more data arrives, which the server never sends before CONNECT.
            # The reader is idle in recv() by now: hand those events over once.
            self.ws._handle_events()
            opened = self.ws.receive(timeout=timeout)
        if not (isinstance(opened, str) and opened.startswith("0")):
            raise ConnectionError(f"no Engine.IO OPEN packet: {opened!r}")
        self.ws.send("40" + json.dumps({"token": token} if token else {}))
        self.connect_reply = self._next_message(timeout=timeout)

    @property
    def connected(self) -> bool:
        return isinstance(self.connect_reply, str) and self.connect_reply.startswith("40")

    def _next_message(self, timeout: float):
        from simple_websocket import ConnectionClosed

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                pkt = self.ws.receive(timeout=max(0.05, deadline - time.monotonic()))
            except ConnectionClosed as exc:
                raise ConnectionError(f"the server closed the Socket.IO connection: {exc}") from None
            if pkt is None:
                return None
            if pkt == "2":  # Engine.IO ping
                self.ws.send("3")
                continue
            return pkt
        return None

    def pump(self, seconds: float) -> list:
        """Answer pings and collect Socket.IO messages for `seconds`; raises if the server hung up."""
        got = []
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            pkt = self._next_message(deadline - time.monotonic())
            if pkt is not None:
                got.append(pkt)
        if not self.ws.connected:
            raise ConnectionError("the server closed the Socket.IO connection")
        return got

    def close(self) -> None:
        try:
            self.ws.close()
        except Exception:  # noqa: BLE001 - already gone
            pass


def raw_request(port: int, method: str, path: str, *, source: str = "127.0.0.1", timeout: float = 5.0,
                stop=None, body: bytes = b"", headers: dict | None = None) -> int:
    """One request from the loopback address `source` (127.0.0.2 is another client); its status,
    0 when the server closed without answering, -1 when it could not connect, -2 when `stop` was
    set while waiting (the socket is closed then: the attacker left)."""
    head = {"Host": f"127.0.0.1:{port}", "Connection": "close", "Content-Length": str(len(body)), **(headers or {})}
    lines = [f"{method} {path} HTTP/1.1"] + [f"{k}: {v}" for k, v in head.items()]
    try:
        s = socket.create_connection(("127.0.0.1", port), timeout=timeout, source_address=(source, 0))
    except OSError:
        return -1
    deadline = time.monotonic() + timeout
    try:
        s.settimeout(0.25)
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode() + body)
        raw = b""
        while b"\r\n" not in raw and time.monotonic() < deadline:
            if stop is not None and stop.is_set():
                return -2
            try:
                data = s.recv(4096)
            except socket.timeout:
                continue
            if not data:
                break
            raw += data
    except OSError:
        return 0
    finally:
        s.close()
    return int(raw.split(b" ", 2)[1]) if raw.startswith(b"HTTP/") else 0


class LongPollFlood:
    """The long-poll flood: one Engine.IO polling handshake, then `concurrency` long-poll GETs on its
    session id at once, each re-sent as soon as it returns, and a fresh handshake every `refresh_s`
    (or as soon as the session is refused), no token needed. From `source`, a loopback address.

        flood = LongPollFlood(port, source="127.0.0.2").start()
        ...
        flood.stop()   # every socket closed, every thread joined; flood.statuses counts the answers
    """

    def __init__(self, port: int, concurrency: int = 200, refresh_s: float = 8.0, source: str = "127.0.0.1",
                 retry_pause_s: float = 0.2, hold_s: float = 60.0):
        self.port, self.concurrency, self.refresh_s = port, concurrency, refresh_s
        self.source, self.retry_pause_s, self.hold_s = source, retry_pause_s, hold_s
        self.statuses: dict[int, int] = {}
        self.handshakes = 0
        self._sid: str | None = None
        self._stale = True
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []

    def _handshake(self) -> None:
        try:
            s = socket.create_connection(("127.0.0.1", self.port), timeout=5, source_address=(self.source, 0))
        except OSError:
            return
        try:
            s.sendall(f"GET /socket.io/?EIO=4&transport=polling HTTP/1.1\r\nHost: 127.0.0.1:{self.port}\r\n"
                      "Connection: close\r\n\r\n".encode())
            raw = b""
            while not _complete(raw):
                data = s.recv(65536)
                if not data:
                    break
                raw += data
        except OSError:
            return
        finally:
            s.close()
        head, _, body = raw.partition(b"\r\n\r\n")
        body = _dechunk(body) if b"transfer-encoding: chunked" in head.lower() else body
        if raw.startswith(b"HTTP/1.1 200") and body.startswith(b"0"):
            with self._lock:
                self._sid, self._stale = json.loads(body[1:])["sid"], False
                self.handshakes += 1

    def _refresher(self) -> None:
        last = 0.0
        while not self._stop.is_set():
            if self._stale or time.monotonic() - last >= self.refresh_s:
                self._handshake()
                last = time.monotonic()
            self._stop.wait(0.5)

    def _poller(self) -> None:
        while not self._stop.is_set():
            sid = self._sid
            if sid is None:
                self._stop.wait(0.1)
                continue
            status = raw_request(self.port, "GET", f"/socket.io/?EIO=4&transport=polling&sid={sid}",
                                 source=self.source, timeout=self.hold_s, stop=self._stop)
            with self._lock:
                self.statuses[status] = self.statuses.get(status, 0) + 1
                if status == 400:
                    self._stale = True
            if status != 200:
                self._stop.wait(self.retry_pause_s)

    def start(self) -> "LongPollFlood":
        self._threads = [threading.Thread(target=self._refresher, name="flood-handshakes", daemon=True)]
        self._threads += [threading.Thread(target=self._poller, name=f"flood-{i}", daemon=True)
                          for i in range(self.concurrency)]
        for t in self._threads:
            t.start()
        return self

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.1, deadline - time.monotonic()))


# Bodies a polling client POSTs that python-engineio / python-socketio cannot decode: each once wrote
# a traceback (twice) into the log. `x`, `\xff`, `bZZZ` fail Engine.IO's decoding (the session stays
# open); `42[`, `4x` fail Socket.IO's (the session is closed).
LOG_FLOOD_BODIES = (b"x", b"42[", b"\xff", b"4x", b"bZZZ")


def log_flood(port: int, packets: int = 500, bodies: tuple = LOG_FLOOD_BODIES, timeout: float = 5.0,
              source: str | None = None) -> dict:
    """No token: `packets` malformed polling POSTs, on one Engine.IO session while it stays open (a
    new handshake when it is closed). Returns {POST status: count}, -1 for a refused handshake."""
    statuses: dict = {}
    sid = None
    for i in range(packets):
        if sid is None:
            sid = polling_handshake(port, timeout=timeout, source=source)
        if sid is None:
            statuses[-1] = statuses.get(-1, 0) + 1
            time.sleep(0.05)  # refused by the session rate limit: a moment before the next try
            continue
        try:
            status, _ = http_request(port, "POST", f"/socket.io/?EIO=4&transport=polling&sid={sid}",
                                     body=bodies[i % len(bodies)], timeout=timeout, source=source,
                                     headers={"Content-Type": "text/plain;charset=UTF-8"})
        except OSError:
            status = 0
        statuses[status] = statuses.get(status, 0) + 1
        if status != 200:
            sid = None
    return statuses


# A Socket.IO BINARY_EVENT declaring 999,999,999 attachments: python-socketio appends every later
# message of the session to it until that many have come.
ATTACHMENT_BOMB = '45999999999-["x",{"_placeholder":true,"num":0}]'


def binary_attachment_bomb(port: int, token: str, megabytes: float = 16.0, chunk: int = 32 * 1024,
                           timeout: float = 10.0) -> dict:
    """A token holder's Socket.IO client sends ATTACHMENT_BOMB, then `megabytes` of binary messages
    of `chunk` bytes. Returns {"logged_in", "sent" (bytes the socket took), "closed" (the server
    closed the connection), "client"} (the SocketIOClient, still open if the server kept it)."""
    from simple_websocket import ConnectionClosed

    client = SocketIOClient(port, token, timeout=timeout)
    out = {"logged_in": client.connected, "sent": 0, "closed": False, "client": client}
    if not client.connected:
        return out
    payload = os.urandom(chunk)
    client.ws.sock.settimeout(timeout)  # a server that stops reading without closing: no send waits for ever
    try:
        client.ws.send(ATTACHMENT_BOMB)
        while out["sent"] < megabytes * 1024 * 1024:
            if not client.ws.connected:
                break
            client.ws.send(payload)
            out["sent"] += len(payload)
    except (ConnectionClosed, OSError):
        pass
    out["closed"] = not client.ws.connected
    return out
