"""`train --sequential`: each component in its own process, the parent never imports torch."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hope_models.data.synthetic import generate_dataset
from hope_models import checkpoints as ckpt
from hope_models.components.chain import SequenceError, parse_sequence

REPO = Path(__file__).resolve().parents[1]

# Runs the CLI's main() in this interpreter, then reports which heavy modules the parent imported.
PARENT = """
import json, sys
sys.path.insert(0, {repo!r})
import run_trainer
code = run_trainer.main({argv!r})
print(json.dumps({{"exit": code, "torch": "torch" in sys.modules, "numpy": "numpy" in sys.modules}}),
      file=sys.stderr)
"""


@pytest.fixture(scope="module")
def ds(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("seq")
    generate_dataset(root / "ds", 3000, obs_dim=6, act_dim=2, episode_seconds=(3, 9), seed=2)
    return root


def _parent(argv: list[str]) -> tuple[subprocess.CompletedProcess, dict]:
    proc = subprocess.run([sys.executable, "-c", PARENT.format(repo=str(REPO), argv=argv)], capture_output=True,
                          text=True, timeout=300, cwd=REPO)
    report = json.loads(proc.stderr.strip().splitlines()[-1])
    return proc, report


def test_three_components_in_child_processes_parent_free_of_torch(ds, tmp_path):
    run = tmp_path / "run"
    argv = ["train", "--sequential", "vqvae,fast_loop,mid_loop", "--data", str(ds / "ds"), "--run-dir", str(run),
            "--steps", "30", "--seed", "1", "--batch-size", "16", "--threads", "1", "--checkpoint-every", "10",
            "--cache-dir", str(ds / "cache"), "--thermal-zone", str(tmp_path / "none"), "--json"]
    proc, report = _parent(argv)
    assert report == {"exit": 0, "torch": False, "numpy": False}, proc.stderr[-3000:]
    rows = json.loads(proc.stdout.strip().splitlines()[-1])
    assert [r["component"] for r in rows] == ["vqvae", "fast_loop", "mid_loop"]
    vq_ckpt = str(run / "vqvae" / "checkpoints" / "00000030")
    for r in rows:
        assert r["outcome"] == "completed" and r["exit_code"] == 0 and r["steps"] == 30
        assert r["checkpoint"] == str(run / r["component"] / "checkpoints" / "00000030")
        assert ckpt.verify(r["checkpoint"]) is None
        # peak RSS per component: polled by the parent and reported by the child, both torch-sized
        assert r["polled_peak_rss_mb"] > 100 and r["child_reported_peak_rss_mb"] > 100
        assert r["peak_rss_mb"] >= max(r["polled_peak_rss_mb"], r["child_reported_peak_rss_mb"]) - 0.1
    assert rows[0]["vqvae"] is None and rows[1]["vqvae"] == vq_ckpt and rows[2]["vqvae"] == vq_ckpt
    mid_cfg = json.loads((Path(rows[2]["checkpoint"]) / "config.json").read_text())
    assert mid_cfg["vqvae"]["path"] == vq_ckpt
    assert "== mid_loop" in proc.stderr  # children's progress passes through

    # re-running resumes: every component is already done
    proc2, report2 = _parent(argv[:-1])  # human table this time
    assert report2["exit"] == 0 and not report2["torch"]
    table = proc2.stdout
    assert table.splitlines()[0].startswith("component") and table.count("completed") == 3


def test_sequence_stops_at_the_first_failure_with_its_message(ds, tmp_path):
    run = tmp_path / "run"
    argv = ["train", "--sequential", "fast_loop,mid_loop", "--data", str(ds / "ds"), "--run-dir", str(run),
            "--steps", "5", "--batch-size", "8", "--threads", "1", "--cache-dir", str(ds / "cache"),
            "--memory-budget-mb", "100", "--json"]
    proc, report = _parent(argv)
    assert report["exit"] == 2 and not report["torch"]
    rows = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(rows) == 1 and rows[0]["component"] == "fast_loop" and rows[0]["outcome"] == "error"
    assert "exceeds the budget of 100 MB" in rows[0]["message"]
    assert "the sequence stopped at fast_loop (error)" in proc.stderr


def test_mid_loop_without_a_vqvae_is_refused_before_any_child(ds, tmp_path):
    argv = ["train", "--sequential", "mid_loop", "--data", str(ds / "ds"), "--run-dir", str(tmp_path / "r"),
            "--steps", "5"]
    proc, report = _parent(argv)
    assert report["exit"] == 2 and "needs a trained VQ-VAE" in proc.stderr + proc.stdout


def test_parse_sequence():
    assert parse_sequence("vqvae, fast_loop,mid_loop") == ["vqvae", "fast_loop", "mid_loop"]
    for bad, msg in (("", "at least one"), ("vqvae,nope", "unknown component"), ("fast_loop,fast_loop", "twice"),
                     ("mid_loop,vqvae", "must come before")):
        with pytest.raises(SequenceError, match=msg):
            parse_sequence(bad)
