"""The host over time (daemon/system_history.py, registry/system_samples.py, GET /api/system/history):
the ring is bounded, samples reach the registry in batches and are pruned to 24 h, a daemon's start
refills the ring from the registry's last hour, a failing write never stops a tick, and the
endpoint answers from the daemon's ring under serve and from the registry without one."""
from __future__ import annotations

import logging
from datetime import datetime, timedelta, timezone

import pytest

from daemon.events import STATS_EVENT, ListSink
from daemon.system_history import SystemHistory
from daemon_fixtures import Home, home  # noqa: F401
from registry import system_samples
from registry.system_samples import FIELDS

NOW = datetime.now(timezone.utc)


@pytest.fixture(autouse=True)
def _now():
    """Each test's own NOW (set at import it would be minutes old when a test runs under xdist)."""
    global NOW
    NOW = datetime.now(timezone.utc)


class Clock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def sample(at: datetime, mem: float = 40.0) -> dict:
    return {"time": at.isoformat(), "mem_percent": mem, "mem_used_mb": 1600.0, "mem_available_mb": 2400.0,
            "mem_total_mb": 4000.0, "temp_c": 55.5, "cpu_percent": 12.0, "throttled": None, "sources": {}}


def stored(home) -> list[dict]:
    with home.registry.session(readonly=True) as s:
        return system_samples.recent_samples(s, 10 * 86400)


def test_ring_is_bounded_writes_in_batches_and_prunes(home):
    with home.registry.session() as s:  # a day and more ago: pruned by the first flush
        system_samples.record_sample(s, sample(NOW - timedelta(hours=25)))
        system_samples.record_sample(s, sample(NOW - timedelta(hours=23)))
    clock = Clock()
    h = SystemHistory(home.registry, interval_s=1.0, window_s=10.0, flush_s=3.0, clock=clock)
    assert h.capacity == 11 and h.flush_every == 3
    kept = []
    for i in range(25):
        kept.append(h.observe(sample(NOW - timedelta(seconds=25 - i), mem=i), throttle_level=i % 3))
        assert not h.observe(sample(NOW), 0), "a second sample within interval_s was kept"
        clock.t += 1.0
    assert all(kept)
    assert len(h) == 11  # the ring keeps the window, not everything
    # read by time: never more than the window (the 11th kept one is just older than 10 s)
    assert [x["mem_percent"] for x in h.samples(3600, now=NOW)] == list(range(15, 25))
    # read by time too: the last 5 s of the ring
    assert [x["mem_percent"] for x in h.samples(5, now=NOW)] == [20, 21, 22, 23, 24]
    rows = stored(home)
    # 24 written in batches of 3 (one pending), the 25 h old row pruned, the 23 h old one kept
    assert len(rows) == 1 + 24 and len(h.unflushed()) == 1
    assert rows[0]["time"] == (NOW - timedelta(hours=23)).isoformat()
    assert [r["mem_percent"] for r in rows[1:]] == list(range(24))
    assert rows[-1]["throttle_level"] == 23 % 3 and set(rows[-1]) == {"time", *FIELDS}
    assert h.flush() and not h.unflushed() and len(stored(home)) == 26


def test_a_failing_write_is_logged_kept_and_retried(home, caplog):
    class Locked:
        def __init__(self, registry):
            self.registry, self.broken = registry, True

        def session(self, **kw):
            if self.broken:
                raise RuntimeError("database is locked")
            return self.registry.session(**kw)

    reg = Locked(home.registry)
    clock = Clock()
    h = SystemHistory(reg, interval_s=1.0, flush_s=1.0, clock=clock)
    with caplog.at_level(logging.WARNING, logger="daemon.system_history"):
        for i in range(3):
            assert h.observe(sample(NOW - timedelta(seconds=3 - i)), 0)  # no exception reaches the tick
            clock.t += 1.0
    assert len(h.unflushed()) == 3 and len(h) == 3
    assert len([r for r in caplog.records if "database is locked" in r.getMessage()]) == 1  # once per streak
    reg.broken = False
    assert h.observe(sample(NOW), 0)
    assert not h.unflushed() and len(stored(home)) == 4


def make_daemon(home, sink=None):
    from daemon.monitor import SystemMonitor, ThrottlePolicy
    from daemon.service import Daemon

    monitor = SystemMonitor(None, zone_path=None, vcgencmd=None)
    d = Daemon(home.settings, sink, tick_s=0.05, stats_every_s=0.0, monitor=monitor, policy=ThrottlePolicy(75, 82, 70),
               registry=home.registry, send=lambda *a: None)
    d.start()
    return d


def api_client(home, daemon=None):
    from webapp import create_app
    from webapp.auth import load_or_create_token

    token = load_or_create_token(home.settings)
    app, _ = create_app(home.settings, token=token, registry=home.registry, daemon=daemon)
    client = app.test_client()
    return app, lambda path: client.get(path, headers={"Authorization": f"Bearer {token}"})


def test_daemon_refills_the_last_hour_at_start_and_serves_it(home):
    with home.registry.session() as s:
        for minutes in (90, 61, 30, 10, 1):
            system_samples.record_sample(s, sample(NOW - timedelta(minutes=minutes), mem=minutes))
    sink = ListSink()
    d = make_daemon(home, sink)
    try:
        assert [x["mem_percent"] for x in d.history.samples()] == [30, 10, 1]
        d.tick()
        app, get = api_client(home, d)
        body = get("/api/system/history").get_json()
        assert body["source"] == "daemon" and body["interval_s"] == home.settings.system_sample_s == 5.0
        assert [x["mem_percent"] for x in body["samples"][:3]] == [30, 10, 1] and len(body["samples"]) == 4
        live = body["samples"][-1]
        assert set(live) == {"time", *FIELDS} and live["mem_total_mb"] > 0 and live["throttle_level"] == 0
        assert live["mem_used_mb"] == pytest.approx(live["mem_total_mb"] - live["mem_available_mb"], abs=0.2)
        # the live event carries the same names (and "time"): a browser appends it to this chart
        stats = sink.of(STATS_EVENT)[-1]
        assert {"time", *FIELDS} <= set(stats) and stats["time"] == live["time"]
        assert [x["mem_percent"] for x in get("/api/system/history?seconds=900").get_json()["samples"][:1]] == [10]
        # longer than the ring: the registry, plus the sample the daemon has not written yet
        day = get("/api/system/history?seconds=86400").get_json()
        assert day["source"] == "registry" and [x["mem_percent"] for x in day["samples"][:-1]] == [90, 61, 30, 10, 1]
        assert day["samples"][-1]["time"] == live["time"]
        app.extensions["hope"].close()
    finally:
        d.stop()
    # the stop wrote what was pending: a restart keeps the live sample too
    assert stored(home)[-1]["time"] == live["time"]


def test_history_without_a_daemon_reads_the_registry_and_refuses_bad_seconds(home):
    with home.registry.session() as s:
        for minutes in (120, 50, 2):
            system_samples.record_sample(s, {**sample(NOW - timedelta(minutes=minutes), mem=minutes),
                                             "temp_c": None, "throttle_level": 1})
    app, get = api_client(home)
    body = get("/api/system/history").get_json()
    assert body == {"interval_s": 5.0, "source": "registry",
                    "samples": [{"time": (NOW - timedelta(minutes=m)).isoformat(), "mem_percent": float(m),
                                 "mem_used_mb": 1600.0, "mem_available_mb": 2400.0, "mem_total_mb": 4000.0,
                                 "temp_c": None, "cpu_percent": 12.0, "throttle_level": 1} for m in (50, 2)]}
    assert len(get("/api/system/history?seconds=86400").get_json()["samples"]) == 3
    assert len(get("/api/system/history?seconds=300").get_json()["samples"]) == 1
    for bad in ("0", "86401", "abc", "1.5", "-5"):
        r = get(f"/api/system/history?seconds={bad}")
        assert r.status_code == 400 and "seconds" in r.get_json()["error"], (bad, r.get_json())
    r = get("/api/system/history?second=5")
    assert r.status_code == 400 and "second" in r.get_json()["error"]
    app.extensions["hope"].close()


def test_sample_interval_setting_is_validated(tmp_path):
    from hope_models.settings import SettingsError, load_settings

    env = {"HOPE_HOME": str(tmp_path / "h"), "HOPE_SYSTEM_SAMPLE_S": "2.5", "HOPE_WORKER_HEARTBEAT_S": "1"}
    got = load_settings(env=env)
    assert got.system_sample_s == 2.5 and got.worker_heartbeat_s == 1.0
    for var, name in (("HOPE_SYSTEM_SAMPLE_S", "system_sample_s"), ("HOPE_WORKER_HEARTBEAT_S", "worker_heartbeat_s")):
        for bad in ("0", "-1", "fast"):
            with pytest.raises(SettingsError, match=name):
                load_settings(env={**env, var: bad})
