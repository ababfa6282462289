"""TFRecord framing, gzip detection, corruption recovery and the tf.train.Example codec, on the
real samples and on generated files."""
from __future__ import annotations

import gzip
import json
import struct
from pathlib import Path

import pytest

from hope_models.rlds.discover import read_path
from hope_models.rlds.episode import ERROR, WARNING, Episode, Step
from hope_models.rlds.read_tfrecord import read_tfrecord
from hope_models.rlds.tf_example import (BYTES, FLOAT, INT64, ExampleDecodeError, Feature, decode_example,
                                         encode_example, float32_value)
from hope_models.rlds.write_tfrecord import episode_to_examples, frame_record, write_tfrecord

RAW = "continuonbrain/rlds/tfrecord_raw"
DAMAGED = "continuonbrain/rlds/tfrecord"


def one(path: Path) -> Episode:
    [report] = read_path(path)
    [ep] = report.episodes
    return ep


def example(eid: str, i: int, **extra) -> dict:
    feats = {"episode_id": eid, "step_index": i, "reward": 0.0, "is_terminal": 0,
             "observation": json.dumps({"robot_state": {"joint_positions": [0.1 * i, 0.0]}}),
             "action": json.dumps({"command": [0.5, -0.25]}), "timestamp_ns": i * 100_000_000}
    feats.update(extra)
    return feats


# -- real samples -------------------------------------------------------------------------------

@pytest.mark.parametrize("name, have, total, cut", [
    ("pi5_follow_synthetic", 4, 5, 50),
    ("sample_pi5_mock", 1, 2, 45),
    ("studio_mock_editor", 2, 3, 48),
])
def test_damaged_gzip_samples_are_recovered(samples_dir: Path, name: str, have: int, total: int, cut: int):
    ep = one(samples_dir / DAMAGED / f"{name}.tfrecord.gz")
    assert len(ep.steps) == have and ep.steps_lost == 1
    assert [s.extras["source_step_index"] for s in ep.steps] == list(range(1, total))
    msgs = [p.message for p in ep.warnings]
    assert any(f"gzip data ends at byte {cut}" in m and "read as uncompressed TFRecord" in m for m in msgs)
    assert any("1 corrupt region(s)" in m and f"steps 0 missing (recovered {have} of {total} by step_index)" in m
               for m in msgs)
    assert ep.errors == []


def test_damaged_samples_match_the_intact_files(samples_dir: Path):
    for name in ("sample_pi5_mock", "studio_mock_editor"):
        damaged = one(samples_dir / DAMAGED / f"{name}.tfrecord.gz")
        intact = one(samples_dir / RAW / f"{name}.tfrecord")
        for got, want in zip(damaged.steps, intact.steps[1:]):
            assert got.observation == want.observation and got.action == want.action
            assert got.timestamp_ns == want.timestamp_ns and got.is_terminal == want.is_terminal
    # the damaged pi5 file comes from the newer JSON: 2-float commands, no terminal flag
    pi5 = one(samples_dir / DAMAGED / "pi5_follow_synthetic.tfrecord.gz")
    assert all(len(s.action["command"]) == 2 for s in pi5.steps)
    assert not any(s.is_terminal for s in pi5.steps)


def test_intact_raw_samples(samples_dir: Path):
    pi5 = one(samples_dir / RAW / "pi5_follow_synthetic.tfrecord")
    assert len(pi5.steps) == 5 and pi5.layout == "tfrecord" and pi5.episode_id == "pi5_follow_synthetic"
    assert "command" not in pi5.steps[0].action  # empty action_command adds nothing
    assert pi5.steps[0].step_metadata == {"human_distance_m": 3.5, "human_visible": True}

    mock = one(samples_dir / RAW / "sample_pi5_mock.tfrecord")
    assert len(mock.steps) == 2 and [s.is_terminal for s in mock.steps] == [False, True]
    assert mock.steps[0].step_metadata == {}
    assert len(mock.steps[0].observation["robot_state"]["joint_positions"]) == 3
    assert mock.steps[0].action["command"] == [0.2, 0.1]  # JSON value; the float32 copy agrees
    assert not any("disagrees" in p.message for p in mock.problems)

    studio = one(samples_dir / RAW / "studio_mock_editor.tfrecord")
    assert len(studio.steps) == 3 and all(len(s.action["command"]) == 6 for s in studio.steps)


def test_vlm_sample(samples_dir: Path):
    [report] = read_path(samples_dir / "rlds/vlm_tfrecord/vlm_data.tfrecord")
    assert [e.episode_id for e in report.episodes] == [f"vlm_{i}" for i in range(20)]
    for ep in report.episodes:
        assert ep.source.endswith(f"vlm_data.tfrecord#{ep.episode_id}")
        [step] = ep.steps
        image = step.observation["image_rgb"]
        assert len(image) == 12288 and all(0.0 <= v <= 1.0 for v in image)
        assert step.observation["robot_state"]["joint_positions"] == [0.0] * 7
        assert step.action == {"command": [0.0] * 32, "text": ""}
        assert step.step_metadata == {} and step.is_terminal is True
        assert step.extras["is_first"] == 1 and step.extras["is_last"] == 1 and step.extras["discount"] == 1.0


def test_wiki_sample(samples_dir: Path):
    [report] = read_path(samples_dir / "rlds/wiki_tfrecord/wiki_data.tfrecord")
    assert [e.episode_id for e in report.episodes] == [str(i) for i in range(50)]
    for ep in report.episodes:
        [step] = ep.steps
        assert len(step.observation["robot_state"]["joint_positions"]) == 128
        assert len(step.action["command"]) == 32
        text = step.step_metadata["text"]
        assert set(step.step_metadata) == {"text"} and 0 < len(text) <= 200


@pytest.mark.parametrize("name", ["test.tfrecord", "test_gzip.tfrecord"])
def test_empty_samples_hold_zero_records(samples_dir: Path, name: str):
    [report] = read_path(samples_dir / "history/repo_root" / name)
    assert report.skipped and report.episodes == [] and report.skip_reason == "no records"
    [p] = report.problems
    assert p.severity == WARNING and "no records" in p.message


# -- generated files ----------------------------------------------------------------------------

def test_write_read_round_trip_and_gzip_by_magic(tmp_path: Path):
    plain = write_tfrecord(tmp_path / "a.tfrecord", [example("ep", i) for i in range(3)])
    zipped = write_tfrecord(tmp_path / "b.tfrecord", [example("ep", i) for i in range(3)], gzip=True)
    assert zipped.read_bytes()[:2] == b"\x1f\x8b"  # gzip, though the name says nothing
    for path in (plain, zipped):
        ep = one(path)
        assert [s.timestamp_ns for s in ep.steps] == [0, 100_000_000, 200_000_000]
        assert ep.steps[1].observation == {"robot_state": {"joint_positions": [0.1, 0.0]}}
        assert ep.problems == []


def test_episode_to_examples_round_trip(tmp_path: Path):
    steps = [Step(observation={"robot_state": {"joint_positions": [0.25 * i]}}, action={"command": [0.1, 0.2]},
                  reward=0.5, is_terminal=i == 1, step_metadata={"k": "v"}, timestamp_ns=1764952865006200430 + i)
             for i in range(2)]
    src = Episode("rt", {}, steps, "/gen", "single_json")
    ep = one(write_tfrecord(tmp_path / "rt.tfrecord", episode_to_examples(src)))
    assert ep.episode_id == "rt"
    for got, want in zip(ep.steps, steps):
        assert (got.observation, got.action, got.reward, got.is_terminal, got.step_metadata, got.timestamp_ns) == \
            (want.observation, want.action, want.reward, want.is_terminal, want.step_metadata, want.timestamp_ns)


def test_empty_file_and_empty_gzip_stream(tmp_path: Path):
    empty = tmp_path / "none.tfrecord"
    empty.write_bytes(b"")
    gz = tmp_path / "none.tfrecord.gz"
    gz.write_bytes(gzip.compress(b""))
    for path in (empty, gz):
        r = read_tfrecord(path)
        assert r.skipped and r.episodes == [] and not any(p.severity == ERROR for p in r.problems)


def test_concatenated_gzip_members(tmp_path: Path):
    a = b"".join(frame_record(encode_example(example("ep", i))) for i in range(2))
    b = b"".join(frame_record(encode_example(example("ep", i))) for i in range(2, 4))
    path = tmp_path / "multi.tfrecord.gz"
    path.write_bytes(gzip.compress(a) + gzip.compress(b))
    ep = one(path)
    assert len(ep.steps) == 4 and ep.problems == []


def test_corrupt_payload_crc_in_middle_record_resyncs(tmp_path: Path):
    records = [frame_record(encode_example(example("ep", i))) for i in range(5)]
    damaged = bytearray(records[2])
    damaged[20] ^= 0xFF  # a payload byte: the payload CRC no longer matches
    path = tmp_path / "mid.tfrecord"
    path.write_bytes(b"".join(records[:2]) + bytes(damaged) + b"".join(records[3:]))
    ep = one(path)
    assert [s.extras.get("source_step_index", i) for i, s in enumerate(ep.steps)] == [0, 1, 3, 4]
    assert ep.steps_lost == 1
    offset = len(records[0]) + len(records[1])
    [w] = [p.message for p in ep.warnings if "corrupt region" in p.message]
    assert f"{len(damaged)} bytes at byte {offset}" in w
    assert "steps 2 missing (recovered 4 of 5 by step_index)" in w


def test_corrupt_length_header_and_truncated_tail(tmp_path: Path):
    records = [frame_record(encode_example(example("ep", i))) for i in range(4)]
    bad_header = bytearray(records[1])
    bad_header[9] ^= 0x01  # the length CRC
    body = records[0] + bytes(bad_header) + records[2] + records[3][:-7]  # last record cut short
    path = tmp_path / "hdr.tfrecord"
    path.write_bytes(body)
    ep = one(path)
    assert len(ep.steps) == 2 and ep.steps_lost == 1  # step 1 provably lost; step 3 is a trailing loss
    msgs = [p.message for p in ep.warnings]
    assert any("steps 1 missing (recovered 2 of 3 by step_index)" in m for m in msgs)
    assert any("last record of the file is truncated" in m for m in msgs)


def test_only_garbage_is_an_error(tmp_path: Path):
    path = tmp_path / "junk.tfrecord"
    path.write_bytes(b"\x00\x01garbage bytes that hold no record at all" * 3)
    [r] = read_path(path)
    assert r.episodes == [] and not r.skipped
    assert any(p.severity == ERROR and "no valid record" in p.message for p in r.problems)


def test_valid_frame_with_non_example_payload(tmp_path: Path):
    path = write_tfrecord(tmp_path / "np.tfrecord",
                          [example("ep", 0), b"\x0f\xff\xff", example("ep", 1)])
    ep = one(path)
    assert len(ep.steps) == 2
    assert any("not a tf.train.Example" in p.message for p in ep.warnings)


def test_grouping_ordering_and_command_copies(tmp_path: Path):
    order = [("b", 2), ("a", 1), ("b", 0), ("a", 0), ("b", 1)]
    rows = []
    for eid, i in order:
        extra = {}
        if eid == "a" and i == 1:
            extra["action_command"] = [0.5, 0.75]  # disagrees with the JSON command [0.5, -0.25]
        if eid == "b":
            extra["action"] = json.dumps({"source": "vla_policy"})
            extra["action_command"] = [0.1, 0.2]  # the JSON has no command: the copy fills it
        extra["custom_flag"] = 7
        rows.append(example(eid, i, **extra))
    [report] = read_path(write_tfrecord(tmp_path / "mix.tfrecord", rows))
    a, b = sorted(report.episodes, key=lambda e: e.episode_id)
    assert [s.timestamp_ns for s in b.steps] == [0, 100_000_000, 200_000_000]  # ordered by step_index
    assert [s.action["command"] for s in b.steps] == [[0.1, 0.2]] * 3
    assert a.steps[1].action["command"] == [0.5, -0.25]  # JSON wins
    [w] = [p for p in a.warnings if "disagrees" in p.message]
    assert w.step == 1 and w.field == "action.command"
    assert all(s.extras["custom_flag"] == 7 for s in a.steps + b.steps)
    assert a.source.endswith("mix.tfrecord#a")


def test_missing_episode_id_uses_file_name_and_bad_json_is_an_error(tmp_path: Path):
    rows = [{"step_index": 0, "observation": "{not json", "action": json.dumps({}), "timestamp_ms": 0},
            {"step_index": 1, "observation": json.dumps({}), "action": json.dumps({}), "timestamp_ms": 50}]
    ep = one(write_tfrecord(tmp_path / "nameless.tfrecord", rows))
    assert ep.episode_id == "nameless" and len(ep.steps) == 2
    [e] = ep.errors
    assert e.step == 0 and e.field == "observation" and "not valid JSON" in e.message
    assert [s.timestamp_ns for s in ep.steps] == [0, 50_000_000]


# -- the Example codec ----------------------------------------------------------------------------

def _varint(v: int) -> bytes:
    out = bytearray()
    while True:
        b, v = v & 0x7F, v >> 7
        out.append(b | (0x80 if v else 0))
        if not v:
            return bytes(out)


def _ld(field: int, data: bytes) -> bytes:
    return _varint(field << 3 | 2) + _varint(len(data)) + data


def test_decode_unpacked_repeated_scalars_written_by_hand():
    # FloatList with unpacked fixed32 values and Int64List with unpacked varints (incl. -1)
    floats = b"".join(_varint(1 << 3 | 5) + struct.pack("<f", v) for v in (1.5, -2.0))
    ints = b"".join(_varint(1 << 3 | 0) + _varint(v) for v in (3, (1 << 64) - 1))
    feature_map = (_ld(1, _ld(1, b"f") + _ld(2, _ld(2, floats)))
                   + _ld(1, _ld(1, b"i") + _ld(2, _ld(3, ints)))
                   + _ld(1, _ld(1, b"s") + _ld(2, _ld(1, _ld(1, b"abc") + _ld(1, b"")))))
    decoded = decode_example(_ld(1, feature_map))
    assert decoded == {"f": Feature(FLOAT, [1.5, -2.0]), "i": Feature(INT64, [3, -1]),
                       "s": Feature(BYTES, [b"abc", b""])}


def test_encode_decode_round_trip_and_errors():
    feats = {"b": [b"x", "y"], "i": [-5, 2**40], "f": [0.25], "empty": Feature(FLOAT, [])}
    decoded = decode_example(encode_example(feats))
    assert decoded["b"] == Feature(BYTES, [b"x", b"y"])
    assert decoded["i"] == Feature(INT64, [-5, 2**40])
    assert decoded["f"] == Feature(FLOAT, [0.25]) and decoded["empty"] == Feature(FLOAT, [])
    with pytest.raises(ExampleDecodeError):
        decode_example(b"\x0a\x05\x0a\x03")  # runs past the end
    with pytest.raises(TypeError):
        encode_example({"bad": [object()]})
    assert float32_value(struct.unpack("<f", struct.pack("<f", 0.05))[0]) == 0.05


def test_only_unusable_records_is_an_error(tmp_path: Path):
    not_examples = write_tfrecord(tmp_path / "np_only.tfrecord", [b"\x0f\xff\xff"])
    cut = tmp_path / "cut_only.tfrecord"
    cut.write_bytes(frame_record(encode_example(example("ep", 0)))[:-3])
    for path in (not_examples, cut):
        [r] = read_path(path)
        assert r.episodes == [] and not r.skipped
        assert any(p.severity == ERROR and "no valid record found" in p.message for p in r.problems)
