"""Clock choice and unit detection (timestamps.py), on generated steps and on the real samples."""
from __future__ import annotations

from pathlib import Path

import pytest

from hope_models.rlds.discover import read_path
from hope_models.rlds.episode import Episode, Step
from hope_models.rlds.timestamps import assign_timestamps

T0_NS = 1_764_952_865_006_200_430  # > 2**53


def episode(steps: list[dict]) -> Episode:
    """Steps given as {"extras": {...}, "robot_state": {...}, "step_metadata": {...}}."""
    built = [Step(observation={"robot_state": s["robot_state"]} if "robot_state" in s else {},
                  action={}, step_metadata=dict(s.get("step_metadata", {})), extras=dict(s.get("extras", {})))
             for s in steps]
    return Episode("t", {}, built, "/gen/t", "single_json")


def run(steps: list[dict]) -> tuple[Episode, str | None, list[int | None]]:
    ep = episode(steps)
    clock = assign_timestamps(ep)
    return ep, clock, [s.timestamp_ns for s in ep.steps]


def unit_warnings(ep: Episode) -> list[str]:
    return [str(p) for p in ep.warnings if "holds" in p.message]


def test_epoch_ns_beyond_2_53_stays_exact():
    ep, clock, ts = run([{"extras": {"timestamp_ns": T0_NS + i * 50_000_000}} for i in range(4)])
    assert clock == "timestamp_ns"
    assert ts == [T0_NS + i * 50_000_000 for i in range(4)]
    assert all(type(t) is int for t in ts) and ep.problems == []


def test_microsecond_and_nanosecond_relative_clocks():
    _, clock, ts = run([{"extras": {"timestamp_us": i * 20_000}} for i in range(5)])
    assert clock == "timestamp_us" and ts == [i * 20_000_000 for i in range(5)]
    _, clock, ts = run([{"extras": {"timestamp_ns": i * 20_000_000}} for i in range(5)])
    assert clock == "timestamp_ns" and ts == [i * 20_000_000 for i in range(5)]
    # a field named micros that holds nanoseconds: 50 Hz is only plausible as ns
    ep, clock, ts = run([{"extras": {"timestamp_micros": i * 20_000_000}} for i in range(5)])
    assert ts == [i * 20_000_000 for i in range(5)]
    [w] = unit_warnings(ep)
    assert "field named micros holds nanoseconds" in w and "timestamp_micros" in w


def test_wall_millis_holding_unix_seconds_is_read_and_reported():
    steps = [{"robot_state": {"wall_time_millis": 1_733_790_000 + i}} for i in range(3)]
    ep, clock, ts = run(steps)
    assert clock == "observation.robot_state.wall_time_millis"
    assert ts == [(1_733_790_000 + i) * 10**9 for i in range(3)]
    [w] = unit_warnings(ep)
    assert "field named millis holds seconds" in w


def test_epoch_millis_in_millis_field_no_warning():
    ep, _, ts = run([{"robot_state": {"wall_time_millis": 1_764_952_865_006 + 100 * i}} for i in range(3)])
    assert ts == [(1_764_952_865_006 + 100 * i) * 1_000_000 for i in range(3)]
    assert ep.problems == []


def test_monotonic_nanos_that_look_like_epoch_millis_stay_nanos():
    # 1 h of uptime in ns has the magnitude of epoch ms; a 20 ms period says ns
    base = 3_600_000_000_000
    ep, _, ts = run([{"robot_state": {"timestamp_nanos": base + i * 20_000_000}} for i in range(5)])
    assert ts == [base + i * 20_000_000 for i in range(5)]
    assert unit_warnings(ep) == []


def test_seconds_as_strings_and_floats_convert_exactly():
    _, clock, ts = run([{"step_metadata": {"timestamp": s}} for s in ("1765843752.8017461", "1765843752.9017461")])
    assert clock == "step_metadata.timestamp"
    assert ts == [1765843752801746100, 1765843752901746100]
    _, _, ts = run([{"extras": {"timestamp": t}} for t in (0.0, 0.05, 0.1)])
    assert ts == [0, 50_000_000, 100_000_000]  # float seconds, no binary rounding error


def test_clock_order_and_constant_clock_skipped():
    steps = [{"extras": {"timestamp_ms": 7, "timestamp_micros": i * 100_000},
              "robot_state": {"timestamp_nanos": i * 100_000_000}} for i in range(3)]
    ep, clock, ts = run(steps)
    assert clock == "timestamp_micros"  # timestamp_ms is constant, so the next clock in order wins
    assert ts == [0, 100_000_000, 200_000_000]

    ep, clock, ts = run([{"extras": {"timestamp_ms": 7}} for _ in range(3)])
    assert clock == "timestamp_ms" and ts == [7_000_000] * 3
    assert any("constant" in p.message for p in ep.warnings)


def test_partial_and_missing_clocks():
    ep, clock, ts = run([{"extras": {"timestamp_ns": 0}}, {}, {"extras": {"timestamp_ns": 200_000_000}}])
    assert clock is None and ts == [None, None, None]
    [w] = ep.warnings
    assert "no clock on every step" in w.message and "timestamp_ns (2 of 3 steps)" in w.message

    ep, clock, ts = run([{"extras": {"timestamp_ns": "soon"}}, {"extras": {"timestamp_ns": float("nan")}}])
    assert clock is None and ts == [None, None]


def test_single_step_uses_the_name_unit():
    _, clock, ts = run([{"extras": {"timestamp_micros": 0}}])
    assert clock == "timestamp_micros" and ts == [0]
    ep, _, ts = run([{"extras": {"timestamp": 12.5}}])
    assert ts == [12_500_000_000]
    assert any("assumed seconds" in p.message for p in ep.warnings)


def test_canonical_mode_takes_timestamp_ns_as_written():
    # 100 s between steps would be implausible for detection; canonical files are ns by definition
    ep = episode([{"extras": {"timestamp_ns": i * 100 * 10**9}} for i in range(3)])
    assert assign_timestamps(ep, canonical=True) == "timestamp_ns"
    assert [s.timestamp_ns for s in ep.steps] == [0, 100 * 10**9, 200 * 10**9]
    assert all("timestamp_ns" not in s.extras for s in ep.steps)


# -- the real samples ---------------------------------------------------------------------------

@pytest.mark.parametrize("rel, expected", [
    ("history/continuonbrain/rlds/episodes/follow_user_mr_v2", [0, 100_000_000, 200_000_000]),
    ("history/continuonbrain/rlds/episodes/stack_boxes_vr", [0]),
    ("history/older_versions/pi5_follow_synthetic.v0_cd87ff1.json", [i * 100_000_000 for i in range(5)]),
    ("continuonbrain/rlds/tfrecord_raw/sample_pi5_mock.tfrecord", [1_000_000, 2_000_000]),
    ("continuonbrain/rlds/tfrecord_raw/studio_mock_editor.tfrecord",
     [1764952865006200430, 1764952865056200430, 1764952865106200430]),
])
def test_sample_clocks(samples_dir: Path, rel: str, expected: list[int]):
    [report] = read_path(samples_dir / rel)
    [ep] = report.episodes
    assert [s.timestamp_ns for s in ep.steps] == expected


def test_sample_pi5_mock_seconds_in_millis_warning(samples_dir: Path):
    [report] = read_path(samples_dir / "continuonbrain/rlds/tfrecord_raw/sample_pi5_mock.tfrecord")
    [ep] = report.episodes
    [w] = unit_warnings(ep)
    assert w.endswith("read as seconds") and "field named millis holds seconds" in w
    assert "observation.robot_state.wall_time_millis" in w


def test_sample_without_any_clock(samples_dir: Path):
    [report] = read_path(samples_dir / "continuonbrain/rlds/tfrecord_raw/pi5_follow_synthetic.tfrecord")
    [ep] = report.episodes
    assert [s.timestamp_ns for s in ep.steps] == [None] * 5
    assert any("no clock on every step" in p.message for p in ep.warnings)
