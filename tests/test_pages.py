"""The Robot Editor's pages without a browser: the shell, its static files, no CDN, the headers,
and the vendor check (tests/test_browser.py drives the same pages in chromium)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
STATIC = REPO / "webapp" / "static"


@pytest.fixture
def client(tmp_path):
    from registry.db import Registry
    from hope_models.settings import load_settings
    from webapp import create_app
    from webapp.auth import load_or_create_token

    settings = load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})
    registry = Registry.open(settings, migrate=True)
    app, _ = create_app(settings, token=load_or_create_token(settings), registry=registry)
    yield app.test_client()
    app.extensions["hope"].close()
    registry.close()


@pytest.mark.parametrize("path", ["/", "/jobs", "/episodes", "/system", "/models", "/inference"])
def test_every_page_is_the_editor_shell(client, path):
    r = client.get(path)  # no token: the shell holds no data
    assert r.status_code == 200
    assert r.mimetype == "text/html"
    html = r.get_data(as_text=True)
    assert 'id="login-form"' in html and 'id="page-jobs"' in html and 'id="loss-chart"' in html
    expected = "jobs" if path == "/" else path[1:]
    assert f'data-page="{expected}"' in html
    csp = r.headers["Content-Security-Policy"]
    assert "script-src 'self'" in csp and "connect-src 'self'" in csp
    assert r.headers["Cache-Control"] == "no-store"


def test_unknown_page_is_404_json(client):
    r = client.get("/nowhere")
    assert r.status_code == 404 and "no such endpoint" in r.get_json()["error"]


def test_no_cdn_and_every_referenced_static_file_is_served(client):
    """Offline robots: every script and stylesheet is local, and the server has each one."""
    html = client.get("/").get_data(as_text=True)
    refs = re.findall(r'(?:src|href)="([^"#]+)"', html)
    assert refs, html
    for ref in refs:
        assert ref.startswith("/static/"), f"{ref}: the editor must not load anything from another host"
        r = client.get(ref)
        assert r.status_code == 200, f"{ref}: HTTP {r.status_code}"
        r.close()
    # the modules import only each other (no bare package names, no URLs)
    for js in (STATIC / "js").glob("*.js"):
        for target in re.findall(r'from\s+"([^"]+)"', js.read_text()):
            assert target.startswith("./") and (STATIC / "js" / target[2:]).is_file(), f"{js.name}: import {target}"
        assert "http://" not in js.read_text() and "https://" not in js.read_text(), js.name


def test_static_and_pages_need_no_token_but_the_api_does(client):
    assert client.get("/static/js/app.js").status_code == 200
    assert client.get("/api/runs").status_code == 401


def test_vendor_files_missing_shows_what_to_run(client, monkeypatch, tmp_path):
    import webapp.pages as pages
    from webapp import build_assets

    monkeypatch.setattr(pages, "missing_vendor_files", lambda: build_assets.missing_vendor_files(tmp_path / "none"))
    html = client.get("/").get_data(as_text=True)
    assert 'id="vendor-missing"' in html and "make setup" in html and "socket.io.min.js" in html


def test_vendor_files_installed_by_setup():
    """`make setup` runs npm ci + webapp/build_assets.py; a checkout without them fails here with the fix."""
    from webapp.build_assets import missing_vendor_files

    assert not missing_vendor_files(), ("webapp/static/vendor/ is incomplete: run `make setup` "
                                        "(npm ci && python webapp/build_assets.py)")


def test_build_assets_copies_and_names_a_missing_source(tmp_path):
    from webapp import build_assets

    nm = tmp_path / "node_modules"
    assert build_assets.main(["--node-modules", str(nm), "--vendor-dir", str(tmp_path / "v")]) == 1
    for src in build_assets.VENDOR_FILES.values():
        (nm / src).parent.mkdir(parents=True, exist_ok=True)
        (nm / src).write_text(f"/* {src} */")
    assert build_assets.main(["--node-modules", str(nm), "--vendor-dir", str(tmp_path / "v")]) == 0
    for name, src in build_assets.VENDOR_FILES.items():
        assert (tmp_path / "v" / name).read_text() == f"/* {src} */"
    assert build_assets.missing_vendor_files(tmp_path / "v") == []


def test_the_episodes_page_is_in_the_shell_and_its_script_is_served(client):
    html = client.get("/episodes").get_data(as_text=True)
    for needle in ('id="page-episodes"', 'id="drop-zone"', 'id="upload-input"', 'id="episodes-table"',
                   'href="#episodes"'):
        assert needle in html, needle
    r = client.get("/static/js/episodes.js")
    assert r.status_code == 200 and "/api/episodes/upload" in r.get_data(as_text=True)
    assert 'import * as episodes from "./episodes.js"' in client.get("/static/js/app.js").get_data(as_text=True)
