"""The end-to-end demo (hope_trainer/commands/demo.py), short: a real subprocess on its own HOPE_HOME records a
few sim demos, runs the chain vqvae,fast_loop,mid_loop through the daemon and the worker, gates and
promotes, serves through BrainService, infers over HTTP, evaluates the reflex and exits (--exit).

The full-size figures (50 demos, each member its own steps, mean return >= 900 on seeds 0-19 within 10 minutes)
are measured by running `run_trainer.py demo` itself; here the steps are too few to promise a
return, so --target-return 0, and the verdict's refusals are tested on plain summaries below.
Its few steps are also too few for the tokenizer and the predictor to beat their baselines: the gate
refuses both with the figures, which the demo reports as its only shortfalls (exit 1).
"""
from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
STEPS = 60  # each member: enough to run every stage; the Mid Loop's steps are most of the test's time


def _demo_argv() -> list[str]:
    """`run_trainer.py demo` (hope_trainer/commands/demo.py)."""
    return [sys.executable, str(REPO / "run_trainer.py"), "demo"]


def _env(home: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update({"HOPE_HOME": str(home), "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1",
                # no thermal source: this machine's zone must not throttle the jobs
                "HOPE_THERMAL_ZONE": str(home / "no-thermal-zone"), "HOPE_VCGENCMD": "",
                # the demo turns auto-promotion on for its own process whatever the settings say
                "HOPE_AUTO_PROMOTE": "0"})
    return env


@pytest.mark.slow
def test_demo_short_runs_the_whole_loop_through_the_services(tmp_path):
    home = tmp_path / "home"
    argv = _demo_argv() + ["--episodes", "6", "--steps", str(STEPS), "--eval-episodes", "2", "--target-return", "0",
                           "--exit", "--port", "0"]
    proc = subprocess.run(argv, cwd=REPO, env=_env(home), capture_output=True, text=True, timeout=240)
    out = proc.stdout
    assert proc.returncode == 1, f"exit {proc.returncode}\n{out}\n{proc.stderr[-3000:]}"
    assert "auto_promote is off" in out  # and it gated anyway (below)

    summary = json.loads((home / "demo" / "summary.json").read_text())
    rows = summary["components"]
    assert [r["component"] for r in rows] == ["vqvae", "fast_loop", "mid_loop"]
    for r in rows:
        assert r["state"] == "completed" and r["steps"] == r["total_steps"] == STEPS, r
        assert math.isfinite(r["first_loss"]) and math.isfinite(r["final_loss"]), r
        assert r["peak_rss_mb"] > 50 and r["train_s"] > 0, r
    assert rows[1]["gate"]["state"] == "promoted", rows[1]
    # the undertrained tokenizer and predictor: refused, with their held-out figures and baselines
    vq, mid = rows[0], rows[2]
    assert vq["gate"]["state"] == "refused" and "of the variance" in vq["gate"]["reasons"][0], vq
    assert mid["gate"]["state"] == "refused" and "copy-last" in mid["gate"]["reasons"][0], mid
    assert 0 < vq["held_out"]["recon_nmse"] and set(mid["held_out"]) == {"0.5s", "1s"}
    assert summary["ok"] is False and [p.split(":")[0] for p in summary["problems"]] == [
        "the gate refused the vqvae", "the gate refused the mid_loop"]
    assert "vqvae (held-out episodes): keeps" in out and "mid_loop (held-out episodes): 0.5s" in out
    fast = rows[1]
    version = fast["gate"]["version"]
    assert version.startswith(f"{fast['run_id']}@{STEPS}:")
    # the version the gate promoted is the one BrainService served, answered with and evaluated
    assert summary["served_version"] == version
    inference = summary["inference"]
    assert inference["model_version"] == version
    assert len(inference["action"]) == 2 and all(-1.0 <= a <= 1.0 for a in inference["action"])
    assert inference["latency_ms"] > 0
    assert isinstance(summary["loop_closure_s"], float) and summary["loop_closure_s"] >= 0
    reflex = summary["reflex"]
    assert reflex["version"] == version and reflex["episodes"] == 2 and reflex["seeds"] == [0, 1]
    assert reflex["expert_mean_return"] > 900 and reflex["random_mean_return"] < 200
    assert 0 <= reflex["mean_return"] <= 1000

    # what the terminal showed: progress, the inference, the table, the URL and the token
    token = (home / "token").read_text().strip()
    assert f"token: {token}" in out and "Robot Editor: http://127.0.0.1:" in out
    assert "POST /api/brain/infer -> action" in out
    assert "loss first -> last" in out and f"promoted {version}" in out
    assert "completed: " + fast["run_id"] + f" fast_loop at step {STEPS}/{STEPS}" in out

    # the registry: one chain, whose fast_loop read the codes of the chain's own VQ-VAE
    from registry.db import Registry
    from registry.models import Run
    from hope_models.settings import load_settings

    registry = Registry.open(load_settings(env=_env(home)))
    try:
        with registry.session(readonly=True) as s:
            runs = {r.component: r for r in s.query(Run).all()}
    finally:
        registry.close()
    assert len({r.sequence_id for r in runs.values()}) == 1 and len(runs) == 3
    assert runs["fast_loop"].config["vqvae_run"] == runs["vqvae"].id
    assert runs["fast_loop"].loop_closure_s == summary["loop_closure_s"]
    ckpt_cfg = json.loads((Path(runs["fast_loop"].last_checkpoint) / "config.json").read_text())
    assert ckpt_cfg["model_config"]["n_codes"] > 0
    assert ckpt_cfg["vqvae"]["path"].startswith(runs["vqvae"].run_dir)

    # --exit stopped everything: the port is closed and the job children are gone
    port = int(summary["url"].rstrip("/").rsplit(":", 1)[1])
    with socket.socket() as sock:
        assert sock.connect_ex(("127.0.0.1", port)) != 0
    import psutil

    for r in runs.values():
        if r.worker_pid and psutil.pid_exists(r.worker_pid):
            assert psutil.Process(r.worker_pid).status() == psutil.STATUS_ZOMBIE


# -- the verdict and the table, on plain summaries ------------------------------------------------

def _row(component, state="completed", gate=None, **kw):
    base = {"component": component, "run_id": f"r-{component}", "state": state, "steps": 10, "total_steps": 10,
            "first_loss": 1.0, "final_loss": 0.1, "peak_rss_mb": 300.0, "train_s": 5.0, "error": None,
            "gate": gate if gate is not None else {"state": "promoted", "version": f"r-{component}@10:abc"},
            "loop_closure_s": None}
    return {**base, **kw}


def _summary(mean_return=950.0, **kw):
    s = {"components": [_row("vqvae"), _row("fast_loop"), _row("mid_loop")],
         "inference": {"action": [0.1, -0.2], "expert_action": [0.0, 0.0], "model_version": "r-fast_loop@10:abc",
                       "latency_ms": 0.3},
         "reflex": {"mean_return": mean_return, "success_rate": 1.0, "expert_mean_return": 985.0,
                    "random_mean_return": 30.0, "seeds": [0, 19], "version": "r-fast_loop@10:abc"},
         "loop_closure_s": 7.5, "target_return": 900.0, "timings": {"total": 400.0}}
    s.update(kw)
    return s


def test_verdict_passes_a_good_summary_and_names_each_shortfall():
    from hope_trainer.demo.report import format_summary, verdict

    assert verdict(_summary(), 900) == []
    assert verdict(_summary(mean_return=899.9), 900) == [
        "the promoted fast_loop's mean return 899.9 is below the target 900"]
    refused = _summary(components=[_row("vqvae"), _row("fast_loop", gate={"state": "refused", "version": "v",
                                                                           "reasons": ["val_loss: worse"]}),
                                   _row("mid_loop")])
    assert verdict(refused, 900) == ["the gate refused the fast_loop: val_loss: worse"]
    failed = _summary(components=[_row("vqvae"), _row("fast_loop", state="failed", error="NaN loss"),
                                  _row("mid_loop", state="cancelled")], reflex={"error": "no fast_loop is promoted"})
    problems = verdict(failed, 900)
    assert problems[0] == "fast_loop run r-fast_loop ended failed: NaN loss"
    assert "mid_loop run r-mid_loop ended cancelled" in problems[1]
    assert problems[-1] == "the reflex evaluation failed: no fast_loop is promoted"
    assert verdict(_summary(inference={"error": "HTTP 401"}), 900) == ["inference through the API failed: HTTP 401"]

    vq_refused = _summary(components=[
        _row("vqvae", gate={"state": "refused", "version": "v", "reasons": ["held-out reconstruction keeps 52.0%"]}),
        _row("fast_loop"), _row("mid_loop", gate=None) | {"gate": None}])
    assert verdict(vq_refused, 900) == ["the gate refused the vqvae: held-out reconstruction keeps 52.0%",
                                        "the mid_loop run was not gated (auto-promotion did not finish)"]
    held = _summary(components=[
        _row("vqvae", held_out={"recon_nmse": 0.039, "perplexity": 36.4, "code_usage": 1.0}), _row("fast_loop"),
        _row("mid_loop", held_out={"0.5s": {"obs_mse": 0.5, "copy_last_obs_mse": 0.9, "nll": 10.8,
                                             "copy_last_nll": 14.2, "code_freq_nll": 14.5},
                                    "1s": {"obs_mse": 1.1, "copy_last_obs_mse": 1.0, "nll": 10.9,
                                           "copy_last_nll": 14.2, "code_freq_nll": 14.5}})],
        brain={"action": [0.1], "versions": {"fast_loop": "v"}, "code": [1, 2, 3], "ticks": 75,
               "prediction": {"0.5s": [0.25, -1.0]}, "surprise": 4.5})
    text = format_summary(held)
    assert "keeps 96.1 % of the variance (normalised MSE 0.0390" in text and "perplexity 36 per group" in text
    assert "0.5s: observation error 0.500 vs copy-last 0.900 (44 % lower), nll 10.80 vs copy-last 14.20" in text
    assert "1s: observation error 1.100 vs copy-last 1.000 (10 % higher)" in text
    assert "whole brain (session ticked through 75 steps" in text
    assert "code [1, 2, 3]" in text and "prediction at +0.5s: [+0.250, -1.000]" in text and "surprise 4.50 nats" in text
    assert verdict(_summary(brain={"error": "BrainService does not serve"}), 900) == [
        "the whole-brain inference failed: BrainService does not serve"]

    text = format_summary(_summary())
    assert "fast_loop" in text and "1 -> 0.1" in text and "300 MB" in text and "promoted r-fast_loop@10:abc" in text
    assert "mean return 950.0" in text and "expert 985.0" in text and "random 30.0" in text
    assert "loop closure: 7.5 s" in text


class _DoorBehind:
    """ClosureSteps' surroundings: the demo's own BrainService serves the promoted version at once,
    the robot's port (another process) answers 503, then the previous version, then the promoted one."""

    def __init__(self, answers: list[dict]):
        from types import SimpleNamespace

        from hope_trainer.demo.closure import ClosureSteps

        class Steps(ClosureSteps):
            def _gate(self, run_id):
                return {"state": "promoted", "version": "r-new@60:aa"}

            def _post_infer(self, request):
                self.posted.append(request)
                return answers.pop(0)

            def loop_closed(self):
                self.closed += 1

            def sleep(self, seconds):
                pass

        brain = SimpleNamespace(status=lambda: {"fast_loop": {"version": "r-new@60:aa"},
                                                "vqvae": {"version": "v"}, "mid_loop": {"version": "m"}})
        self.steps = Steps()
        self.steps.serve = SimpleNamespace(brain=brain)
        self.steps.first_observation = ({"observation": [0.0] * 6}, [1.0, 1.0])
        self.steps.inference, self.steps.door_answer, self.steps.posted, self.steps.closed = None, None, [], 0


def test_the_loop_closes_on_the_robots_port_only_once_it_answers_with_the_promoted_version():
    door = _DoorBehind([{"error": 'HTTP 503: {"error":"no promoted fast_loop to serve yet"}'},
                        {"action": [0.0, 0.0], "model_version": "r-old@10:bb"},
                        {"action": [0.1, -0.2], "model_version": "r-new@60:aa", "latency_ms": 0.5}])
    steps = door.steps
    assert steps._try_close_loop("r-new") is False and steps.inference is None and steps.closed == 0
    assert steps._try_close_loop("r-new") is False and steps.door_answer["model_version"] == "r-old@10:bb"
    assert steps._try_close_loop("r-new") is True and steps.closed == 1
    assert steps.inference["model_version"] == "r-new@60:aa" and steps.inference["expert_action"] == [1.0, 1.0]


def test_the_whole_brain_answer_waits_for_the_robots_port_to_serve_every_promoted_version(tmp_path):
    ep = tmp_path / "data" / "ep0" / "steps"
    ep.mkdir(parents=True)
    step = {"observation": {"robot_state": {"joint_positions": [0.1, 0.2], "joint_velocities": [0.0, 0.0]}},
            "action": {"command": [0.5, 0.5]}}
    (ep / "000000.jsonl").write_text("\n".join(json.dumps(step) for _ in range(80)) + "\n")
    versions = {"vqvae": "v", "fast_loop": "r-new@60:aa", "mid_loop": "m"}
    stale = {"action": [0.0, 0.0], "versions": {**versions, "mid_loop": None}}
    door = _DoorBehind([{"error": "HTTP 503: no promoted fast_loop"}, stale]
                       + [{"action": [0.1, 0.1], "versions": versions}] * 200)
    gates = {i: {"state": "promoted", "version": v} for i, v in zip(("a", "b", "c"), versions.values(), strict=True)}
    answer = door.steps.brain_inference(gates, ["a", "b", "c"], tmp_path / "data")
    assert "error" not in answer and answer["versions"] == versions, answer
    posted = door.steps.posted
    assert [p["reset"] for p in posted[:3]] == [True, True, True] and not any(p["reset"] for p in posted[3:])
    assert len(posted) == 2 + answer["ticks"]
