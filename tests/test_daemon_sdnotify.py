"""sd_notify over a real unix datagram socket (path and abstract), as systemd's would receive it."""
from __future__ import annotations

import os
import socket

import pytest

from daemon.sdnotify import SdNotifier


@pytest.fixture
def listener(tmp_path):
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    path = str(tmp_path / "notify")
    sock.bind(path)
    sock.settimeout(2)
    yield sock, path
    sock.close()


def test_ready_status_watchdog_stopping_reach_the_socket(listener):
    sock, path = listener
    n = SdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "30000000", "WATCHDOG_PID": str(os.getpid())})
    assert n.enabled and n.watchdog_s == 30.0
    assert n.ready("idle")
    assert sock.recv(1024) == b"READY=1\nSTATUS=idle"
    assert n.status("running r-1")
    assert sock.recv(1024) == b"STATUS=running r-1"
    assert n.maybe_watchdog(now=0.0)
    assert sock.recv(1024) == b"WATCHDOG=1"
    assert not n.maybe_watchdog(now=14.9)  # every half of WATCHDOG_USEC
    assert n.maybe_watchdog(now=15.0)
    assert sock.recv(1024) == b"WATCHDOG=1"
    assert n.stopping()
    assert sock.recv(1024) == b"STOPPING=1"
    n.close()


def test_abstract_socket_name():
    name = f"hope-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    sock.settimeout(2)
    try:
        n = SdNotifier({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert sock.recv(1024) == b"READY=1"
    finally:
        sock.close()


def test_outside_systemd_everything_is_a_no_op():
    n = SdNotifier({})
    assert not n.enabled and n.watchdog_s is None
    assert n.ready() is False and n.watchdog() is False and n.maybe_watchdog() is False


def test_watchdog_for_another_pid_is_ignored(listener):
    _, path = listener
    n = SdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"})
    assert n.watchdog_s is None and not n.maybe_watchdog()


def test_a_vanished_socket_is_not_fatal(tmp_path, caplog):
    n = SdNotifier({"NOTIFY_SOCKET": str(tmp_path / "gone")})
    assert n.ready() is False and n.status("x") is False
    assert len([r for r in caplog.records if "sd_notify" in r.getMessage()]) == 1
