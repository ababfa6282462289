"""examples/data_tour.py as a new user runs it: a real subprocess, its own HOPE_HOME."""
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOUR = REPO / "examples" / "data_tour.py"


def _tour(home: Path, *extra: str) -> dict:
    env = dict(os.environ, HOPE_HOME=str(home))
    proc = subprocess.run([sys.executable, str(TOUR), "--steps", "4000", "--train-steps", "60", "--json", *extra],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    return json.loads(proc.stdout)


def test_tour_end_to_end_then_rerun_changes_nothing(tmp_path):
    first = _tour(tmp_path)
    assert first["ok"] is True
    assert first["out"] == str(tmp_path / "data_tour")
    # the messy sources: one NaN file rejected, one metadata-only dir skipped, the rest in
    assert first["validate"]["rejected"] == 1 and first["validate"]["skipped"] == 1
    assert first["ingest_first"]["written"] == first["dataset"]["episodes"]
    assert first["ingest_second"]["written"] == 0
    assert first["dataset"]["obs_dim"] == 20 and first["dataset"]["act_dim"] == 6
    assert set(first["dataset"]["rates"]) == {"10 Hz", "20 Hz", "50 Hz"}
    assert first["sampler_resume_identical"] is True
    trained = {r["component"]: r for r in first["training"]}
    assert list(trained) == ["vqvae", "fast_loop", "mid_loop"]
    for r in trained.values():
        assert r["outcome"] == "completed" and r["steps"] == 60, r
        assert r["final_loss"] < r["first_loss"], r
        assert Path(r["checkpoint"]).is_dir()

    again = _tour(tmp_path)
    assert again["ingest_first"]["written"] == 0  # the episodes from the first run are all there
    assert again["dataset"]["fingerprint"] == first["dataset"]["fingerprint"]
    # re-running finds every component finished: same checkpoints, nothing retrained
    assert [r["checkpoint"] for r in again["training"]] == [r["checkpoint"] for r in first["training"]]


def test_tour_refuses_a_too_small_dataset(tmp_path):
    env = dict(os.environ, HOPE_HOME=str(tmp_path))
    proc = subprocess.run([sys.executable, str(TOUR), "--steps", "10"],
                          capture_output=True, text=True, env=env, timeout=60)
    assert proc.returncode == 2
    assert "--steps" in proc.stderr


def test_the_documented_minimum_runs_from_any_directory(tmp_path):
    # 2000 steps make only a few episodes: the messy sources reuse them, and none is imagined
    env = dict(os.environ, HOPE_HOME=str(tmp_path))
    proc = subprocess.run([sys.executable, str(TOUR), "--steps", "2000", "--train-steps", "0", "--json"],
                          capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    result = json.loads(proc.stdout)
    assert result["ok"] is True and result["training"] == []
    assert result["validate"]["rejected"] == 1 and result["validate"]["skipped"] == 1
    assert result["sampler_resume_identical"] is True
