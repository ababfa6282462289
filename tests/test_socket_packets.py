"""Socket.IO input this server never takes (webapp/socket_packets.py), on the real server in this
process: a binary event (a token holder's attachment bomb) closes the session at once, before
python-socketio collects anything; Engine.IO buffers at most MAX_MESSAGE_BYTES per message; the
Robot Editor's own traffic (log in, pings) is unaffected.
"""
from __future__ import annotations

import gc
import logging

import psutil
import pytest

from hostile_clients import (SocketIOClient, binary_attachment_bomb, http_request, polling_handshake,
                             wait_until)
from test_server_hardening import Served

MB = 1024 * 1024


@pytest.fixture
def served(tmp_path):
    s = Served(tmp_path / "s")
    yield s
    s.close()


def _rss() -> int:
    gc.collect()
    return psutil.Process().memory_info().rss


def test_a_binary_attachment_bomb_closes_the_session_and_holds_no_memory(served, caplog):
    eio = served.socketio.server.eio
    warm = SocketIOClient(served.port, served.token)  # first-session allocations out of the measurement
    assert warm.connected
    warm.close()
    before = _rss()
    with caplog.at_level(logging.WARNING, logger="webapp.socket_packets"):
        out = binary_attachment_bomb(served.port, served.token, megabytes=24)
        client = out.pop("client")
        try:
            assert out["logged_in"]
            closed = wait_until(lambda: not client.ws.connected, timeout=10)
        finally:
            client.close()
    assert closed, f"the server kept the session open after {out['sent']} bytes"
    assert wait_until(lambda: all(s.closed for s in list(eio.sockets.values())), timeout=10), "a session is open"
    grown = _rss() - before
    # python-socketio once held every message after the bomb: 24 MB sent would be 24 MB more
    assert grown < 8 * MB, f"RSS grew {grown / MB:.1f} MB after {out['sent'] / MB:.1f} MB sent"
    refusals = [r for r in caplog.records if "binary Socket.IO event" in r.getMessage()]
    assert len(refusals) == 1 and refusals[0].levelno == logging.WARNING
    assert not any(r.exc_info for r in caplog.records)


def test_a_binary_message_closes_a_session_that_has_not_logged_in(served):
    client = SocketIOClient(served.port, None, timeout=3.0)  # refused: no token, the session stays open
    try:
        client.ws.send(b"\x00" * 1024)
        assert wait_until(lambda: not client.ws.connected, timeout=5)  # well before its 10 s login deadline
    finally:
        client.close()


def test_engineio_buffers_at_most_the_cap_per_message(served):
    from webapp.socket_packets import MAX_MESSAGE_BYTES

    served.guard._rate = served.guard._burst = 1000.0
    sid = polling_handshake(served.port)
    body = b"4" + b'42["x","' + b"y" * (MAX_MESSAGE_BYTES + 1) + b'"]'
    status, _ = http_request(served.port, "POST", f"/socket.io/?EIO=4&transport=polling&sid={sid}", body=body,
                             headers={"Content-Type": "text/plain;charset=UTF-8"})
    assert status == 400
    client = SocketIOClient(served.port, served.token)
    try:
        assert client.connected
        client.ws.send('42["x","' + "y" * (MAX_MESSAGE_BYTES + 1) + '"]')
        assert wait_until(lambda: not client.ws.connected, timeout=10)
    finally:
        client.close()
    # the Robot Editor's traffic still passes: log in, stay connected through a ping
    ok = SocketIOClient(served.port, served.token)
    try:
        assert ok.connected
        ok.pump(0.5)
    finally:
        ok.close()


def test_a_websocket_closed_for_an_oversized_message_leaves_no_connection_behind(served):
    # simple-websocket ends its reader on an oversized message in an order that could leave
    # Engine.IO's receive() waiting for ever: one thread and one connection per message, which
    # filled a client address's share of connections in a soak (new editors then got 503)
    from webapp.socket_packets import MAX_MESSAGE_BYTES

    served.guard._rate = served.guard._burst = 1000.0
    for _ in range(5):
        client = SocketIOClient(served.port, served.token)
        try:
            assert client.connected, client.connect_reply
            client.ws.send('42["x","' + "y" * (MAX_MESSAGE_BYTES + 1) + '"]')
            assert wait_until(lambda: not client.ws.connected, timeout=10)
        finally:
            client.close()
    assert wait_until(lambda: served.server.open_connections == 0, timeout=5), served.server.open_connections
