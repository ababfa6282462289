"""`run_trainer.py demo --camera` end to end, small: a real subprocess on its own HOPE_HOME records 4
camera demonstrations in 2 sim-demos children (full 1000-step episodes: frames rendered with EGL),
queues the chain with the camera recipe (here --steps 30 for every member), gates and promotes,
serves the camera fast_loop through BrainService and infers over HTTP with the first frame,
evaluates the reflex from pixels (eval-reflex, EGL) while the Mid Loop trains, and exits.

About 3 minutes on 2 cores: marked heavy, outside `make test` (`make test-heavy`). 30 steps are too
few for the tokenizer and the Mid Loop to beat their baselines, so the gate refuses both and the
demo reports those as its shortfalls (exit 1); a stage that fails outright would stop it with exit
1 and no summary (tests/test_demo_camera.py). The full-size figures are docs/reflex.md's.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hope_models.components import ACTOR, PREDICTOR, TOKENIZER
from hope_trainer.demo.camera import GRID_TOKENIZER

pytestmark = [pytest.mark.slow, pytest.mark.heavy]

REPO = Path(__file__).resolve().parents[1]
STEPS = 30


def _env(home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_") and k != "MUJOCO_GL"}
    env.update({"HOPE_HOME": str(home), "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1",
                "HOPE_THERMAL_ZONE": str(home / "no-thermal-zone"), "HOPE_VCGENCMD": ""})
    return env


def test_demo_camera_short_runs_the_whole_loop_on_frames(tmp_path):
    home = tmp_path / "home"
    argv = [sys.executable, str(REPO / "run_trainer.py"), "demo", "--camera", "--episodes", "4", "--steps", str(STEPS),
            "--eval-episodes", "2", "--target-return", "0", "--exit", "--port", "0"]
    proc = subprocess.run(argv, cwd=REPO, env=_env(home), capture_output=True, text=True, timeout=900)
    out = proc.stdout
    assert proc.returncode == 1, f"exit {proc.returncode}\n{out}\n{proc.stderr[-3000:]}"

    # 1. the recording: 4 camera episodes from 2 children, seeds 100000-100003
    data = home / "demo" / "camera" / "reach-4-dart1"
    episodes = sorted(p.name for p in data.iterdir())
    assert episodes == [f"dmc-reacher-reach-s{100000 + i:06d}" for i in range(4)]
    first = json.loads((data / episodes[0] / "steps" / "000000.jsonl").read_text().splitlines()[0])
    assert set(first["observation"]) == {"robot_state", "camera"}  # nothing about the target
    assert "recording 4 expert episodes of the reacher seen by its top-down camera" in out and "in 2 processes" in out

    summary = json.loads((home / "demo" / "camera" / "summary.json").read_text())
    rows = {r["component"]: r for r in summary["components"]}
    assert list(rows) == [TOKENIZER, ACTOR, PREDICTOR]
    for r in rows.values():
        assert r["state"] == "completed" and r["steps"] == r["total_steps"] == STEPS, r
        assert math.isfinite(r["first_loss"]) and math.isfinite(r["final_loss"]) and r["peak_rss_mb"] > 50, r
    # the held-out figures: the frame tokenizer's variance and PSNR, the grid Mid Loop's joints and codes
    vq, fast, mid = rows[TOKENIZER], rows[ACTOR], rows[PREDICTOR]
    assert vq["held_out"]["recon_nmse"] > 0 and vq["held_out"]["psnr_db"] > 0
    assert set(mid["held_out"]) == {"0.5s", "1s"} and mid["held_out"]["1s"]["copy_last_joint_mse"] > 0
    assert "of the variance" in out and " dB" in out and "joint error" in out and "nll" in out
    # the undertrained tokenizer and Mid Loop: refused with their figures, the demo's only shortfalls
    assert vq["gate"]["state"] == "refused" and mid["gate"]["state"] == "refused"
    assert [p.split(":")[0] for p in summary["problems"]] == [f"the gate refused the {TOKENIZER}",
                                                              f"the gate refused the {PREDICTOR}"]

    # 4. the camera fast_loop promoted, served, and answering a frame over HTTP
    version = fast["gate"]["version"]
    assert fast["gate"]["state"] == "promoted" and summary["served_version"] == version
    inference = summary["inference"]
    assert inference["model_version"] == version and len(inference["action"]) == 2
    assert len(inference["observation"]) == 4  # the joints; the frame went beside them
    assert isinstance(summary["loop_closure_s"], float) and summary["loop_closure_s"] >= 0

    # 5. the reflex from pixels on held-out seeds 0-1, begun while the Mid Loop trained
    reflex = summary["reflex"]
    assert reflex["version"] == version and reflex["episodes"] == 2 and reflex["seeds"] == [0, 1]
    assert reflex["expert_mean_return"] > 900 and 0 <= reflex["mean_return"] <= 1000
    assert out.index("5. reflex:") < out.index(f"completed: {mid['run_id']}")
    assert "mean return" in out and "| expert" in out and "| random" in out

    # every stage's wall time, and in the printed line
    timings = summary["timings"]
    assert set(timings) == {"demos", "training", TOKENIZER, ACTOR, PREDICTOR, "reflex", "total"}
    assert all(v > 0 for v in timings.values()) and "time: demos" in out

    # the chain: one sequence, each member with its recipe, the readers on the chain's tokenizer
    from hope_models.settings import load_settings
    from registry.db import Registry
    from registry.models import Run

    with Registry.open(load_settings(env=_env(home))) as registry, registry.session(readonly=True) as s:
        runs = {r.component: r for r in s.query(Run).all()}
        assert len({r.sequence_id for r in runs.values()}) == 1
        assert runs[TOKENIZER].config["model_config"] == GRID_TOKENIZER and runs[TOKENIZER].config["lr"] == 2e-3
        assert runs[ACTOR].config["vqvae_run"] == runs[PREDICTOR].config["vqvae_run"] == runs[TOKENIZER].id
