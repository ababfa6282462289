"""sim-demos: recorded reacher episodes are canonical RLDS v1.1 that validate with the train profile."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hope_models.data.features import FRAME_SHAPE
from hope_models.rlds.discover import read_path
from hope_models.rlds.validation_report import validate_paths
from hope_models.sim.expert import ExpertController
from hope_models.sim.reacher import CONTROL_PERIOD_S, EPISODE_STEPS, observation_vector
from hope_models.sim.recorder import DEFAULT_SEED_BASE, record_dataset, record_episodes

REPO = Path(__file__).resolve().parents[1]


def _episodes(path: Path):
    eps = [ep for report in read_path(path) for ep in report.episodes]
    return sorted(eps, key=lambda e: e.episode_id)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, object]:
    out = tmp_path_factory.mktemp("demos") / "ds"
    result = record_dataset(out, 2, seed=500, task="reach", noise=0.5)
    record_dataset(out, 1, seed=600, task="track")
    return out, result


def test_recorded_episodes_validate_with_the_train_profile(recorded):
    out, _ = recorded
    report = validate_paths([out], "train")
    assert report["summary"]["ok"] and report["summary"]["rejected"] == 0
    assert report["summary"]["episodes"] == 3
    for entry in report["episodes"]:
        assert entry["ok"] and entry["errors"] == [] and entry["steps"] == EPISODE_STEPS
        # the only warning is the honest, undocumented control role of a scripted expert
        assert all("control_role" in w for w in entry["warnings"]), entry["warnings"]
    # the CLI says the same (exit 0)
    proc = subprocess.run([sys.executable, "run_trainer.py", "validate", str(out), "--profile", "train", "--json"],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["summary"]["ok"] is True


def test_episode_content_metadata_and_clock(recorded):
    out, result = recorded
    eps = _episodes(out)
    assert [e.episode_id for e in eps] == ["dmc-reacher-reach-s000500", "dmc-reacher-reach-s000501",
                                          "dmc-reacher-track-s000600"]
    for ep in eps:
        meta = ep.metadata
        assert meta["schema_version"] == "1.1"
        assert meta["robot_model"] == "dmc-reacher"
        assert meta["provenance"]["origin"] == "sim:dm_control"
        task = meta["provenance"]["sim"]["task"]
        assert meta["environment_id"] == f"dm_control/reacher-{task}" and task in meta["tags"]
        ts = [s.timestamp_ns for s in ep.steps]
        assert ts == [i * int(CONTROL_PERIOD_S * 1e9) for i in range(EPISODE_STEPS)]
        assert [s.is_terminal for s in ep.steps] == [False] * (EPISODE_STEPS - 1) + [True]
        for s in ep.steps[:3]:
            assert set(s.observation) == {"robot_state", "target_offset"}
            assert len(s.observation["robot_state"]["joint_positions"]) == 2
            assert len(s.observation["robot_state"]["joint_velocities"]) == 2
            assert len(s.observation["target_offset"]) == 2
            assert len(s.action["command"]) == 2
        assert sum(s.reward for s in ep.steps) == meta["provenance"]["sim"]["return"]
    assert [round(e.ret) for e in result.episodes] == [round(sum(s.reward for s in ep.steps)) for ep in eps[:2]]


def test_dart_noise_records_expert_labels_but_executes_noisy_actions(recorded):
    out, _ = recorded
    noisy, clean = _episodes(out)[1], _episodes(out)[2]
    expert = ExpertController()
    assert noisy.metadata["provenance"]["sim"]["noise_std"] == 0.5 and "dart_noise" in noisy.metadata["tags"]
    diffs = []
    for s in noisy.steps[:200]:
        label = np.array(s.action["command"])
        np.testing.assert_allclose(label, expert.act(s.observation), rtol=0, atol=1e-12)
        executed = np.array(s.action["executed_command"])
        assert np.all(np.abs(executed) <= 1.0)
        diffs.append(np.abs(executed - label).max())
    assert np.mean(diffs) > 0.1  # the env really was driven off the expert's action
    assert "executed_command" not in clean.steps[0].action
    for s in clean.steps[:50]:
        np.testing.assert_allclose(s.action["command"], expert.act(s.observation), rtol=0, atol=1e-12)


def test_recording_is_deterministic(tmp_path):
    a = record_episodes(tmp_path / "a", 1, seed=7, task="track", noise=0.3)
    b = record_episodes(tmp_path / "b", 1, seed=7, task="track", noise=0.3)
    assert (a[0] / "steps" / "000000.jsonl").read_bytes() == (b[0] / "steps" / "000000.jsonl").read_bytes()


def test_existing_episode_is_not_overwritten(recorded):
    out, _ = recorded
    before = (out / "dmc-reacher-reach-s000500" / "steps" / "000000.jsonl").read_bytes()
    with pytest.raises(FileExistsError, match="dmc-reacher-reach-s000500"):
        record_dataset(out, 1, seed=500, task="reach")
    assert (out / "dmc-reacher-reach-s000500" / "steps" / "000000.jsonl").read_bytes() == before


def test_bad_arguments_are_named(tmp_path):
    with pytest.raises(ValueError, match="task"):
        record_dataset(tmp_path / "x", 1, task="juggle")
    with pytest.raises(ValueError, match="episodes"):
        record_dataset(tmp_path / "x", 0)
    with pytest.raises(ValueError, match="noise"):
        record_dataset(tmp_path / "x", 1, noise=-1.0)


def _cli(*args: str, env: dict | None = None, timeout: int = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "run_trainer.py", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_sim_demos_cli_with_frames_json_shape(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}  # the command picks egl for frames
    out = tmp_path / "frames"
    proc = _cli("sim-demos", "--episodes", "2", "--steps", "6", "--out", str(out), "--frames", "--task", "track",
                "--seed", "42", "--json", env=env)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert res["ok"] is True and res["task"] == "track" and res["frames"] is True and res["seeds"] == [42, 43]
    assert {"out", "noise", "mean_return", "episodes", "elapsed_s"} <= set(res)
    assert [e["seed"] for e in res["episodes"]] == [42, 43] and all(e["steps"] == 6 for e in res["episodes"])
    ep_dir = Path(res["episodes"][0]["path"])
    steps = [json.loads(line) for line in (ep_dir / "steps" / "000000.jsonl").read_text().splitlines()]
    ref = steps[3]["observation"]["media"]["rgb"]
    assert ref == {"uri": "blobs/step_000003_rgb.npy", "width": 64, "height": 64, "format": "npy_uint8_hwc"}
    frames = [np.load(ep_dir / s["observation"]["media"]["rgb"]["uri"], allow_pickle=False) for s in steps]
    assert all(f.shape == FRAME_SHAPE and f.dtype == np.uint8 for f in frames)
    assert frames[0].std() > 5  # a rendered scene, not a blank image
    assert validate_paths([out], "train")["summary"]["ok"]
    # the data layer picks the blob frames up as the frame feature
    from hope_models.data.spec_inference import episode_signature, infer_spec
    ep = _episodes(out)[0]
    spec = infer_spec([episode_signature(ep.episode_id, ep.steps, ep.blob_root)])
    assert spec.frame is not None and spec.frame.path == "observation.media.rgb" and spec.frame.source == "blob"
    assert [f.path for f in spec.observation.fields] == ["observation.robot_state.joint_positions",
                                                        "observation.robot_state.joint_velocities",
                                                        "observation.target_offset"]
    assert [f.path for f in spec.action.fields] == ["action.command"]


def test_sim_demos_cli_defaults_and_usage_errors(tmp_path):
    out = tmp_path / "d"
    proc = _cli("sim-demos", "--episodes", "1", "--steps", "3", "--out", str(out), "--json")
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert res["seeds"] == [DEFAULT_SEED_BASE, DEFAULT_SEED_BASE] and res["task"] == "reach"
    again = _cli("sim-demos", "--episodes", "1", "--steps", "3", "--out", str(out), "--json")
    assert again.returncode == 2 and "already exists" in json.loads(again.stdout)["error"]
    bad = _cli("sim-demos", "--episodes", "0", "--out", str(out))
    assert bad.returncode == 2 and "--episodes" in bad.stderr


def test_observation_vector_matches_the_recorded_block(recorded):
    out, _ = recorded
    s = _episodes(out)[0].steps[5]
    v = observation_vector(s.observation)
    assert v.tolist() == [*s.observation["robot_state"]["joint_positions"],
                          *s.observation["robot_state"]["joint_velocities"], *s.observation["target_offset"]]
