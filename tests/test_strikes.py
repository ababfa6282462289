"""An address that keeps sending what no client sends is refused at accept for a while, before a
thread or a parse: a flood of refused long-polls stops costing serve a request each."""
from __future__ import annotations

import json
import time

import pytest

from hostile_clients import LongPollFlood, http_request, log_flood, wait_until
from test_server_hardening import served  # noqa: F401 - the fixture

from webapp import strikes
from webapp.strikes import Strikes


def test_the_twentieth_strike_within_the_window_bans_and_the_ban_ends():
    s = Strikes(to_ban=20, window_s=10.0, ban_s=0.3)
    for _ in range(19):
        s.strike("10.0.0.9", "x")
    assert s.banned("10.0.0.9") == 0.0
    s.strike("10.0.0.9", "x")
    assert 0.0 < s.banned("10.0.0.9") <= 0.3
    assert s.banned("10.0.0.8") == 0.0, "only the striking address"
    assert wait_until(lambda: s.banned("10.0.0.9") == 0.0, 2.0, step=0.05)
    assert s.bans == 1


def test_strikes_spread_wider_than_the_window_do_not_ban():
    s = Strikes(to_ban=3, window_s=0.1, ban_s=5.0)
    for _ in range(6):
        s.strike("10.0.0.9", "x")
        time.sleep(0.06)  # two per window at most
    assert s.banned("10.0.0.9") == 0.0


def test_a_long_poll_flood_is_refused_at_accept_while_other_clients_are_served(served, monkeypatch):
    monkeypatch.setattr(strikes, "BAN_S", 3.0)
    s = served()
    flood = LongPollFlood(s.port, concurrency=50, refresh_s=2.0, source="127.0.0.2").start()
    try:
        end = time.monotonic() + 8.0
        pings = []
        while time.monotonic() < end:
            pings.append(http_request(s.port, "GET", "/api/ping", timeout=10.0)[0])
            time.sleep(0.2)
    finally:
        flood.stop()
    refused_at_accept = flood.statuses.get(503, 0)
    reached_the_app = flood.statuses.get(400, 0)
    # at most a window's strikes (plus the GETs already in flight) per ban: 8 s / 3 s bans
    bound = (8.0 / 3.0 + 1) * (strikes.STRIKES_TO_BAN + 50)
    assert refused_at_accept > 0, flood.statuses
    assert reached_the_app <= bound and s.guard.second_polls <= bound, (flood.statuses, s.guard.second_polls)
    assert pings and set(pings) == {200}, pings
    assert s.server.strikes.bans >= 1


def test_a_users_own_mistakes_are_not_strikes(served):
    """A bad run request, a malformed body: the user's errors, answered 4xx as often as they come."""
    s = served()
    auth = {"Authorization": f"Bearer {s.token}", "Content-Type": "application/json"}
    for _ in range(3 * strikes.STRIKES_TO_BAN):
        status, _ = http_request(s.port, "POST", "/api/runs", body=json.dumps({"component": "nope"}).encode(),
                                 headers=auth)
        assert status == 400
        assert http_request(s.port, "GET", "/api/runs/r-missing", headers=auth)[0] == 404
    assert http_request(s.port, "GET", "/api/ping")[0] == 200


def test_malformed_engineio_packets_are_strikes(served):
    s = served()
    for _ in range(4):
        log_flood(s.port, packets=10, source="127.0.0.3")
    status, answer = http_request(s.port, "GET", "/api/ping", source="127.0.0.3")
    assert status == 503 and b"no client sends" in answer, (status, answer[:200])
    assert http_request(s.port, "GET", "/api/ping")[0] == 200
