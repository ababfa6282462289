"""`run_trainer.py validate|ingest|export` as a user runs them: exit codes, --json shape, messages."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from test_rlds_validate import SAFETY

ENTRY_KEYS = {"source", "episode_id", "ok", "status", "steps", "steps_lost", "errors", "warnings"}
STATUSES = {"accepted", "accepted_with_warnings", "partly_recovered", "rejected", "skipped"}


def run_cli(repo_root: Path, *args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, str(repo_root / "run_trainer.py"), *map(str, args)],
                          capture_output=True, text=True, cwd=repo_root, timeout=120)
    assert "Traceback" not in proc.stderr, proc.stderr
    return proc


def write_episode_json(path: Path, steps: list[dict] | None = None, **metadata) -> Path:
    steps = steps if steps is not None else [
        {"observation": {"robot_state": {"timestamp_nanos": i * 50_000_000, "joint_positions": [0.0, 0.1]}},
         "action": {"command": [0.1, 0.2], "source": "human_teleop_xr"}, "reward": 0.0,
         "is_terminal": i == 2} for i in range(3)]
    meta = {"xr_mode": "trainer", "control_role": "human_teleop", "environment_id": "lab",
            "tags": ["t"], "software": {"xr_app": "1"}, **metadata}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"metadata": meta, "steps": steps}), encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def samples_report(repo_root: Path, samples_dir: Path) -> tuple[int, dict]:
    proc = run_cli(repo_root, "validate", samples_dir, "--json")
    return proc.returncode, json.loads(proc.stdout)


def by_name(report: dict, samples_dir: Path) -> dict[str, dict]:
    return {str(Path(e["source"]).relative_to(samples_dir)): e for e in report["episodes"]}


# -- validate on the real samples ---------------------------------------------------------------

def test_samples_json_shape_and_exit_code(samples_report):
    code, report = samples_report
    assert set(report) == {"episodes", "summary"}
    for entry in report["episodes"]:
        assert set(entry) == ENTRY_KEYS
        assert entry["status"] in STATUSES
        assert entry["ok"] == (entry["status"] != "rejected")
        assert all(isinstance(m, str) for m in entry["errors"] + entry["warnings"])
    summary = report["summary"]
    for status in STATUSES:
        assert summary[status] == sum(1 for e in report["episodes"] if e["status"] == status)
    assert summary["ok"] == all(e["ok"] for e in report["episodes"])
    assert code == (0 if summary["ok"] else 1)
    assert summary["rejected"] == 0 and code == 0  # the samples are messy, not corrupt for training


def test_samples_corrupt_gzip_tfrecords_are_partly_recovered(samples_report, samples_dir):
    entries = by_name(samples_report[1], samples_dir)
    expected_steps = {"pi5_follow_synthetic": 4, "sample_pi5_mock": 1, "studio_mock_editor": 2}
    for name, steps in expected_steps.items():
        entry = entries[f"continuonbrain/rlds/tfrecord/{name}.tfrecord.gz"]
        assert (entry["status"], entry["ok"], entry["steps"], entry["steps_lost"]) == \
            ("partly_recovered", True, steps, 1)
        assert any("corrupt" in w for w in entry["warnings"])
        assert entry["errors"] == []
    for name, steps in {"pi5_follow_synthetic": 5, "sample_pi5_mock": 2, "studio_mock_editor": 3}.items():
        entry = entries[f"continuonbrain/rlds/tfrecord_raw/{name}.tfrecord"]
        assert (entry["ok"], entry["steps"], entry["steps_lost"]) == (True, steps, 0)


def test_samples_skipped_sources(samples_report, samples_dir):
    entries = by_name(samples_report[1], samples_dir)
    autonomous = {k: e for k, e in entries.items() if k.startswith("brain_config/rlds/autonomous_learning/")}
    skipped = [e for e in autonomous.values() if e["status"] == "skipped"]
    assert len(autonomous) == 19 and len(skipped) == 16
    for entry in skipped:
        assert (entry["ok"], entry["steps"], entry["episode_id"]) == (True, 0, None)
        assert len(entry["warnings"]) == 1 and "without steps" in entry["warnings"][0]
    with_steps = [e for e in autonomous.values() if e["status"] != "skipped"]
    assert {(e["status"], e["steps"]) for e in with_steps} == {("accepted_with_warnings", 1)}
    assert all(any("undocumented value 'autonomous'" in w for w in e["warnings"]) for e in with_steps)
    for name in ("history/repo_root/test.tfrecord", "history/repo_root/test_gzip.tfrecord"):
        assert (entries[name]["status"], entries[name]["steps"], entries[name]["ok"]) == ("skipped", 0, True)
        assert "no records" in entries[name]["warnings"][0]
    assert samples_report[1]["summary"]["skipped"] == 18


def test_samples_every_episode_is_reported(samples_report, samples_dir):
    entries = by_name(samples_report[1], samples_dir)
    assert sum(1 for k in entries if k.startswith("rlds/vlm_tfrecord/vlm_data.tfrecord#")) == 20
    assert sum(1 for k in entries if k.startswith("rlds/wiki_tfrecord/wiki_data.tfrecord#")) == 50
    assert entries["history/continuonbrain/rlds/episodes/studio_mock_editor.json"]["status"] == "accepted"
    legacy = entries["history/continuonbrain/rlds/episodes/follow_user_mr_v1"]
    assert legacy["status"] == "accepted_with_warnings" and legacy["steps"] == 2
    assert any("metadata.control_role: undocumented value 'pilot'" in w for w in legacy["warnings"])
    # 19 autonomous_learning dirs, 6 Continuon TFRecords, 5 history episodes, 2 older versions,
    # 2 zero-record TFRecords, and the one-step episodes of the VLM and wiki TFRecords
    assert len(entries) == 19 + 6 + 5 + 2 + 2 + 20 + 50


def test_samples_human_output(repo_root, samples_dir):
    proc = run_cli(repo_root, "validate", samples_dir / "continuonbrain")
    assert proc.returncode == 0
    heads = [line for line in proc.stdout.splitlines() if not line.startswith("    ")]
    assert len(heads) == 6 + 1
    assert heads[0].split()[:2] == ["partly_recovered", "4"] and "pi5_follow_synthetic.tfrecord.gz" in heads[0]
    assert heads[-1].startswith("6 episodes, 17 steps (") and heads[-1].endswith("profile train: ok")
    assert "3 partly_recovered" in heads[-1]


# -- exit codes and bad input -------------------------------------------------------------------

def test_rejected_and_unreadable_sources_exit_1(repo_root, tmp_path):
    good = write_episode_json(tmp_path / "good.json")
    nan_file = tmp_path / "nan.json"
    nan_file.write_text(good.read_text().replace('"joint_positions": [0.0, 0.1]}}, "action": {"command": [0.1, 0.2]',
                                                 '"joint_positions": [0.0, 0.1]}}, "action": {"command": [0.1, NaN]', 1))
    (tmp_path / "broken.json").write_text('{"metadata": {}, "steps": [')
    proc = run_cli(repo_root, "validate", tmp_path, "--json")
    assert proc.returncode == 1
    entries = {Path(e["source"]).name: e for e in json.loads(proc.stdout)["episodes"]}
    assert entries["good.json"]["status"] == "accepted"
    assert entries["nan.json"]["status"] == "rejected"
    assert entries["nan.json"]["errors"] == [f"{nan_file}: step 0: action.command[1]: nan is not a finite number"]
    assert entries["broken.json"]["status"] == "rejected" and entries["broken.json"]["steps"] == 0
    assert entries["broken.json"]["errors"][0].startswith(str(tmp_path / "broken.json"))

    human = run_cli(repo_root, "validate", nan_file)
    assert human.returncode == 1
    assert f"    error: {nan_file}: step 0: action.command[1]: nan is not a finite number" in human.stdout.splitlines()


def test_missing_path_is_a_usage_error(repo_root, tmp_path):
    write_episode_json(tmp_path / "good.json")
    proc = run_cli(repo_root, "validate", tmp_path / "good.json", tmp_path / "missing.json", "--json")
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert str(tmp_path / "missing.json") in proc.stderr
    assert run_cli(repo_root, "validate", tmp_path, "--profile", "strict").returncode == 2


def test_cloud_profile(repo_root, tmp_path):
    plain = write_episode_json(tmp_path / "plain.json")
    proc = run_cli(repo_root, "validate", plain, "--profile", "cloud", "--json")
    assert proc.returncode == 1
    [entry] = json.loads(proc.stdout)["episodes"]
    assert f"{plain}: metadata.robot_type: missing robot_type (or robot_model), required by the upload package" \
        in entry["errors"]
    assert run_cli(repo_root, "validate", plain).returncode == 0  # train profile is content only

    ready = write_episode_json(tmp_path / "ready" / "ready.json", robot_model="so-arm101", safety=SAFETY,
                               share={"public": True, "slug": "s", "title": "T", "license": "MIT", "tags": ["a"]})
    proc = run_cli(repo_root, "validate", ready, "--profile", "cloud", "--json")
    assert proc.returncode == 0, proc.stdout
    assert json.loads(proc.stdout)["episodes"][0]["status"] == "accepted"


# -- ingest and export --------------------------------------------------------------------------

def test_ingest_cli(repo_root, tmp_path):
    src = tmp_path / "src"
    write_episode_json(src / "a.json")
    ds = tmp_path / "ds"
    proc = run_cli(repo_root, "ingest", src, "--into", ds, "--json")
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert [(e["episode_id"], e["action"]) for e in result["episodes"]] == [("a", "written")]
    again = run_cli(repo_root, "ingest", src, "--into", ds)
    assert again.returncode == 0
    assert again.stdout.splitlines()[0].split()[:3] == ["unchanged", "3", "steps"]
    assert run_cli(repo_root, "validate", ds, "--profile", "train").returncode == 0

    (src / "b.json").write_text('{"steps": [{"observation": {"x": [1.0]}, "action": {}, "reward": Infinity}]}')
    proc = run_cli(repo_root, "ingest", src, "--into", ds, "--json")
    assert proc.returncode == 1
    rejected = json.loads((ds / "manifest.json").read_text())["rejected"]
    assert rejected == [{"source": str(src / "b.json"), "episode_id": "b",
                         "reasons": [f"{src / 'b.json'}: step 0: reward: inf is not a finite number"]}]
    assert not (ds / "b").exists()

    missing = run_cli(repo_root, "ingest", tmp_path / "nope", "--into", ds)
    assert missing.returncode == 2 and str(tmp_path / "nope") in missing.stderr


def test_export_cli_refuses_then_allows(repo_root, tmp_path):
    plain = write_episode_json(tmp_path / "plain.json")
    out = tmp_path / "out"
    proc = run_cli(repo_root, "export", "--cloud", plain, "--out", out)
    assert proc.returncode == 1
    assert "refused" in proc.stdout and "metadata.safety: missing safety block" in proc.stdout
    assert "--allow-invalid" in proc.stderr
    assert not out.exists() or list(out.iterdir()) == []

    proc = run_cli(repo_root, "export", "--cloud", plain, "--out", out, "--allow-invalid", "--json")
    assert proc.returncode == 0
    [entry] = json.loads(proc.stdout)["episodes"]
    assert (entry["action"], entry["ok"], entry["package"]) == ("exported", False, str(out / "plain.tar.gz"))

    assert run_cli(repo_root, "export", plain, "--out", out).returncode == 2  # no --cloud
    assert run_cli(repo_root, "export", "--cloud", tmp_path / "nope", "--out", out).returncode == 2


def test_export_out_must_be_a_directory(repo_root, tmp_path):
    ready = write_episode_json(tmp_path / "ready.json", robot_type="rc", safety=SAFETY)
    (tmp_path / "file").write_text("x")
    proc = run_cli(repo_root, "export", "--cloud", ready, "--out", tmp_path / "file")
    assert proc.returncode == 2 and "exists and is not a directory" in proc.stderr
    proc = run_cli(repo_root, "export", "--cloud", ready, "--out", tmp_path / "out", "--json")
    assert proc.returncode == 0
    assert json.loads(proc.stdout)["summary"] == {"exported": 1, "refused": 0, "skipped": 0, "ok": True}
    assert (tmp_path / "out" / "ready.tar.gz").is_file()
