"""Every HTTP call the Continuon app makes to its robot's brain, replayed byte for byte the way its
Dart client (continuonai/lib/services/brain_client.dart, package:http) sends it, against a real
`run_trainer.py serve` (daemon, worker, BrainService) on a free port with a tmp $HOPE_HOME.

How the Dart client sends, reproduced here by hand (not through a helper that would hide the wire):
- a lower-case `authorization: Bearer <token>` header on every call but runDiagnostics' ping;
- JSON bodies from jsonEncode (compact, non-ASCII as raw UTF-8) with `content-type:
  application/json; charset=utf-8` (package:http adds the charset to a String body);
- POSTs without a body (pause, resume) with Content-Length 0 and no content type;
- the episode handoff as http.MultipartRequest writes it: boundary "dart-http-boundary-...", the
  fields `manifest` (jsonEncode(EpisodeRecord.toJson())) and `assets` (jsonEncode of the
  EpisodeAsset list), each `content-disposition: form-data; name="..."` (plus a text/plain utf-8
  content type when the value is not plain ASCII), then one `asset` file part per file that exists
  on the phone, `content-type: application/octet-stream`, filename = the local_uri's last segment.

Every field the app reads is checked with the type its Dart code casts it to (learning_metrics.dart,
model_manager_screen.dart, robot_list_screen.dart). A call without the token or with a wrong one
is a 401 (ping excepted); a malformed manifest, an asset part whose name matches no local_uri and a
part over upload_max_mb are 4xx with a message, and nothing is written under the inbox.
"""
from __future__ import annotations

import http.client
import json
import os
import secrets
import sys
import time
from datetime import datetime
from pathlib import Path

import pytest

from brain_fixtures import brain_runs
from daemon_fixtures import Home, Proc, free_port, wait_until
from test_api import add_completed_run
from test_api_app_metrics import dart_metrics, dart_progress

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow
UPLOAD_MAX_MB = 1
PROMOTE_TIMEOUT_S = 300


# -- the wire, as package:http writes it ------------------------------------------------------------

class DartClient:
    def __init__(self, port: int, token: str | None):
        self.port, self.token = port, token

    def _headers(self, token: str | None = ...) -> dict[str, str]:
        token = self.token if token is ... else token
        return {"authorization": f"Bearer {token}"} if token is not None else {}

    def send(self, method: str, path: str, body: bytes = b"", headers: dict[str, str] | None = None):
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=PROMOTE_TIMEOUT_S)
        try:
            hdrs = {"user-agent": "Dart/3.5 (dart:io)", "accept-encoding": "gzip", "content-length": str(len(body)),
                    **(headers or {})}
            conn.putrequest(method, path, skip_accept_encoding=True)
            for k, v in hdrs.items():
                conn.putheader(k, v)  # as given: lower-case names on the wire
            conn.endheaders(body or None)
            resp = conn.getresponse()
            raw = resp.read()
        finally:
            conn.close()
        return resp.status, (json.loads(raw) if raw else None)

    def get(self, path: str, token=...):
        return self.send("GET", path, headers=self._headers(token))

    def post_json(self, path: str, obj, token=...):
        # {'Content-Type': 'application/json', ..._headers()}; package:http appends the charset
        body = json.dumps(obj, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
        return self.send("POST", path, body, {"content-type": "application/json; charset=utf-8", **self._headers(token)})

    def post_empty(self, path: str, token=...):
        return self.send("POST", path, headers=self._headers(token))

    def handoff(self, manifest: str, assets: str, files: list[tuple[str, bytes]], token=...):
        boundary = "dart-http-boundary-" + secrets.token_hex(26)[:51]
        body, ctype = multipart(boundary, [("manifest", manifest), ("assets", assets)], files)
        return self.send("POST", "/api/training/episode_handoff", body, {**self._headers(token), "content-type": ctype})


def _browser_encode(value: str) -> str:
    return value.replace("\r\n", "%0D%0A").replace("\r", "%0D%0A").replace("\n", "%0D%0A").replace('"', "%22")


def multipart(boundary: str, fields: list[tuple[str, str]], files: list[tuple[str, bytes]]) -> tuple[bytes, str]:
    """http.MultipartRequest's body: its field and file headers exactly as package:http writes them."""
    out = bytearray()
    for name, value in fields:
        header = f'content-disposition: form-data; name="{_browser_encode(name)}"'
        if not value.isascii():
            header += "\r\ncontent-type: text/plain; charset=utf-8\r\ncontent-transfer-encoding: binary"
        out += f"--{boundary}\r\n{header}\r\n\r\n".encode() + value.encode("utf-8") + b"\r\n"
    for filename, data in files:
        header = ('content-type: application/octet-stream\r\n'
                  f'content-disposition: form-data; name="asset"; filename="{_browser_encode(filename)}"')
        out += f"--{boundary}\r\n{header}\r\n\r\n".encode() + data + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return bytes(out), f"multipart/form-data; boundary={boundary}"


# -- what the record screen sends -----------------------------------------------------------------------

PHONE = "/data/user/0/com.continuonai.app/files/episodes/ep-1732395000"


def app_record(n_steps: int = 6) -> tuple[dict, list[dict]]:
    """An EpisodeRecord.toJson() and its EpisodeAsset list as record_screen.dart builds them:
    `action.command` is [] (nothing a fast_loop could learn), audio and video assets."""
    assets = [
        {"local_uri": f"{PHONE}/device_mic_1732395000123.wav", "sensor": "device_mic", "frame_id": "mic-0",
         "captured_at_ms": 1732395000123, "mime_type": "audio/wav", "status": "queued"},
        {"local_uri": f"{PHONE}/egocentric_1732395000456.mp4", "sensor": "egocentric", "frame_id": "cam-0",
         "captured_at_ms": 1732395000456, "mount": "head", "mime_type": "video/mp4", "status": "queued"},
    ]
    steps = [{"observation": {"robot_state": {"joint_positions": [0.1 * i, -0.2, 0.3], "gripper_open": i % 2 == 0,
                                              "frame_id": f"f{i}", "wall_time_millis": 1732395000000 + 100 * i},
                              "ui_context": {"notes": "tasse à café ☕", "voice_hint": ""}},
              "action": {"command": [], "source": "human_teleop_xr"},
              "is_terminal": i == n_steps - 1, "step_metadata": {"step": str(i)}} for i in range(n_steps)]
    record = {"metadata": {"xr_mode": "trainer", "control_role": "human_teleop", "environment_id": "kitchen-1",
                           "tags": ["task:pick", "motion:reach"], "software": {"xr_app": "1.4.0"},
                           "source": "continuonai-flutter", "schema_version": "1.1",
                           "safety": {"content_rating": {"audience": "general", "violence": "none",
                                                         "language": "clean"},
                                      "intended_audience": "general", "pii_attested": True, "pii_cleared": True,
                                      "pii_redacted": False, "pending_review": False}},
              "steps": steps,
              "task_classification": {"tasks": ["pick"], "motion_primitives": ["reach"]},
              "assets": assets}
    return record, assets


def dart_json(obj) -> str:
    return json.dumps(obj, separators=(",", ":"), ensure_ascii=False)


def tree(path: Path) -> dict[str, tuple[int, int]]:
    """Every file and dir under `path` (relative name -> size, mtime_ns): what a refused call must not change."""
    if not path.exists():
        return {}
    out = {}
    for root, dirs, files in os.walk(path):
        for name in dirs + files:
            p = Path(root) / name
            st = p.lstat()
            out[str(p.relative_to(path))] = (st.st_size if name in files else 0, st.st_mtime_ns)
    return out


# -- the real serve ------------------------------------------------------------------------------------------



@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """serve on a tmp home holding a completed fast_loop run (two checkpoints, @15 and @30)."""
    tmp = tmp_path_factory.mktemp("replay")
    home = Home(tmp / "home", extra_env={"HOPE_UPLOAD_MAX_MB": str(UPLOAD_MAX_MB)})
    runs = brain_runs(tmp_path_factory)
    run_id, last = add_completed_run(home.registry, home.settings, runs["alpha30"].parent.parent)
    with home.registry.session() as s:
        from registry.models import Run, utcnow

        s.get(Run, run_id).started_at = utcnow()
    port = free_port()
    log = home.path / "serve.log"
    home.logs.append(log)
    proc = Proc("serve", [sys.executable, str(REPO / "run_trainer.py"), "serve", "--port", str(port), "--tick", "0.2"],
                home.env, log)
    try:
        token = (home.path / "token")
        wait_until(lambda: token.exists() and proc.alive() and _health(port), 60, "serve to answer /api/health", home)
        yield {"home": home, "port": port, "token": token.read_text().strip(), "run_id": run_id, "last": last,
               "at15": last.parent / "00000015", "proc": proc}
    finally:
        proc.stop(timeout=30)
        home.close()


def _health(port: int) -> bool:
    try:
        status, body = DartClient(port, None).get("/api/health")
    except OSError:
        return False
    return status == 200 and body.get("status") == "ok"


@pytest.fixture(scope="module")
def app(served):
    return DartClient(served["port"], served["token"])


@pytest.fixture(scope="module")
def promoted(served, app):
    """Two versions promoted through the real gate (POST /api/brain/promote): @15, then @30."""
    first = app.post_json("/api/brain/promote", {"checkpoint": str(served["at15"])})
    assert first[0] == 200 and first[1]["promoted"] is True, first
    second = app.post_json("/api/brain/promote", {"run_id": served["run_id"]})
    assert second[0] == 200 and second[1]["promoted"] is True, second
    return {"first": first[1], "second": second[1]}


# -- the calls -------------------------------------------------------------------------------------------------

def test_ping_answers_without_a_token_and_says_little(served):
    status, body = DartClient(served["port"], None).get("/api/ping")  # runDiagnostics: no headers at all
    assert status == 200 and isinstance(body, dict)
    assert body["status"] == "ok" and isinstance(body["device_id"], str) and isinstance(body["name"], str)
    assert served["token"] not in json.dumps(body) and str(served["home"].path) not in json.dumps(body)
    assert DartClient(served["port"], served["token"]).get("/api/ping") == (status, body)  # ping() sends the token


def test_episode_handoff_stores_the_record_and_its_assets(served, app):
    record, assets = app_record()
    audio = b"RIFF" + os.urandom(2048)
    status, body = app.handoff(dart_json(record), dart_json(assets), [("device_mic_1732395000123.wav", audio)])
    assert 200 <= status < 300, body
    remote = body["remote_uris"]  # (body['remote_uris'] as Map?)?.cast<String, String>()
    assert isinstance(remote, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in remote.items())
    assert assets[0]["local_uri"] in remote
    # the same episode again (a retry after a dropped answer) is stored once
    before = tree(served["home"].settings.inbox_dir)
    again = app.handoff(dart_json(record), dart_json(assets), [("device_mic_1732395000123.wav", audio)])
    assert 200 <= again[0] < 300 and again[1]["remote_uris"][assets[0]["local_uri"]] == remote[assets[0]["local_uri"]]
    episodes = [k for k in tree(served["home"].settings.inbox_dir) if k.count(os.sep) == 0]
    assert sorted(episodes) == sorted(k for k in before if k.count(os.sep) == 0)


@pytest.mark.parametrize("case", ["malformed manifest", "manifest not a record", "asset without local_uri",
                                  "oversized part"])
def test_a_bad_handoff_is_a_4xx_with_a_message_and_writes_nothing(served, app, case):
    record, assets = app_record()
    manifest, files = dart_json(record), [("device_mic_1732395000123.wav", b"RIFF" + b"\0" * 100)]
    if case == "malformed manifest":
        manifest = manifest[: len(manifest) // 2]
    elif case == "manifest not a record":
        manifest = dart_json({"metadata": "kitchen", "steps": {"observation": 1}})
    elif case == "asset without local_uri":
        files = [("not_in_the_manifest.wav", b"RIFF" + b"\0" * 100)]
    else:
        files = [("device_mic_1732395000123.wav", b"\0" * (UPLOAD_MAX_MB * 1024 * 1024 + 4096))]
    inbox = served["home"].settings.inbox_dir
    before = tree(inbox)
    status, body = app.handoff(manifest, dart_json(assets), files)
    assert 400 <= status < 500, (case, status, body)
    assert isinstance(body, dict) and isinstance(body.get("error"), str) and body["error"], body
    assert tree(inbox) == before, case


def test_training_status(app):
    status, body = app.get("/api/training/status")
    assert status == 200
    st = body["status"]  # data['status'] ?? {...}: a map with enabled and running
    assert isinstance(st, dict) and isinstance(st["enabled"], bool) and isinstance(st["running"], bool)


def test_training_metrics_shows_the_run_loss_history(app, served):
    status, body = app.get("/api/training/metrics?limit=25")
    assert status == 200
    dart_metrics(body)
    assert 0 < len(body["loss_history"]) <= 25
    assert served["run_id"] in body["loss_history"][-1]["label"]
    assert body["surprise"] is None and body["curiosity"] is None  # no mid_loop trained in this home


def _learning_status(app) -> dict:
    status, body = app.get("/api/learning/status")
    assert status == 200 and isinstance(body, dict)
    assert isinstance(body["enabled"], bool) and isinstance(body["running"], bool)
    paused = body.get("is_paused", body.get("paused"))
    assert isinstance(paused, bool)
    phase = body.get("current_phase", body.get("phase"))
    assert phase is None or isinstance(phase, str)
    if body.get("last_update_time") is not None:
        datetime.fromisoformat(str(body["last_update_time"]).replace("Z", "+00:00"))
    return body


def test_learning_status_pause_and_resume(app):
    _learning_status(app)
    status, body = app.post_empty("/api/learning/pause")
    assert status == 200 and body["success"] is True
    paused = _learning_status(app)
    assert paused.get("is_paused", paused.get("paused")) is True
    status, body = app.post_empty("/api/learning/resume")
    assert status == 200 and body["success"] is True
    resumed = _learning_status(app)
    assert resumed.get("is_paused", resumed.get("paused")) is False


def test_learning_progress(app, promoted):
    status, body = app.get("/api/learning/progress")
    assert status == 200
    dart_progress(body)
    assert body["total_steps"] >= 30 and body["learning_updates"] >= 2
    assert body["avg_parameter_change"] > 0  # @30 against the @15 it replaced


def test_models_list_and_activate_a_version_promoted_before(app, promoted, served):
    status, body = app.get("/api/v1/models")
    assert status == 200 and isinstance(body["models"], list)
    for m in body["models"]:
        assert isinstance(m["id"], str) and isinstance(m["name"], str) and isinstance(m["backend"], str)
    first_id = str(promoted["first"]["model_id"])
    assert first_id in {m["id"] for m in body["models"]}
    status, out = app.post_json("/api/v1/models/activate", {"model_id": first_id})
    assert status == 200 and out["success"] is True and out["version"] == promoted["first"]["version"]

    def serving():
        return app.get("/api/brain")[1]["components"]["fast_loop"]["serving"]["version"]
    wait_until(lambda: serving() == promoted["first"]["version"], 15, "the activated version to serve", served["home"])
    assert app.post_json("/api/v1/models/activate", {"model_id": "999999"})[0] == 404


def test_data_episodes_and_tag(app, served):
    record, assets = app_record(4)
    record["metadata"]["environment_id"] = "garage-2"
    assert 200 <= app.handoff(dart_json(record), dart_json(assets), [])[0] < 300
    status, body = app.get("/api/v1/data/episodes")
    assert status == 200 and isinstance(body["episodes"], list) and body["episodes"]
    ep = body["episodes"][0]
    episode_id = ep.get("episode_id", ep.get("id"))
    assert isinstance(episode_id, str) and episode_id
    status, out = app.post_json("/api/v1/data/tag", {"episode_id": episode_id, "tag": "good-grasp"})
    assert status == 200 and out["success"] is True
    listed = {e.get("episode_id", e.get("id")): e for e in app.get("/api/v1/data/episodes")[1]["episodes"]}
    assert "good-grasp" in json.dumps(listed[episode_id])


def test_training_benchmarks_are_the_gate_results(app, promoted):
    status, body = app.get("/api/training/benchmarks")
    assert status == 200 and isinstance(body, dict) and isinstance(body["benchmarks"], list)
    versions = {b["model_version"] for b in body["benchmarks"]}
    assert {promoted["first"]["version"], promoted["second"]["version"]} <= versions
    for b in body["benchmarks"]:
        assert isinstance(b["id"], str) and isinstance(b["details"], dict)
        assert isinstance(b["score"], (int, float)) and datetime.fromisoformat(b["timestamp"])


CALLS = [("GET", "/api/training/status"), ("GET", "/api/training/metrics?limit=10"), ("GET", "/api/learning/status"),
         ("GET", "/api/learning/progress"), ("POST", "/api/learning/pause"), ("POST", "/api/learning/resume"),
         ("GET", "/api/v1/models"), ("POST", "/api/v1/models/activate"), ("GET", "/api/v1/data/episodes"),
         ("POST", "/api/v1/data/tag"), ("GET", "/api/training/benchmarks"),
         ("POST", "/api/training/episode_handoff")]


@pytest.mark.parametrize("token", [None, "wrong-token-of-a-decent-length"])
@pytest.mark.parametrize("method, path", CALLS)
def test_every_call_but_ping_needs_the_token(served, method, path, token):
    client = DartClient(served["port"], token)
    inbox = served["home"].settings.inbox_dir
    before = tree(inbox)
    if path == "/api/training/episode_handoff":
        record, assets = app_record(2)
        status, body = client.handoff(dart_json(record), dart_json(assets), [])
    elif path == "/api/v1/models/activate":
        status, body = client.post_json(path, {"model_id": "1"})
    elif path == "/api/v1/data/tag":
        status, body = client.post_json(path, {"episode_id": "x", "tag": "y"})
    elif method == "POST":
        status, body = client.post_empty(path)
    else:
        status, body = client.get(path)
    assert status == 401, (method, path, status, body)
    assert "token" in body["error"]
    assert tree(inbox) == before
