"""The Continuon app's remaining calls, sent as its Dart code sends them and read as it reads them:

- GET /api/ownership/status: continuonai/lib/services/brain_client.dart fetchOwnershipStatus
  (`http.get(uri, headers: _headers())`: `authorization: Bearer <token>` only when the app has one),
  read by robot_list_screen.dart _refreshStatus and robot_init_state.dart RobotOwnershipStatus.fromJson;
- POST /api/training/queue/episodes: continuonai/lib/services/training_queue_service.dart
  enqueueEpisode, with the EpisodeRecord youtube_import_service.dart _fetchTranscodeAndBuildRecord
  builds (rlds_models.dart toJson) and ShareMetadata.toJson;
- POST /api/learning/reset: brain_client.dart resetLearning (`http.post(uri, headers: _headers())`,
  no body, success = `data['success'] == true`), against continuous learning's real registry state
  and a real policy (daemon/continuous.py) whose cached watermark must see the reset.
"""
from __future__ import annotations

import json
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import pytest
from test_app_handoff import make_client
from test_continuous_learning import COOL, MIN_NEW, chains, complete_all, episode_dirs, hand_off, home, policy

from registry import learning

__all__ = ["episode_dirs", "home"]  # fixtures imported from test_continuous_learning


@pytest.fixture
def client(tmp_path):
    c = make_client(tmp_path / "home", 1)
    yield c
    c.close()


def app_headers(token: str | None) -> dict[str, str]:
    """BrainClient._headers(): the lower-case header, only when the app has a token."""
    return {"authorization": f"Bearer {token}"} if token is not None else {}


# -- GET /api/ownership/status ---------------------------------------------------------------------

def dart_fetch_ownership_status(response) -> dict[str, Any]:
    """fetchOwnershipStatus, ported: 200 + a JSON object, its `ownership` map merged over it; else {}."""
    if response.status_code != 200:
        return {}
    try:
        decoded = json.loads(response.get_data(as_text=True))
    except ValueError:  # jsonDecode throws; the catch returns {}
        return {}
    if not isinstance(decoded, dict):
        return {}
    out = dict(decoded)
    if isinstance(out.get("ownership"), dict):
        out.update(out["ownership"])
    return out


def dart_robot_list_card(status: dict[str, Any], account_id: str | None) -> tuple[bool, bool, bool, str | None]:
    """_refreshStatus: (owned, subscription, seed, the error shown on the card or None)."""
    owned, sub, seed = status.get("owned") is True, status.get("subscription_active") is True, \
        status.get("seed_installed") is True
    error = None
    if not status:
        error = "Status fetch failed"
    elif account_id is not None and status.get("account_id") is not None and status["account_id"] != account_id:
        error = "Account mismatch"
    return owned, sub, seed, error


def dart_ownership_from_json(status: dict[str, Any]) -> dict[str, Any]:
    """RobotOwnershipStatus.fromJson: `as bool?` / `as String?` casts throw on any other type."""
    out = {}
    for key in ("owned", "subscription_active", "seed_installed"):
        assert status.get(key) is None or isinstance(status[key], bool), (key, status.get(key))
        out[key] = status.get(key) or False
    for key in ("owner_id", "account_id", "account_type"):
        assert status.get(key) is None or isinstance(status[key], str), (key, status.get(key))
        out[key] = status.get(key)
    return out


def promote_a_model(client, component: str = "fast_loop") -> str:
    from registry.models import utcnow
    from registry.promotion import record_candidate

    version = "r-test@100:0123456789ab"
    with client.application.extensions["hope"].registry.session() as s:
        model = record_candidate(s, component=component, checkpoint_path=client.settings.home / "ckpt",
                                 version=version, run_id=None, metrics=None, gate_result=None)
        model.promoted_at = utcnow()
    return version


def test_ownership_status_reads_as_reachable_in_the_robot_list_with_and_without_the_token(client):
    for token in (None, client.token, "not-this-trainers-token-at-all"):
        r = client.get("/api/ownership/status", headers=app_headers(token))
        assert r.status_code == 200, r.get_json()
        status = dart_fetch_ownership_status(r)
        owned, sub, seed, error = dart_robot_list_card(status, account_id="someone@example.com")
        assert error is None  # reachable: no "Status fetch failed", and no account to mismatch
        fields = dart_ownership_from_json(status)
        assert owned is (token == client.token) and fields["owned"] is owned
        assert sub is False and seed is False  # no subscription exists; nothing promoted yet
        assert fields["account_id"] is None and fields["owner_id"] is None
        body = r.get_json()
        assert body["ownership"]["owned"] is owned and body["status"] == "ok"
        assert body["device_id"] == client.get("/api/ping").get_json()["device_id"]
    # without the token, no more than /api/ping tells: the served models are not disclosed
    anon = client.get("/api/ownership/status").get_json()
    assert anon["seed_installed"] is None and "seed_models" not in anon and anon["token"] == "missing"
    assert client.get("/api/ownership/status", headers=app_headers("x" * 43)).get_json()["token"] == "invalid"


def test_seed_installed_says_whether_a_promoted_model_is_served(client):
    version = promote_a_model(client)
    r = client.get("/api/ownership/status", headers=app_headers(client.token))
    status = dart_fetch_ownership_status(r)
    assert dart_robot_list_card(status, None)[2] is True
    assert r.get_json()["seed_models"]["fast_loop"] == version
    assert r.get_json()["seed_models"]["vqvae"] is None


def test_ownership_status_refuses_unknown_query_parameters(client):
    r = client.get("/api/ownership/status?owner=1")
    assert r.status_code == 400 and "owner" in r.get_json()["error"]


# -- POST /api/training/queue/episodes -------------------------------------------------------------

VIDEO = "https://www.youtube.com/watch?v=dQw4w9WgXcQ"


def youtube_record(n: int = 6) -> dict[str, Any]:
    """EpisodeRecord.toJson() of what _fetchTranscodeAndBuildRecord builds from the cloud's answer
    (its defaults where the cloud names nothing: xr_mode youtube_tv, control_role observer, ...)."""
    steps = [{"observation": {"pose": {"wrist": [0.1 * i, 0.2, 0.3]}, "frame_index": i},
              "action": {"command": [0.05 * i, -0.1]}, "is_terminal": i == n - 1,
              "step_metadata": {"source": "youtube_import"}} for i in range(n)]
    return {"metadata": {"xr_mode": "youtube_tv", "control_role": "observer", "environment_id": "youtube_import",
                         "tags": ["youtube", "import"], "source": "youtube",
                         "provenance": {"video_url": VIDEO, "job_id": "job-42"}},
            "steps": steps,
            "task_classification": {"tasks": ["unlabeled"], "motion_primitives": ["unknown_motion"],
                                    "confidence": {"unlabeled": 0.4}},
            "source_context": {"youtube_url": VIDEO, "transcoded_video": None}}


SHARE = {"public": False, "slug": "wave-demo", "title": "Wave demo", "license": "CC-BY-4.0", "tags": ["wave"]}


def enqueue(client, body: Any, token: str | None = "app") -> Any:
    """TrainingQueueService.enqueueEpisode: JSON with 'Content-Type' and, when set, 'authorization'."""
    headers = {"Content-Type": "application/json"}
    if token is not None:
        headers["authorization"] = f"Bearer {client.token if token == 'app' else token}"
    return client.post("/api/training/queue/episodes", data=json.dumps(body), headers=headers)


def test_a_youtube_episode_lands_in_the_inbox_and_a_repeat_is_the_same_episode(client):
    body = {"episode": youtube_record(), "request_public_listing": False, "share": SHARE}
    r = enqueue(client, body)
    assert 200 <= r.status_code < 300, r.get_json()  # all the importer checks
    got = r.get_json()
    assert got["success"] is True and got["action"] == "written" and got["episode_id"].startswith("app-")
    assert got["public_listing"] is False and isinstance(got["trainable"], list)
    assert set(got["not_trainable"]) | set(got["trainable"]) == {"vqvae", "fast_loop", "mid_loop"}
    listed = client.get("/api/episodes", headers=app_headers(client.token)).get_json()
    ids = [e["episode_id"] for e in listed["episodes"]]
    assert got["episode_id"] in ids
    entry = next(e for e in listed["episodes"] if e["episode_id"] == got["episode_id"])
    assert entry["origin"] == "app:training_queue"
    meta = json.loads((client.settings.inbox_dir / got["episode_id"] / "metadata.json").read_text())
    assert meta["provenance"]["video_url"] == VIDEO and meta["provenance"]["origin"] == "app:training_queue"
    again = enqueue(client, body)
    assert again.status_code == 200 and again.get_json()["episode_id"] == got["episode_id"]
    assert again.get_json()["action"] in ("unchanged", "duplicate")
    relisted = client.get("/api/episodes", headers=app_headers(client.token)).get_json()["episodes"]
    assert [e["episode_id"] for e in relisted].count(got["episode_id"]) == 1


def test_a_public_listing_request_is_answered_honestly(client):
    r = enqueue(client, {"episode": youtube_record(), "request_public_listing": True})  # no share: Dart omits it
    assert r.status_code == 200
    assert r.get_json()["public_listing"] is False
    assert any("publishes nothing" in w for w in r.get_json()["warnings"])


@pytest.mark.parametrize("body, needle", [
    ([], "JSON object"),
    ({"request_public_listing": False}, "episode: required"),
    ({"episode": [1], "request_public_listing": False}, "episode: expected an object"),
    ({"episode": {"metadata": {}, "steps": []}, "request_public_listing": False}, "episode.steps"),
    ({"episode": {"metadata": {}, "steps": [{"observation": {}, "action": 3}]}}, "episode.steps[0].action"),
    ({"episode": {"steps": [{"observation": {}, "action": {}}]}}, "episode.metadata"),
    ({"episode": youtube_record(), "request_public_listing": "yes"}, "request_public_listing"),
    ({"episode": youtube_record(), "share": "public"}, "share: expected an object"),
    ({"episode": youtube_record(), "share": {**SHARE, "tags": "wave"}}, "share.tags"),
    ({"episode": youtube_record(), "share": {**SHARE, "tags": [3]}}, "share.tags[0]"),
    ({"episode": youtube_record(), "publish": True}, "publish"),
])
def test_a_bad_shape_is_a_400_naming_the_field_and_writes_nothing(client, body, needle):
    r = enqueue(client, body)
    assert r.status_code == 400 and needle in r.get_json()["error"], r.get_json()
    inbox = client.settings.inbox_dir
    assert not inbox.exists() or not [p for p in inbox.iterdir() if p.is_dir() and p.name.startswith("app-")]


def test_an_episode_validation_rejects_is_a_422_with_its_reasons(client):
    from hope_models.intake.inbox import list_inbox

    # 1e999 is valid JSON that parses to infinity: the train profile refuses a non-finite action
    text = json.dumps({"episode": youtube_record(), "request_public_listing": False}).replace("-0.1]", "1e999]", 1)
    r = client.post("/api/training/queue/episodes", data=text,
                    headers={"Content-Type": "application/json", "authorization": f"Bearer {client.token}"})
    assert r.status_code == 422, r.get_json()
    assert "not a finite number" in r.get_json()["error"] and r.get_json()["errors"]
    (entry,) = list_inbox(client.settings.inbox_dir)
    assert entry["status"] == "rejected" and entry["origin"] == "app:training_queue"


def test_the_queue_needs_the_token(client):
    r = enqueue(client, {"episode": youtube_record(), "request_public_listing": False}, token=None)
    assert r.status_code == 401
    assert not client.settings.inbox_dir.exists() or not list(client.settings.inbox_dir.glob("app-*"))


# -- POST /api/learning/reset ----------------------------------------------------------------------

def dart_reset_learning(response) -> bool:
    """resetLearning: 200 and data['success'] == true."""
    if response.status_code != 200:
        return False
    try:
        return json.loads(response.get_data(as_text=True)).get("success") is True
    except ValueError:
        return False


@pytest.fixture
def app_client(home):
    from webapp import create_app
    from webapp.auth import load_or_create_token

    token = load_or_create_token(home.settings)
    app, _socketio = create_app(home.settings, token=token, registry=home.registry)
    c = app.test_client()
    c.token = token
    yield c
    app.extensions["hope"].close()


def reset(c, token: str | None = "app"):
    return c.post("/api/learning/reset", headers=app_headers(c.token if token == "app" else token))


def test_reset_forgets_the_watermark_so_every_inbox_episode_is_new_again_and_keeps_the_runs(home, app_client,
                                                                                            episode_dirs):
    hand_off(home, episode_dirs[:MIN_NEW + 1])
    p = policy(home)
    first = p.tick(COOL)
    assert first.sequence_id is not None
    complete_all(home)
    assert p.tick(COOL).phase == "waiting for data"  # the same episodes: nothing new
    runs_before = sorted(r["id"] for r in home.runs())
    with home.registry.session(readonly=True) as s:
        assert learning.watermark(s)
    r = reset(app_client)
    assert dart_reset_learning(r), r.get_json()
    assert set(r.get_json()["forgot_watermark"]) == {"vqvae", "fast_loop", "mid_loop"}
    assert r.get_json()["forgot_last_auto_run"] == first.sequence_id
    with home.registry.session(readonly=True) as s:
        assert learning.watermark(s) == {}
    status = app_client.get("/api/learning/status", headers=app_headers(app_client.token)).get_json()
    assert status["reset_at"] == r.get_json()["reset_at"] and status["last_auto_run"] is None
    # the same daemon policy (its watermark cached) counts every inbox episode as new again
    d = p.tick(COOL)
    assert d.sequence_id not in (None, first.sequence_id), (d.phase, d.detail)
    assert f"{MIN_NEW + 1} new trainable" in d.detail
    # runs, their dirs and the inbox are all still there
    assert set(runs_before) <= {r["id"] for r in home.runs()} and len(chains(home)) == 2
    inbox = [p.name for p in Path(home.settings.inbox_dir).iterdir() if p.is_dir() and not p.name.startswith(".")]
    assert len(inbox) == MIN_NEW + 1


def test_reset_is_idempotent_needs_the_token_takes_no_body_and_keeps_a_pause(home, app_client):
    assert reset(app_client, token=None).status_code == 401
    assert app_client.post("/api/learning/pause", headers=app_headers(app_client.token)).status_code == 200
    first, second = reset(app_client), reset(app_client)
    assert dart_reset_learning(first) and dart_reset_learning(second)
    assert second.get_json()["forgot_watermark"] == {} and second.get_json()["forgot_last_auto_run"] is None
    assert second.get_json()["paused"] is True
    with home.registry.session(readonly=True) as s:
        assert learning.is_paused(s)
    r = app_client.post("/api/learning/reset", json={"everything": True}, headers=app_headers(app_client.token))
    assert r.status_code == 400 and "everything" in r.get_json()["error"]


def add_mid_loop_run(home, finished: datetime, loss: float) -> str:
    """A completed mid_loop run whose result.json holds its held-out cross-entropy (summary.val.loss)."""
    from registry import runs
    from registry.models import new_run_id

    run_id = new_run_id() + "mi"
    run_dir = Path(home.settings.runs_dir) / run_id
    run_dir.mkdir(parents=True)
    (run_dir / "result.json").write_text(json.dumps({"summary": {"val": {"loss": loss}}}))
    with home.registry.session() as s:
        run = runs.create_run(s, component="mid_loop", config={"data": "ds", "steps": 10}, total_steps=10,
                              run_dir=str(run_dir), run_id=run_id)
        run.state, run.step, run.started_at, run.finished_at = "completed", 10, finished - timedelta(minutes=1), finished
    return run_id


def test_reset_starts_the_surprise_history_and_keeps_the_current_figure(home, app_client):
    now = datetime.now(timezone.utc)
    old = add_mid_loop_run(home, now - timedelta(hours=2), 3.0)
    h = app_headers(app_client.token)
    before = app_client.get("/api/training/metrics", headers=h).get_json()
    assert [p["value"] for p in before["surprise_history"]] == [3.0]
    assert dart_reset_learning(reset(app_client))
    after = app_client.get("/api/training/metrics", headers=h).get_json()
    assert after["surprise_history"] == [] and after["curiosity_history"] == []
    assert after["surprise"] == 3.0 and after["surprise_source"]["run_id"] == old  # still the newest measured
    new = add_mid_loop_run(home, datetime.now(timezone.utc) + timedelta(seconds=1), 2.0)
    later = app_client.get("/api/training/metrics", headers=h).get_json()
    assert [p["value"] for p in later["surprise_history"]] == [2.0] and new in later["surprise_history"][0]["label"]
    runs_dirs = {p.name for p in Path(home.settings.runs_dir).iterdir()}
    assert {old, new} <= runs_dirs
