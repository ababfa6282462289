"""The Continuon app's model calls, GET /api/v1/models and POST /api/v1/models/activate, in process
with a real BrainService, a real registry and real tiny checkpoints (brain_fixtures).

The answers are checked against what the app's Dart code does with them (model_manager_screen.dart):
`Text(model['name'])` and `Text(model['backend'])` need Strings, `_activateModel(id)` passes the id
on as a String, and `res['success'] == true` decides whether the activation worked.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from brain_fixtures import brain_runs
from test_api import App, add_completed_run, wait_for


@pytest.fixture
def settings(tmp_path):
    from hope_models.settings import load_settings

    return load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})


@pytest.fixture
def api(settings):
    a = App(settings)
    yield a
    a.close()


def _record(api, ckpt: Path, run_id: str | None, *, component: str = "fast_loop", passed: bool = True,
            promote: bool = False, reasons=(), metrics=None) -> int:
    from registry import promotion
    from hope_models.promoted import checkpoint_version

    version, _sha = checkpoint_version(ckpt)
    with api.registry.session() as s:
        m = promotion.record_candidate(s, component=component, checkpoint_path=ckpt, version=version, run_id=run_id,
                                       metrics=metrics or {"candidate_val_loss": 0.5},
                                       gate_result={"passed": passed, "promoted": promote, "forced": False,
                                                    "reasons": list(reasons), "mode": "manual"})
        if promote:
            promotion.promote(s, api.settings, m.id)
        return m.id


@pytest.fixture
def models(api, tmp_path_factory):
    """Model rows: a (alpha @15, promoted first, then replaced), b (alpha @30, served), refused (the
    gate said no), untried (passed but never promoted), vq (a promoted VQ-VAE)."""
    runs = brain_runs(tmp_path_factory)
    run_id, last = add_completed_run(api.registry, api.settings, runs["alpha30"].parent.parent)
    at15 = last.parent / "00000015"
    big_id, big = add_completed_run(api.registry, api.settings, runs["big"].parent.parent)
    vq_id, vq = add_completed_run(api.registry, api.settings, runs["vq"].parent.parent)
    ids = {"a": _record(api, at15, run_id, promote=True), "b": _record(api, last, run_id, promote=True)}
    ids["refused"] = _record(api, big, big_id, passed=False, reasons=["val loss 3.1 is worse than the promoted 0.4"])
    ids["untried"] = _record(api, big, big_id, passed=True)
    ids["vq"] = _record(api, vq, vq_id, component="vqvae", promote=True)
    ids["run_id"], ids["at15"], ids["last"] = run_id, at15, last
    return ids


def _version(api, model_id: int) -> str:
    from registry.models import Model

    with api.registry.session(readonly=True) as s:
        return s.get(Model, model_id).version


def _promoted_id(api, component="fast_loop") -> int | None:
    from registry import promotion

    with api.registry.session(readonly=True) as s:
        m = promotion.promoted(s, component)
        return m.id if m is not None else None


def test_list_has_every_version_with_the_types_the_app_casts(api, models):
    r = api.get("/api/v1/models")
    assert r.status_code == 200
    body = r.get_json()
    assert body["success"] is True and isinstance(body["models"], list)
    for m in body["models"]:
        assert isinstance(m["id"], str) and isinstance(m["name"], str) and isinstance(m["backend"], str)
        assert m["backend"] in ("numpy", "torch") and isinstance(m["active"], bool)
    by_id = {m["id"]: m for m in body["models"]}
    assert set(by_id) == {str(models[k]) for k in ("a", "b", "refused", "untried", "vq")}
    fast = [m for m in body["models"] if m["component"] == "fast_loop"]
    served = fast[0]  # the served one first, then the history newest first
    assert served["id"] == str(models["b"]) and served["active"] and served["status"] == "serving"
    assert served["backend"] == "numpy" and by_id[str(models["vq"])]["backend"] == "numpy"  # every component: NumPy
    assert served["name"].startswith(f"fast_loop · run {models['run_id']} step 30 (serving, promoted 20")
    assert served["version"] == _version(api, models["b"])
    assert by_id[str(models["a"])]["status"] == "promoted before" and by_id[str(models["a"])]["activatable"]
    refused = by_id[str(models["refused"])]
    assert refused["status"] == "refused by the gate" and not refused["activatable"]
    assert "worse than the promoted" in refused["why_not"] and "refused by the gate" in refused["name"]
    assert not by_id[str(models["untried"])]["activatable"]
    assert [m["id"] for m in fast[1:]] == [str(models["untried"]), str(models["refused"]), str(models["a"])]
    json.dumps(body, allow_nan=False)  # what the Dart decoder gets is strict JSON


def test_activating_a_version_promoted_before_serves_it_again_without_a_gate(api, models):
    wait_for(lambda: api.brain.status()["fast_loop"]["version"] == _version(api, models["b"]), 10, "b served")
    r = api.post("/api/v1/models/activate", {"model_id": str(models["a"])})
    assert r.status_code == 200, r.get_json()
    out = r.get_json()
    version_a = _version(api, models["a"])
    assert out["success"] is True and out["id"] == str(models["a"]) and out["version"] == version_a
    assert out["serving"] == version_a == api.brain.status()["fast_loop"]["version"]
    assert _promoted_id(api) == models["a"]
    pointer = json.loads((Path(api.settings.home) / "promoted" / "fast_loop.json").read_text())
    assert pointer["version"] == version_a and pointer["model_id"] == models["a"]
    # the list shows the switch; a rollback now goes back to b (the promote rule: a's previous is b)
    listed = {m["id"]: m for m in api.get("/api/v1/models").get_json()["models"]}
    assert listed[str(models["a"])]["active"] and not listed[str(models["b"])]["active"]
    assert api.post("/api/brain/rollback", {"component": "fast_loop"}).get_json()["version"] == _version(api, models["b"])
    # activating the served one again changes nothing and succeeds
    again = api.post("/api/v1/models/activate", {"model_id": str(models["b"])})
    assert again.status_code == 200 and again.get_json()["success"] is True and _promoted_id(api) == models["b"]


def test_a_refused_or_never_promoted_version_is_not_forced(api, models):
    r = api.post("/api/v1/models/activate", {"model_id": str(models["refused"])})
    assert r.status_code == 409
    body = r.get_json()
    assert body["success"] is False and "refused by the gate" in body["error"]
    assert body["reasons"] == ["val loss 3.1 is worse than the promoted 0.4"]
    r = api.post("/api/v1/models/activate", {"model_id": str(models["untried"])})
    assert r.status_code == 409 and "never promoted" in r.get_json()["error"]
    assert _promoted_id(api) == models["b"]


def test_a_version_whose_checkpoint_is_gone_or_changed_is_refused(api, models):
    shutil.rmtree(models["at15"])
    r = api.post("/api/v1/models/activate", {"model_id": str(models["a"])})
    assert r.status_code == 409 and "no longer exists" in r.get_json()["error"]
    assert _promoted_id(api) == models["b"]


@pytest.mark.parametrize("body, status, text", [
    ({"model_id": "999999"}, 404, "no model"),
    ({"model_id": "not-a-model"}, 404, "no model"),
    ({"model_id": 1}, 400, "model_id"),
    ({"model_id": ""}, 400, "model_id"),
    ({"model_id": "   "}, 400, "model_id"),
    ({"model_id": "9" * 40}, 400, "model_id"),
    ({"model_id": None}, 400, "model_id"),
    ({}, 400, "model_id"),
    ({"model_id": "1", "force": True}, 400, "force"),
    ([1], 400, "object"),
])
def test_activate_bad_input(api, models, body, status, text):
    r = api.post("/api/v1/models/activate", body)
    assert r.status_code == status, r.get_json()
    assert text in r.get_json()["error"]
    assert _promoted_id(api) == models["b"]


def test_activate_needs_json(api, models):
    r = api.client.post("/api/v1/models/activate", headers=api.headers, data="model_id=1")
    assert r.status_code == 415 and "JSON" in r.get_json()["error"]


def test_an_empty_registry_lists_no_models(api):
    r = api.get("/api/v1/models")
    assert r.status_code == 200 and r.get_json() == {"success": True, "models": []}
    assert api.get("/api/v1/models?history=0").status_code == 400
    assert "unknown query" in api.get("/api/v1/models?x=1").get_json()["error"]


def test_ping_is_open_stable_and_names_no_path(api, tmp_path):
    from hope_models.settings import load_settings

    r = api.client.get("/api/ping")  # no token: the app's runDiagnostics sends none
    assert r.status_code == 200
    body = r.get_json()
    assert body["status"] == "ok" and isinstance(body["device_id"], str) and body["device_id"].startswith("hope-")
    assert api.client.get("/api/ping").get_json() == body
    assert str(api.settings.home) not in r.get_data(as_text=True) and api.token not in r.get_data(as_text=True)
    other = App(load_settings(env={"HOPE_HOME": str(tmp_path / "other"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""}),
                brain=False)
    try:
        assert other.client.get("/api/ping").get_json()["device_id"] != body["device_id"]
    finally:
        other.close()
