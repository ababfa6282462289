"""The webapp's API of issue 6, in process with a real BrainService and real tiny checkpoints.

- the bad-input table: every entry gets a 4xx JSON {"error"} naming the problem, never a 500, both
  through Flask's test client and through the real HTTP server (a 20 MB body, chunked or not);
- promote (the gate runs as a `run_trainer.py promote` child) -> infer answers with the new version
  -> a refused candidate (409) -> a forced one -> rollback -> infer answers with the previous one,
  all over HTTP, with `brain.reloaded` pushed on Socket.IO and the loop-closure time recorded and
  shown by `status`;
- /api/runs/<id>/metrics paging, /api/system (standalone and with the daemon in the process),
  /api/training/sequential, the sim reflex jobs;
- the webapp never imports torch, even while it serves inference.
The token checks of every route are in test_webapp_auth.py.
"""
from __future__ import annotations

import http.client
import json
import os
import shutil
import subprocess
import sys
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from brain_fixtures import brain_runs, promote_pointer, rewrite_manifest

REPO = Path(__file__).resolve().parents[1]
OBS = [0.1, -0.2, 0.3, 0.0, 0.5, -0.4]  # brain_fixtures' fast_loop reads 6 observation values


# -- fixtures -------------------------------------------------------------------------------------

@pytest.fixture
def settings(tmp_path):
    from hope_models.settings import load_settings

    return load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})


def add_completed_run(registry, settings, source_run_dir: Path, *, finished_ago_s: float = 5.0) -> tuple[str, Path]:
    """A completed fast_loop run in the registry whose run dir is a copy of `source_run_dir`
    (the same weights, under $HOPE_HOME/runs/<id> like a run the worker trained)."""
    from registry import runs
    from registry.models import new_run_id, utcnow

    run_id = new_run_id()
    run_dir = Path(settings.runs_dir) / run_id
    shutil.copytree(source_run_dir, run_dir, symlinks=True)
    steps = sorted(int(p.name) for p in (run_dir / "checkpoints").iterdir() if p.name.isdigit())
    last = run_dir / "checkpoints" / f"{steps[-1]:08d}"
    # the dataset the run was trained on, as the registry holds it (promote RUN gates on it)
    data = json.loads((last / "config.json").read_text())["train"]["data"]
    with registry.session() as s:
        run = runs.create_run(s, component="fast_loop", config={"data": data, "steps": steps[-1]},
                              total_steps=steps[-1], run_dir=str(run_dir), run_id=run_id)
        run.state = "completed"
        run.step = steps[-1]
        run.last_checkpoint = str(last)
        run.finished_at = utcnow() - timedelta(seconds=finished_ago_s)
    return run_id, last


class App:
    """create_app with a started BrainService (fast poll) on a tmp $HOPE_HOME."""

    def __init__(self, settings, *, brain: bool = True):
        from registry.db import Registry
        from hope_models.runtime.brain_service import BrainService
        from webapp import create_app
        from webapp.auth import load_or_create_token

        self.settings = settings
        self.token = load_or_create_token(settings)
        self.registry = Registry.open(settings)
        self.brain = BrainService(settings.home, poll_s=0.1) if brain else None
        self.app, self.socketio = create_app(settings, token=self.token, registry=self.registry, brain=self.brain)
        if self.brain is not None:
            self.brain.start()
        self.client = self.app.test_client()
        self.headers = {"Authorization": f"Bearer {self.token}"}

    def get(self, path: str):
        return self.client.get(path, headers=self.headers)

    def post(self, path: str, body=None, **kw):
        return self.client.post(path, headers=self.headers, json=body, **kw)

    def close(self) -> None:
        self.app.extensions["hope"].close()
        if self.brain is not None:
            self.brain.stop()
        self.registry.close()


@pytest.fixture
def api(settings):
    a = App(settings)
    yield a
    a.close()


def wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.05)


# -- the bad-input table ------------------------------------------------------------------------

def bad_input_table(run_id: str, token_file_in_home: str) -> list[tuple]:
    """(method, path, body, expected status, text the error must contain). A body that is a dict
    or list is sent as JSON; bytes are sent raw as application/json; ("ctype", bytes) sets the type."""
    obs = OBS
    infer = "/api/brain/infer"
    runs_ = "/api/runs"
    seq = "/api/training/sequential"
    return [
        # missing / invalid fields, wrong types
        ("POST", infer, {"observation": obs}, 400, "component: required"),
        ("POST", infer, {"component": "fast_loop"}, 400, "observation: required"),
        ("POST", infer, {"component": 7, "observation": obs}, 400, "component: expected a string"),
        ("POST", infer, {"component": "fast_loop", "observation": "0.1,0.2"}, 400, "observation: expected a list"),
        ("POST", infer, {"component": "fast_loop", "observation": {"x": 1}}, 400, "observation: expected a list"),
        ("POST", infer, {"component": "fast_loop", "observation": [0.1, "x", 0, 0, 0, 0]}, 400, "observation[1]"),
        ("POST", infer, {"component": "fast_loop", "observation": [True, 0, 0, 0, 0, 0]}, 400, "observation[0]"),
        ("POST", infer, {"component": "fast_loop", "observation": [[0.1]] * 6}, 400, "observation[0]"),
        ("POST", infer, {"component": "fast_loop", "observation": []}, 400, "observation: has 0 values"),
        ("POST", infer, {"component": "fast_loop", "observation": [0.0] * 4097}, 400, "4096"),
        ("POST", infer, {"component": "fast_loop", "observation": [0.1, 0.2, 0.3]}, 400, "6"),  # wrong length
        ("POST", infer, {"component": "fast_loop", "observation": obs, "session": 5}, 400, "session"),
        ("POST", infer, {"component": "fast_loop", "observation": obs, "session": "s" * 200}, 400, "session"),
        ("POST", infer, {"component": "fast_loop", "observation": obs, "reset": "yes"}, 400, "reset"),
        ("POST", infer, {"component": "fast_loop", "observation": obs, "temperature": 1}, 400, "unknown field"),
        # unknown component
        ("POST", infer, {"component": "wings", "observation": obs}, 404, "wings"),
        ("POST", "/api/brain/rollback", {"component": "wings"}, 400, "component"),
        ("POST", "/api/brain/promote", {"run_id": run_id, "component": "wings"}, 400, "component"),
        # NaN / overflow in observations
        ("POST", infer, b'{"component": "fast_loop", "observation": [NaN, 0, 0, 0, 0, 0]}', 400, "NaN"),
        ("POST", infer, b'{"component": "fast_loop", "observation": [Infinity, 0, 0, 0, 0, 0]}', 400, "Infinity"),
        ("POST", infer, b'{"component": "fast_loop", "observation": [-Infinity, 0, 0, 0, 0, 0]}', 400, "Infinity"),
        ("POST", infer, b'{"component": "fast_loop", "observation": [1e999, 0, 0, 0, 0, 0]}', 400, "finite"),
        ("POST", infer, b'{"component": "fast_loop", "observation": [0, -1e400, 0, 0, 0, 0]}', 400,
         "observation[1]"),
        # finite, but beyond any robot's values (near float32's limit they answered NaN)
        ("POST", infer, b'{"component": "fast_loop", "observation": [3.5e38, 0, 0, 0, 0, 0]}', 400,
         "observation[0] = 3.5e+38 is outside the accepted range [-1e+06, 1e+06]"),
        # malformed JSON, wrong content type, not an object
        ("POST", infer, b'{"component": "fast_loop", "observation": [0.1,', 400, "not valid JSON"),
        ("POST", infer, b"", 400, "empty"),
        ("POST", infer, b"\xff\xfe{}", 400, "UTF-8"),
        ("POST", infer, b"[" * 100_000, 400, "not valid JSON"),
        ("POST", infer, [1, 2, 3], 400, "JSON object"),
        ("POST", infer, ("text/plain", b'{"component": "fast_loop"}'), 415, "application/json"),
        ("POST", infer, ("application/x-www-form-urlencoded", b"component=fast_loop"), 415, "application/json"),
        ("POST", runs_, ("text/plain", b"component=fast_loop"), 415, "application/json"),
        # negative or non-numeric steps
        ("POST", runs_, {"component": "fast_loop", "data": "ds", "steps": -5}, 400, "steps"),
        ("POST", runs_, {"component": "fast_loop", "data": "ds", "steps": "ten"}, 400, "steps"),
        ("POST", runs_, {"component": "fast_loop", "data": "ds", "steps": 2.5}, 400, "steps"),
        ("POST", seq, {"components": "vqvae,fast_loop", "data": "ds", "steps": 0}, 400, "steps"),
        ("POST", seq, {"components": "vqvae,fast_loop", "data": "ds", "steps": "many"}, 400, "steps"),
        ("POST", seq, {"components": "vqvae,wings", "data": "ds"}, 400, "wings"),
        ("POST", seq, {"components": [], "data": "ds"}, 400, "components"),
        ("POST", seq, {"components": 3, "data": "ds"}, 400, "components"),
        ("POST", seq, {"components": "mid_loop", "data": "ds"}, 400, "vqvae"),
        ("POST", seq, {"data": "ds"}, 400, "components: required"),
        ("POST", seq, {"components": "fast_loop", "data": "ds", "queue_name": "x"}, 400, "unknown field"),
        ("POST", "/api/sim/reflex", {"episodes": 0}, 400, "episodes"),
        ("POST", "/api/sim/reflex", {"episodes": 6}, 400, "episodes"),
        ("POST", "/api/sim/reflex", {"episodes": "two"}, 400, "episodes"),
        ("POST", "/api/sim/reflex", {"seed": -1}, 400, "seed"),
        ("POST", "/api/sim/reflex", {"task": "fly"}, 400, "task"),
        # path traversal and absolute paths outside the data roots
        ("POST", runs_, {"component": "fast_loop", "data": "../../../../etc"}, 400, "outside the allowed data roots"),
        ("POST", runs_, {"component": "fast_loop", "data": "/etc"}, 400, "outside the allowed data roots"),
        ("POST", runs_, {"component": "fast_loop", "data": "ds\u0000/x"}, 400, "data: 'ds\\x00/x' is not a path"),
        ("POST", runs_, {"component": "fast_loop", "data": "ds/../../../../../etc/passwd"}, 400, "outside"),
        ("POST", seq, {"components": "fast_loop", "data": "/etc"}, 400, "outside the allowed data roots"),
        ("POST", seq, {"components": "fast_loop", "data": "../../.."}, 400, "outside the allowed data roots"),
        ("POST", "/api/brain/promote", {"checkpoint": "/etc"}, 400, "outside the allowed data roots"),
        ("POST", "/api/brain/promote", {"checkpoint": "runs/../../../etc"}, 400, "outside"),
        ("POST", "/api/brain/promote", {"checkpoint": token_file_in_home}, 400, "not a directory"),
        ("POST", "/api/brain/promote", {}, 400, "run_id"),
        ("POST", "/api/brain/promote", {"run_id": run_id, "checkpoint": "runs"}, 400, "not both"),
        ("POST", "/api/brain/promote", {"run_id": run_id, "force": "yes"}, 400, "force"),
        ("POST", "/api/brain/promote", {"run_id": 12}, 400, "run_id"),
        # unknown run ids (and other unknown things)
        ("POST", "/api/brain/promote", {"run_id": "r-nope"}, 404, "r-nope"),
        ("GET", "/api/runs/r-nope", None, 404, "r-nope"),
        ("GET", "/api/runs/r-nope/metrics", None, 404, "r-nope"),
        ("POST", "/api/runs/r-nope/cancel", None, 404, "r-nope"),
        ("POST", runs_, {"component": "mid_loop", "data": "ds", "vqvae_run": "r-nope"}, 400, "r-nope"),
        ("GET", "/api/sim/reflex/reflex-99-abc", None, 404, "reflex-99-abc"),
        ("GET", f"/api/runs/{run_id}/metrics?after=abc", None, 400, "after"),
        ("GET", f"/api/runs/{run_id}/metrics?after=-3", None, 400, "after"),
        ("GET", f"/api/runs/{run_id}/metrics?limit=0", None, 400, "limit"),
        ("GET", f"/api/runs/{run_id}/metrics?limit=10000000", None, 400, "limit"),
        ("GET", "/api/brain?history=lots", None, 400, "history"),
        ("POST", "/api/brain/rollback", {}, 400, "component: required"),
        ("POST", "/api/brain/rollback", {"component": "mid_loop"}, 409, "nothing to roll back"),
        ("GET", "/api/no-such-thing", None, 404, "no such endpoint"),
        ("DELETE", "/api/brain", None, 405, "not allowed"),
        ("GET", "/api/brain/infer", None, 405, "allowed: POST"),
    ]


def _encode(body) -> tuple[bytes | None, str | None]:
    if body is None:
        return None, None
    if isinstance(body, tuple):
        return body[1], body[0]
    if isinstance(body, bytes):
        return body, "application/json"
    return json.dumps(body).encode(), "application/json"


class HttpTransport:
    """The same requests through the real server (werkzeug's threaded WSGI server on a free port)."""

    def __init__(self, app, token: str):
        from webapp.server import HttpServer

        self.server = HttpServer(app, "127.0.0.1", 0)
        self.server.start()
        self.token = token

    def request(self, method: str, path: str, data: bytes | None, ctype: str | None,
                extra: dict | None = None) -> tuple[int, dict | None, str]:
        conn = http.client.HTTPConnection("127.0.0.1", self.server.port, timeout=30)
        try:
            headers = {"Authorization": f"Bearer {self.token}", **(extra or {})}
            if ctype:
                headers["Content-Type"] = ctype
            conn.request(method, path, body=data, headers=headers)
            resp = conn.getresponse()
            text = resp.read().decode("utf-8", "replace")
            ctype_out = resp.getheader("Content-Type", "")
        finally:
            conn.close()
        return resp.status, (json.loads(text) if ctype_out.startswith("application/json") else None), text

    def close(self) -> None:
        self.server.stop()


def _check_table(api, settings, send):
    from registry import runs

    (settings.datasets_dir / "ds").mkdir(parents=True, exist_ok=True)
    with api.registry.session() as s:
        run_id = runs.create_run(s, component="fast_loop", config={"data": "ds"}, total_steps=10,
                                 run_dir=str(settings.runs_dir / "r-table")).id
    failures = []
    for method, path, body, status, needle in bad_input_table(run_id, "token"):
        data, ctype = _encode(body)
        got, obj, text = send(method, path, data, ctype)
        ok = (got == status and isinstance(obj, dict) and isinstance(obj.get("error"), str)
              and needle in obj["error"])
        if not ok:
            failures.append(f"{method} {path} {str(body)[:80]!r}: expected {status} with {needle!r}, got {got} "
                            f"{text[:300]}")
    assert not failures, "\n".join(failures)


def _serve_alpha(api, tmp_path_factory):
    ckpt = brain_runs(tmp_path_factory)["alpha30"]
    promote_pointer(api.settings.home, ckpt)
    wait_for(lambda: api.brain.version("fast_loop"), 5, "BrainService to load alpha30")
    return ckpt


def test_bad_input_table_is_4xx_with_a_message_in_process(api, settings, tmp_path_factory):
    _serve_alpha(api, tmp_path_factory)

    def send(method, path, data, ctype):
        headers = dict(api.headers)
        if ctype:
            headers["Content-Type"] = ctype
        r = api.client.open(path, method=method, data=data, headers=headers)
        return r.status_code, r.get_json(silent=True), r.get_data(as_text=True)

    _check_table(api, settings, send)
    big = api.client.post("/api/brain/infer", headers=api.headers, data=b"[" + b"0.5," * 5_000_000 + b"0]",
                          content_type="application/json")
    assert big.status_code == 413 and "too large" in big.get_json()["error"]
    # after all that, inference still answers
    ok = api.post("/api/brain/infer", {"component": "fast_loop", "observation": OBS})
    assert ok.status_code == 200, ok.get_data(as_text=True)


def test_bad_input_table_through_the_real_server(api, settings, tmp_path_factory):
    _serve_alpha(api, tmp_path_factory)
    http_ = HttpTransport(api.app, api.token)
    try:
        _check_table(api, settings, lambda m, p, d, c: http_.request(m, p, d, c))
        twenty_mb = b'{"component": "fast_loop", "observation": [' + b"0.5," * (5 * 2**20) + b"0]}"
        assert len(twenty_mb) > 20 * 2**20
        status, obj, text = http_.request("POST", "/api/brain/infer", twenty_mb, "application/json")
        assert status == 413 and "too large" in obj["error"], text[:300]
        # chunked (no Content-Length): cut at the limit while reading, still a 413
        conn = http.client.HTTPConnection("127.0.0.1", http_.server.port, timeout=30)
        try:
            chunks = (b"[" + b"0.5," * 2**18 for _ in range(20))
            conn.request("POST", "/api/brain/infer", body=chunks, encode_chunked=True,
                         headers={"Authorization": f"Bearer {api.token}", "Content-Type": "application/json"})
            resp = conn.getresponse()
            assert resp.status == 413 and "too large" in json.loads(resp.read())["error"]
        finally:
            conn.close()
        # the token is checked even for a body that is too large (413 first: nothing is read)
        status, obj, _ = http_.request("POST", "/api/brain/infer", twenty_mb, "application/json",
                                       extra={"Authorization": "Bearer wrong-token-wrong-token"})
        assert status in (401, 413) and "error" in obj
        status, obj, _ = http_.request("POST", "/api/brain/infer",
                                       json.dumps({"component": "fast_loop", "observation": OBS}).encode(),
                                       "application/json")
        assert status == 200 and obj["model_version"] == api.brain.version("fast_loop")
    finally:
        http_.close()


def test_infer_without_a_promoted_model_or_brain(settings):
    a = App(settings)
    try:
        r = a.post("/api/brain/infer", {"component": "fast_loop", "observation": OBS})
        assert r.status_code == 503 and "promot" in r.get_json()["error"]
        brain = a.get("/api/brain").get_json()
        assert brain["brain"] == "running"
        assert brain["components"]["fast_loop"]["promoted"] is None
        assert brain["components"]["fast_loop"]["pointer"] is None
    finally:
        a.close()
    b = App(settings, brain=False)
    try:
        r = b.post("/api/brain/infer", {"component": "fast_loop", "observation": OBS})
        assert r.status_code == 503 and "BrainService is not running" in r.get_json()["error"]
        assert b.get("/api/brain").get_json()["brain"] == "not running in this process"
    finally:
        b.close()


def test_corrupt_pointer_is_reported_not_a_500(api):
    path = Path(api.settings.home) / "promoted" / "fast_loop.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("{not json")
    r = api.get("/api/brain")
    assert r.status_code == 200
    assert "not valid JSON" in r.get_json()["components"]["fast_loop"]["pointer_error"]
    reflex = api.post("/api/sim/reflex", {"episodes": 1})
    assert reflex.status_code == 409 and "fast_loop.json" in reflex.get_json()["error"]


# -- every answer is valid JSON --------------------------------------------------------------------

def _no_constant(name: str):
    raise ValueError(f"{name} in an answer: not JSON")


def strict_json(response):
    """The body as a strict parser (a browser's JSON.parse) reads it: NaN / Infinity refused."""
    return json.loads(response.get_data(as_text=True), parse_constant=_no_constant)


def test_a_non_finite_tick_is_a_500_without_nan_and_the_session_is_not_poisoned(api, tmp_path_factory, tmp_path):
    from brain_fixtures import overflowing_copy

    ckpt, mean0 = overflowing_copy(brain_runs(tmp_path_factory)["alpha30"],
                                   tmp_path / "ovf" / "checkpoints" / "00000030")
    version = promote_pointer(api.settings.home, ckpt)["version"]
    wait_for(lambda: api.brain.version("fast_loop") == version, 5, "BrainService to load the overflowing copy")
    normal = [[mean0] + OBS[1:], [mean0, 0.5, -0.3, 0.1, 0.2, -0.1]]

    def infer(obs, session):
        return api.post("/api/brain/infer", {"component": "fast_loop", "observation": obs, "session": session})

    first = infer(normal[0], "arm")
    assert first.status_code == 200
    huge = infer([3.5e38] + OBS[1:], "arm")  # bad input: 400 with the range, the state untouched
    assert huge.status_code == 400 and "[-1e+06, 1e+06]" in strict_json(huge)["error"]
    fault = infer([1e6] + OBS[1:], "arm")  # in range, but this model overflows on it: its fault
    assert fault.status_code == 500, fault.get_data(as_text=True)
    body = strict_json(fault)
    assert "non-finite" in body["error"] and version in body["error"] and "action" not in body
    second = infer(normal[1], "arm")
    ref = [strict_json(infer(x, "ref"))["action"] for x in normal]  # a session that never saw them
    assert [strict_json(first)["action"], strict_json(second)["action"]] == ref
    served = strict_json(api.get("/api/brain"))["components"]["fast_loop"]["serving"]
    assert served["non_finite"] == 1


def test_the_json_provider_writes_null_for_non_finite_floats(api):
    """The floor under every view: whatever a view returns, the body is valid JSON."""
    from dataclasses import dataclass

    from flask import jsonify

    @dataclass
    class Metrics:  # serialised through the provider's `default`
        loss: float
        history: list

    with api.app.test_request_context():
        body = jsonify({"loss": float("nan"), "series": [1.0, float("inf"), -float("inf")],
                        "nested": {"m": Metrics(float("nan"), [float("-inf"), 2])}, "ok": 0.5})
        text = body.get_data(as_text=True)
    assert json.loads(text, parse_constant=_no_constant) == {
        "loss": None, "series": [1.0, None, None], "nested": {"m": {"loss": None, "history": [None, 2]}}, "ok": 0.5}


# -- promote -> infer -> rollback over HTTP, the loop closure ---------------------------------------

def _nan_copy(ckpt: Path, dest: Path) -> Path:
    """A copy of a checkpoint whose weights hold a NaN (manifest re-hashed: only the gate objects)."""
    import numpy as np
    from safetensors.numpy import load_file, save_file

    shutil.copytree(ckpt, dest)
    tensors = load_file(str(dest / "model.safetensors"))
    name = sorted(k for k, v in tensors.items() if v.dtype.kind == "f")[0]
    tensors[name] = tensors[name].copy()
    tensors[name].flat[0] = np.nan
    save_file(tensors, str(dest / "model.safetensors"))
    rewrite_manifest(dest)
    return dest


def test_promote_infer_rollback_over_http_and_the_loop_closure(api, settings, tmp_path_factory, monkeypatch,
                                                               capsys):
    src = brain_runs(tmp_path_factory)
    run_id, last = add_completed_run(api.registry, settings, src["alpha30"].parent.parent, finished_ago_s=7.0)
    sock = api.socketio.test_client(api.app, auth={"token": api.token})
    assert sock.is_connected()

    # 1. promote the run: the gate runs in a child, the pointer is written, BrainService follows
    r = api.post("/api/brain/promote", {"run_id": run_id})
    assert r.status_code == 200, r.get_data(as_text=True)
    first = r.get_json()
    assert first["promoted"] is True and first["version"].startswith(f"{run_id}@")
    assert first["serving"] == first["version"]
    infer = api.post("/api/brain/infer", {"component": "fast_loop", "observation": OBS, "session": "arm"})
    assert infer.status_code == 200, infer.get_data(as_text=True)
    answer = infer.get_json()
    assert answer["model_version"] == first["version"]
    assert len(answer["action"]) == 2 and all(isinstance(v, float) for v in answer["action"])
    assert answer["latency_ms"] >= 0
    reloaded = [e["args"][0] for e in sock.get_received() if e["name"] == "brain.reloaded"]
    assert {"component": "fast_loop", "version": first["version"]}.items() <= reloaded[-1].items()

    # the loop closure: the first inference on the run's weights, ~7 s after it finished
    run = wait_for(lambda: (api.get(f"/api/runs/{run_id}").get_json()["run"]
                            if api.get(f"/api/runs/{run_id}").get_json()["run"]["loop_closure_s"] is not None
                            else None), 5, "loop_closure_s")
    assert 7.0 <= run["loop_closure_s"] < 120, run
    monkeypatch.setenv("HOPE_HOME", str(settings.home))
    import run_trainer

    assert run_trainer.main(["status", run_id]) == 0
    table = capsys.readouterr().out
    assert "CLOSURE" in table.splitlines()[0] and f"{run['loop_closure_s']:.1f}s" in table, table

    # promoting it again changes nothing; a run that has not completed is a usage error (400)
    r = api.post("/api/brain/promote", {"run_id": run_id})
    assert r.status_code == 200 and r.get_json()["already"] is True and r.get_json()["serving"] == first["version"]
    from registry import runs

    with api.registry.session() as s:
        queued = runs.create_run(s, component="fast_loop", config={"data": "ds"}, total_steps=5,
                                 run_dir=str(settings.runs_dir / "q")).id
    r = api.post("/api/brain/promote", {"run_id": queued})
    assert r.status_code == 400 and queued in r.get_json()["error"], r.get_data(as_text=True)

    # 2. a candidate with NaN weights: refused by the gate (409), the reason recorded, nothing changes
    bad = _nan_copy(last, Path(settings.runs_dir) / "imported" / "nan-candidate")
    r = api.post("/api/brain/promote", {"checkpoint": str(bad)})
    assert r.status_code == 409, r.get_data(as_text=True)
    refused = r.get_json()
    assert refused["promoted"] is False and "refused by the gate" in refused["error"]
    assert any("finite" in reason or "NaN" in reason for reason in refused["reasons"]), refused
    assert api.brain.version("fast_loop") == first["version"]

    # 3. an older checkpoint of the run, forced past the gate (by a path relative to $HOPE_HOME), with
    # the admin credential forcing over HTTP needs (webapp/admin.py)
    older = last.parent / "00000015"
    settings.allow_http_force = True
    (Path(settings.home) / "admin_token").write_text("the-robot-owners-admin-token\n")
    os.chmod(Path(settings.home) / "admin_token", 0o600)
    r = api.client.post("/api/brain/promote", json={"checkpoint": str(older.relative_to(settings.home)), "force": True},
                        headers={**api.headers, "X-Hope-Admin": "the-robot-owners-admin-token"})
    assert r.status_code == 200, r.get_data(as_text=True)
    second = r.get_json()
    assert second["promoted"] is True and second["version"] != first["version"]
    assert second["serving"] == second["version"]
    again = api.post("/api/brain/infer", {"component": "fast_loop", "observation": OBS, "session": "arm"})
    assert again.get_json()["model_version"] == second["version"]

    # 4. rollback: back to the first version, over HTTP and in BrainService
    r = api.post("/api/brain/rollback", {"component": "fast_loop"})
    assert r.status_code == 200, r.get_data(as_text=True)
    assert r.get_json()["version"] == first["version"] and r.get_json()["serving"] == first["version"]
    back = api.post("/api/brain/infer", {"component": "fast_loop", "observation": OBS})
    assert back.get_json()["model_version"] == first["version"]
    versions = [e["args"][0]["version"] for e in sock.get_received() if e["name"] == "brain.reloaded"]
    assert versions == [second["version"], first["version"]]

    # GET /api/brain: what is served, the promoted row, the pointer and the history (refused one included)
    brain = api.get("/api/brain").get_json()["components"]["fast_loop"]
    assert brain["serving"]["version"] == first["version"]
    assert brain["promoted"]["version"] == first["version"] and brain["pointer"]["version"] == first["version"]
    history = brain["history"]
    assert [m["version"] for m in history][:2] == [second["version"], refused["version"]]
    assert any(m["promoted"] is False and m["gate_result"] and not m["gate_result"].get("passed")
               for m in history)
    # a second rollback goes further back than the first promotion: nothing there
    r = api.post("/api/brain/rollback", {"component": "fast_loop"})
    assert r.status_code == 409 and "roll back" in r.get_json()["error"]
    sock.disconnect()


# -- metrics, system, sequential, sim ------------------------------------------------------------------

def test_run_metrics_paging(api, settings, tmp_path_factory):
    from hope_models.train.metrics import read_metrics

    run_id, _ = add_completed_run(api.registry, settings, brain_runs(tmp_path_factory)["alpha30"].parent.parent)
    all_metrics = [r for r in read_metrics(settings.runs_dir / run_id) if r["type"] == "metric"]
    assert len(all_metrics) >= 3
    got, after = [], None
    for _ in range(20):
        q = f"/api/runs/{run_id}/metrics?limit=2" + (f"&after={after}" if after is not None else "")
        page = api.get(q).get_json()
        assert len(page["records"]) <= 2
        got += page["records"]
        after = page["next_after"]
        if not page["more"]:
            break
    assert got == all_metrics
    assert [r["step"] for r in got] == sorted(r["step"] for r in got)
    tail = api.get(f"/api/runs/{run_id}/metrics?after={all_metrics[-2]['step']}").get_json()
    assert tail["records"] == all_metrics[-1:] and tail["more"] is False
    with_events = api.get(f"/api/runs/{run_id}/metrics?events=1").get_json()["records"]
    assert {r["type"] for r in with_events} == {"metric", "event"}
    # a run that has not written metrics yet: an empty page, not an error
    from registry import runs

    with api.registry.session() as s:
        fresh = runs.create_run(s, component="fast_loop", config={}, total_steps=5,
                                run_dir=str(settings.runs_dir / "not-started")).id
    assert api.get(f"/api/runs/{fresh}/metrics").get_json() == {"run_id": fresh, "records": [], "next_after": None,
                                                                 "more": False}


def test_system_standalone_and_with_the_daemon(api, settings):
    from registry import runs
    from daemon.events import ListSink
    from daemon.service import Daemon

    (settings.datasets_dir / "ds").mkdir(parents=True)
    with api.registry.session() as s:
        queued = runs.create_run(s, component="fast_loop", config={"data": "ds"}, total_steps=5,
                                 run_dir=str(settings.runs_dir / "q"), priority=3).id
    r = api.get("/api/system")
    assert r.status_code == 200
    body = r.get_json()
    assert body["stats"]["mem_total_mb"] > 0 and "sources" in body["stats"]
    assert body["throttle"] == {"level": None, "source": None}
    assert body["queue"]["counts"] == {"queued": 1} and [x["id"] for x in body["queue"]["queued"]] == [queued]
    assert 0 < body["process"]["rss_mb"] < 4096

    sent = []
    daemon = Daemon(settings, ListSink(), registry=api.registry, send=lambda *a: sent.append(a))
    daemon.start()
    daemon.tick()  # dispatches the queued run (to our fake broker) and samples the host
    api.app.extensions["hope"].daemon = daemon
    body = api.get("/api/system").get_json()
    assert body["throttle"] == {"level": 0, "source": "daemon"}
    assert body["stats"]["time"] == daemon.last_sample["time"]
    # sent to the (fake) broker, no worker has taken it: starting, and it says what it waits for
    assert [x["id"] for x in body["queue"]["starting"]] == [queued] and body["queue"]["running"] == [] and sent
    assert body["queue"]["starting"][0]["waiting"].startswith("waiting for a worker on queue 'pi' since ")


def test_a_run_no_worker_takes_is_starting_over_http_and_cancel_ends_it_at_once(api, settings):
    """GET /api/runs and /api/runs/<id> show a sent, unclaimed run as starting with why; POST
    cancel ends it at once (no worker could ever answer a request), and the queue moves on."""
    from registry import runs
    from daemon.dispatch import Dispatcher

    with api.registry.session() as s:
        first, behind = (runs.create_run(s, component="fast_loop", config={"data": "ds"}, total_steps=5,
                                         run_dir=str(settings.runs_dir / name), queue="gpu").id
                         for name in ("a", "b"))
    sent = []
    dispatcher = Dispatcher(api.registry, settings, send=lambda *a: sent.append(a))
    assert [d.run_id for d in dispatcher.dispatch(0)] == [first]
    listed = {r["id"]: r for r in api.get("/api/runs").get_json()["runs"]}
    assert listed[first]["state"] == "starting" and listed[first]["worker_pid"] is None
    assert listed[first]["waiting"].startswith("waiting for a worker on queue 'gpu' since ")
    assert listed[behind]["state"] == "queued" and f"behind run {first}" in listed[behind]["waiting"]
    assert api.get("/api/runs?state=starting").get_json()["runs"] == [listed[first]]
    # the one run's object is the listed one plus its held-out figures (none before it has finished)
    assert api.get(f"/api/runs/{first}").get_json()["run"] == {**listed[first], "validation": None}

    r = api.post(f"/api/runs/{first}/cancel")
    assert r.status_code == 200
    run = r.get_json()["run"]
    assert run["state"] == "cancelled" and run["waiting"] is None and run["error"] == "cancelled by user"
    assert api.post(f"/api/runs/{first}/cancel").status_code == 409  # nothing left to cancel
    assert [d.run_id for d in dispatcher.dispatch(0)] == [behind] and len(sent) == 2
    with api.registry.session() as s:  # the first message, taken by a late worker, is refused
        assert runs.claim(s, first, sent[0][3], 1, "gpu-box", 99) is None


def test_sequential_queues_a_chain(api, settings):
    from hope_models.data.synthetic import generate_dataset

    # a real dataset: the chain is checked against it (episodes, each member's model) before it exists
    generate_dataset(settings.datasets_dir / "ds", 200, obs_dim=6, act_dim=2, seed=0, episode_seconds=(4.0, 6.0))
    woken = []
    api.app.extensions["hope"].daemon = type("D", (), {"wake": lambda self: woken.append(1)})()
    r = api.post("/api/training/sequential", {"components": ["vqvae", "fast_loop", "mid_loop"], "data": "ds",
                                             "steps": 30, "threads": 1, "seed": 4})
    assert r.status_code == 201, r.get_data(as_text=True)
    out = r.get_json()
    members = out["runs"]
    assert [m["component"] for m in members] == ["vqvae", "fast_loop", "mid_loop"]
    assert {m["sequence_id"] for m in members} == {out["sequence_id"]}
    assert [m["sequence_index"] for m in members] == [0, 1, 2]
    assert all(m["state"] == "queued" and m["total_steps"] == 30 for m in members)
    assert members[1]["config"]["vqvae_run"] == members[0]["id"] == members[2]["config"]["vqvae_run"]
    assert members[0]["config"]["data"] == str((settings.datasets_dir / "ds").resolve())
    assert woken
    listed = api.get("/api/runs?state=queued").get_json()["runs"]
    assert {m["id"] for m in members} == {x["id"] for x in listed}
    # a comma-separated string works like the CLI's --components
    r = api.post("/api/training/sequential", {"components": "vqvae,fast_loop", "data": "ds"})
    assert r.status_code == 201 and len(r.get_json()["runs"]) == 2


def test_sim_reflex_job_runs_in_the_background(api, settings, tmp_path_factory):
    from hope_models.sim.reacher import TASKS
    from webapp.api import sim

    assert tuple(TASKS) == sim.TASKS
    none = api.post("/api/sim/reflex", {"episodes": 1})
    assert none.status_code == 409 and "no fast_loop has been promoted" in none.get_json()["error"]

    # brain_fixtures' fast_loop reads 6 synthetic values, not the reacher's observation: eval-reflex
    # (a real child, torch and MuJoCo) refuses it, and the job reports its reason
    _serve_alpha(api, tmp_path_factory)
    r = api.post("/api/sim/reflex", {"episodes": 2, "seed": 7, "task": "track"})
    assert r.status_code == 202, r.get_data(as_text=True)
    job = r.get_json()["job"]
    assert job["state"] == "running" and (job["episodes"], job["seed"], job["task"]) == (2, 7, "track")
    assert r.headers["Location"] == f"/api/sim/reflex/{job['id']}"
    busy = api.post("/api/sim/reflex", {"episodes": 1})
    assert busy.status_code == 409 and job["id"] in busy.get_json()["error"]
    done = wait_for(lambda: (lambda j: j if j["state"] != "running" else None)(
        api.get(f"/api/sim/reflex/{job['id']}").get_json()["job"]), 120, "the eval-reflex child")
    assert done["state"] == "failed" and done["result"] is None, done
    assert "observation" in done["error"] or "reacher" in done["error"], done
    assert done["finished_at"] and done["elapsed_s"] > 0

    # a fast_loop trained on 4 joint values (the reacher's observation) runs: the job's result is
    # eval-reflex's JSON, on the promoted version; one at a time, not one ever: this next job starts.
    # Its first episode streams as sim.frame events (as fast as the child renders here, instead of
    # in real time, so the webapp's throttle has frames to drop)
    ckpt = _reacher_shaped_fast_loop(tmp_path_factory)
    pointer = promote_pointer(settings.home, ckpt)
    sock = api.socketio.test_client(api.app, auth={"token": api.token})
    assert sock.is_connected()
    sock.get_received()
    api.app.extensions["hope"].reflex_jobs.stream_speed = 0
    r = api.post("/api/sim/reflex", {})
    assert r.status_code == 202, r.get_data(as_text=True)
    job_id = r.get_json()["job"]["id"]
    done = wait_for(lambda: (lambda j: j if j["state"] != "running" else None)(
        api.get(f"/api/sim/reflex/{job_id}").get_json()["job"]), 120, "the second eval-reflex child")
    assert done["state"] == "completed" and done["error"] is None, done
    result = done["result"]
    assert result["version"] == pointer["version"] and result["episodes"] == 1 and result["task"] == "reach"
    assert result["expert_mean_return"] > result["random_mean_return"]
    assert [e["seed"] for e in result["per_episode"]] == [0]

    from png_decode import decode_data_url

    frames = [e["args"][0] for e in sock.get_received() if e["name"] == "sim.frame"]
    assert len(frames) >= 2 and done["frames"] == {"emitted": len(frames), "error": None}, done["frames"]
    assert result["frames"]["sent"] == 201 and result["frames"]["error"] is None  # the child rendered them all ...
    assert len(frames) <= done["elapsed_s"] * sim.MAX_EMITS_PER_S + 2  # ... the browser got at most ~10 a second
    assert all(f["job_id"] == job_id and f["episode"] == 0 and f["seed"] == 0 for f in frames)
    steps = [f["step"] for f in frames]
    assert steps == sorted(set(steps)) and steps[-1] == 1000 and frames[-1]["done"] is True
    assert frames[-1]["return_so_far"] == result["per_episode"][0]["return"]
    for f in (frames[0], frames[-1]):
        img = decode_data_url(f["image"])
        assert img.shape == (128, 128, 3) and len(np.unique(img.reshape(-1, 3), axis=0)) > 20
    assert "image" not in json.dumps(result)  # the result is the child's answer, not its frame lines


def test_sim_reflex_job_reports_frames_it_could_not_render():
    """A child whose renders fail: the job completes with its result and says why there were no frames."""
    from webapp.api import sim
    from webapp.commands import ChildResult

    class Children:
        def run(self, args, *, timeout_s, on_line=None):
            assert "--stream-frames" in args and on_line is not None
            err = "cannot render the reacher (MUJOCO_GL=egl): RuntimeError: no EGL display"
            assert on_line(json.dumps({"frame_error": err}) + "\n") is True
            assert on_line('{"ok": true, "mean_return": 3.0}\n') is False
            return ChildResult(args, 0, {"ok": True, "mean_return": 3.0, "frames": {"sent": 0, "error": err}}, "",
                               1.0)

    class Socket:
        def __init__(self):
            self.emitted = []

        def emit(self, *a):
            self.emitted.append(a)

    sock = Socket()
    jobs = sim.ReflexJobs(Children(), socketio=sock)
    job = jobs.start(episodes=1, seed=0, task="reach")
    done = wait_for(lambda: (lambda j: j if j["state"] != "running" else None)(jobs.get(job["id"])), 5, "the job")
    assert done["state"] == "completed" and done["result"]["mean_return"] == 3.0
    assert done["frames"]["emitted"] == 0 and "no EGL display" in done["frames"]["error"]
    assert sock.emitted == []


def _reacher_shaped_fast_loop(tmp_path_factory) -> Path:
    """A tiny fast_loop on synthetic episodes of 2 joint positions + 2 velocities -> 2 commands,
    which is the reacher's observation and action layout (10 steps: it only has to run)."""
    import torch

    from daemon_fixtures import tiny_dataset_path
    from hope_models.train.loop import TrainConfig, train

    root = tmp_path_factory.mktemp("reacher-shaped")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result = train(TrainConfig(component="fast_loop", data=str(tiny_dataset_path(tmp_path_factory)),
                                   run_dir=str(root / "run"), steps=10, batch_size=8, threads=1,
                                   checkpoint_every_steps=10, cache_dir=str(root / "cache"), thermal_zone=None,
                                   vcgencmd=None, model_config={"d_model": 16, "d_state": 32}, val_batches=1))
    finally:
        torch.set_num_threads(threads)
    assert result.outcome == "completed", result.message
    return Path(result.checkpoint)


# -- no torch in the webapp -------------------------------------------------------------------------

def test_webapp_serving_inference_never_imports_torch(tmp_path, tmp_path_factory):
    ckpt = brain_runs(tmp_path_factory)["alpha30"]
    home = tmp_path / "home"
    promote_pointer(home, ckpt)
    code = f"""
import sys, json
from hope_models.settings import load_settings
from hope_models.runtime.brain_service import BrainService
from registry.db import Registry
from webapp import create_app
from webapp.auth import load_or_create_token
import webapp.api.brain, webapp.api.sim, webapp.api.system, webapp.api.training, webapp.api.runs, webapp.commands
s = load_settings()
brain = BrainService(s.home).start()
registry = Registry.open(s)
app, sio = create_app(s, token=load_or_create_token(s), registry=registry, brain=brain)
c = app.test_client()
h = {{"Authorization": "Bearer " + load_or_create_token(s)}}
r = c.post("/api/brain/infer", headers=h, json={{"component": "fast_loop", "observation": {OBS}}})
assert r.status_code == 200, r.get_data(as_text=True)
for path in ("/api/brain", "/api/system", "/api/runs"):
    assert c.get(path, headers=h).status_code == 200, path
assert c.post("/api/brain/rollback", headers=h, json={{"component": "fast_loop"}}).status_code == 409
brain.stop()
print(json.dumps({{"torch": "torch" in sys.modules, "version": r.get_json()["model_version"]}}))
"""
    env = {**os.environ, "HOPE_HOME": str(home), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["torch"] is False
    assert out["version"].startswith("alpha@30:")


def test_first_inference_time_is_recorded_once_through_the_callback(api, settings, tmp_path_factory):
    """wire_brain: BrainService's on_first_inference -> registry.promotion.record_first_inference."""
    from registry import promotion
    from registry.models import Run

    run_id, last = add_completed_run(api.registry, settings, brain_runs(tmp_path_factory)["alpha30"].parent.parent,
                                     finished_ago_s=3.0)
    from hope_models.promoted import checkpoint_version

    version, _ = checkpoint_version(last)
    with api.registry.session() as s:
        model = promotion.record_candidate(s, component="fast_loop", checkpoint_path=last, version=version,
                                           run_id=run_id, metrics={}, gate_result={"passed": True, "reasons": []})
        promotion.promote(s, settings, model.id)
    wait_for(lambda: api.brain.version("fast_loop") == version, 5, "the swap")
    with api.registry.session(readonly=True) as s:
        assert s.get(Run, run_id).first_inference_at is None  # loaded, but nobody asked yet
    t0 = datetime.now(timezone.utc)
    for _ in range(3):
        assert api.post("/api/brain/infer", {"component": "fast_loop", "observation": OBS}).status_code == 200

    def recorded():
        with api.registry.session(readonly=True) as s:
            run = s.get(Run, run_id)
            return (run.first_inference_at, run.loop_closure_s) if run.first_inference_at else None

    first, closure = wait_for(recorded, 5, "the loop-closure record (written beside the request)")
    assert first is not None and abs((first - t0).total_seconds()) < 5
    assert 3.0 <= closure < 60
    assert api.post("/api/brain/infer", {"component": "fast_loop", "observation": OBS}).status_code == 200
    time.sleep(0.3)
    with api.registry.session(readonly=True) as s:
        assert s.get(Run, run_id).first_inference_at == first  # once
