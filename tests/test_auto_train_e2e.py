"""Learning that continues by itself, end to end: a real `run_trainer.py serve` (webapp, daemon,
BrainService, the worker child) with auto_train on; 20 sim reacher episodes, each turned into the
Continuon app's EpisodeRecord JSON (rlds_models.dart: metadata, steps of observation / action /
is_terminal / step_metadata strings, no episode id) and handed off one by one through
`POST /api/training/episode_handoff` as the app's http.MultipartRequest sends it (lower-case
authorization header). Until the 20th the phase says how many more are needed; then a chain
starts by itself with its reason recorded, completes, the gate promotes the new fast_loop,
BrainService serves it (GET /api/brain, an inference names its version), `GET /api/v1/models`
lists it and `GET /api/training/metrics` shows its loss history. Small steps: a couple of minutes.
"""
from __future__ import annotations

import http.client
import json
import subprocess
import sys
import time
from pathlib import Path

import pytest

from daemon_fixtures import Home, Proc, free_port, wait_until
from test_app_client_replay import DartClient

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow
EPISODES = 20
STEPS_PER_EPISODE = 200  # 4 s at 50 Hz: longer than the mid_loop's window and horizon (3 s)
TRAIN_STEPS = 40
EPOCH_MS = 1_732_395_000_000  # the app's wall-clock milliseconds


# -- the app's side ---------------------------------------------------------------------------------

def app_record(episode_dir: Path, n: int) -> dict:
    """A recorded reacher episode as the app would hand it off: EpisodeRecord.toJson()."""
    from hope_models.rlds.read_episode_dir import read_episode_dir

    ep = read_episode_dir(episode_dir).episodes[0]
    t0 = EPOCH_MS + n * 60_000
    steps = [{"observation": s.observation, "action": {"command": s.action["command"], "source": "human_teleop_xr"},
              "is_terminal": s.is_terminal,
              # Dart's step_metadata is Map<String, String>: the capture time as text
              "step_metadata": {"timestamp_ms": str(t0 + s.timestamp_ns // 1_000_000), "step": str(i)}}
             for i, s in enumerate(ep.steps)]
    return {"metadata": {"xr_mode": "trainer", "control_role": "human_teleop",
                         "environment_id": "dm_control/reacher-reach", "tags": ["task:reach"],
                         "software": {"xr_app": "1.4.0"}, "source": "continuonai-flutter", "schema_version": "1.1"},
            "steps": steps, "task_classification": {"tasks": ["reach"]}}


class App(DartClient):
    """The app's client, on the wire as the replay test writes it; a call that is not 200 fails."""

    def get(self, path: str):
        status, body = super().get(path)
        assert status == 200, (path, status, body)
        return body

    def handoff(self, record: dict) -> dict:  # the record screen's episode here has no asset files
        status, out = super().handoff(json.dumps(record, separators=(",", ":")), "[]", [])
        assert status == 200, (status, out)
        return out


# -- the trainer's side ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> list[Path]:
    out = tmp_path_factory.mktemp("reacher") / "demos"
    proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "sim-demos", "--episodes", str(EPISODES),
                           "--out", str(out), "--noise", "1.0", "--steps", str(STEPS_PER_EPISODE), "--json"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    dirs = sorted(p for p in out.iterdir() if p.is_dir())
    assert len(dirs) == EPISODES
    return dirs




def test_handed_off_episodes_train_promote_and_serve_by_themselves(tmp_path, recorded):
    home = Home(tmp_path / "home", extra_env={
        "HOPE_AUTO_TRAIN": "1", "HOPE_AUTO_TRAIN_MIN_NEW_EPISODES": str(EPISODES),
        "HOPE_AUTO_TRAIN_STEPS": str(TRAIN_STEPS), "HOPE_AUTO_PROMOTE": "1", "HOPE_MEMORY_BUDGET_MB": "1536",
        # the fast_loop's reflex check after serving runs in the worker before the mid_loop behind it
        # starts: 2 episodes instead of 5 (tests/test_gate.py checks the check itself)
        "HOPE_GATE_REFLEX_EPISODES": "2"})
    port = free_port()
    log = home.path / "serve.log"
    home.logs += [log, home.path / "logs" / "worker.log", home.path / "logs" / "promote.log"]
    proc = Proc("serve", [sys.executable, str(REPO / "run_trainer.py"), "serve", "--port", str(port), "--tick", "0.2"],
                home.env, log)
    try:
        token_file = home.path / "token"
        wait_until(lambda: token_file.exists() and proc.alive() and _answers(port), 60, "serve to answer", home)
        app = App(port, token_file.read_text().strip())
        st = app.get("/api/learning/status")
        assert st["enabled"] is True and st["running"] is False and st["is_paused"] is False

        stored = []
        for n, episode_dir in enumerate(recorded):
            out = app.handoff(app_record(episode_dir, n))
            assert out["status"] in ("ok", "warnings") and sorted(out["trainable"]) == ["fast_loop", "mid_loop", "vqvae"], out
            stored.append(out["episode_id"])
            if n == EPISODES - 2:  # one short: nothing starts, and the app is told how many more
                wait_until(lambda: app.get("/api/learning/status")["current_phase"] == "waiting for data (1 more)",
                         10, "the phase to ask for 1 more episode", home)
                assert app.get("/api/runs")["runs"] == []
        assert len(set(stored)) == EPISODES

        # the chain starts by itself, saying why
        chain = wait_until(lambda: _chain(app), 30, "an auto chain to be queued", home)
        assert [r["component"] for r in chain] == ["vqvae", "fast_loop", "mid_loop"]
        assert all(r["config"]["data"] == str(home.settings.inbox_dir) and r["total_steps"] == TRAIN_STEPS
                   for r in chain)
        reason = app.get("/api/learning/status")["last_auto_run"]["reason"]
        assert reason.startswith(f"auto-train: {EPISODES} new trainable episodes in {home.settings.inbox_dir}")
        assert f"fast_loop: {EPISODES}" in reason
        fast = chain[1]["id"]

        # it completes, the gate promotes the fast_loop and BrainService serves it
        version = wait_until(lambda: _served(app, fast), 600, "the chain's fast_loop to be served", home)
        assert version.startswith(f"{fast}@{TRAIN_STEPS}:")
        # the fast_loop is served within a second of its run (the worker gates it), maybe before the
        # mid_loop behind it has finished: wait for the whole chain
        def finished():
            runs_ = _chain(app)
            return runs_ if all(r["state"] in ("completed", "failed", "cancelled") for r in runs_) else None

        chain = wait_until(finished, 600, "the chain to finish", home)
        for r in chain:
            assert r["state"] == "completed", r
        status, answer = app.send("POST", "/api/brain/infer", json.dumps(
            {"component": "fast_loop", "observation": [0.1, -0.2, 0.0, 0.3, 0.05, -0.05]}).encode(),
            {"content-type": "application/json", **app._headers()})
        assert status == 200 and answer["model_version"] == version, answer

        models = app.get("/api/v1/models")["models"]
        listed = [m for m in models if m.get("version") == version]
        assert listed and listed[0]["backend"] == "numpy" and listed[0]["name"] and listed[0]["id"]

        metrics = app.get("/api/training/metrics")
        labels = [p["label"] for p in metrics["loss_history"]]
        assert any(fast in label for label in labels), labels
        assert all(isinstance(p["value"], float) for p in metrics["loss_history"])

        # once the chain's last gates are done, the loop waits for new episodes: the same ones never
        # start a second chain (the phase moves through the gates first; wait for where it settles)
        wait_until(lambda: app.get("/api/learning/status")["current_phase"] == f"waiting for data ({EPISODES} more)",
                   300, "the loop to wait for new episodes", home)
        time.sleep(2)
        assert len({r["sequence_id"] for r in app.get("/api/runs")["runs"]}) == 1
        assert app.get("/api/learning/status")["current_phase"] == f"waiting for data ({EPISODES} more)"
    finally:
        proc.stop(timeout=60)
        home.close()


def _answers(port: int) -> bool:
    try:
        conn = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
        conn.request("GET", "/api/health")
        return conn.getresponse().status == 200
    except OSError:
        return False


def _chain(app: App) -> list[dict] | None:
    members = [r for r in app.get("/api/runs")["runs"] if r["sequence_id"]]
    return sorted(members, key=lambda r: r["sequence_index"]) if len(members) == 3 else None


def _served(app: App, run_id: str) -> str | None:
    serving = app.get("/api/brain")["components"]["fast_loop"]["serving"]
    version = (serving or {}).get("version") if isinstance(serving, dict) else serving
    return version if isinstance(version, str) and version.startswith(run_id + "@") else None
