"""Validation rules, table-driven: each case breaks one thing in a clean episode and names the
finding it must produce (severity, step, field, words of the message)."""
from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Any, Callable

import pytest

from hope_models.rlds.episode import ERROR, WARNING, Episode, Problem, SourceReport, Step
from hope_models.rlds.validate import derive_action_source, validate_episode
from hope_models.rlds.validation_report import episode_report, report_entries, summarize

PERIOD_NS = 100_000_000  # 10 Hz
DELETE = object()  # a mutation value meaning "remove this key"
T0 = 1_764_952_865_006_200_430  # epoch ns beyond 2**53, as producers write them

SAFETY = {"content_rating": {"audience": "general", "violence": "none", "language": "clean"},
          "pii_attestation": {"pii_present": False, "faces_present": False, "name_present": False,
                              "consent": True},
          "pii_cleared": True, "pending_review": False}
PUBLIC_SHARE = {"public": True, "slug": "pick-cup", "title": "Pick a cup", "license": "CC-BY-4.0",
                "tags": ["manipulation"]}


def clean_episode(n: int = 5, blob_root: str | None = None) -> Episode:
    steps = [Step(observation={"robot_state": {"joint_positions": [0.1 * i, 0.2, 0.3],
                                               "gripper_open": True, "frame_id": "base_link"},
                               "video_frame_id": f"frame_{i:04d}"},
                  action={"command": [0.03 * i, 0.1], "source": "human_teleop_xr"},
                  reward=0.0, is_terminal=(i == n - 1), step_metadata={"note": "ok"},
                  timestamp_ns=T0 + i * PERIOD_NS)
             for i in range(n)]
    metadata = {"schema_version": "1.1", "episode_id": "ep1", "xr_mode": "trainer",
                "control_role": "human_teleop", "environment_id": "lab", "tags": ["pick"],
                "software": {"xr_app": "1.0", "continuonbrain_os": "1.0", "glove_firmware": "1.0"},
                "provenance": {"origin": "import:single_json"}}
    return Episode("ep1", metadata, steps, "/data/ep1.json", "single_json", blob_root=blob_root)


def cloud_episode() -> Episode:
    ep = clean_episode()
    ep.metadata.update(robot_type="donkeycar", safety=copy.deepcopy(SAFETY))
    return ep


def public_episode() -> Episode:
    ep = cloud_episode()
    ep.metadata["share"] = copy.deepcopy(PUBLIC_SHARE)
    return ep


# -- mutations ----------------------------------------------------------------------------------

def set_joint(i: int, k: int, value: Any) -> Callable[[Episode], None]:
    def mutate(ep: Episode) -> None:
        ep.steps[i].observation["robot_state"]["joint_positions"][k] = value
    return mutate


def set_step(i: int, **changes: Any) -> Callable[[Episode], None]:
    def mutate(ep: Episode) -> None:
        for key, value in changes.items():
            setattr(ep.steps[i], key, value)
    return mutate


def set_action(i: int, key: str, value: Any) -> Callable[[Episode], None]:
    def mutate(ep: Episode) -> None:
        ep.steps[i].action[key] = value
    return mutate


def set_meta(**changes: Any) -> Callable[[Episode], None]:
    def mutate(ep: Episode) -> None:
        for key, value in changes.items():
            if value is DELETE:
                ep.metadata.pop(key, None)
            else:
                ep.metadata[key] = value
    return mutate


def set_safety(**changes: Any) -> Callable[[Episode], None]:
    def mutate(ep: Episode) -> None:
        for key, value in changes.items():
            if value is DELETE:
                ep.metadata["safety"].pop(key)
            else:
                ep.metadata["safety"][key] = value
    return mutate


def set_share(**changes: Any) -> Callable[[Episode], None]:
    def mutate(ep: Episode) -> None:
        for key, value in changes.items():
            if value is DELETE:
                ep.metadata["share"].pop(key)
            else:
                ep.metadata["share"][key] = value
    return mutate


def nan_token_step(ep: Episode) -> None:
    # The bare token as Python writers emit it, parsed the way the readers parse JSON.
    line = '{"robot_state": {"joint_positions": [0.1, NaN, 0.3]}, "video_frame_id": "frame_0003"}'
    ep.steps[3].observation = json.loads(line)


def no_steps(ep: Episode) -> None:
    ep.steps.clear()


def empty_steps(ep: Episode) -> None:
    for step in ep.steps:
        step.observation, step.action = {}, {}


def command_length_changes(ep: Episode) -> None:
    ep.steps[2].action["command"] = [0.1, 0.2, 0.3]


def joints_become_text(ep: Episode) -> None:
    ep.steps[4].observation["robot_state"]["joint_positions"] = "n/a"


def empty_then_filled(ep: Episode) -> None:
    for i, step in enumerate(ep.steps):
        step.action["command"] = [] if i < 2 else [0.1, 0.2]


def gap_before_step_3(ep: Episode) -> None:
    for i, step in enumerate(ep.steps):
        step.timestamp_ns = T0 + i * PERIOD_NS + (int(0.5e9) if i >= 3 else 0)


def many_nans(ep: Episode) -> None:
    ep.steps[1].observation["image"] = [math.nan] * 100
    for step in ep.steps:
        step.observation.setdefault("image", [0.5] * 100)


def missing_blob(ep: Episode) -> None:
    ep.steps[1].observation["media"] = {"rgb": {"uri": "blobs/rgb_0001.png", "width": 64}}


def escaping_blob(ep: Episode) -> None:
    ep.steps[0].observation["media"] = {"depth": {"uri": "../../etc/passwd"}}


def opaque_blob(ep: Episode) -> None:
    ep.steps[0].observation["audio"] = {"uri": "mock://audio/frame_0000.wav"}


def mixed_sources(ep: Episode) -> None:
    ep.steps[0].action["source"] = "vla_policy"


def no_step_sources(ep: Episode) -> None:
    for step in ep.steps:
        step.action.pop("source")


# (mutation, profile, base, expected findings: (severity, step, field, words in the message))
CASES = [
    pytest.param(set_joint(2, 1, math.nan), "train", clean_episode,
                 [(ERROR, 2, "observation.robot_state.joint_positions[1]", "not a finite number")], id="nan"),
    pytest.param(nan_token_step, "train", clean_episode,
                 [(ERROR, 3, "observation.robot_state.joint_positions[1]", "nan is not a finite")], id="nan-token"),
    pytest.param(set_action(1, "command", [math.inf, 0.1]), "train", clean_episode,
                 [(ERROR, 1, "action.command[0]", "inf is not a finite number")], id="plus-inf"),
    pytest.param(set_step(4, reward=-math.inf), "train", clean_episode,
                 [(ERROR, 4, "reward", "-inf is not a finite number")], id="minus-inf-reward"),
    pytest.param(set_step(2, observation={"robot_state": {"joint_positions": [0.1, 0.2, 0.3]},
                                          "diagnostics": {"latency_ms": math.nan}}), "train", clean_episode,
                 [(ERROR, 2, "observation.diagnostics.latency_ms", "not a finite number")], id="nan-scalar"),
    pytest.param(set_step(0, reward="0.5"), "train", clean_episode,
                 [(ERROR, 0, "reward", "not a number")], id="reward-text"),
    pytest.param(set_joint(1, 2, "0.3"), "train", clean_episode,
                 [(ERROR, 1, "observation.robot_state.joint_positions[2]", "str '0.3' in a numeric vector")],
                 id="non-numeric-string"),
    pytest.param(set_joint(3, 0, None), "train", clean_episode,
                 [(ERROR, 3, "observation.robot_state.joint_positions[0]", "null in a numeric vector")],
                 id="non-numeric-null"),
    pytest.param(set_joint(0, 1, True), "train", clean_episode,
                 [(ERROR, 0, "observation.robot_state.joint_positions[1]", "bool True in a numeric vector")],
                 id="non-numeric-bool"),
    pytest.param(command_length_changes, "train", clean_episode,
                 [(ERROR, 2, "action.command", "length changed within the episode: 3 here, 2 at step 0")],
                 id="vector-length-change"),
    pytest.param(empty_then_filled, "train", clean_episode,
                 [(ERROR, 2, "action.command", "2 here, 0 at step 0")], id="empty-then-filled"),
    pytest.param(joints_become_text, "train", clean_episode,
                 [(ERROR, 4, "observation.robot_state.joint_positions", "expected a numeric vector")],
                 id="vector-becomes-text"),
    pytest.param(set_step(3, timestamp_ns=T0 + PERIOD_NS // 2), "train", clean_episode,
                 [(ERROR, 3, "timestamp_ns", "goes backwards")], id="timestamps-backwards"),
    pytest.param(no_steps, "train", clean_episode,
                 [(ERROR, None, "steps", "no usable steps")], id="no-steps"),
    pytest.param(empty_steps, "train", clean_episode,
                 [(ERROR, None, "steps", "no usable steps: all 5 steps")], id="only-empty-steps"),
    pytest.param(many_nans, "train", clean_episode,
                 [(ERROR, 1, "observation.image[0]", "(99 more like this")], id="nan-repeats-summarised"),
    # warnings
    pytest.param(set_meta(xr_mode="autonomous"), "train", clean_episode,
                 [(WARNING, None, "metadata.xr_mode", "undocumented value 'autonomous'")], id="enum-xr-mode"),
    pytest.param(set_meta(control_role="pilot"), "train", clean_episode,
                 [(WARNING, None, "metadata.control_role", "undocumented value 'pilot'")], id="enum-control-role"),
    pytest.param(set_meta(environment_id=DELETE, software=None), "train", clean_episode,
                 [(WARNING, None, "metadata", "missing optional metadata: environment_id, software")],
                 id="missing-optional-metadata"),
    pytest.param(gap_before_step_3, "train", clean_episode,
                 [(WARNING, 3, "timestamp_ns", "gap of 0.600 s before this step is over 3x the median "
                   "period 0.100 s")], id="gap"),
    pytest.param(set_step(4, is_terminal=False), "train", clean_episode,
                 [(WARNING, 4, "is_terminal", "last step is not marked terminal")], id="terminal-missing"),
    pytest.param(set_step(2, is_terminal=True), "train", clean_episode,
                 [(WARNING, 2, "is_terminal", "not the last")], id="terminal-early"),
    pytest.param(set_step(2, timestamp_ns=T0 + PERIOD_NS), "train", clean_episode,
                 [(WARNING, 2, "timestamp_ns", "repeats step 1")], id="timestamp-repeats"),
    pytest.param(set_step(2, timestamp_ns=None), "train", clean_episode,
                 [(WARNING, 2, "timestamp_ns", "1 of 5 steps have no timestamp")], id="timestamp-missing"),
    pytest.param(escaping_blob, "train", clean_episode,
                 [(WARNING, 0, "observation.media.depth.uri", "points outside the episode dir")],
                 id="blob-escapes"),
    # cloud profile
    pytest.param(set_meta(robot_type=DELETE), "cloud", cloud_episode,
                 [(ERROR, None, "metadata.robot_type", "missing robot_type (or robot_model)")],
                 id="cloud-no-robot-type"),
    pytest.param(set_meta(xr_mode=DELETE), "cloud", cloud_episode,
                 [(ERROR, None, "metadata.xr_mode", "missing xr_mode")], id="cloud-no-xr-mode"),
    pytest.param(set_meta(episode_id=""), "cloud", cloud_episode,
                 [(ERROR, None, "metadata.episode_id", "missing episode_id")], id="cloud-no-episode-id"),
    pytest.param(no_step_sources, "cloud", cloud_episode,
                 [(ERROR, None, "metadata.action_source", "no step has action.source")], id="cloud-no-action-source"),
    pytest.param(mixed_sources, "cloud", cloud_episode,
                 [(WARNING, None, "metadata.action_source", "'human_teleop_xr'")], id="cloud-mixed-sources"),
    pytest.param(set_meta(total_steps=7), "cloud", cloud_episode,
                 [(ERROR, None, "metadata.total_steps", "total_steps is 7 but the episode has 5 steps")],
                 id="cloud-total-steps"),
    pytest.param(set_meta(safety=DELETE), "cloud", cloud_episode,
                 [(ERROR, None, "metadata.safety", "missing safety block")], id="cloud-no-safety"),
    pytest.param(set_safety(pii_attestation=DELETE), "cloud", cloud_episode,
                 [(ERROR, None, "metadata.safety.pii_attestation", "must be an object")], id="cloud-no-attestation"),
    pytest.param(set_safety(pending_review="no"), "cloud", cloud_episode,
                 [(ERROR, None, "metadata.safety.pending_review", "true or false")], id="cloud-review-text"),
    pytest.param(set_safety(pii_cleared=False), "cloud", public_episode,
                 [(ERROR, None, "metadata.safety.pii_cleared", "public sharing requires safety.pii_cleared true")],
                 id="public-not-cleared"),
    pytest.param(set_safety(pending_review=True), "cloud", public_episode,
                 [(ERROR, None, "metadata.safety.pending_review", "requires safety.pending_review false")],
                 id="public-pending-review"),
    pytest.param(set_share(slug=DELETE, license=""), "cloud", public_episode,
                 [(ERROR, None, "metadata.share.slug", "requires share.slug"),
                  (ERROR, None, "metadata.share.license", "requires share.license")], id="public-no-slug-license"),
    pytest.param(set_share(title=DELETE), "cloud", public_episode,
                 [(ERROR, None, "metadata.share.title", "requires share.title")], id="public-no-title"),
    pytest.param(set_share(tags=[]), "cloud", public_episode,
                 [(ERROR, None, "metadata.share.tags", "at least one tag")], id="public-no-tags"),
    pytest.param(set_share(public="yes"), "cloud", public_episode,
                 [(ERROR, None, "metadata.share.public", "true or false")], id="public-not-bool"),
]


def _matches(problem: Problem, severity: str, step: int | None, field: str, words: str) -> bool:
    return (problem.severity == severity and problem.step == step and problem.field == field
            and words in problem.message)


@pytest.mark.parametrize("mutate, profile, base, expected", CASES)
def test_case_produces_its_finding(mutate, profile, base, expected):
    ep = base()
    assert validate_episode(ep, profile) == [], "the base episode must be clean in its profile"
    mutate(ep)
    problems = validate_episode(ep, profile)
    for severity, step, field, words in expected:
        assert any(_matches(p, severity, step, field, words) for p in problems), \
            f"expected {severity} at step {step} {field}: {words!r}; got:\n" + "\n".join(map(str, problems))
    if all(severity == WARNING for severity, *_ in expected):
        assert not [p for p in problems if p.severity == ERROR], "a warning case must not reject"
    # Every message names the file, and the step and field when it has them.
    for p in problems:
        text = str(p)
        assert text.startswith(ep.source + ": ")
        if p.step is not None:
            assert f": step {p.step}: " in text
        if p.field:
            assert f": {p.field}: " in text


def test_clean_episodes_pass_both_profiles():
    assert validate_episode(clean_episode(), "train") == []
    assert validate_episode(cloud_episode(), "cloud") == []
    assert validate_episode(public_episode(), "cloud") == []


def test_cloud_accepts_robot_model_and_derives_action_source():
    ep = cloud_episode()
    del ep.metadata["robot_type"]
    ep.metadata["robot_model"] = "so-arm101"
    assert validate_episode(ep, "cloud") == []
    assert derive_action_source(ep) == ("human_teleop_xr", ["human_teleop_xr"])
    ep.metadata["action_source"] = "human_supervisor"
    assert derive_action_source(ep)[0] == "human_supervisor"


def test_cloud_rules_are_not_applied_by_train_profile():
    ep = clean_episode()  # no robot_type, no safety block
    assert validate_episode(ep, "train") == []
    fields = {p.field for p in validate_episode(ep, "cloud")}
    assert {"metadata.robot_type", "metadata.safety"} <= fields


def test_private_share_needs_no_listing_fields():
    ep = cloud_episode()
    ep.metadata["share"] = {"public": False}
    ep.metadata["safety"]["pii_cleared"] = False
    assert validate_episode(ep, "cloud") == []


def test_vector_lengths_may_differ_between_episodes():
    six_joints = clean_episode()
    for step in six_joints.steps:
        step.observation["robot_state"]["joint_positions"] = [0.0] * 6
        step.action["command"] = [0.0] * 32
    assert validate_episode(clean_episode(), "train") == []
    assert validate_episode(six_joints, "train") == []


def test_lists_of_text_and_of_objects_are_not_vectors():
    ep = clean_episode()
    for i, step in enumerate(ep.steps):
        step.observation["labels"] = ["cup"] * (i + 1)
        step.observation["objects"] = [{"position": [0.1, 0.2, 0.3]}] * (i % 2 + 1)
    assert validate_episode(ep, "train") == []
    ep.steps[3].observation["objects"][0] = {"position": [0.1, 0.2]}
    problems = validate_episode(ep, "train")
    assert [(p.step, p.field) for p in problems] == [(3, "observation.objects[0].position")]


def test_blob_present_missing_and_opaque(tmp_path: Path):
    (tmp_path / "blobs").mkdir()
    (tmp_path / "blobs" / "rgb_0000.png").write_bytes(b"png")
    ep = clean_episode(blob_root=str(tmp_path))
    ep.steps[0].observation["media"] = {"rgb": {"uri": "blobs/rgb_0000.png"}}
    opaque_blob(ep)
    assert validate_episode(ep, "train") == []
    missing_blob(ep)
    problems = validate_episode(ep, "train")
    assert len(problems) == 1
    assert _matches(problems[0], WARNING, 1, "observation.media.rgb.uri", "'blobs/rgb_0001.png' not found")
    assert str(tmp_path / "blobs" / "rgb_0001.png") in problems[0].message


def test_relative_blob_without_blob_root_is_a_warning():
    ep = clean_episode(blob_root=None)
    missing_blob(ep)
    problems = validate_episode(ep, "train")
    assert [(p.severity, p.step) for p in problems] == [(WARNING, 1)]
    assert "no blob root" in problems[0].message


def test_unknown_profile_is_refused():
    with pytest.raises(ValueError, match="unknown validation profile 'strict'"):
        validate_episode(clean_episode(), "strict")


# -- reports and statuses -----------------------------------------------------------------------

def test_statuses():
    assert episode_report(clean_episode())["status"] == "accepted"
    warned = clean_episode()
    warned.steps[-1].is_terminal = False
    report = episode_report(warned)
    assert (report["status"], report["ok"], len(report["warnings"])) == ("accepted_with_warnings", True, 1)

    recovered = clean_episode()
    recovered.steps_lost = 1
    recovered.warn("record 0 failed its CRC; resynchronised at byte 45", field="record")
    report = episode_report(recovered)
    assert (report["status"], report["ok"], report["steps_lost"]) == ("partly_recovered", True, 1)
    assert report["warnings"] == ["/data/ep1.json: record: record 0 failed its CRC; resynchronised at byte 45"]

    broken = clean_episode()
    broken.steps[1].action["command"] = [math.nan, 0.0]
    broken.steps_lost = 2  # errors win over recovery
    report = episode_report(broken, "train")
    assert (report["status"], report["ok"]) == ("rejected", False)
    assert report["errors"] == ["/data/ep1.json: step 1: action.command[0]: nan is not a finite number"]

    reader_error = clean_episode()
    reader_error.error("line 3 is not JSON", step=3)
    assert episode_report(reader_error)["status"] == "rejected"


def test_report_entries_for_skipped_unreadable_and_multi_episode_sources():
    skipped = SourceReport("/data/meta_only", skipped=True, skip_reason="metadata-only dir",
                           problems=[Problem(WARNING, "/data/meta_only", "metadata.json but no steps; skipped")])
    [entry] = report_entries(skipped)
    assert entry == {"source": "/data/meta_only", "episode_id": None, "ok": True, "status": "skipped",
                     "steps": 0, "steps_lost": 0, "errors": [],
                     "warnings": ["/data/meta_only: metadata.json but no steps; skipped"]}

    unreadable = SourceReport("/data/x.json", problems=[Problem(ERROR, "/data/x.json", "not JSON: line 1")])
    [entry] = report_entries(unreadable)
    assert (entry["status"], entry["ok"], entry["errors"]) == ("rejected", False, ["/data/x.json: not JSON: line 1"])

    silent = SourceReport("/data/y.json")
    [entry] = report_entries(silent)
    assert entry["status"] == "rejected" and "no episode could be read" in entry["errors"][0]

    a, b = clean_episode(), clean_episode()
    b.episode_id, b.source = "ep2", "/data/x.tfrecord#ep2"
    b.steps[0].reward = math.nan
    file_warning = Problem(WARNING, "/data/x.tfrecord", "3 bytes of garbage after the last record")
    entries = report_entries(SourceReport("/data/x.tfrecord", episodes=[a, b], problems=[file_warning]))
    assert [(e["episode_id"], e["status"]) for e in entries] == [("ep1", "accepted_with_warnings"),
                                                                  ("ep2", "rejected")]
    assert all(str(file_warning) in e["warnings"] for e in entries)

    summary = summarize(entries + report_entries(skipped))
    assert summary["rejected"] == 1 and summary["skipped"] == 1 and summary["accepted_with_warnings"] == 1
    assert summary["episodes"] == 2 and summary["steps"] == 10 and summary["ok"] is False
