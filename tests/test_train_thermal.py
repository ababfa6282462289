"""The thermal governor on a fake thermal-zone file and a fake vcgencmd on PATH: slows, goes hot,
waits (with hysteresis), resumes, and emits an event for every change."""
import logging
import os
import stat

import pytest

from hope_models.train.contract import ControlCommand
from hope_models.train.thermal import ThermalGovernor, parse_temperature, parse_throttled


class FakeTime:
    """A clock that only moves when the governor sleeps, so a 5 s poll takes no time."""

    def __init__(self):
        self.now = 1000.0
        self.sleeps = []
        self.on_sleep = None

    def clock(self):
        return self.now

    def sleep(self, seconds):
        self.sleeps.append(seconds)
        self.now += seconds
        if self.on_sleep:
            self.on_sleep()


@pytest.fixture
def zone(tmp_path):
    path = tmp_path / "temp"

    def write(celsius):
        path.write_text(f"{int(celsius * 1000)}\n")  # millidegrees, as the kernel writes them
    return path, write


def governor(path, fake, events, **kw):
    return ThermalGovernor(path, vcgencmd=None, read_fn=None, sleep_fn=fake.sleep, clock=fake.clock,
                           emit=lambda kind, payload: events.append((kind, payload)),
                           sample_interval_s=0.0, poll_s=5.0, **kw)


def test_60_78_85_72_68_slows_goes_hot_waits_and_resumes_below_70(zone):
    path, write = zone
    fake, events = FakeTime(), []
    gov = governor(path, fake, events)

    write(60)
    a = gov.before_step(0.2)
    assert (a.level, a.sleep_s, a.temp_c) == ("normal", 0.0, 60.0)
    assert events == []

    write(78)  # 3/7 of the way from soft (75) to hard (82): fraction 0.5 * 3/7 of the last step
    a = gov.before_step(0.2)
    assert a.level == "slow"
    assert a.fraction == pytest.approx(0.5 * 3 / 7)
    assert a.sleep_s == pytest.approx(0.2 * 0.5 * 3 / 7)
    assert events[-1][0] == "throttle"
    assert events[-1][1]["event"] == "level" and events[-1][1]["previous"] == "normal"
    assert events[-1][1]["level"] == "slow" and events[-1][1]["temp_c"] == 78.0
    assert gov.before_step(0.1).sleep_s == pytest.approx(0.1 * 0.5 * 3 / 7)  # scales with the step
    assert len(events) == 1  # no event without a change

    write(85)
    a = gov.before_step(0.2)
    assert a.level == "hot" and a.sleep_s == 0.0
    assert events[-1][1]["level"] == "hot" and events[-1][1]["previous"] == "slow"
    assert "hard limit" in events[-1][1]["reason"]

    # The loop now checkpoints and waits. Each poll the "SoC" cools: 85 -> 72 -> 68.
    order = []
    temps = iter([72, 68])
    fake.on_sleep = lambda: write(next(temps))
    why = gov.wait_until_cool(checkpoint_fn=lambda: order.append("checkpoint"),
                              poll_control_fn=lambda: order.append("poll") or ControlCommand())
    assert why == "cool"
    assert order[0] == "checkpoint"  # before any waiting
    assert fake.sleeps == [5.0, 5.0]  # 72 is below hard but not below resume (70): one more poll
    kinds = [p["event"] for _, p in events]
    assert kinds == ["level", "level", "wait_start", "wait_end"]
    start, end = events[2][1], events[3][1]
    assert start["level"] == "hot" and start["temp_c"] == 85.0
    assert end["ended_by"] == "cool" and end["temp_c"] == 68.0
    assert (end["previous"], end["level"]) == ("hot", "normal")  # the wait's end is the level change
    assert end["waited_s"] == pytest.approx(10.0)
    assert gov.level == "normal"

    a = gov.before_step(0.2)
    assert (a.level, a.sleep_s) == ("normal", 0.0)


def test_hysteresis_a_hot_governor_stays_hot_until_below_resume(zone):
    path, write = zone
    fake, events = FakeTime(), []
    gov = governor(path, fake, events)
    write(83)
    assert gov.before_step(0.1).level == "hot"
    for t in (80, 76, 72, 70.0):  # all below hard; none below resume
        write(t)
        assert gov.before_step(0.1).level == "hot", t
    write(69.5)
    assert gov.before_step(0.1).level == "normal"
    assert [p["level"] for _, p in events] == ["hot", "normal"]


def test_control_cancel_or_pause_ends_the_wait_early(zone):
    path, write = zone
    for desired in ("cancel", "pause"):
        fake, events = FakeTime(), []
        gov = governor(path, fake, events)
        write(90)
        assert gov.before_step(0.1).level == "hot"
        polls = iter([ControlCommand(), ControlCommand(desired=desired)])
        assert gov.wait_until_cool(None, lambda: next(polls)) == desired
        assert fake.sleeps == [5.0]  # one poll period, then the control's answer
        assert events[-1][1]["event"] == "wait_end" and events[-1][1]["ended_by"] == desired


def test_missing_or_garbage_zone_file_means_no_reading_logged_once(tmp_path, caplog):
    fake, events = FakeTime(), []
    path = tmp_path / "nope"
    gov = governor(path, fake, events)
    with caplog.at_level(logging.WARNING, logger="hope_models.train.thermal"):
        for _ in range(3):
            a = gov.before_step(0.1)
            assert (a.level, a.temp_c) == ("normal", None)
        assert gov.sample().source == "none"
    assert len([r for r in caplog.records if "not readable" in r.message]) == 1
    path.write_text("garbage\n")
    assert gov.sample().temp_c is None
    path.write_text("61250\n")  # the zone appears: read again
    r = gov.sample()
    assert (r.temp_c, r.source) == (61.25, "thermal_zone")


def test_degrees_and_millidegrees():
    assert parse_temperature("48312\n") == pytest.approx(48.312)
    assert parse_temperature("78") == 78.0
    assert parse_temperature("77.5\n") == 77.5
    with pytest.raises(ValueError):
        parse_temperature("nan")


def test_sampling_is_rate_limited(zone):
    path, write = zone
    fake, events = FakeTime(), []
    gov = ThermalGovernor(path, vcgencmd=None, sleep_fn=fake.sleep, clock=fake.clock, sample_interval_s=1.0)
    write(60)
    assert gov.before_step(0.1).temp_c == 60.0
    write(79)
    assert gov.before_step(0.1).temp_c == 60.0  # same instant: the cached reading
    fake.now += 1.0
    assert gov.before_step(0.1).temp_c == 79.0


@pytest.mark.parametrize("soft,hard,resume", [(82, 82, 70), (80, 75, 70), (75, 82, 76)])
def test_limits_are_checked(soft, hard, resume):
    with pytest.raises(ValueError, match="thermal limits"):
        ThermalGovernor(None, None, soft, hard, resume)


# -- vcgencmd -----------------------------------------------------------------------------------

def fake_vcgencmd(bin_dir, output, exit_code=0):
    """A `vcgencmd` script that records each call and prints `output`."""
    bin_dir.mkdir(exist_ok=True)
    script = bin_dir / "vcgencmd"
    calls = bin_dir / "calls"
    script.write_text(f"#!/bin/sh\necho \"$@\" >> '{calls}'\necho '{output}'\nexit {exit_code}\n")
    script.chmod(script.stat().st_mode | stat.S_IEXEC)
    return calls


def test_parse_throttled_flags():
    f = parse_throttled("throttled=0x50005\n")
    assert f.raw == 0x50005
    assert (f.under_voltage, f.arm_freq_capped, f.throttled, f.soft_temp_limit) == (True, False, True, False)
    assert (f.under_voltage_occurred, f.arm_freq_capped_occurred, f.throttled_occurred,
            f.soft_temp_limit_occurred) == (True, False, True, False)
    assert f.slowing_now
    g = parse_throttled("throttled=0x80008")
    assert g.soft_temp_limit and g.soft_temp_limit_occurred and not g.throttled
    zero = parse_throttled("throttled=0x0")
    assert not zero.slowing_now and not zero.under_voltage
    assert zero.to_json_obj()["raw"] == "0x0"
    for bad in ("temp=48.3'C", "throttled=", "throttled=0xZZ", ""):
        with pytest.raises(ValueError):
            parse_throttled(bad)


def test_vcgencmd_on_path_is_read_and_firmware_throttling_means_slow(tmp_path, zone, monkeypatch):
    path, write = zone
    calls = fake_vcgencmd(tmp_path / "bin", "throttled=0x50005")
    monkeypatch.setenv("PATH", f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}")
    fake, events = FakeTime(), []
    gov = ThermalGovernor(path, "vcgencmd", sleep_fn=fake.sleep, clock=fake.clock, sample_interval_s=0.0,
                          emit=lambda k, p: events.append(p))
    write(60)
    r = gov.sample()
    assert r.source == "thermal_zone+vcgencmd" and r.temp_c == 60.0
    assert r.throttled_flags.under_voltage and r.throttled_flags.throttled
    assert calls.read_text().split("\n")[0] == "get_throttled"
    a = gov.before_step(0.4)  # 60 C, but the firmware says it is throttling right now
    assert a.level == "slow" and a.sleep_s == pytest.approx(0.4 * 0.25)
    assert events[-1]["reason"] == "firmware reports throttling"
    assert events[-1]["throttled"]["raw"] == "0x50005"


def test_a_failing_vcgencmd_is_asked_once(tmp_path, zone, monkeypatch, caplog):
    path, write = zone
    calls = fake_vcgencmd(tmp_path / "bin", "VCHI initialization failed", exit_code=255)
    monkeypatch.setenv("PATH", f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}")
    gov = ThermalGovernor(path, "vcgencmd", sample_interval_s=0.0)
    write(50)
    with caplog.at_level(logging.WARNING, logger="hope_models.train.thermal"):
        for _ in range(4):
            r = gov.sample()
            assert r.throttled_flags is None and r.temp_c == 50.0
    assert calls.read_text().count("get_throttled") == 1
    assert len([m for m in caplog.messages if "get_throttled failed" in m]) == 1


def test_no_vcgencmd_on_path(tmp_path, zone, monkeypatch):
    path, write = zone
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    gov = ThermalGovernor(path, "vcgencmd", sample_interval_s=0.0)
    write(50)
    r = gov.sample()
    assert r.throttled_flags is None and r.source == "thermal_zone"


def test_slow_ends_a_degree_below_the_soft_limit(zone):
    path, write = zone
    fake, events = FakeTime(), []
    gov = governor(path, fake, events)
    write(76)
    assert gov.before_step(0.1).level == "slow"
    write(74.5)  # under soft, but within the 1 C band: no flapping at the limit
    a = gov.before_step(0.1)
    assert a.level == "slow" and a.sleep_s == 0.0
    write(73.9)
    assert gov.before_step(0.1).level == "normal"
    assert [p["level"] for _, p in events] == ["slow", "normal"]
