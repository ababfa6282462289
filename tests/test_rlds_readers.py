"""Readers on the real Continuon samples (expected outcomes from continuon/README.md) and on
generated files for each layout: episode dirs, single JSON, steps-only JSONL, discovery."""
from __future__ import annotations

import json
import math
from pathlib import Path


from hope_models.rlds.discover import read_path, read_paths
from hope_models.rlds.episode import ERROR, WARNING, Episode, SourceReport, Step
from hope_models.rlds.read_single_json import read_single_json
from hope_models.rlds.read_steps_jsonl import read_steps_jsonl

AUTO = "brain_config/rlds/autonomous_learning"
HIST = "history/continuonbrain/rlds/episodes"
OLD = "history/older_versions"
AUTO_WITH_STEPS = {"autonomous_learning_1765843752_25216cc2", "autonomous_learning_1765854529_a94a458e",
                   "autonomous_learning_1765939335_7cada579"}


def only_episode(reports: list[SourceReport]) -> Episode:
    assert len(reports) == 1, [r.source for r in reports]
    assert len(reports[0].episodes) == 1, reports[0].problems
    return reports[0].episodes[0]


def messages(problems, severity=None) -> list[str]:
    return [str(p) for p in problems if severity is None or p.severity == severity]


# -- real samples: episode dirs ------------------------------------------------------------------

def test_autonomous_learning_three_episodes_sixteen_skipped(samples_dir: Path):
    reports = read_path(samples_dir / AUTO)
    assert len(reports) == 19
    skipped = [r for r in reports if r.skipped]
    read = [r for r in reports if not r.skipped]
    assert len(skipped) == 16
    for r in skipped:
        assert r.episodes == [] and r.skip_reason
        assert any(p.severity == WARNING and "without steps" in p.message for p in r.problems)
    assert {Path(r.source).name for r in read} == AUTO_WITH_STEPS
    for r in read:
        ep = only_episode([r])
        assert ep.layout == "episode_dir"
        assert ep.episode_id == Path(r.source).name  # derived from the dir name
        assert len(ep.steps) == 1
        md = ep.metadata
        assert md["schema_version"] == "1.1" and md["source_schema_version"] == "1.0"
        assert md["xr_mode"] == "autonomous"  # open enum kept as written
        assert md["provenance"]["origin"] == "import:episode_dir"
        step = ep.steps[0]
        assert step.action == {"kind": "autonomous_learning_tick"}
        assert step.step_metadata["is_stable"] == "True"
        # the only clock is step_metadata.timestamp, Unix seconds as a string: converted exactly
        ts_text = step.step_metadata["timestamp"]
        whole, frac = ts_text.split(".")
        assert step.timestamp_ns == int(whole) * 10**9 + int(frac.ljust(9, "0")[:9])
        assert ep.errors == []


def test_legacy_wrapped_metadata_dirs(samples_dir: Path):
    expected = {"follow_user_mr_v1": ("follow_user_mr_v1", 2, "mixed_reality", "pilot"),
                "follow_user_mr_v2": ("follow_user_mr_v2", 3, "mixed_reality", "pilot"),
                "stack_boxes_vr": ("stack_boxes_vr_001", 1, "virtual_reality", "copilot")}
    for dirname, (eid, n, xr_mode, role) in expected.items():
        ep = only_episode(read_path(samples_dir / HIST / dirname))
        assert ep.episode_id == eid  # metadata's own id wins over the dir name
        assert len(ep.steps) == n
        md = ep.metadata
        assert md["xr_mode"] == xr_mode and md["control_role"] == role  # lifted from continuon{}
        assert "xr_mode" not in md["continuon"] and "quality_flags" in md["continuon"]
        assert "episode_metadata" not in md
        assert md["tags"] and all(isinstance(t, str) for t in md["tags"])
        assert md["source_schema_version"] == "1.0"
        # legacy timestamp_micros at 10 Hz
        assert [s.timestamp_ns for s in ep.steps] == [i * 100_000_000 for i in range(n)]
        assert all(s.is_terminal is False for s in ep.steps)  # no is_terminal key: default
        assert "pose" in ep.steps[0].observation


def test_episode_dir_reads_all_step_files_and_bad_metadata(tmp_path: Path):
    d = tmp_path / "ep_a"
    (d / "steps").mkdir(parents=True)
    (d / "metadata.json").write_text(json.dumps({"xr_mode": "trainer"}))
    (d / "steps" / "000001.jsonl").write_text('{"timestamp_ms": 100, "observation": {}, "action": {}}\n')
    (d / "steps" / "000000.jsonl").write_text('{"timestamp_ms": 0, "observation": {}, "action": {}}\n')
    (d / "steps" / "notes.txt").write_text("not steps")
    ep = only_episode(read_path(d))
    assert [s.timestamp_ns for s in ep.steps] == [0, 100_000_000]  # lexical file order

    bad = tmp_path / "ep_bad"
    (bad / "steps").mkdir(parents=True)
    (bad / "metadata.json").write_text("{not json")
    (bad / "steps" / "000000.jsonl").write_text('{"observation": {}, "action": {}}\n')
    [report] = read_path(bad)
    assert report.episodes == []
    assert any(p.severity == ERROR and "metadata.json" in p.source and "not valid JSON" in p.message
               for p in report.problems)


def test_legacy_top_level_steps_jsonl_and_missing_metadata(tmp_path: Path):
    legacy = tmp_path / "legacy_ep"
    legacy.mkdir()
    (legacy / "metadata.json").write_text("{}")
    (legacy / "steps.jsonl").write_text('{"timestamp_micros": 0, "observation": {}, "action": {}}\n'
                                        '{"timestamp_micros": 50000, "observation": {}, "action": {}}\n')
    ep = only_episode(read_path(legacy))
    assert ep.episode_id == "legacy_ep" and len(ep.steps) == 2
    assert ep.steps[1].timestamp_ns == 50_000_000

    no_meta = tmp_path / "no_meta"
    (no_meta / "steps").mkdir(parents=True)
    (no_meta / "steps" / "000000.jsonl").write_text('{"observation": {}, "action": {}}\n')
    ep = only_episode(read_path(no_meta))
    assert ep.episode_id == "no_meta"
    assert any("no metadata.json" in p.message for p in ep.warnings)


# -- real samples: single JSON -------------------------------------------------------------------

def test_pi5_follow_synthetic_json(samples_dir: Path):
    ep = only_episode(read_path(samples_dir / HIST / "pi5_follow_synthetic.json"))
    assert ep.layout == "single_json" and ep.episode_id == "pi5_follow_synthetic"
    assert len(ep.steps) == 5
    # robot_state.timestamp_nanos 0..4e8: relative, 10 Hz
    assert [s.timestamp_ns for s in ep.steps] == [i * 100_000_000 for i in range(5)]
    assert all(len(s.action["command"]) == 2 for s in ep.steps)
    assert ep.steps[0].action["source"] == "human_teleop_xr"
    assert not any(s.is_terminal for s in ep.steps)
    rs = ep.steps[0].observation["robot_state"]
    assert rs["frame_id"] == "base_link" and rs["joint_efforts"] == []
    assert ep.metadata["software"]["glove_firmware"] == "absent"
    assert ep.errors == [] and ep.warnings == []


def test_studio_mock_editor_json_epoch_ns_20hz(samples_dir: Path):
    path = samples_dir / HIST / "studio_mock_editor.json"
    ep = only_episode(read_path(path))
    raw = json.loads(path.read_text())
    expected = [s["observation"]["robot_state"]["timestamp_nanos"] for s in raw["steps"]]
    got = [s.timestamp_ns for s in ep.steps]
    assert got == expected and all(type(t) is int for t in got)  # exact, beyond 2**53
    assert got[0] > 2**53
    assert [b - a for a, b in zip(got, got[1:])] == [50_000_000, 50_000_000]  # 20 Hz
    assert [s.is_terminal for s in ep.steps] == [False, False, True]
    assert len(ep.steps[0].action["command"]) == 6
    assert ep.metadata["xr_mode"] == "workstation"
    assert ep.warnings == [] and ep.errors == []


def test_older_versions_wrapped_metadata(samples_dir: Path):
    v0 = only_episode(read_path(samples_dir / OLD / "pi5_follow_synthetic.v0_cd87ff1.json"))
    assert v0.episode_id == "synthetic_pi5_follow_0001"
    assert v0.metadata["camera"]["fps"] == 30  # unknown keys kept
    assert len(v0.steps) == 5
    assert [s.timestamp_ns for s in v0.steps] == [i * 100_000_000 for i in range(5)]
    assert v0.steps[0].step_metadata == {"human_visible": True, "human_distance_m": 3.5}
    assert v0.steps[0].action == {"steering": 0.05, "throttle": 0.1}

    mock = only_episode(read_path(samples_dir / OLD / "studio_mock_editor.v0_e8eab17.json"))
    assert mock.episode_id == "studio_mock_mode_episode"
    assert mock.metadata["xr_mode"] == "workstation" and mock.metadata["control_role"] == "human_dev_xr"
    assert "continuon" not in mock.metadata  # fully lifted, nothing left in it
    assert mock.steps[0].observation["diagnostics"]["mock_mode"] is True
    assert len(mock.steps) == 3


def test_arm_recorder_episode_json_takes_dir_name(tmp_path: Path):
    d = tmp_path / "arm_20250101_120000"
    d.mkdir()
    (d / "episode.json").write_text(json.dumps({"metadata": {"robot_type": "so100"}, "steps": [
        {"observation": {"joint_positions": [0.0] * 6}, "action": {"command": [0.0] * 6}, "timestamp_ns": 0},
        {"observation": {"joint_positions": [0.1] * 6}, "action": {"command": [0.0] * 6}, "timestamp_ns": 33_000_000},
    ]}))
    (d / "step_000000.npy").write_bytes(b"\x93NUMPY")
    (d / "audio.wav").write_bytes(b"RIFF")
    ep = only_episode(read_path(d))
    assert ep.episode_id == "arm_20250101_120000"
    assert ep.blob_root == str(d)
    assert ep.metadata["robot_type"] == "so100"


def test_single_json_shapes(tmp_path: Path):
    not_episode = tmp_path / "config.json"
    not_episode.write_text(json.dumps({"learning_rate": 0.1}))
    r = read_single_json(not_episode)
    assert r.skipped and r.episodes == [] and "steps" in r.skip_reason

    bad_steps = tmp_path / "bad_steps.json"
    bad_steps.write_text(json.dumps({"metadata": {}, "steps": {"0": {}}}))
    r = read_single_json(bad_steps)
    assert r.episodes == [] and any(p.severity == ERROR and p.field == "steps" for p in r.problems)

    mixed = tmp_path / "mixed.json"
    mixed.write_text(json.dumps({"metadata": {"schema_version": "2.0"}, "steps": [
        {"observation": {}, "action": {}}, [1, 2], {"observation": {}, "action": {}}]}))
    ep = only_episode([read_single_json(mixed)])
    assert len(ep.steps) == 2 and ep.steps_lost == 1
    assert any(p.severity == ERROR and p.field == "steps[1]" for p in ep.problems)
    assert ep.metadata["schema_version"] == "1.1" and ep.metadata["source_schema_version"] == "2.0"


# -- normalisation of Kotlin / camelCase / alias shapes ------------------------------------------

KOTLIN_METADATA = {
    "continuon.xr_mode": "trainer",
    "continuon.control_role": "human_teleop",
    "environment_id": "lab-mock",
    "software": {"xrAppVersion": "0.3.1", "brainVersion": "os-7", "gloveFirmwareVersion": None},
    "tags": ["pick"],
    "robot_id": None,
    "robot_model": None,
    "start_time_unix_ms": 1764952865006,
    "duration_ms": None,
}

KOTLIN_STEP = {
    "observation": {
        "headsetPose": {"position": [0, 0, 0], "orientationQuat": [0, 0, 0, 1], "valid": True},
        "rightHandPose": {"position": [0, 0, 0], "orientationQuat": [0, 0, 0, 1], "valid": True},
        "leftHandPose": None,
        "gloveFrame": {"timestampNanos": 5, "flex": [0.1] * 5, "fsr": [0.0] * 8,
                       "orientationQuat": [0, 0, 0, 1], "accel": [0, 9.8, 0], "valid": True},
        "robotState": {"timestampNanos": 1764952865006200430, "jointPositions": [0.1, 0.2],
                       "wallTimeMillis": 1764952865006, "frameId": "frame_0001"},
        "videoFrameId": "frame_0001",
        "diagnostics": {"latencyMs": 3.0, "gloveDrops": 0, "bleRssi": -60},
    },
    "action": {"command": {"type": "com.continuonxr.app.connectivity.ControlCommand.EndEffectorVelocity",
                           "linearMps": {"x": 0.1, "y": 0.0, "z": 0.0},
                           "angularRadS": {"x": 0.0, "y": 0.0, "z": 0.2}},
               "source": "human_teleop_xr", "uiAction": None},
    "isTerminal": False,
    "stepMetadata": {"operatorNote": "ok"},
}


def _kotlin_dir(root: Path) -> Path:
    d = root / "episode-1764952865006"
    (d / "steps").mkdir(parents=True)
    (d / "metadata.json").write_text(json.dumps(KOTLIN_METADATA))
    lines = []
    for i in range(3):
        step = json.loads(json.dumps(KOTLIN_STEP))
        step["observation"]["robotState"]["timestampNanos"] += i * 50_000_000
        step["isTerminal"] = i == 2
        lines.append(json.dumps(step))
    (d / "steps" / "000000.jsonl").write_text("\n".join(lines) + "\n")
    return d


def test_kotlin_camelcase_episode_dir(tmp_path: Path):
    ep = only_episode(read_path(_kotlin_dir(tmp_path)))
    md = ep.metadata
    assert md["xr_mode"] == "trainer" and md["control_role"] == "human_teleop"
    assert not any(k.startswith("continuon.") for k in md)
    assert md["software"] == {"xr_app": "0.3.1", "continuonbrain_os": "os-7"}  # null firmware dropped
    assert "robot_id" not in md and "duration_ms" not in md  # explicit nulls mean absent
    assert md["episode_id"] == "episode-1764952865006"
    step = ep.steps[0]
    obs = step.observation
    assert set(obs) >= {"headset_pose", "right_hand_pose", "glove", "robot_state", "video_frame_id"}
    assert "gloveFrame" not in obs and "glove_frame" not in obs
    assert obs["robot_state"]["joint_positions"] == [0.1, 0.2]
    assert obs["glove"]["orientation_quat"] == [0, 0, 0, 1]
    assert obs["diagnostics"]["ble_rssi"] == -60
    # the tagged Kotlin command keeps its structure and its type tag; only keys are snake_cased
    cmd = step.action["command"]
    assert cmd["type"].endswith("EndEffectorVelocity")
    assert cmd["angular_rad_s"] == {"x": 0.0, "y": 0.0, "z": 0.2} and "linear_mps" in cmd
    assert step.step_metadata == {"operator_note": "ok"}
    assert [s.is_terminal for s in ep.steps] == [False, False, True]
    assert [s.timestamp_ns for s in ep.steps] == [1764952865006200430 + i * 50_000_000 for i in range(3)]
    assert ep.errors == []


def test_aliases_obs_done_and_conflicts(tmp_path: Path):
    f = tmp_path / "aliases.json"
    f.write_text(json.dumps({
        "metadata": {"xr_mode": "observer", "continuon": {"xr_mode": "trainer", "tags": ["a", "b"]},
                     "tags": ["b", "c"], "capabilities": ["camera", "arm"],
                     "provenance": {"origin": "sim:mujoco", "source_host": "pi"}, "schema_version": "1.1"},
        "steps": [{"obs": {"x": 1}, "action": {}, "done": False, "timestamp_ms": 0},
                  {"obs": {"x": 2}, "action": {}, "done": 1, "timestamp_ms": 100}]}))
    ep = only_episode(read_path(f))
    assert [s.observation for s in ep.steps] == [{"x": 1}, {"x": 2}]
    assert [s.is_terminal for s in ep.steps] == [False, True]
    md = ep.metadata
    assert md["xr_mode"] == "observer"  # the flat key is used; the disagreeing one is kept and reported
    assert md["continuon"]["xr_mode"] == "trainer"
    assert any(p.field == "continuon.xr_mode" and "disagrees" in p.message for p in ep.warnings)
    assert md["tags"] == ["b", "c", "a"]
    assert md["capabilities"] == ["camera", "arm"]  # list form kept as written
    assert md["provenance"] == {"origin": "sim:mujoco", "source_host": "pi"}
    assert "source_schema_version" not in md


def test_structural_step_problems(tmp_path: Path):
    f = tmp_path / "structure.json"
    f.write_text(json.dumps({"steps": [
        {"observation": [1, 2], "action": {}, "timestamp_ms": 0},
        {"observation": {}, "action": [0.1, 0.2], "reward": "abc", "timestamp_ms": 10},
        {"observation": {}, "action": {}, "is_terminal": "maybe", "step_metadata": "free text",
         "timestamp_ms": 20, "language_instruction": "pick the cup"},
    ]}))
    ep = only_episode(read_path(f))
    errs = {(p.step, p.field) for p in ep.errors}
    assert (0, "observation") in errs and (1, "reward") in errs and (2, "is_terminal") in errs
    assert ep.steps[1].action == {"command": [0.1, 0.2]}
    assert any(p.step == 1 and p.field == "action" for p in ep.warnings)
    assert ep.steps[2].step_metadata == {"text": "free text"}
    assert ep.steps[2].extras == {"language_instruction": "pick the cup", "timestamp_ms": 20}


# -- steps-only JSONL ----------------------------------------------------------------------------

def test_steps_jsonl_grouped_by_episode_id(tmp_path: Path):
    f = tmp_path / "mixed_steps.jsonl"
    rows = []
    for i in range(3):
        for eid in ("ep_a", "ep_b"):
            rows.append({"episode_id": eid, "step_index": i, "timestamp_ns": i * 100_000_000,
                         "observation": {"v": [i]}, "action": {"command": [0.0]}})
    rows.append({"episode_id": "ep_b", "metadata": {"xr_mode": "trainer"}})
    f.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    [report] = read_path(f)
    assert [e.episode_id for e in report.episodes] == ["ep_a", "ep_b"]
    a, b = report.episodes
    assert a.source == f"{f}#ep_a" and a.layout == "steps_jsonl"
    assert [s.observation["v"] for s in a.steps] == [[0], [1], [2]]
    assert [s.timestamp_ns for s in b.steps] == [0, 100_000_000, 200_000_000]
    assert b.metadata["xr_mode"] == "trainer" and "xr_mode" not in a.metadata
    assert all("episode_id" not in s.extras for s in a.steps)


def test_steps_jsonl_without_ids_and_unparseable(tmp_path: Path):
    f = tmp_path / "run_7.jsonl"
    f.write_text('{"timestamp_us": 0, "observation": {}, "action": {}}\n'
                 '{"timestamp_us": 20000, "observation": {}, "action": {}}\n')
    ep = only_episode(read_path(f))
    assert ep.episode_id == "run_7" and ep.source == str(f)
    assert [s.timestamp_ns for s in ep.steps] == [0, 20_000_000]

    garbage = tmp_path / "garbage.jsonl"
    garbage.write_text("this is not json\nnor is this\n")
    [r] = read_path(garbage)
    assert r.episodes == [] and not r.skipped
    assert any(p.severity == ERROR and "none of the 2" in p.message for p in r.problems)

    empty = tmp_path / "empty.jsonl"
    empty.write_text("\n\n")
    r = read_steps_jsonl(empty)
    assert r.skipped and r.episodes == []


# -- discovery ------------------------------------------------------------------------------------

def test_whole_sample_tree(samples_dir: Path):
    reports = read_path(samples_dir)
    episodes = [e for r in reports for e in r.episodes]
    skipped = [r for r in reports if r.skipped]
    # 19 autonomous dirs, 3 legacy dirs, 2+2 single JSON, 3 raw + 3 damaged + 2 empty + vlm + wiki TFRecords
    assert len(reports) == 36
    assert len(skipped) == 18  # 16 metadata-only dirs + 2 zero-record TFRecords
    assert len(episodes) == 3 + 3 + 2 + 2 + 3 + 3 + 20 + 50
    assert not any(r.source.endswith("README.md") for r in reports)
    for r in reports:
        assert not (r.episodes and r.skipped)
        for p in r.problems:
            assert p.severity in (ERROR, WARNING)
    # every episode is canonical: snake_case keys, schema 1.1, an id and an origin
    for ep in episodes:
        assert ep.metadata["schema_version"] == "1.1"
        assert ep.metadata["episode_id"] == ep.episode_id
        assert ep.metadata["provenance"]["origin"].startswith("import:")
        for step in ep.steps:
            assert isinstance(step.observation, dict) and isinstance(step.action, dict)
            assert not any(c.isupper() for k in step.observation for c in k)


def test_discover_skips_manifests_and_unknown_files(tmp_path: Path):
    root = tmp_path / "ds"
    root.mkdir()
    for name in ("upload_manifest.json", "manifest.json", "ep1.validation.json", "dataset.json"):
        (root / name).write_text(json.dumps({"steps": [{"observation": {}, "action": {}}]}))
    (root / "notes.md").write_text("# notes")
    (root / "frame.npy").write_bytes(b"\x93NUMPY")
    (root / "half.mcap.partial").write_bytes(b"\x89MCAP0\r\n")
    hidden = root / ".tmp-ep"
    (hidden / "steps").mkdir(parents=True)
    (hidden / "steps" / "000000.jsonl").write_text('{"observation": {}, "action": {}}\n')
    assert read_path(root) == []

    (root / "broken.json").write_text("{")
    (root / "broken.mcap").write_bytes(b"not an mcap at all")
    (root / "broken.jsonl").write_text("{\n{\n")
    reports = {Path(r.source).name: r for r in read_path(root)}
    assert set(reports) == {"broken.json", "broken.mcap", "broken.jsonl"}
    for r in reports.values():
        assert r.episodes == [] and any(p.severity == ERROR for p in r.problems)

    [meta] = read_path(root / "manifest.json")
    assert meta.skipped and meta.episodes == []


def test_discover_explicit_paths(tmp_path: Path, samples_dir: Path):
    [missing] = read_path(tmp_path / "nope")
    assert missing.episodes == [] and "no such file" in missing.problems[0].message

    # a TFRecord under a name that says nothing is recognised by its bytes
    odd = tmp_path / "capture.bin"
    odd.write_bytes((samples_dir / "continuonbrain/rlds/tfrecord_raw/sample_pi5_mock.tfrecord").read_bytes())
    ep = only_episode(read_path(odd))
    assert ep.layout == "tfrecord" and len(ep.steps) == 2
    text = tmp_path / "readme.txt"
    text.write_text("hello")
    [r] = read_path(text)
    assert r.episodes == [] and "not a recognised episode file" in r.problems[0].message

    # naming metadata.json means its episode dir
    ep = only_episode(read_path(samples_dir / HIST / "follow_user_mr_v1" / "metadata.json"))
    assert ep.episode_id == "follow_user_mr_v1"

    same = samples_dir / HIST / "pi5_follow_synthetic.json"
    reports = read_paths([same, same, samples_dir / HIST / "stack_boxes_vr"])
    assert [len(r.episodes) for r in reports] == [1, 1]


def test_size_limits_are_reported(tmp_path: Path, samples_dir: Path):
    [r] = read_path(samples_dir / HIST / "studio_mock_editor.json", max_file_bytes=1000)
    assert r.episodes == []
    [p] = r.problems
    assert p.severity == ERROR and "max_file_bytes=1000" in p.message and p.source.endswith("studio_mock_editor.json")

    f = tmp_path / "long.jsonl"
    f.write_text('{"observation": {"pad": "' + "x" * 500 + '"}, "action": {}}\n'
                 '{"observation": {}, "action": {}, "timestamp_ms": 1}\n'
                 '{"observation": {}, "action": {}, "timestamp_ms": 2}\n')
    ep = only_episode(read_path(f, max_line_bytes=200))
    assert len(ep.steps) == 2 and ep.steps_lost == 1
    assert any(p.severity == ERROR and "line 1" in p.message and "max_line_bytes=200" in p.message
               for p in ep.problems)


def test_nan_reaches_the_episode_for_validation(tmp_path: Path):
    f = tmp_path / "nan.json"
    f.write_text('{"steps": [{"observation": {"robot_state": {"joint_positions": [NaN, 1.0]}}, '
                 '"action": {"command": [Infinity, -Infinity]}, "timestamp_ms": 0}]}')
    ep = only_episode(read_path(f))
    assert math.isnan(ep.steps[0].observation["robot_state"]["joint_positions"][0])
    assert ep.steps[0].action["command"] == [math.inf, -math.inf]
    assert ep.errors == []  # content rules are validation's


def test_canonical_dir_round_trip_is_lossless(tmp_path: Path):
    steps = [Step(observation={"robot_state": {"joint_positions": [0.1 * i, 0.5]}, "media": {"rgb": {"uri": f"blobs/{i}.png"}}},
                  action={"command": [0.1, -0.2], "source": "vla_policy"}, reward=float(i), is_terminal=i == 3,
                  step_metadata={"note": "k"} if i else {}, timestamp_ns=1764952865006200430 + i * 20_000_000,
                  extras={"language_instruction": "pick"} if i == 1 else {})
             for i in range(4)]
    metadata = {"schema_version": "1.1", "episode_id": "ep_rt", "xr_mode": "trainer", "tags": ["x"],
                "capabilities": ["camera"], "provenance": {"origin": "import:single_json"},
                "source_schema_version": "1.0", "owner": None}
    d = tmp_path / "dataset" / "ep_rt"
    (d / "steps").mkdir(parents=True)
    (d / "blobs").mkdir()
    (d / "metadata.json").write_text(json.dumps(metadata))
    (d / "steps" / "000000.jsonl").write_text("".join(json.dumps(s.to_json_obj(i)) + "\n" for i, s in enumerate(steps)))
    ep = only_episode(read_path(tmp_path / "dataset"))
    assert ep.layout == "canonical_dir" and ep.episode_id == "ep_rt"
    assert ep.metadata == metadata  # as written, nulls included
    assert ep.blob_root == str(d)
    assert ep.steps == steps
    assert ep.problems == []

    # a foreign camelCase line appended to a canonical dir still gets the full mapping
    with open(d / "steps" / "000000.jsonl", "a") as f:
        f.write(json.dumps({"observation": {"robotState": {"jointPositions": [1, 2]}}, "action": {},
                            "isTerminal": True, "step_index": 4, "timestamp_ns": 1764952865086200430}) + "\n")
    ep = only_episode(read_path(d))
    assert ep.steps[4].observation == {"robot_state": {"joint_positions": [1, 2]}}
    assert ep.steps[4].is_terminal is True and ep.steps[4].timestamp_ns == 1764952865086200430
