"""The held-out pictures a frame run leaves (train/held_out_picture.py: a frame VQ-VAE's
held_out_frames.png, a grid Mid Loop's predicted_frames.png) over HTTP: listed by GET
/api/runs/<id>/artifacts as kind "picture" and sent as image/png with the bearer token only; a run
without one lists none and 404s; a picture that resolves outside the run dir is refused."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from run_page_fixtures import RunPageApp

from hope_models.components.picture import png
from hope_models.train.held_out_picture import HELD_OUT_PICTURE, PREDICTED_PICTURE


@pytest.fixture
def api(tmp_path):
    a = RunPageApp(tmp_path / "home")
    yield a
    a.close()


def _add_run(api: RunPageApp, component: str = "vqvae") -> tuple[str, Path]:
    from registry import runs
    from registry.models import new_run_id

    rid = new_run_id()
    run_dir = Path(api.settings.runs_dir) / rid
    run_dir.mkdir(parents=True)
    with api.registry.session() as s:
        runs.create_run(s, component=component, config={"data": "/data/ds", "steps": 20}, total_steps=20,
                        run_dir=str(run_dir), run_id=rid, dataset_fingerprint="fp")
    return rid, run_dir


def _picture() -> bytes:
    return png(np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3))


@pytest.mark.parametrize(("component", "name", "words"), [
    ("vqvae", HELD_OUT_PICTURE, ("held-out", "reconstruction")),
    ("mid_loop", PREDICTED_PICTURE, ("held-out", "the frame now", "predicted codes", "recorded")),
])
def test_the_picture_is_listed_and_sent_with_the_token_only(api, component, name, words):
    rid, run_dir = _add_run(api, component)
    (run_dir / "result.json").write_text("{}")
    (run_dir / name).write_bytes(_picture())
    arts = {a["name"]: a for a in api.get(f"/api/runs/{rid}/artifacts").get_json()["artifacts"]}
    assert list(arts) == ["result.json", name]
    pic = arts[name]
    assert pic["kind"] == "picture" and pic["media_type"] == "image/png"
    assert all(w in pic["description"] for w in words), pic["description"]
    assert pic["size"] == len(_picture()) and pic["url"] == f"/api/runs/{rid}/artifacts/{name}"
    r = api.get(pic["url"])
    assert r.status_code == 200 and r.headers["Content-Type"] == "image/png" and r.data == _picture()
    assert api.client.get(pic["url"]).status_code == 401
    assert api.client.get(pic["url"], headers={"Authorization": "Bearer wrong"}).status_code == 401


def test_a_run_without_a_picture_lists_none_and_404s(api):
    rid, run_dir = _add_run(api)
    (run_dir / "result.json").write_text("{}")
    kinds = [a["kind"] for a in api.get(f"/api/runs/{rid}/artifacts").get_json()["artifacts"]]
    assert kinds == ["result"]
    r = api.get(f"/api/runs/{rid}/artifacts/{HELD_OUT_PICTURE}")
    assert r.status_code == 404 and HELD_OUT_PICTURE in r.get_json()["error"]


def test_a_picture_outside_the_run_dir_is_refused(api, tmp_path):
    rid, run_dir = _add_run(api)
    (tmp_path / "secret.png").write_bytes(b"secret" + _picture())
    (run_dir / HELD_OUT_PICTURE).symlink_to(tmp_path / "secret.png")
    assert api.get(f"/api/runs/{rid}/artifacts").get_json()["artifacts"] == []
    r = api.get(f"/api/runs/{rid}/artifacts/{HELD_OUT_PICTURE}")
    assert r.status_code == 404 and "outside the run dir" in r.get_json()["error"] and b"secret" not in r.data
    for name in (f"..%2f{rid}%2f{HELD_OUT_PICTURE}", f"checkpoints/{HELD_OUT_PICTURE}"):
        assert api.get(f"/api/runs/{rid}/artifacts/{name}").status_code == 404
