"""GET /api/runs/<id>/artifacts[/<name>] and /provenance (webapp/api/run_artifacts.py,
run_files.py, run_provenance.py): the listing of a real MetricsLog run dir with two checkpoints,
the bytes of every download (the jsonl as on disk, the MCAP magic, the checkpoint tar's members),
names that are paths, symlinks out of the run dir, unknown runs; provenance from provenance.json,
from a checkpoint's config.json when there is none, and the gate's registry records."""
from __future__ import annotations

import io
import json
import tarfile
from pathlib import Path
from types import SimpleNamespace
from urllib.parse import quote

import numpy as np
import pytest

from run_page_fixtures import RunPageApp

MAGIC = b"\x89MCAP0\r\n"


@pytest.fixture
def api(tmp_path):
    a = RunPageApp(tmp_path / "home")
    yield a
    a.close()


def _add_run(api: RunPageApp, component: str = "fast_loop", config: dict | None = None) -> tuple[str, Path]:
    from registry import runs
    from registry.models import new_run_id

    rid = new_run_id()
    run_dir = Path(api.settings.runs_dir) / rid
    run_dir.mkdir(parents=True)
    with api.registry.session() as s:
        runs.create_run(s, component=component, config=config or {"data": "/data/ds", "steps": 20}, total_steps=20,
                        run_dir=str(run_dir), run_id=rid, dataset_fingerprint="fp-registry")
    return rid, run_dir


def _write_run(run_dir: Path) -> None:
    from hope_models.train.metrics import MetricsLog

    for attempt in range(2):  # a paused attempt and a resumed one: two MCAP segments
        log = MetricsLog(run_dir)
        for s in range(1, 11):
            log.log(s + 10 * attempt, {"loss": 1.0 / s})
        log.event("state", {"state": "paused_user", "step": 10})
        log.close()
    for step in (10, 20):
        ck = run_dir / "checkpoints" / f"{step:08d}"
        ck.mkdir(parents=True)
        (ck / "model.safetensors").write_bytes(bytes(range(256)) * (3 + step))
        (ck / "config.json").write_text(json.dumps({"component": "fast_loop", "train": {"data": "/data/ds",
                                                    "steps": 20, "seed": 7}, "data_fingerprint": "fp-ckpt",
                                                    "vqvae": {"path": "/h/runs/r-vq/checkpoints/00000100"}}))
        (ck / "manifest.json").write_text("{}")
    (run_dir / "checkpoints" / "last").write_text("00000020")
    (run_dir / "result.json").write_text(json.dumps({"outcome": "completed"}))


def test_listing_and_every_download(api):
    rid, run_dir = _add_run(api)
    _write_run(run_dir)
    listed = api.get(f"/api/runs/{rid}/artifacts").get_json()
    assert listed["run_id"] == rid
    arts = {a["name"]: a for a in listed["artifacts"]}
    assert list(arts) == ["metrics.jsonl", "metrics.mcap", "metrics.1.mcap", "result.json",
                          "checkpoint-10.tar", "checkpoint-20.tar"]
    assert [a["kind"] for a in arts.values()] == ["metrics", "mcap", "mcap", "result", "checkpoint", "checkpoint"]
    assert arts["metrics.mcap"]["description"].startswith("metrics.mcap opens in Foxglove")
    for name, a in arts.items():
        assert a["url"] == f"/api/runs/{rid}/artifacts/{name}"
        assert a["media_type"] and a["description"]
    assert arts["metrics.jsonl"]["size"] == (run_dir / "metrics.jsonl").stat().st_size
    ck = run_dir / "checkpoints" / "00000020"
    assert arts["checkpoint-20.tar"]["size"] == sum(p.stat().st_size for p in ck.iterdir())
    assert arts["checkpoint-20.tar"]["step"] == 20

    r = api.get(arts["metrics.jsonl"]["url"])
    assert r.status_code == 200 and r.data == (run_dir / "metrics.jsonl").read_bytes()
    assert r.headers["Content-Disposition"] == "attachment; filename=metrics.jsonl"
    assert int(r.headers["Content-Length"]) == len(r.data)
    for name in ("metrics.mcap", "metrics.1.mcap"):
        r = api.get(arts[name]["url"])
        assert r.data[:8] == MAGIC and r.data == (run_dir / name).read_bytes()
    assert api.get(arts["result.json"]["url"]).get_json() == {"outcome": "completed"}
    r = api.client.get(arts["metrics.mcap"]["url"], headers={**api.headers, "Range": "bytes=0-7"})
    assert r.status_code == 206 and r.data == MAGIC

    r = api.get(arts["checkpoint-20.tar"]["url"])
    assert r.status_code == 200 and r.headers["Content-Type"] == "application/x-tar"
    assert r.headers["Content-Disposition"] == "attachment; filename=checkpoint-20.tar"
    assert int(r.headers["Content-Length"]) == len(r.data)
    with tarfile.open(fileobj=io.BytesIO(r.data)) as tar:
        members = {m.name: m for m in tar.getmembers()}
        assert sorted(members) == ["checkpoint-20", "checkpoint-20/config.json", "checkpoint-20/manifest.json",
                                   "checkpoint-20/model.safetensors"]
        for f in ck.iterdir():
            assert tar.extractfile(members[f"checkpoint-20/{f.name}"]).read() == f.read_bytes()


def test_names_that_are_not_listed_are_404(api, tmp_path):
    rid, run_dir = _add_run(api)
    _write_run(run_dir)
    (tmp_path / "secret.txt").write_text("outside")
    for name in ("nope.json", "checkpoint-11.tar", "checkpoints/00000010/model.safetensors", "../../hope.db",
                 quote("../result.json", safe=""), "..%2f..%2fsecret.txt", ".lock"):
        r = api.get(f"/api/runs/{rid}/artifacts/{name}")
        assert r.status_code == 404, name
        assert "error" in r.get_json(), name


def test_symlinks_out_of_the_run_dir_are_refused(api, tmp_path):
    rid, run_dir = _add_run(api)
    _write_run(run_dir)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "secret.json").write_text('{"secret": 1}')
    (run_dir / "result.json").unlink()
    (run_dir / "result.json").symlink_to(outside / "secret.json")
    (run_dir / "checkpoints" / "00000010" / "config.json").unlink()
    (run_dir / "checkpoints" / "00000010" / "config.json").symlink_to(outside / "secret.json")
    (run_dir / "checkpoints" / "00000030").symlink_to(outside, target_is_directory=True)
    # a link that stays inside the run dir is fine
    (run_dir / "gate.json").symlink_to(run_dir / "checkpoints" / "00000020" / "manifest.json")

    names = [a["name"] for a in api.get(f"/api/runs/{rid}/artifacts").get_json()["artifacts"]]
    assert "result.json" not in names and "checkpoint-10.tar" not in names and "checkpoint-30.tar" not in names
    assert "gate.json" in names and "checkpoint-20.tar" in names
    for name in ("result.json", "checkpoint-10.tar", "checkpoint-30.tar"):
        r = api.get(f"/api/runs/{rid}/artifacts/{name}")
        assert r.status_code == 404 and "outside the run dir" in r.get_json()["error"], name
        assert b"secret" not in r.data
    assert api.get(f"/api/runs/{rid}/artifacts/gate.json").data == b"{}"


def test_unknown_run_bad_query_and_token(api):
    for path in ("/api/runs/r-nope/artifacts", "/api/runs/r-nope/artifacts/metrics.jsonl", "/api/runs/r-nope/provenance"):
        r = api.get(path)
        assert r.status_code == 404 and "r-nope" in r.get_json()["error"], path
        assert api.client.get(path).status_code == 401, path
    rid, _ = _add_run(api)
    r = api.get(f"/api/runs/{rid}/artifacts?x=1")
    assert r.status_code == 400 and "x" in r.get_json()["error"]
    assert api.get(f"/api/runs/{rid}/artifacts").get_json() == {"run_id": rid, "artifacts": []}


def test_provenance_from_provenance_json_and_the_gate_records(api):
    from registry.models import Model, utcnow

    from hope_models.train.provenance import write_provenance

    rid, run_dir = _add_run(api, component="mid_loop")
    cfg = SimpleNamespace(component="mid_loop", data="/data/ds", imagined_ratio=0.25,
                          to_json_obj=lambda: {"component": "mid_loop", "data": "/data/ds", "steps": 20, "lr": 3e-4})
    cache = SimpleNamespace(path=Path("/cache/abc"), fingerprint="fp-cache", n_episodes=8, n_steps=800,
                            imagined=np.array([True, False, False, True, False, False, False, False]))
    vq = Path(api.settings.runs_dir) / "r-vq" / "checkpoints" / "00000100"  # no weights: version unknown
    write_provenance(run_dir, cfg, cache, vq)
    with api.registry.session() as s:
        s.add(Model(component="mid_loop", checkpoint_path="/c/1", version=f"{rid}@20:abc", run_id=rid,
                    gate_result={"passed": False, "promoted": False, "forced": False, "reasons": ["worse"],
                                 "checks": {"val_loss": {"ok": False}}}))
        s.add(Model(component="mid_loop", checkpoint_path="/c/2", version=f"{rid}@20:abc", run_id=rid,
                    gate_result={"passed": True, "promoted": True, "forced": False, "reasons": [],
                                 "checks": {"val_loss": {"ok": True}}}, promoted_at=utcnow()))
    got = api.get(f"/api/runs/{rid}/provenance").get_json()
    assert got["run_id"] == rid and got["component"] == "mid_loop" and got["config_source"] == "provenance"
    assert got["config"] == cfg.to_json_obj()
    d = got["dataset"]
    assert (d["path"], d["fingerprint"], d["episodes"], d["steps"], d["imagined_episodes"]) == \
        ("/data/ds", "fp-cache", 8, 800, 2)
    assert d["imagined_share"] == 0.25 and d["imagined_ratio"] == 0.25
    assert got["vqvae"] == {"dir": str(vq), "run_id": "r-vq", "version": None}
    assert got["code"]["version"] == "0.1.0"
    assert got["code"]["git_commit"] is None or len(got["code"]["git_commit"]) == 40
    assert [(g["verdict"], g["checks"]["val_loss"]["ok"]) for g in got["gate"]] == [("refused", False),
                                                                                  ("promoted", True)]
    assert all(g["model_id"] and g["version"] == f"{rid}@20:abc" and g["at"] for g in got["gate"])


def test_provenance_without_provenance_json_is_null_where_unknown(api):
    rid, run_dir = _add_run(api, config={"data": "/data/ds", "steps": 20, "vqvae_run": "r-vq"})
    _write_run(run_dir)
    got = api.get(f"/api/runs/{rid}/provenance").get_json()
    assert got["config_source"] == "checkpoint" and got["config"] == {"data": "/data/ds", "steps": 20, "seed": 7}
    assert got["dataset"] == {"path": "/data/ds", "fingerprint": "fp-registry", "episodes": None, "steps": None,
                              "imagined_episodes": None, "imagined_share": None}
    assert got["vqvae"] == {"dir": "/h/runs/r-vq/checkpoints/00000100", "run_id": "r-vq", "version": None}
    assert got["code"] == {"version": None, "git_commit": None, "git_dirty": None}
    assert got["gate"] == []

    rid2, _ = _add_run(api, component="vqvae")  # nothing on disk at all: the request's config
    got = api.get(f"/api/runs/{rid2}/provenance").get_json()
    assert got["config_source"] == "request" and got["config"] == {"data": "/data/ds", "steps": 20}
    assert got["vqvae"] is None and got["dataset"]["episodes"] is None
