"""The daemon's monitor (psutil memory, thermal zone, a fake vcgencmd) and its throttle policy."""
from __future__ import annotations

import logging
import os
import stat

import psutil
import pytest

from daemon.monitor import SystemMonitor, ThrottlePolicy


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def fake_vcgencmd(tmp_path, output: str = "throttled=0x50005", rc: int = 0):
    exe = tmp_path / "vcgencmd"
    exe.write_text(f"#!/bin/sh\necho '{output}'\nexit {rc}\n")
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    return str(exe)


def test_sample_has_memory_cpu_and_the_zone_temperature(tmp_path):
    zone = tmp_path / "temp"
    zone.write_text("48312\n")  # millidegrees, as the kernel writes them
    mon = SystemMonitor(None, zone_path=str(zone), vcgencmd=None)
    s = mon.sample()
    assert set(s) == {"time", "mem_total_mb", "mem_used_mb", "mem_available_mb", "mem_percent", "cpu_percent",
                      "temp_c", "throttled", "sources"}
    total = psutil.virtual_memory().total / 2**20
    assert s["mem_total_mb"] == pytest.approx(total, rel=1e-3)
    assert 0 < s["mem_available_mb"] <= s["mem_total_mb"] and 0 <= s["mem_percent"] <= 100
    assert s["mem_used_mb"] == pytest.approx(s["mem_total_mb"] - s["mem_available_mb"], abs=0.2)
    assert 0 <= s["cpu_percent"] <= 100
    assert s["temp_c"] == pytest.approx(48.312) and s["throttled"] is None
    assert s["sources"]["thermal_zone"] == {"path": str(zone), "ok": True, "error": None}
    assert s["sources"]["vcgencmd"]["ok"] is False and s["sources"]["vcgencmd"]["error"] == "not configured"
    assert s["time"].endswith("+00:00")


def test_vcgencmd_flags_are_read_and_zone_is_rate_limited(tmp_path):
    zone = tmp_path / "temp"
    zone.write_text("60000\n")
    clock = Clock()
    mon = SystemMonitor(None, zone_path=str(zone), vcgencmd=fake_vcgencmd(tmp_path), thermal_interval_s=1.0,
                        clock=clock)
    s = mon.sample()
    assert s["throttled"]["throttled"] is True and s["throttled"]["under_voltage"] is True
    assert s["throttled"]["raw"] == "0x50005" and s["sources"]["vcgencmd"]["ok"] is True
    zone.write_text("70000\n")
    assert mon.sample()["temp_c"] == 60.0  # within the interval: the cached reading
    clock.now += 1.0
    assert mon.sample()["temp_c"] == 70.0


def test_missing_sources_are_reported_once_not_errors(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    missing = tmp_path / "no-such-zone"
    mon = SystemMonitor(None, zone_path=str(missing), vcgencmd=str(tmp_path / "no-vcgencmd"),
                        thermal_interval_s=0.0)
    for _ in range(3):
        s = mon.sample()
    assert s["temp_c"] is None and s["throttled"] is None
    assert s["sources"]["thermal_zone"] == {"path": str(missing), "ok": False, "error": "not readable"}
    assert s["sources"]["vcgencmd"]["error"] == "not available"
    zone_msgs = [r for r in caplog.records if str(missing) in r.getMessage()]
    assert 1 <= len(zone_msgs) <= 2  # the reader's warning and the monitor's note, once each, not per sample
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_monitor_takes_sources_from_settings(tmp_path):
    from hope_models.settings import load_settings

    zone = tmp_path / "t"
    zone.write_text("55\n")  # degrees (below 1000)
    settings = load_settings(tmp_path / "home", env={"HOPE_THERMAL_ZONE": str(zone), "HOPE_VCGENCMD": ""})
    mon = SystemMonitor(settings)
    assert mon.zone_path == str(zone) and mon.sample()["temp_c"] == 55.0


@pytest.mark.parametrize("temps, slowing, expected", [
    # soft 75, hard 82, resume 70
    ([60, 74.9, 60], None, [0, 0, 0]),
    ([76, 72, 70, 69.9], None, [1, 1, 1, 0]),            # slow holds down to the resume limit
    ([83, 78, 71, 69], None, [2, 2, 2, 0]),              # hot holds until below resume, then straight to 0
    ([76, 82, 80, 60, 76], None, [1, 2, 2, 0, 1]),
    ([60, 60, 60], [False, True, False], [0, 1, 0]),     # firmware throttling alone: at least 1
    ([83, 65], [False, True], [2, 1]),                   # cooled but firmware still slowing
    ([None, None, 83, None], [False, True, False, False], [0, 1, 2, 0]),  # no reading: only the firmware counts
])
def test_throttle_policy_levels_with_hysteresis(temps, slowing, expected):
    policy = ThrottlePolicy(75, 82, 70)
    slowing = slowing or [False] * len(temps)
    levels, changes = [], []
    for t, sl in zip(temps, slowing):
        change = policy.update(t, sl)
        if change is not None:
            changes.append(change)
        levels.append(policy.level)
    assert levels == expected
    # one change record per level change, naming the levels and why
    transitions = [(a, b) for a, b in zip([0] + expected, expected) if a != b]
    assert [(c.previous, c.level) for c in changes] == transitions
    assert all(c.reason for c in changes)


def test_throttle_policy_refuses_inconsistent_limits():
    with pytest.raises(ValueError, match="thermal_soft_c"):
        ThrottlePolicy(80, 80, 70)
    with pytest.raises(ValueError, match="thermal_resume_c"):
        ThrottlePolicy(75, 82, 76)


def test_policy_reads_a_monitor_sample(tmp_path):
    policy = ThrottlePolicy(75, 82, 70)
    change = policy.update_from_sample({"temp_c": 50.0, "throttled": {"throttled": False, "soft_temp_limit": True}})
    assert change is not None and change.level == 1 and "firmware" in change.reason
    assert change.to_json_obj() == {"level": 1, "previous": 0, "reason": change.reason, "temp_c": 50.0}


def test_no_torch_in_the_daemon_modules_or_the_celery_app_it_sends_with():
    import subprocess
    import sys

    code = ("import sys, daemon.monitor, daemon.sdnotify, daemon.events, daemon.dispatch, daemon.reconcile, "
            "daemon.service, daemon.cli.daemon\n"
            "from hope_models.settings import load_settings\n"
            "from daemon.dispatch import Dispatcher\n"
            "app = Dispatcher(None, load_settings('/tmp/hope-no-such-home')).app  # the Celery app used to send\n"
            "assert app.conf.task_serializer == 'json'\n"
            "assert 'torch' not in sys.modules, 'torch imported'")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          cwd=os.path.dirname(os.path.dirname(__file__)))
    assert proc.returncode == 0, proc.stderr
