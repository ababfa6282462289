"""`run_trainer.py dataset`, summarise_dataset and the synthetic dataset generator."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hope_models.data.summary import summarise_dataset
from hope_models.rlds.discover import read_path

REPO = Path(__file__).resolve().parents[1]


from hope_models.data import synthetic as gen  # noqa: E402


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "dataset", *args],
                          capture_output=True, text=True, cwd=REPO, timeout=120)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    ds = tmp_path_factory.mktemp("ds")
    gen.generate_dataset(ds, 3000, obs_dim=6, act_dim=2, rates_hz=(10, 20, 50), seed=5, episode_seconds=(3, 9),
                         imagined_fraction=0.2)
    gen.write_episode(ds, "zz_three_joints", [{"timestamp_ns": i * 10**8, "observation": {"robot_state": {
        "joint_positions": [0.0] * 2, "joint_velocities": [0.0] * 3}}, "action": {"command": [0.0, 0.0]}} for i in range(4)])
    return ds


def test_generator_writes_canonical_episodes_the_readers_accept(tmp_path):
    g = gen.generate_dataset(tmp_path / "g", 1234, obs_dim=5, act_dim=3, rates_hz=(10, 50), seed=9,
                             episode_seconds=(2, 5), imagined_fraction=0.5)
    assert g.steps == 1234 and g.imagined_episodes == round(g.episodes * 0.5)
    episodes = [ep for r in read_path(tmp_path / "g") for ep in r.episodes]
    assert len(episodes) == g.episodes and sum(len(ep.steps) for ep in episodes) == 1234
    for ep in episodes:
        assert ep.layout == "canonical_dir" and not ep.errors, ep.problems
        assert ep.metadata["schema_version"] == "1.1"
        assert ep.is_imagined == ep.episode_id.startswith("imag_")
        step = ep.steps[1]
        assert len(step.observation["robot_state"]["joint_positions"]) == 2
        assert len(step.observation["robot_state"]["joint_velocities"]) == 3
        assert len(step.action["command"]) == 3
        period = ep.steps[1].timestamp_ns - ep.steps[0].timestamp_ns
        assert period in (100_000_000, 20_000_000)


def test_summary_reports_everything_the_issue_lists(dataset, tmp_path):
    s = summarise_dataset(dataset, tmp_path / "cache")
    n_eps = len([p for p in dataset.iterdir() if p.is_dir()])
    assert s["episodes"] == n_eps - 1 and s["steps"] == 3000
    assert set(s["rates"]) == {"10 Hz", "20 Hz", "50 Hz"}
    assert s["imagined_episodes"] > 0
    assert s["obs_dim"] == 6 and s["act_dim"] == 2
    assert [f["path"] for f in s["action_fields"]] == ["action.command"]
    assert s["excluded"] == [{"episode_id": "zz_three_joints", "source": str(dataset / "zz_three_joints"),
                              "reason": "step 0: observation.robot_state.joint_positions: has 2 values, the spec needs 3"}]
    assert not s["reused"] and s["build_seconds"] > 0
    assert s["duration_s"]["min"] <= s["duration_s"]["median"] <= s["duration_s"]["max"]
    assert s["split"]["train_episodes"] + s["split"]["val_episodes"] == s["episodes"]
    again = summarise_dataset(dataset, tmp_path / "cache")
    assert again["reused"] and again["fingerprint"] == s["fingerprint"] and again["cache_path"] == s["cache_path"]


def test_cli_prints_a_summary_and_json(dataset, tmp_path):
    text = _run(str(dataset), "--cache-dir", str(tmp_path / "c"))
    assert text.returncode == 0, text.stderr
    assert "built in" in text.stdout and "excluded     1 episode(s):" in text.stdout
    assert "zz_three_joints: step 0: observation.robot_state.joint_positions: has 2 values" in text.stdout
    js = _run(str(dataset), "--cache-dir", str(tmp_path / "c"), "--json")
    assert js.returncode == 0, js.stderr
    out = json.loads(js.stdout)
    assert out["ok"] and out["reused"] and out["steps"] == 3000


def test_cli_bad_input_is_an_error_message_not_a_traceback(dataset, tmp_path):
    missing = _run(str(tmp_path / "nope"), "--cache-dir", str(tmp_path / "c"))
    assert missing.returncode == 2 and "dataset dir not found" in missing.stderr and "Traceback" not in missing.stderr
    bad_spec = tmp_path / "spec.json"
    bad_spec.write_text('{"observation": {"fields": ["observation.robot_state.nothing_here"]}}')
    res = _run(str(dataset), "--cache-dir", str(tmp_path / "c"), "--spec", str(bad_spec), "--json")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert "observation.robot_state.nothing_here: named in the spec override but no episode has it" in res.stderr
    assert json.loads(res.stdout)["ok"] is False
