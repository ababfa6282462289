"""What a client holding the app's token (in clear on the LAN, inside the phone app) must not get.

- an integer of 5,000 digits at every JSON door is a 4xx (or a skipped, reported line) naming the
  field, never a 500: an API body, the handoff's manifest and assets fields, an uploaded episode's
  files, config.toml;
- a handoff naming a host path answers the same whether the path exists or not, and copies nothing;
- POST /api/brain/promote with force: true needs the admin credential (off by default): 403 and
  nothing served without it; with it, the forced promotion is recorded (the model's gate_result, a
  log event on its run, a WARNING line).
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest

from daemon_fixtures import home  # noqa: F401
from hostile_clients import http_request
from test_app_handoff import ASSETS, multipart, record
from test_retention_and_queue_cap import Server

HUGE = "9" * 5000


@pytest.fixture
def server(home):
    s = Server(home)
    yield s
    s.close()


def post(server, path: str, body: bytes, content_type: str) -> tuple[int, dict]:
    status, raw = http_request(server.port, "POST", path, body=body, timeout=60.0, headers={
        "Authorization": f"Bearer {server.token}", "Content-Type": content_type})
    return status, json.loads(raw or b"{}")


def handoff(server, manifest: str, assets: str | None = None) -> tuple[int, dict]:
    body, ctype = multipart({"manifest": manifest, "assets": assets or json.dumps(ASSETS)}, [])
    return post(server, "/api/training/episode_handoff", body, ctype)


# -- huge integers -----------------------------------------------------------------------------

def test_a_huge_integer_in_an_api_body_is_a_400_naming_the_field(server):
    body = ('{"component": "fast_loop", "data": "ds", "model_config": {"d_model": %s}}' % HUGE).encode()
    status, answer = post(server, "/api/runs", body, "application/json")
    assert status == 400 and "model_config.d_model" in answer["error"] and "5000 digits" in answer["error"], answer


def test_a_huge_integer_in_the_handoff_is_a_400_naming_the_field(server, home):
    manifest = json.dumps(record()).replace('"frame_id": "ego-2"', f'"frame_id": {HUGE}', 1)
    assert HUGE in manifest
    status, answer = handoff(server, manifest)
    assert status == 400 and answer["error"].startswith("manifest: "), answer
    assert "steps[2].observation.egocentric_video.frame_id" in answer["error"], answer
    assets = json.dumps(ASSETS).replace('"captured_at_ms": 1732400000000', f'"captured_at_ms": {HUGE}', 1)
    status, answer = handoff(server, json.dumps(record()), assets)
    assert status == 400 and answer["error"].startswith("assets: ") and "[0].captured_at_ms" in answer["error"], answer
    assert not (home.settings.inbox_dir / "manifest.json").exists()


def test_a_huge_integer_in_an_uploaded_episode_is_a_skipped_reported_line(server, samples_dir):
    from test_episode_upload import XR_SAMPLE, zip_of

    src = samples_dir / XR_SAMPLE
    lines = (src / "steps" / "000000.jsonl").read_text().splitlines()
    step = json.loads(lines[1])
    step["step_metadata"] = {**(step.get("step_metadata") or {}), "counter": 0}
    lines[1] = json.dumps(step).replace('"counter": 0', f'"counter": {HUGE}')
    body = zip_of([("metadata.json", (src / "metadata.json").read_bytes()),
                   ("steps/000000.jsonl", "\n".join(lines).encode() + b"\n")])
    status, answer = post(server, "/api/episodes/upload", body, "application/zip")
    assert 400 <= status < 500 or status == 200, answer
    assert "line 2" in json.dumps(answer) and "step_metadata.counter" in json.dumps(answer), answer


def test_a_huge_integer_in_config_toml_names_the_setting(tmp_path):
    from hope_models.settings import SettingsError, load_settings

    (tmp_path / "config.toml").write_text(f"keep_runs = {HUGE}\n")
    with pytest.raises(SettingsError, match="'keep_runs' is an integer of 5000 digits"):
        load_settings(env={"HOPE_HOME": str(tmp_path)})


# -- the host-path oracle ----------------------------------------------------------------------

def _answer_for(server, target: str) -> dict:
    """The handoff's answer for an episode whose asset and step name `target`, with the parts that
    must differ (the content-named id, the path's own text in messages) taken out."""
    rec = record()
    rec["steps"][0]["observation"]["egocentric_video"]["uri"] = target
    assets = [dict(ASSETS[0], uri=target), dict(ASSETS[1], local_uri=target)]
    status, answer = handoff(server, json.dumps(rec), json.dumps(assets))
    assert status == 200, answer
    text = json.dumps(answer).replace(answer["episode_id"], "ID").replace(target, "TARGET")
    text = re.sub(r"app:[0-9a-f]{16}", "app:ID", text)  # the content's hash: the path's text is content
    return json.loads(re.sub(r"is a \S+ file", "is a ... file", text))  # the kind its name suggests


def test_a_host_path_in_a_handoff_answers_the_same_whether_it_exists_or_not(server, home):
    home_dir = Path(home.settings.home)
    assert (home_dir / "token").is_file() and (home_dir / "hope.db").is_file()
    pairs = [("/etc/passwd", "/etc/nope"), (str(home_dir / "token"), str(home_dir / "tokem")),
             (str(home_dir / "hope.db"), str(home_dir / "hopf.db")), ("../../../token", "../../../tokem")]
    for exists, missing in pairs:
        a, b = _answer_for(server, exists), _answer_for(server, missing)
        assert a == b, (exists, a, b)
        assert a["remote_uris"] == {}, a
    secret = (home_dir / "token").read_bytes()
    for p in home.settings.inbox_dir.rglob("*"):
        assert not p.is_file() or secret not in p.read_bytes(), p


# -- forced promotion --------------------------------------------------------------------------

@pytest.fixture
def api(tmp_path):
    from hope_models.settings import load_settings
    from test_api import App

    a = App(load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""}))
    yield a
    a.close()


def test_force_without_the_admin_credential_is_a_403_and_nothing_is_served(api, tmp_path_factory):
    from brain_fixtures import brain_runs
    from test_api import add_completed_run

    run_id, last = add_completed_run(api.registry, api.settings, brain_runs(tmp_path_factory)["alpha30"].parent.parent)
    body = {"checkpoint": str(last.parent / "00000015"), "force": True}
    r = api.post("/api/brain/promote", body)
    assert r.status_code == 403 and "allow_http_force" in r.get_json()["error"], r.get_data(as_text=True)
    api.settings.allow_http_force = True  # on, but the header is missing, then wrong
    r = api.post("/api/brain/promote", body)
    assert r.status_code == 403 and "X-Hope-Admin" in r.get_json()["error"]
    admin = Path(api.settings.home) / "admin_token"
    assert admin.is_file() and (admin.stat().st_mode & 0o777) == 0o600
    r = api.client.post("/api/brain/promote", json=body, headers={**api.headers, "X-Hope-Admin": "guess" * 8})
    assert r.status_code == 403 and "does not hold" in r.get_json()["error"]
    assert api.get("/api/brain").get_json()["components"]["fast_loop"]["promoted"] is None
    assert api.brain.version("fast_loop") is None
    assert not (Path(api.settings.home) / "promoted" / "fast_loop.json").exists()


def test_force_with_the_admin_credential_is_promoted_and_recorded(api, tmp_path_factory, caplog):
    from brain_fixtures import brain_runs
    from registry import runs
    from registry.models import Model
    from test_api import add_completed_run

    run_id, last = add_completed_run(api.registry, api.settings, brain_runs(tmp_path_factory)["alpha30"].parent.parent)
    # a gate that refuses any loss above the served one's: the older checkpoint is refused
    (Path(api.settings.home) / "config.toml").write_text("gate_val_tolerance = 0.0\n")
    first = api.post("/api/brain/promote", {"run_id": run_id})
    assert first.status_code == 200, first.get_data(as_text=True)
    api.settings.allow_http_force = True
    admin = Path(api.settings.home) / "admin_token"
    admin.write_text("an-admin-token-of-the-robot-owner\n")
    os.chmod(admin, 0o600)
    caplog.set_level("WARNING", logger="webapp.api.brain")
    r = api.client.post("/api/brain/promote", json={"checkpoint": str(last.parent / "00000015"), "force": True},
                        headers={**api.headers, "X-Hope-Admin": "an-admin-token-of-the-robot-owner"})
    assert r.status_code == 200, r.get_data(as_text=True)
    out = r.get_json()
    assert out["promoted"] is True and out["forced"] is True and out["serving"] == out["version"], out
    with api.registry.session(readonly=True) as s:
        model = s.get(Model, out["model_id"])
        assert model.gate_result["forced"] is True and model.gate_result["forced_by"] == "http"
        events = [e.payload for e in runs.run_events(s, run_id, kinds=["log"]) if "promotion" in e.payload]
    assert len(events) == 1 and events[0]["promotion"]["by"] == "http" and events[0]["level"] == "warning"
    assert any("forced promotion over HTTP" in r.getMessage() and out["version"] in r.getMessage()
               for r in caplog.records if r.levelname == "WARNING")


def test_the_cli_on_the_robot_can_always_force_and_it_is_recorded(api, tmp_path_factory, monkeypatch, capsys):
    import run_trainer
    from brain_fixtures import brain_runs
    from registry import runs
    from registry.models import Model
    from test_api import add_completed_run

    run_id, last = add_completed_run(api.registry, api.settings, brain_runs(tmp_path_factory)["alpha30"].parent.parent)
    (Path(api.settings.home) / "config.toml").write_text("gate_val_tolerance = 0.0\n")
    monkeypatch.setenv("HOPE_HOME", str(api.settings.home))
    assert not getattr(api.settings, "allow_http_force", False)  # the default: off
    assert run_trainer.main(["promote", run_id, "--json"]) == 0
    capsys.readouterr()
    assert run_trainer.main(["promote", "--checkpoint", str(last.parent / "00000015"), "--force", "--json"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["promoted"] is True and out["forced"] is True, out
    with api.registry.session(readonly=True) as s:
        assert s.get(Model, out["model_id"]).gate_result["forced_by"] == "cli"
        events = [e.payload for e in runs.run_events(s, run_id, kinds=["log"]) if "promotion" in e.payload]
    assert [e["promotion"]["by"] for e in events] == ["cli"] and out["version"] in events[0]["message"]


def test_a_huge_integer_in_an_mcap_episode_is_a_reported_problem_naming_the_field(tmp_path, monkeypatch):
    from hope_models.data.synthetic import generate_dataset
    from hope_models.rlds import write_mcap
    from hope_models.rlds.discover import read_path

    generate_dataset(tmp_path / "ds", 40, obs_dim=2, act_dim=1, episode_seconds=(2, 2), seed=1)
    episode = read_path(tmp_path / "ds")[0].episodes[0]
    episode.steps[1].step_metadata = {"counter": 424242424242}
    dumps = write_mcap._dumps
    monkeypatch.setattr(write_mcap, "_dumps", lambda obj: dumps(obj).replace(b"424242424242", HUGE.encode()))
    path = write_mcap.write_episode_mcap(episode, tmp_path / "ep.mcap")
    monkeypatch.undo()
    reports = read_path(path)
    problems = [p.message for r in reports for p in [*r.problems, *(q for e in r.episodes for q in e.problems)]]
    assert any("step_metadata.counter" in m and "5000 digits" in m for m in problems), problems
    assert not any("reader failed" in m for m in problems), problems
