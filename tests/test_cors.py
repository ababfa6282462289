"""CORS for a web build of the Continuon app (webapp/cors.py, the setting cors_origins).

The requests are what a browser sends for the app's calls (continuonai/lib/services/brain_client.dart:
`http.post(uri, headers: _headers())` with `authorization: Bearer <token>`; training_queue_service.dart
adds `Content-Type: application/json`): both headers make the browser ask first, with
`OPTIONS` + `Origin` + `Access-Control-Request-Method` + `Access-Control-Request-Headers` and
no token. A listed origin is answered and its calls readable; any other origin gets nothing a
browser would accept; with the default settings there is no CORS at all; and no preflight reaches
a view (the spy below counts every request Flask sees).
"""
from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

WEB_APP = "https://app.continuon.example"
DEV_SERVER = "http://192.168.1.50:5173"
EVIL = "https://evil.example"


def make_app(tmp_path, origins: str | None):
    from hope_models.settings import load_settings
    from registry.db import Registry
    from webapp import create_app
    from webapp.auth import load_or_create_token

    env = {"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""}
    if origins is not None:
        env["HOPE_CORS_ORIGINS"] = origins
    settings = load_settings(env=env)
    token = load_or_create_token(settings)
    registry = Registry.open(settings)
    app, _ = create_app(settings, token=token, registry=registry)
    seen: list[tuple[str, str]] = []

    @app.before_request
    def _spy():  # registered last: runs only for requests that reached Flask
        from flask import request

        seen.append((request.method, request.path))

    c = app.test_client()
    c.token, c.settings, c.seen, c.registry = token, settings, seen, registry
    return c, lambda: (app.extensions["hope"].close(), registry.close())


@pytest.fixture
def listed(tmp_path):
    c, close = make_app(tmp_path, f"{WEB_APP}, {DEV_SERVER}")
    yield c
    close()


@pytest.fixture
def default(tmp_path):
    c, close = make_app(tmp_path, None)
    yield c
    close()


def preflight(c, path: str, origin: str, method: str = "POST", headers: str = "authorization,content-type"):
    return c.open(path, method="OPTIONS", headers={"Origin": origin, "Access-Control-Request-Method": method,
                                                   "Access-Control-Request-Headers": headers})


def cors_headers(response) -> dict[str, str]:
    return {k.lower(): v for k, v in response.headers.items() if k.lower().startswith("access-control-")}


def reset_at(c):
    from registry import learning

    with c.registry.session(readonly=True) as s:
        return learning.reset_at(s)


@pytest.mark.parametrize("origin", [WEB_APP, DEV_SERVER])
def test_a_listed_origins_preflight_is_answered_without_the_token_and_reaches_no_view(listed, origin):
    for path in ("/api/learning/reset", "/api/training/queue/episodes", "/api/ownership/status"):
        r = preflight(listed, path, origin)
        assert r.status_code == 204, (path, r.status_code, r.get_data(as_text=True))
        h = cors_headers(r)
        assert h["access-control-allow-origin"] == origin  # that origin, never *
        assert {m.strip() for m in h["access-control-allow-methods"].split(",")} >= {"GET", "POST"}
        assert {m.strip().lower() for m in h["access-control-allow-headers"].split(",")} >= {"authorization",
                                                                                             "content-type"}
        assert int(h["access-control-max-age"]) > 0
        assert "origin" in r.headers.get("Vary", "").lower()
    assert listed.seen == []  # no view ran: nothing a preflight says can change state
    assert reset_at(listed) is None and not listed.settings.inbox_dir.exists()


def test_a_listed_origin_reads_the_answers_of_the_apps_calls(listed):
    h = {"Origin": WEB_APP, "authorization": f"Bearer {listed.token}"}
    ping = listed.get("/api/ping", headers={"Origin": WEB_APP})
    assert ping.status_code == 200 and ping.headers["Access-Control-Allow-Origin"] == WEB_APP
    assert "origin" in ping.headers["Vary"].lower()
    r = listed.post("/api/learning/reset", headers=h)
    assert r.status_code == 200 and r.get_json()["success"] is True
    assert r.headers["Access-Control-Allow-Origin"] == WEB_APP
    # an error is readable too (the page can show why), and the token is still asked for
    denied = listed.post("/api/learning/reset", headers={"Origin": WEB_APP})
    assert denied.status_code == 401 and denied.headers["Access-Control-Allow-Origin"] == WEB_APP
    assert "Access-Control-Allow-Credentials" not in r.headers  # the token is the credential, never a cookie


def test_an_unlisted_origin_gets_no_cors_headers_and_its_preflight_is_refused(listed):
    r = preflight(listed, "/api/learning/reset", EVIL)
    assert r.status_code == 403 and cors_headers(r) == {}
    assert "cors_origins" in r.get_json()["error"]
    for other in ("https://app.continuon.example.evil.example", "http://app.continuon.example",
                  "https://app.continuon.example:8443", "null"):
        assert cors_headers(preflight(listed, "/api/ping", other, method="GET")) == {}
    assert listed.seen == []
    got = listed.get("/api/ping", headers={"Origin": EVIL})
    assert got.status_code == 200 and cors_headers(got) == {}
    token_call = listed.post("/api/learning/reset", headers={"Origin": EVIL, "authorization": f"Bearer {listed.token}"})
    assert cors_headers(token_call) == {}  # a browser would not let that page read it


def test_requests_without_an_origin_and_pages_outside_api_are_untouched(listed):
    r = listed.get("/api/ping")
    assert r.status_code == 200 and cors_headers(r) == {}
    page = listed.get("/", headers={"Origin": WEB_APP})
    assert cors_headers(page) == {}


def test_default_settings_have_no_cors_at_all(default):
    assert default.settings.cors_origins == []
    for origin in (WEB_APP, EVIL):
        r = preflight(default, "/api/learning/reset", origin)
        assert cors_headers(r) == {} and r.status_code != 204
        assert cors_headers(default.get("/api/ping", headers={"Origin": origin})) == {}
        assert cors_headers(default.post("/api/learning/reset", headers={
            "Origin": origin, "authorization": f"Bearer {default.token}"})) == {}
    assert reset_at(default) is not None  # only the real POSTs above reset; no preflight did


def test_the_inference_door_is_not_for_browsers(tmp_path):
    """The door's app (webapp/inference_door.py) has no CORS even with origins listed: a preflight
    gets 405 and no Access-Control-* header, an answer none either."""
    from werkzeug.test import Client

    from hope_models.settings import load_settings
    from registry.db import Registry
    from webapp.auth import load_or_create_token
    from webapp.inference_door import create_door_app, door_app

    settings = load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_CORS_ORIGINS": WEB_APP})
    registry = Registry.open(settings)
    try:
        brain = SimpleNamespace(on_swap=None, on_first_inference=None, on_error=None)
        app = create_door_app(settings, token=load_or_create_token(settings), registry=registry, brain=brain)
        c = Client(door_app(app.wsgi_app))
        r = c.open("/api/brain/infer", method="OPTIONS", headers={
            "Host": "localhost", "Origin": WEB_APP, "Access-Control-Request-Method": "POST",
            "Access-Control-Request-Headers": "authorization,content-type"})
        assert r.status_code == 405 and cors_headers(r) == {}
        ping = c.get("/api/ping", headers={"Host": "localhost", "Origin": WEB_APP})
        assert ping.status_code == 200 and cors_headers(ping) == {}
    finally:
        registry.close()


@pytest.mark.parametrize("value, expected", [
    ("https://App.Continuon.Example", ["https://app.continuon.example"]),
    ("https://a.example:443,http://b.example:80 http://c.example:8080",
     ["https://a.example", "http://b.example", "http://c.example:8080"]),
    ("http://[::1]:5173", ["http://[::1]:5173"]),
    ("", []),
])
def test_cors_origins_are_spelled_as_browsers_send_them(tmp_path, value, expected):
    from hope_models.settings import load_settings

    assert load_settings(tmp_path / "h", env={"HOPE_CORS_ORIGINS": value}).cors_origins == expected


@pytest.mark.parametrize("value, needle", [
    ("*", "name each origin"), ("null", "name each origin"), ("https://a.example/", "no path"),
    ("https://a.example/app", "no path"), ("ftp://a.example", "not an origin"), ("a.example", "not an origin"),
    ("https://user@a.example", "not an origin"), ("https://a.example:99999", "not an origin"),
])
def test_a_value_that_is_no_origin_is_refused_naming_the_setting(tmp_path, value, needle):
    from hope_models.settings import SettingsError, load_settings

    with pytest.raises(SettingsError, match="cors_origins") as exc:
        load_settings(tmp_path / "h", env={"HOPE_CORS_ORIGINS": value})
    assert needle in str(exc.value) and "HOPE_CORS_ORIGINS" in str(exc.value)
    home = tmp_path / "toml"
    home.mkdir()
    (home / "config.toml").write_text(f"cors_origins = [{json.dumps(value)}]\n")
    with pytest.raises(SettingsError, match="config.toml: setting 'cors_origins'"):
        load_settings(home, env={})


def test_through_the_real_server_as_a_browser_sends_it(listed):
    """The preflight and the call over a socket (webapp/server.py's guards in front), with the
    headers Chrome sends for the web build's TrainingQueueService.enqueueEpisode."""
    import http.client

    from test_app_calls import youtube_record

    from webapp.server import HttpServer

    server = HttpServer(listed.application, "127.0.0.1", 0)
    server.start()
    try:
        def send(method, headers, body=None):
            conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
            try:
                conn.request(method, "/api/training/queue/episodes", body=body,
                             headers={"Host": f"127.0.0.1:{server.port}", "Origin": WEB_APP, **headers})
                resp = conn.getresponse()
                return resp.status, {k.lower(): v for k, v in resp.getheaders()}, resp.read()
            finally:
                conn.close()

        status, headers, body = send("OPTIONS", {"Access-Control-Request-Method": "POST",
                                                 "Access-Control-Request-Headers": "authorization,content-type"})
        assert status == 204 and body == b"" and headers["access-control-allow-origin"] == WEB_APP
        assert listed.seen == []
        payload = json.dumps({"episode": youtube_record(), "request_public_listing": False}).encode()
        status, headers, body = send("POST", {"Content-Type": "application/json",
                                              "authorization": f"Bearer {listed.token}"}, payload)
        assert status == 200 and headers["access-control-allow-origin"] == WEB_APP, body
        assert json.loads(body)["action"] == "written" and "origin" in headers["vary"].lower()
    finally:
        server.stop()
