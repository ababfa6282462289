"""`demo --camera` (hope_trainer/demo/camera.py), what can be checked in seconds without training:
the chain it queues, down to the TrainConfig each member's job builds from its run row; the
recording and the evaluation split over processes; the arguments and states it refuses before it
starts; a failed stage stopping it with the stage's name; the evaluations merged and the summary's
lines. The loop itself, trained and served, is tests/test_demo_camera_e2e.py (outside `make test`).
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from hope_models.components import ACTOR, PREDICTOR, TOKENIZER
from hope_trainer.demo.camera import CAMERA, GRID_TOKENIZER, CameraDemo, served_layout_problem
from hope_trainer.demo.report import format_summary, merge_evaluations, split_range
from hope_trainer.demo.shared import COMPONENTS

REPO = Path(__file__).resolve().parents[1]


def _args(**kw) -> argparse.Namespace:
    base = {"episodes": 50, "noise": 1.0, "steps": None, "seed": 0, "eval_episodes": 20, "target_return": 900.0,
            "queue": "pi", "camera": True}
    return argparse.Namespace(**{**base, **kw})


def _settings(home: Path):
    from hope_models.settings import load_settings

    return load_settings(home, env={})


def _demo(tmp_path, recipe=CAMERA, **kw) -> CameraDemo:
    return CameraDemo(_settings(tmp_path / "home"), _args(**kw), recipe)


def test_the_recipe_is_the_documented_one():
    assert GRID_TOKENIZER == {"layout": "grid", "patch": 4, "n_codes": 256, "channels": 16, "decoder_channels": 32,
                              "fg_weight": 10}
    # the Fast Loop's count is the knob the reflex's experiments turn (docs/reflex.md); the others are set
    assert CAMERA.members[TOKENIZER].steps == 2500 and CAMERA.members[PREDICTOR].steps == 3000
    assert CAMERA.members[ACTOR].steps >= 1000
    assert CAMERA.members[TOKENIZER].overrides == {"lr": 2e-3, "threads": 2, "model_config": GRID_TOKENIZER}
    assert CAMERA.members[ACTOR].overrides == {}  # the Fast Loop's own defaults
    assert (CAMERA.frame_size, CAMERA.record_processes, CAMERA.eval_processes) == (64, 2, 1)
    assert set(CAMERA.members) == set(COMPONENTS)


def test_recording_and_evaluation_are_split_over_processes(tmp_path):
    demo = _demo(tmp_path)
    out = tmp_path / "rec"
    argvs = demo.recording_argvs(out)
    assert [a[a.index("--seed") + 1] for a in argvs] == ["100000", "100025"]
    assert [a[a.index("--episodes") + 1] for a in argvs] == ["25", "25"]
    for a in argvs:
        assert a[0] == "sim-demos" and a[a.index("--out") + 1] == str(out)
        assert a[a.index("--observation") + 1] == "camera" and a[a.index("--frame-size") + 1] == "64"
        assert a[a.index("--noise") + 1] == "1.0"
    assert [(a[a.index("--seed") + 1], a[a.index("--episodes") + 1]) for a in demo.eval_argvs()] == [("0", "20")]
    evals = _demo(tmp_path, replace(CAMERA, eval_processes=2)).eval_argvs()
    assert [(a[a.index("--seed") + 1], a[a.index("--episodes") + 1]) for a in evals] == [("0", "10"), ("10", "10")]
    assert all(a[:3] == ["eval-reflex", "--checkpoint", "promoted"] for a in evals)
    # an odd count and fewer items than processes
    odd = _demo(tmp_path, replace(CAMERA, eval_processes=2), episodes=5, eval_episodes=1)
    assert [a[a.index("--seed") + 1] for a in odd.recording_argvs(out)] == ["100000", "100002"]
    assert len(odd.eval_argvs()) == 1
    assert split_range(5, 2) == [(0, 2), (2, 3)] and split_range(1, 2) == [(0, 1)] and split_range(7, 1) == [(0, 7)]
    assert demo.data_dir() == tmp_path / "home" / "demo" / "camera" / "reach-50-dart1"
    assert demo.summary_path() == tmp_path / "home" / "demo" / "camera" / "summary.json"


def test_the_chain_gives_each_member_its_recipe_down_to_the_job(tmp_path):
    from registry.db import Registry
    from registry.report_channel import snapshot_of
    from registry.sequences import create_sequence
    from workers.job import build_train_config

    data = tmp_path / "data"
    data.mkdir()
    demo = _demo(tmp_path)
    configs = demo.member_configs(data)
    settings = _settings(tmp_path / "home")
    with Registry.open(settings) as registry, registry.session() as s:
        first = configs[COMPONENTS[0]]
        runs = create_sequence(s, COMPONENTS, first, total_steps=first["steps"], runs_dir=tmp_path / "runs",
                               member_configs=configs)
        by = {r.component: r for r in runs}
        assert [r.total_steps for r in runs] == [CAMERA.members[c].steps for c in COMPONENTS]
        # the job's view: what workers/job.py builds from each row (the tokenizer's run dir stands in)
        cfgs = {c: build_train_config(settings, snapshot_of(s, r), lambda _rid: str(tmp_path / "vq"))
                for c, r in by.items()}
    tok, fast, mid = cfgs[TOKENIZER], cfgs[ACTOR], cfgs[PREDICTOR]
    assert (tok.steps, tok.lr, tok.threads, tok.model_config, tok.vqvae_dir) == (2500, 2e-3, 2, GRID_TOKENIZER, None)
    assert (fast.steps, fast.lr, fast.threads, fast.model_config) == (CAMERA.members[ACTOR].steps, 1e-3, 1, {})
    assert (mid.steps, mid.lr, mid.threads) == (3000, 2e-3, 1)
    assert by[ACTOR].config["vqvae_run"] == by[PREDICTOR].config["vqvae_run"] == by[TOKENIZER].id
    assert fast.vqvae_dir == mid.vqvae_dir == str(tmp_path / "vq")
    assert all(c.data == str(data) and c.seed == 0 for c in cfgs.values())
    # --steps replaces every member's count (a short run), the rest of the recipe stays
    short = _demo(tmp_path, steps=30).member_configs(data)
    assert {c["steps"] for c in short.values()} == {30} and short[TOKENIZER]["model_config"] == GRID_TOKENIZER


def _demo_cli(home: Path, *args: str, env_extra: dict | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update({"HOPE_HOME": str(home), **(env_extra or {})})
    return subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "demo", "--camera", "--exit", "--port", "0",
                           *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)


def test_bad_options_are_refused_before_anything_starts(tmp_path):
    home = tmp_path / "home"
    proc = _demo_cli(home, "--episodes", "2")
    assert proc.returncode == 2, proc.stderr
    assert "--episodes 2: the camera demo reports held-out figures" in proc.stderr and "at least 3" in proc.stderr
    proc = _demo_cli(home, "--noise", "-0.5")
    assert proc.returncode == 2 and "--noise -0.5: the DART noise is a standard deviation, >= 0" in proc.stderr
    assert not home.exists()  # refused before $HOPE_HOME was even made


def test_a_failed_stage_stops_the_demo_naming_it(tmp_path):
    # no GL for the frames: sim-demos refuses at once, and the demo stops at its first step
    proc = _demo_cli(tmp_path / "home", "--episodes", "3", env_extra={"MUJOCO_GL": "disabled"})
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "error: the camera demo stopped at step 1 (demonstrations): recording the demonstrations failed" \
        in proc.stderr and "frames need a GL backend" in proc.stderr
    assert "2. services" not in proc.stdout  # nothing after it started
    assert not (tmp_path / "home" / "demo" / "camera" / "reach-3-dart1").exists()


def test_a_home_serving_state_models_is_refused_before_recording(tmp_path):
    from brain_fixtures import promote_pointer
    from frame_fixtures import camera_checkpoints, joints_checkpoint

    home = tmp_path / "home"
    assert served_layout_problem(home) is None  # nothing promoted
    camera = camera_checkpoints(tmp_path / "ckpt", "grid")
    promote_pointer(home, camera["vq"], TOKENIZER)
    promote_pointer(home, camera["fast"], ACTOR)
    assert served_layout_problem(home) is None  # a camera demo's models: the same layout
    state = joints_checkpoint(tmp_path / "ckpt")
    promote_pointer(home, state, ACTOR)
    problem = served_layout_problem(home)
    assert problem is not None and f"{home} serves the {ACTOR} " in problem and "reads no camera" in problem
    assert "HOPE_HOME of its own" in problem
    proc = _demo_cli(home, "--episodes", "3")  # the command refuses it before recording anything
    assert proc.returncode == 2 and f"error: the camera demo cannot start: {home} serves" in proc.stderr
    assert not (home / "demo").exists()


def _eval(first: int, n: int, mean: float, reached: int, ttr: float | None) -> dict:
    """What eval-reflex --json writes (hope_models/cli/eval_reflex.py), the keys the demo reads."""
    return {"ok": True, "mean_return": mean, "success_rate": 0.5, "time_to_reach_s": ttr, "expert_mean_return": 980.0,
            "random_mean_return": 30.0 + first, "episodes": n, "task": "reach", "seeds": [first, first + n - 1],
            "checkpoint": "/c", "version": "r@8000:abc", "reached": reached, "elapsed_s": 100.0 + first}


def test_evaluations_over_seed_ranges_merge_into_one():
    one = _eval(0, 20, 50.0, 4, 1.0)
    assert merge_evaluations([one])["mean_return"] == 50.0 and "processes" not in merge_evaluations([one])
    merged = merge_evaluations([_eval(0, 10, 100.0, 3, 2.0), _eval(10, 30, 20.0, 1, 1.0)])
    assert merged["mean_return"] == pytest.approx((100.0 * 10 + 20.0 * 30) / 40)
    assert merged["time_to_reach_s"] == pytest.approx((2.0 * 3 + 1.0 * 1) / 4)  # by the episodes that reached
    assert merged["random_mean_return"] == pytest.approx((30.0 * 10 + 40.0 * 30) / 40)
    assert merged["seeds"] == [0, 39] and merged["episodes"] == 40 and merged["processes"] == 2
    assert merged["elapsed_s"] == 110.0 and merged["version"] == "r@8000:abc"
    assert merge_evaluations([_eval(0, 5, 1.0, 0, None), _eval(5, 5, 2.0, 0, None)])["time_to_reach_s"] is None
    other = {**_eval(10, 10, 1.0, 0, None), "version": "r@10:def"}
    assert "different checkpoints" in merge_evaluations([_eval(0, 10, 1.0, 0, None), other])["error"]


def test_the_summary_shows_the_frame_tokenizer_psnr_and_every_stage_time():
    row = {"component": TOKENIZER, "run_id": "r1", "state": "completed", "steps": 2500, "total_steps": 2500,
           "first_loss": 0.06, "final_loss": 0.003, "peak_rss_mb": 510.0, "train_s": 600.0, "error": None,
           "gate": {"state": "promoted", "version": "r1@2500:abc"}, "loop_closure_s": None,
           "held_out": {"recon_nmse": 0.118, "perplexity": 3.4, "code_usage": 1.0, "psnr_db": 32.64}}
    summary = {"components": [row], "inference": {"action": [0.1, -0.2], "expert_action": [0.0, 0.0],
                                                  "model_version": "v", "latency_ms": 1.5},
               "brain": None, "reflex": None, "loop_closure_s": 3.0,
               "timings": {"demos": 500.0, TOKENIZER: 610.0, "reflex": 240.0, "total": 1700.0}}
    text = format_summary(summary)
    assert "keeps 88.2 % of the variance" in text and ", PSNR 32.6 dB" in text
    assert f"time: demos 500 s, {TOKENIZER} 610 s, reflex 240 s, total 1700 s" in text
    assert "inference: None" not in text  # no error line when the brain was not asked
