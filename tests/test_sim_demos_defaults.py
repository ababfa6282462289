"""sim-demos with no --noise records the recipe's demos (DART 1.0); play with no --noise still records.

The recipe of docs/reflex.md (50 demos with DART noise 1.0) is what every learning figure rests on; a
user who leaves --noise out must get it, and play (which has no label for noise to keep) must not
trip over that default: only a --noise the user wrote is refused with --policy play.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from hope_models.rlds.discover import read_path

REPO = Path(__file__).resolve().parents[1]
RECIPE_NOISE = 1.0  # docs/reflex.md, "What the recipe needs"


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "run_trainer.py", "sim-demos", *args, "--episodes", "1", "--steps", "4",
                           "--json"], cwd=REPO, capture_output=True, text=True, timeout=120,
                          env={**os.environ, "MUJOCO_GL": "disabled"})


def _only_episode(path: Path):
    (episode,) = [ep for report in read_path(path) for ep in report.episodes]
    return episode


def test_expert_demos_default_to_the_recipes_dart_noise(tmp_path):
    proc = _cli("--out", str(tmp_path / "d"))
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["noise"] == RECIPE_NOISE
    ep = _only_episode(tmp_path / "d")
    assert ep.metadata["provenance"]["sim"]["noise_std"] == RECIPE_NOISE
    assert ep.metadata["provenance"]["sim"]["policy"] == "expert" and "dart_noise" in ep.metadata["tags"]
    # DART: the executed command carries the noise, the label stays the expert's
    assert all(s.action["executed_command"] != s.action["command"] for s in ep.steps)


def test_noise_zero_still_records_clean_demos(tmp_path):
    proc = _cli("--out", str(tmp_path / "d"), "--noise", "0")
    assert proc.returncode == 0, proc.stderr
    ep = _only_episode(tmp_path / "d")
    assert ep.metadata["provenance"]["sim"]["noise_std"] == 0.0 and "dart_noise" not in ep.metadata["tags"]
    assert all("executed_command" not in s.action for s in ep.steps)


def test_play_without_noise_records_play_and_an_explicit_noise_is_refused(tmp_path):
    proc = _cli("--out", str(tmp_path / "p"), "--policy", "play")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["noise"] == 0.0
    ep = _only_episode(tmp_path / "p")
    assert ep.metadata["provenance"]["sim"] == {**ep.metadata["provenance"]["sim"], "policy": "play", "noise_std": 0.0}
    refused = _cli("--out", str(tmp_path / "q"), "--policy", "play", "--noise", "1")
    assert refused.returncode == 2 and "--noise" in json.loads(refused.stdout)["error"]
    assert not (tmp_path / "q").exists()
