"""POST /api/training/episode_handoff as the Continuon app sends it (BrainClient.handoffEpisodeAssets).

The multipart bodies are built by hand with the Dart field names (`manifest`, `assets`, `asset`
file parts named by the local_uri's last segment) and the app's lower-case `authorization`
header; the episode is the record screen's shape (audio.device_mic + egocentric_video +
ui_context, `action.command` empty, phone paths as uris). Also: surrogates, duplicates spelled
in camelCase, traversal file names, absolute and file:// uris that must not be copied, malformed
and oversized bodies that must write nothing.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import uuid
from pathlib import Path

import pytest

PHONE = "/data/user/0/ai.continuon.app/cache"
FRAME = b"\xff\xd8\xff\xe0 a jpeg frame" * 10
WAV = b"RIFF\x24\x00\x00\x00WAVEfmt " * 10


def record_step(i: int, *, frame_uri: str = f"{PHONE}/frame_0.jpg", notes: str = "wave at the robot") -> dict:
    t = 1_732_400_000_000 + 100 * i  # epoch milliseconds, one step every 100 ms
    return {"observation": {
                "audio": {"device_mic": {"uri": f"{PHONE}/mic_0.wav", "sample_rate_hz": 16000, "num_channels": 1,
                                         "frame_id": f"mic-{i}", "timestamp_ms": t}},
                "egocentric_video": {"uri": frame_uri, "frame_id": f"ego-{i}", "timestamp_ms": t, "mount": "head"},
                "ui_context": {"notes": notes, "voice_hint": ""}},
            "action": {"command": [], "source": "human_teleop_xr", "voice_command": "wave"},
            "is_terminal": i == 3, "step_metadata": {"capture": str(i)}}


def record(n: int = 4, **kw) -> dict:
    return {"metadata": {"xr_mode": "trainer", "control_role": "human_teleop", "environment_id": "living_room",
                         "tags": ["task:wave"], "software": {"xr_app": "1.4.0"}},
            "steps": [record_step(i, **kw) for i in range(n)]}


ASSETS = [{"local_uri": f"{PHONE}/frame_0.jpg", "sensor": "egocentric", "frame_id": "ego-0",
           "captured_at_ms": 1_732_400_000_000, "mount": "head", "mime_type": "image/jpeg", "status": "queued"},
          {"local_uri": f"{PHONE}/mic_0.wav", "sensor": "device_mic", "frame_id": "mic-0",
           "captured_at_ms": 1_732_400_000_000, "mime_type": "audio/wav", "status": "queued"}]


def multipart(fields: dict[str, str], files: list[tuple[str, str, bytes]]) -> tuple[bytes, str]:
    """The body Dart's http.MultipartRequest sends: fields first, then the file parts."""
    boundary = "dart-http-boundary-" + uuid.uuid4().hex[:20]
    out = bytearray()
    for name, value in fields.items():
        out += (f"--{boundary}\r\ncontent-disposition: form-data; name=\"{name}\"\r\n"
                f"content-type: text/plain; charset=utf-8\r\ncontent-transfer-encoding: binary\r\n\r\n").encode()
        out += value.encode("utf-8", "surrogatepass") + b"\r\n"  # a raw lone surrogate: older Dart's bytes
    for name, filename, data in files:
        out += (f"--{boundary}\r\ncontent-type: application/octet-stream\r\n"
                f"content-disposition: form-data; name=\"{name}\"; filename=\"{filename}\"\r\n\r\n").encode()
        out += data + b"\r\n"
    out += f"--{boundary}--\r\n".encode()
    return bytes(out), f"multipart/form-data; boundary={boundary}"


def dart_json(obj) -> str:
    # Dart's jsonEncode writes a lone surrogate as \udXXX (ASCII), which json.dumps does too.
    return json.dumps(obj)


def make_client(home: Path, upload_max_mb: int = 1, **env: str):
    """The webapp on a fresh HOPE_HOME as a Flask test client with .settings, .token and .close();
    `env` adds HOPE_* variables (e.g. HOPE_UPLOAD_MAX_PARTS="10")."""
    from hope_models.settings import load_settings
    from registry.db import Registry
    from webapp import create_app
    from webapp.auth import load_or_create_token

    settings = load_settings(env={"HOPE_HOME": str(home), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": "",
                                  "HOPE_UPLOAD_MAX_MB": str(upload_max_mb), **env})
    token = load_or_create_token(settings)
    registry = Registry.open(settings)
    app, _ = create_app(settings, token=token, registry=registry)
    c = app.test_client()
    c.settings, c.token = settings, token
    c.close = lambda: (app.extensions["hope"].close(), registry.close())
    return c


@pytest.fixture
def client(tmp_path):
    c = make_client(tmp_path / "home", 1)
    yield c
    c.close()


def handoff(client, manifest, assets=ASSETS, files=(("asset", "frame_0.jpg", FRAME), ("asset", "mic_0.wav", WAV)),
            *, token=None, raw_fields=None):
    fields = raw_fields or {"manifest": manifest if isinstance(manifest, str) else dart_json(manifest),
                            "assets": dart_json(assets)}
    body, ctype = multipart(fields, list(files))
    return client.post("/api/training/episode_handoff", data=body, content_type=ctype,
                       headers={"authorization": f"Bearer {token or client.token}"})


def inbox_files(client) -> list[str]:
    inbox = client.settings.inbox_dir
    return sorted(str(p.relative_to(inbox)) for p in inbox.rglob("*")) if inbox.exists() else []


def test_the_record_screen_episode_is_accepted_and_stored_with_its_assets(client):
    r = handoff(client, record())
    assert r.status_code == 200, r.get_json()
    body = r.get_json()
    eid = body["episode_id"]
    assert eid.startswith("app-") and body["action"] == "written" and body["status"] == "ok"
    assert body["remote_uris"] == {f"{PHONE}/frame_0.jpg": f"datasets/inbox/{eid}/blobs/assets/frame_0.jpg",
                                   f"{PHONE}/mic_0.wav": f"datasets/inbox/{eid}/blobs/assets/mic_0.wav"}
    home = Path(client.settings.home)
    assert (home / body["remote_uris"][f"{PHONE}/frame_0.jpg"]).read_bytes() == FRAME
    assert (home / body["remote_uris"][f"{PHONE}/mic_0.wav"]).read_bytes() == WAV
    # what it cannot train says why: no numeric observation, an empty command, a JPEG frame
    assert body["trainable"] == []
    assert "action.command is always empty" in body["not_trainable"]["fast_loop"]
    assert "jpg" in body["not_trainable"]["vqvae"]
    ep_dir = client.settings.inbox_dir / eid
    meta = json.loads((ep_dir / "metadata.json").read_text())
    assert meta["provenance"]["origin"] == "app:episode_handoff" and meta["episode_id"] == eid
    steps = [json.loads(line) for line in (ep_dir / "steps" / "000000.jsonl").read_text().splitlines()]
    assert steps[0]["observation"]["egocentric_video"]["uri"] == "blobs/assets/frame_0.jpg"
    # the clock is the sensors' capture time: 100 ms apart, epoch milliseconds -> ns
    assert [s["timestamp_ns"] for s in steps] == [(1_732_400_000_000 + 100 * i) * 10**6 for i in range(4)]
    entry = json.loads((client.settings.inbox_dir / "manifest.json").read_text())["episodes"][0]
    assert entry["origin"] == "app:episode_handoff" and entry["trainable"] == []


def test_a_repeated_or_respelled_handoff_is_the_same_episode(client):
    first = handoff(client, record()).get_json()
    before = inbox_files(client)
    again = handoff(client, record()).get_json()
    assert again["episode_id"] == first["episode_id"] and again["action"] == "unchanged"
    assert again["remote_uris"] == first["remote_uris"]

    def camel(obj):
        if isinstance(obj, dict):
            return {"".join(w.capitalize() if i else w for i, w in enumerate(k.split("_"))): camel(v)
                    for k, v in reversed(list(obj.items()))}
        return [camel(v) for v in obj] if isinstance(obj, list) else obj

    respelled = handoff(client, camel(record()), assets=camel(ASSETS)).get_json()
    assert respelled["episode_id"] == first["episode_id"]
    assert inbox_files(client) == before  # nothing new written


def test_lone_surrogates_are_kept_not_lost(client):
    r = handoff(client, record(notes="half an emoji \ud83d"))
    assert r.status_code == 200, r.get_json()
    eid = r.get_json()["episode_id"]
    text = (client.settings.inbox_dir / eid / "steps" / "000000.jsonl").read_bytes().decode("utf-8")
    assert "\\ud83d" in text
    assert json.loads(text.splitlines()[0])["observation"]["ui_context"]["notes"] == "half an emoji \ud83d"
    listed = client.get("/api/health")  # any answer is still valid UTF-8 JSON
    assert listed.status_code == 200


def test_a_lone_surrogate_sent_as_raw_bytes_is_the_same_episode_as_its_escape(client):
    # Dart's jsonEncode escapes a lone surrogate; an older Dart UTF-8 encoder wrote its three bytes
    escaped = handoff(client, record(notes="half an emoji \ud83d"))
    assert escaped.status_code == 200, escaped.get_json()
    raw = json.dumps(record(notes="half an emoji \ud83d"), ensure_ascii=False, separators=(",", ":"))
    assert "\ud83d" in raw  # the str holds the surrogate itself, not its escape
    again = handoff(client, raw)
    assert again.status_code == 200, again.get_json()
    assert again.get_json()["episode_id"] == escaped.get_json()["episode_id"]
    assert again.get_json()["action"] == "unchanged"


@pytest.mark.parametrize("name", ["../../x", "..", "frame_0.jpg/../../etc", "other.jpg", ""])
def test_a_file_part_no_asset_names_is_refused_and_nothing_written(client, name):
    r = handoff(client, record(), files=[("asset", name, b"x")])
    assert r.status_code == 400, r.get_json()
    assert "asset" in r.get_json()["error"]
    assert not (client.settings.inbox_dir / "manifest.json").exists()
    assert not any(p.name == "x" for p in Path(client.settings.home).rglob("x"))


def test_absolute_and_file_uris_in_steps_are_never_copied(client, tmp_path):
    secret = tmp_path / "id_rsa"
    secret.write_text("PRIVATE KEY")
    rec = record(frame_uri=str(secret))
    rec["steps"][1]["observation"]["egocentric_video"]["uri"] = f"file://{secret}"
    rec["steps"][2]["observation"]["egocentric_video"]["uri"] = "file:///etc/passwd"
    r = handoff(client, rec, files=[])
    assert r.status_code == 200, r.get_json()
    body = r.get_json()
    assert body["remote_uris"] == {}
    ep_dir = client.settings.inbox_dir / body["episode_id"]
    assert not (ep_dir / "blobs").exists()
    for p in ep_dir.rglob("*"):
        assert not p.is_file() or b"PRIVATE KEY" not in p.read_bytes()
    steps = (ep_dir / "steps" / "000000.jsonl").read_text()
    assert str(secret) in steps and "file:///etc/passwd" in steps  # kept, as text
    assert not any("id_rsa" in w or "passwd" in w for w in body["warnings"])  # no existence oracle


@pytest.mark.parametrize("manifest, needle", [
    ("{not json", "manifest: not valid JSON"),
    ({"metadata": {}, "steps": [{"observation": {}, "action": [1, 2]}] * 4}, "manifest.steps[0].action"),
    ({"metadata": {}, "steps": [record_step(0), record_step(1), record_step(2), {"observation": 5, "action": {}}]},
     "manifest.steps[3].observation"),
    ({"metadata": [], "steps": []}, "manifest.metadata"),
    ({"metadata": {}}, "manifest.steps"),
    ([1, 2], "manifest: expected a JSON object"),
])
def test_a_malformed_manifest_is_a_400_naming_the_field_and_writes_nothing(client, manifest, needle):
    r = handoff(client, manifest)
    assert r.status_code == 400
    assert needle in r.get_json()["error"]
    assert inbox_files(client) == []


def test_bad_assets_field_and_missing_manifest(client):
    r = handoff(client, record(), assets=[{"sensor": "x"}])
    assert r.status_code == 400 and "assets[0].local_uri" in r.get_json()["error"]
    r = handoff(client, None, raw_fields={"assets": "[]"})
    assert r.status_code == 400 and "manifest" in r.get_json()["error"]


def test_oversized_bodies_are_413_and_write_nothing(client):
    big = [("asset", "frame_0.jpg", b"\0" * (1 << 20) + b"more")]  # HOPE_UPLOAD_MAX_MB=1
    r = handoff(client, record(), files=big)
    assert r.status_code == 413
    assert "the limit is 1048576 bytes" in r.get_json()["error"]  # from Content-Length, before reading
    body, ctype = multipart({"manifest": dart_json(record()), "assets": dart_json(ASSETS)}, big)

    # chunked: no Content-Length, the server says the stream ends (wsgi.input_terminated)
    r = client.post("/api/training/episode_handoff", input_stream=io.BytesIO(body), content_type=ctype,
                    headers={"authorization": f"Bearer {client.token}", "Transfer-Encoding": "chunked"},
                    environ_overrides={"wsgi.input_terminated": True})
    assert r.status_code == 413 and "more than 1048576 bytes" in r.get_json()["error"]  # counted while read
    assert inbox_files(client) == []
    assert list((Path(client.settings.home) / "tmp").iterdir()) == []  # the upload dirs are gone


def test_the_token_is_checked_before_the_body(client):
    r = handoff(client, record(), token="wrong-token-xxxxxxxxxxxx")
    assert r.status_code == 401
    assert not client.settings.inbox_dir.exists()
    assert not (Path(client.settings.home) / "tmp").exists() or not os.listdir(Path(client.settings.home) / "tmp")


def test_bodies_above_the_app_wide_mib_up_to_upload_max_mb_are_taken(tmp_path):
    client = make_client(tmp_path / "home", 3)
    try:
        frame = os.urandom(2 << 20)  # 2 MiB: twice the limit of every other endpoint
        r = handoff(client, record(), files=[("asset", "frame_0.jpg", frame)])
        assert r.status_code == 200, r.get_json()
        body = r.get_json()
        assert (Path(client.settings.home) / body["remote_uris"][f"{PHONE}/frame_0.jpg"]).read_bytes() == frame
        assert f"{PHONE}/mic_0.wav" not in body["remote_uris"]  # not sent: missing on the phone
        big = client.post("/api/brain/infer", data=b"{" + b" " * (2 << 20) + b"}", content_type="application/json",
                          headers={"authorization": f"Bearer {client.token}"})
        assert big.status_code == 413  # the others keep 1 MiB
    finally:
        client.close()


def test_an_asset_no_step_names_is_stored_beside_the_episode(client):
    assets = ASSETS + [{"local_uri": f"{PHONE}/extra.png", "sensor": "screenshot", "frame_id": "x",
                        "captured_at_ms": 5, "status": "queued"}]
    r = handoff(client, record(), assets=assets, files=[("asset", "extra.png", b"\x89PNG extra")])
    assert r.status_code == 200, r.get_json()
    body = r.get_json()
    assert list(body["remote_uris"]) == [f"{PHONE}/extra.png"]
    assert (Path(client.settings.home) / body["remote_uris"][f"{PHONE}/extra.png"]).read_bytes() == b"\x89PNG extra"
    meta = json.loads((client.settings.inbox_dir / body["episode_id"] / "metadata.json").read_text())
    listed = {a["local_uri"]: a for a in meta["assets"]}
    assert listed[f"{PHONE}/extra.png"]["uri"] == "blobs/assets/extra.png"
    assert "uri" not in listed[f"{PHONE}/mic_0.wav"] and "status" not in listed[f"{PHONE}/mic_0.wav"]


def test_too_many_parts_are_refused_naming_the_limit(tmp_path):
    c = make_client(tmp_path / "home", 1, HOPE_UPLOAD_MAX_PARTS="10")
    try:
        files = [("asset", f"f{i}.jpg", b"x") for i in range(9)]  # 2 fields + 9 files: 11 parts
        r = handoff(c, record(), files=files)
        assert r.status_code == 413 and "more than 10 parts (upload_max_parts=10)" in r.get_json()["error"]
        assert inbox_files(c) == []
    finally:
        c.close()


def test_a_rejected_episode_is_a_422_with_its_reasons_and_listed(client):
    from hope_models.intake.inbox import list_inbox

    rec = record()
    rec["steps"][2]["action"]["command"] = [float("nan")]
    r = handoff(client, rec, files=[])
    assert r.status_code == 422, r.get_json()
    assert "not a finite number" in r.get_json()["error"]
    (entry,) = list_inbox(client.settings.inbox_dir)
    assert entry["status"] == "rejected" and entry["errors"]


def test_received_streams_a_raw_body_to_hope_home_and_removes_it(tmp_path):
    """The other way received() reads (an upload that is not multipart), on a view of its own."""
    from flask import current_app, jsonify

    from webapp.uploads import large_body, received

    client = make_client(tmp_path / "home", 1)
    seen = {}

    @large_body
    def raw_view():
        with received(current_app.extensions["hope"].settings) as got:
            seen["path"] = got.body
            seen["in_home"] = got.body.is_relative_to(Path(client.settings.home) / "tmp")
            return jsonify({"size": got.size, "sha": hashlib.sha256(got.body.read_bytes()).hexdigest(),
                            "fields": got.fields, "files": len(got.files)})

    client.application.add_url_rule("/api/test_raw_upload", "test_raw_upload", raw_view, methods=["POST"])
    try:
        data = os.urandom(300_000)
        r = client.post("/api/test_raw_upload", data=data, content_type="application/x-tar",
                        headers={"authorization": f"Bearer {client.token}"})
        assert r.status_code == 200, r.get_json()
        assert r.get_json() == {"size": len(data), "sha": hashlib.sha256(data).hexdigest(), "fields": {}, "files": 0}
        assert seen["in_home"] and not seen["path"].exists()  # under $HOPE_HOME/tmp, gone after
        too_big = io.BytesIO(b"\0" * ((1 << 20) + 10))
        r = client.post("/api/test_raw_upload", input_stream=too_big, content_type="application/x-tar",
                        headers={"authorization": f"Bearer {client.token}", "Transfer-Encoding": "chunked"},
                        environ_overrides={"wsgi.input_terminated": True})
        assert r.status_code == 413 and "more than 1048576 bytes" in r.get_json()["error"]
        assert list((Path(client.settings.home) / "tmp").iterdir()) == []
        r = client.post("/api/test_raw_upload", data=data, content_type="application/x-tar")
        assert r.status_code == 401  # the token before the body
    finally:
        client.close()
