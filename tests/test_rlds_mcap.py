"""The MCAP episode container: write then read equals, Foxglove-facing shape, damaged files."""
from __future__ import annotations

import json
from pathlib import Path

from mcap.reader import make_reader

from hope_models.rlds.discover import read_path
from hope_models.rlds.episode import ERROR, Episode, Step
from hope_models.rlds.read_mcap import read_mcap
from hope_models.rlds.write_mcap import METADATA_TOPIC, STEPS_TOPIC, write_episode_mcap


def make_episode(n: int = 4, with_clock: bool = True) -> Episode:
    steps = [Step(observation={"robot_state": {"joint_positions": [0.1 * i, -0.2]}, "video_frame_id": f"f{i}"},
                  action={"command": [0.3, 0.1 * i], "source": "human_teleop_xr"}, reward=0.5 * i,
                  is_terminal=i == n - 1, step_metadata={"note": "é"} if i % 2 else {},
                  timestamp_ns=(1764952865006200430 + i * 50_000_000) if with_clock else None,
                  extras={"language_instruction": "stack"} if i == 0 else {})
             for i in range(n)]
    metadata = {"schema_version": "1.1", "episode_id": "ep_mcap", "xr_mode": "trainer", "tags": ["a"],
                "provenance": {"origin": "import:single_json"}}
    return Episode("ep_mcap", metadata, steps, "/src/ep.json", "single_json", steps_lost=2, blob_root="/src")


def test_round_trip_equals(tmp_path: Path):
    src = make_episode()
    path = write_episode_mcap(src, tmp_path / "out" / "ep_mcap.mcap")
    assert not (tmp_path / "out" / "ep_mcap.mcap.partial").exists()
    [report] = read_path(path)
    [ep] = report.episodes
    assert ep.layout == "mcap" and ep.source == str(path)
    assert ep.episode_id == src.episode_id and ep.metadata == src.metadata
    assert ep.steps == src.steps
    assert ep.steps_lost == 2 and ep.blob_root == "/src"
    assert ep.problems == []


def test_round_trip_without_clock(tmp_path: Path):
    src = make_episode(3, with_clock=False)
    [ep] = read_mcap(write_episode_mcap(src, tmp_path / "noclock.mcap")).episodes
    assert [s.timestamp_ns for s in ep.steps] == [None] * 3
    assert ep.steps == src.steps
    assert any("no step has timestamp_ns" in p.message for p in ep.warnings)


def test_real_sample_round_trip(tmp_path: Path, samples_dir: Path):
    [report] = read_path(samples_dir / "history/continuonbrain/rlds/episodes/studio_mock_editor.json")
    [src] = report.episodes
    [ep] = read_mcap(write_episode_mcap(src, tmp_path / "studio.mcap")).episodes
    assert ep.metadata == src.metadata and ep.steps == src.steps


def test_foxglove_shape(tmp_path: Path):
    src = make_episode()
    path = write_episode_mcap(src, tmp_path / "fox.mcap")
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        for schema in summary.schemas.values():
            assert json.loads(schema.data)["type"] == "object"
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == {METADATA_TOPIC, STEPS_TOPIC}
        assert all(c.message_encoding == "json" for c in channels.values())
        steps = [(m.log_time, json.loads(m.data)) for _, c, m in reader.iter_messages(topics=[STEPS_TOPIC])]
    assert [t for t, _ in steps] == [s.timestamp_ns for s in src.steps]  # log_time is the step time
    assert [obj["step_index"] for _, obj in steps] == list(range(len(src.steps)))


def test_truncated_file_keeps_earlier_steps(tmp_path: Path):
    src = make_episode(40)
    for step in src.steps:  # ~20 KB a step: the file spans several 256 KiB chunks
        step.observation["pad"] = "x" * 20_000
    path = write_episode_mcap(src, tmp_path / "full.mcap")
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])  # a crash mid-write: no footer, a partial chunk
    [report] = read_path(cut)
    [ep] = report.episodes
    assert 0 < len(ep.steps) < 40
    assert ep.steps == src.steps[: len(ep.steps)]
    assert any("ends early or is damaged" in p.message for p in ep.warnings)

    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(data[:5])
    [report] = read_path(garbage)
    assert report.episodes == [] and any(p.severity == ERROR for p in report.problems)


def test_not_an_episode_mcap(tmp_path: Path):
    from mcap.writer import Writer
    path = tmp_path / "other.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema(name="x", encoding="jsonschema", data=b"{}")
        cid = w.register_channel(topic="/camera", message_encoding="json", schema_id=sid)
        w.add_message(cid, log_time=1, publish_time=1, data=b"{}")
        w.finish()
    [report] = read_path(path)
    assert report.episodes == []
    assert any(p.severity == ERROR and "not an episode MCAP" in p.message for p in report.problems)
