"""ContinuonCloud's upload format: `export --cloud --format npz` and the npz reader, round trip and refusals."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from hope_models.data.cache import load_or_build
from hope_models.data.export_npz import NpzTooLarge, episode_spec, export_npz_paths, write_cloud_npz
from hope_models.data.extract import group_matrix
from hope_models.data.features import FeatureSpec
from hope_models.data.source import iter_sources
from hope_models.data.spec_request import SpecRequest
from hope_models.durable import file_sha256
from hope_models.rlds.discover import read_path
from hope_models.rlds.ingest import ingest_paths
from hope_models.rlds.read_npz import CLOUD_MAX_BYTES, sidecar_path
from hope_models.rlds.validation_report import validate_paths
from hope_models.sim.recorder import record_dataset

REPO = Path(__file__).resolve().parents[1]
SAMPLE = "history/continuonbrain/rlds/episodes/studio_mock_editor.json"  # 3 steps, 89 + 6 numbers, epoch ns


def only_episode(path: Path):
    reports = read_path(path)
    episodes = [ep for r in reports for ep in r.episodes]
    assert len(episodes) == 1, [str(p) for r in reports for p in r.problems]
    return episodes[0]


def export_one(source: Path, out: Path, **kwargs) -> tuple[Path, dict]:
    result = export_npz_paths([source], out, **kwargs)
    assert result["summary"]["ok"], result
    (entry,) = result["episodes"]
    npz = Path(entry["package"])
    return npz, json.loads(sidecar_path(npz).read_text())


def spec_of(sidecar: dict) -> FeatureSpec:
    """The sidecar's spec (no statistics: it is an override file as --spec takes it)."""
    request = SpecRequest.from_json_obj(sidecar["spec"], "sidecar spec")
    return FeatureSpec(request.observation.resolved(), request.action.resolved())


def assert_same_through_spec(original, back, spec: FeatureSpec) -> None:
    """The spec compiles both episodes to the same arrays (float32 rounding aside) and the
    rewards, clock and terminal flags are the same."""
    for group in (spec.observation, spec.action):
        a, b = group_matrix(original.steps, group), group_matrix(back.steps, group)
        np.testing.assert_array_equal(a.astype(np.float32), b)
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)
    assert [np.float32(s.reward) for s in original.steps] == [np.float32(s.reward) for s in back.steps]
    assert [s.timestamp_ns for s in back.steps] == [s.timestamp_ns for s in original.steps]
    assert [s.is_terminal for s in back.steps] == [s.is_terminal for s in original.steps]


@pytest.fixture
def sample_pair(samples_dir: Path, tmp_path: Path) -> tuple[Path, Path, dict]:
    source = samples_dir / SAMPLE
    npz, sidecar = export_one(source, tmp_path / "out")
    return source, npz, sidecar


def test_real_sample_round_trip(sample_pair):
    source, npz, sidecar = sample_pair
    original = only_episode(source)
    with np.load(npz, allow_pickle=False) as data:  # what the backend stores, opened the plain way
        assert sorted(data.files) == ["actions", "observations", "rewards", "timestamps"]
        assert (data["observations"].shape, data["observations"].dtype) == ((3, 89), np.float32)
        assert (data["actions"].shape, data["actions"].dtype) == ((3, 6), np.float32)
        assert (data["rewards"].dtype, data["timestamps"].dtype) == (np.float32, np.float64)
        np.testing.assert_allclose(data["timestamps"], [0.0, 0.05, 0.1])
    assert sidecar["query"] == {"episode_id": "studio_mock_editor", "task_name": None, "duration_seconds": 0.1,
                                "num_steps": 3, "success": None}
    assert sidecar["npz"] == {"file": npz.name, "bytes": npz.stat().st_size, "sha256": file_sha256(npz)}
    assert sidecar["arrays"]["timestamps"]["origin_ns"] == original.steps[0].timestamp_ns
    spec = spec_of(sidecar)
    assert [f["path"] for f in sidecar["arrays"]["observations"]["fields"]] == [f.path for f in spec.observation.fields]
    back = only_episode(npz)
    assert back.layout == "cloud_npz" and back.episode_id == "studio_mock_editor" and not back.errors
    assert back.metadata["environment_id"] == original.metadata["environment_id"]
    assert_same_through_spec(original, back, spec)


def test_ingest_and_the_dataset_pipeline_read_the_pair(sample_pair, tmp_path: Path):
    source, npz, sidecar = sample_pair
    assert list(iter_sources(npz.parent)) == [npz]  # the sidecar is not a source of its own
    report = validate_paths([npz.parent], "train")
    assert report["summary"]["episodes"] == 1 and report["summary"]["ok"] and not report["skipped"]
    result = ingest_paths([npz.parent], tmp_path / "ds")
    assert result["summary"]["written"] == 1, result
    spec = spec_of(sidecar)
    assert_same_through_spec(only_episode(source), only_episode(tmp_path / "ds" / "studio_mock_editor"), spec)
    assert only_episode(sidecar_path(npz)).source == str(npz)  # naming the sidecar means its npz


def test_sim_reacher_round_trip(tmp_path: Path):
    recorded = record_dataset(tmp_path / "sim", 1, seed=900, task="reach", noise=0.3).episodes[0]
    npz, sidecar = export_one(recorded.path, tmp_path / "out")
    original, back = only_episode(recorded.path), only_episode(npz)
    spec = spec_of(sidecar)
    assert [f.path for f in spec.all_fields()] == ["observation.robot_state.joint_positions",
                                                   "observation.robot_state.joint_velocities",
                                                   "observation.target_offset", "action.command"]
    assert sidecar["query"]["task_name"] == "reach" and sidecar["query"]["num_steps"] == recorded.steps
    assert sum(s.reward for s in back.steps) > 0  # real rewards went through
    assert_same_through_spec(original, back, spec)
    # the same episode exported twice is the same bytes
    again, _ = export_one(recorded.path, tmp_path / "again")
    assert again.read_bytes() == npz.read_bytes()
    # the dataset pipeline compiles the npz dir like any other dataset, to the exported arrays
    cache, _ = load_or_build(npz.parent, tmp_path / "cache")
    assert [f.path for f in cache.spec.all_fields()] == [f.path for f in spec.all_fields()]
    with np.load(npz, allow_pickle=False) as data:
        np.testing.assert_array_equal(cache.obs, data["observations"])
        np.testing.assert_array_equal(cache.act, data["actions"])


def hand_episode(path: Path, drop_at: int | None = None) -> Path:
    steps = []
    for i in range(4):
        obs = {"robot_state": {"joint_positions": [0.1 * i, 1.5, -2.0]}, "gripper_closed": i % 2 == 1,
               "force": 1e-3 * i}
        if i == drop_at:
            del obs["robot_state"]["joint_positions"]
        steps.append({"observation": obs, "action": {"command": [0.5, -0.25 * i]}, "reward": float(i),
                      "is_terminal": i == 3, "timestamp_ns": 1_764_952_865_006_200_431 + i * 33_333_333})
    doc = {"metadata": {"episode_id": "hand", "task_name": "pick", "success": True, "xr_mode": "trainer"},
           "steps": steps}
    path.write_text(json.dumps(doc))
    return path


def test_types_and_query_fields_come_back(tmp_path: Path):
    source = hand_episode(tmp_path / "hand.json")
    npz, sidecar = export_one(source, tmp_path / "out")
    assert sidecar["query"] == {"episode_id": "hand", "task_name": "pick", "duration_seconds": 0.099999999,
                                "num_steps": 4, "success": True}
    kinds = {f["path"]: f["kind"] for f in sidecar["arrays"]["observations"]["fields"]}
    assert kinds == {"observation.force": "number", "observation.gripper_closed": "bool",
                     "observation.robot_state.joint_positions": "vector"}
    back = only_episode(npz)
    assert back.steps[1].observation == {"force": pytest.approx(1e-3), "gripper_closed": True,
                                         "robot_state": {"joint_positions": [pytest.approx(0.1), 1.5, -2.0]}}
    assert [s.reward for s in back.steps] == [0.0, 1.0, 2.0, 3.0]
    assert_same_through_spec(only_episode(source), back, spec_of(sidecar))


def test_episode_that_does_not_fit_the_spec_is_refused_with_step_and_field(tmp_path: Path):
    source = hand_episode(tmp_path / "hand.json", drop_at=2)
    request = SpecRequest.from_json_obj({"observation": {"fields": ["observation.robot_state.joint_positions"]},
                                         "action": {"fields": ["action.command"]}}, "test spec")
    result = export_npz_paths([source], tmp_path / "out", request)
    (entry,) = result["episodes"]
    assert entry["action"] == "refused" and not result["summary"]["ok"]
    assert "step 2: observation.robot_state.joint_positions: missing" in entry["errors"][0], entry["errors"]
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_over_the_size_limit_is_refused_with_its_size_and_nothing_written(tmp_path: Path):
    source = hand_episode(tmp_path / "hand.json")
    ep = only_episode(source)
    spec = episode_spec(ep)
    out = tmp_path / "out"
    data_bytes = 4 * 4 * (3 + 1 + 1) + 4 * 4 * 2 + 4 * 4 + 8 * 4  # the arrays alone
    with pytest.raises(NpzTooLarge, match=rf"over {data_bytes} bytes, above the cloud's limit of 100 bytes"):
        write_cloud_npz(ep, spec, out, max_bytes=100)
    # the arrays fit, the archive around them does not: caught after writing, the temp file removed
    with pytest.raises(NpzTooLarge, match=rf"its npz is \d+ bytes, above the cloud's limit of {data_bytes}"):
        write_cloud_npz(ep, spec, out, max_bytes=data_bytes)
    assert list(out.iterdir()) == []
    result = export_npz_paths([source], out, max_bytes=data_bytes)
    assert result["episodes"][0]["action"] == "refused" and "bytes, above the cloud's limit" in \
        result["episodes"][0]["errors"][0]
    assert CLOUD_MAX_BYTES == 100 * 1024 * 1024  # the backend's own check: len(content) > 100 * 1024 * 1024


class Evil:
    """Unpickling this opens (creates) the marker file: the proof that nothing was unpickled."""

    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def rewrite(npz: Path, arrays: dict, sidecar: dict | None = None) -> None:
    np.savez(npz, **arrays)  # np.savez pickles object arrays: the hostile file
    doc = sidecar or json.loads(sidecar_path(npz).read_text())
    doc["npz"]["sha256"] = file_sha256(npz)  # a consistent pair: only the content is wrong
    sidecar_path(npz).write_text(json.dumps(doc))


def read_error(npz: Path) -> str:
    reports = read_path(npz)
    assert len(reports) == 1 and not reports[0].episodes
    return " | ".join(str(p) for p in reports[0].problems)


def test_pickled_object_arrays_are_refused_unopened(sample_pair, tmp_path: Path):
    _, npz, _ = sample_pair
    marker = tmp_path / "unpickled"
    with np.load(npz) as data:
        arrays = {k: data[k] for k in data.files}
    evil = np.empty(arrays["observations"].shape, dtype=object)
    evil[...] = Evil(str(marker))
    arrays["observations"] = evil
    rewrite(npz, arrays)
    message = read_error(npz)
    assert str(npz) in message and "observations" in message and "pickle" in message
    assert not marker.exists()
    proc = subprocess.run([sys.executable, "run_trainer.py", "validate", str(npz)], cwd=REPO, capture_output=True,
                          text=True, timeout=120, env=cli_env(tmp_path))
    assert proc.returncode == 1 and "pickle" in proc.stdout
    assert not marker.exists()


def test_shapes_that_differ_from_the_sidecar_are_rejected(sample_pair):
    _, npz, sidecar = sample_pair
    with np.load(npz) as data:
        arrays = {k: data[k] for k in data.files}
    rewrite(npz, dict(arrays, actions=arrays["actions"][:, :5]), sidecar)
    message = read_error(npz)
    assert "actions: shape [3, 5]" in message and "says [3, 6]" in message and str(npz) in message
    rewrite(npz, dict(arrays, rewards=arrays["rewards"][:2]), sidecar)
    assert "rewards: shape [2]" in read_error(npz)
    # a sidecar whose own shape and fields disagree names its key
    broken = json.loads(json.dumps(sidecar))
    broken["arrays"]["observations"]["shape"] = [3, 88]
    rewrite(npz, arrays, broken)
    assert "arrays.observations: shape [3, 88], but its fields add up to 89 columns" in read_error(npz)
    # an extra member the sidecar does not list
    rewrite(npz, dict(arrays, extra=np.zeros(3)), sidecar)
    assert "extra.npy" in read_error(npz)


def test_pair_from_two_exports_and_missing_sidecar_are_clear_errors(sample_pair, tmp_path: Path):
    _, npz, sidecar = sample_pair
    with zipfile.ZipFile(npz, "a") as archive:  # the npz changed after its sidecar was written
        archive.writestr("note.txt", "x")
    assert "sha256 differs from the one in its sidecar" in read_error(npz)
    sidecar_path(npz).unlink()
    message = read_error(npz)
    assert f"no sidecar {npz.name}.json beside it" in message and str(npz) in message
    proc = subprocess.run([sys.executable, "run_trainer.py", "ingest", str(npz), "--into", str(tmp_path / "ds")],
                          cwd=REPO, capture_output=True, text=True, timeout=120, env=cli_env(tmp_path))
    assert proc.returncode == 1 and "no sidecar" in proc.stdout + proc.stderr
    assert not (tmp_path / "ds").exists() or not any(p.is_dir() for p in (tmp_path / "ds").iterdir())


def cli_env(tmp_path: Path) -> dict[str, str]:
    return {**os.environ, "HOPE_HOME": str(tmp_path / "home")}


def test_cli_export_npz_and_its_exit_codes(tmp_path: Path, samples_dir: Path):
    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "run_trainer.py", "export", *args], cwd=REPO, capture_output=True,
                              text=True, timeout=120, env=cli_env(tmp_path))

    good, bad = samples_dir / SAMPLE, hand_episode(tmp_path / "bad.json", drop_at=2)
    proc = cli("--cloud", "--format", "npz", str(good), "--out", str(tmp_path / "out"), "--json")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["episodes"][0]["sidecar"] == str(tmp_path / "out" / "studio_mock_editor.npz.json")
    proc = cli("--cloud", "--format", "npz", str(good), str(bad), "--out", str(tmp_path / "out2"))
    assert proc.returncode == 1 and "step 2: observation.robot_state.joint_positions: missing" in proc.stdout
    assert (tmp_path / "out2" / "studio_mock_editor.npz").is_file()  # the good one is still written
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"observation": {"fields": ["observation.gaze.direction"]}}))
    proc = cli("--cloud", "--format", "npz", "--spec", str(spec), str(good), "--out", str(tmp_path / "out3"))
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (side,) = [json.loads(p.read_text()) for p in (tmp_path / "out3").glob("*.npz.json")]
    assert side["arrays"]["observations"]["shape"] == [3, 3]
    # usage errors: no --cloud, --spec with the package, an unreadable spec
    assert cli("--format", "npz", str(good), "--out", str(tmp_path / "x")).returncode == 2
    assert cli("--cloud", "--spec", str(spec), str(good), "--out", str(tmp_path / "x")).returncode == 2
    proc = cli("--cloud", "--format", "npz", "--spec", str(tmp_path / "nope.json"), str(good), "--out",
               str(tmp_path / "x"))
    assert proc.returncode == 2 and "nope.json" in proc.stderr
    # the default is still the Pi runtime's package
    proc = cli("--cloud", "--allow-invalid", str(good), "--out", str(tmp_path / "pkg"))
    assert proc.returncode == 0 and (tmp_path / "pkg" / "studio_mock_editor.tar.gz").is_file()
