"""The Robot Editor's Episodes page in a real browser (the system chromium, Playwright) against a real
`run_trainer.py serve` on a free port with a tmp $HOPE_HOME.

As a user would: log in, open Episodes, drop a Pi-runtime package (a real `drop` event carrying a
DataTransfer with the file, dispatched on the drop zone) and see its verdict and what it can train;
pick an XR zip with the file picker and see why it cannot train the loops; tag an episode and see the
tag in the table (and in the inbox's manifest); a refused archive says why and changes nothing.
Fixtures (chromium, `serve`) come from tests/test_browser.py; never `playwright install`.
"""
from __future__ import annotations

import base64
import json
from pathlib import Path

import pytest

from daemon_fixtures import Home
from test_browser import Shots, browser, serving  # noqa: F401 - `browser` is a fixture used here
from test_episode_upload import pi_package, xr_zip, zip_of

pytestmark = pytest.mark.slow

DROP = """([name, b64]) => {
  const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const dt = new DataTransfer();
  dt.items.add(new File([bytes], name, { type: "application/gzip" }));
  return dt;
}"""


@pytest.fixture
def serve(tmp_path):
    home = Home(tmp_path / "home")
    yield from serving(home)


def drop(page, name: str, data: bytes) -> None:
    transfer = page.evaluate_handle(DROP, [name, base64.b64encode(data).decode()])
    page.dispatch_event("#drop-zone", "dragover", {"dataTransfer": transfer})
    page.dispatch_event("#drop-zone", "drop", {"dataTransfer": transfer})


def test_episodes_page_upload_verdicts_and_tags(browser, serve, tmp_path, samples_dir):  # noqa: F811
    from playwright.sync_api import expect

    package = pi_package(tmp_path / "pi")
    xr = tmp_path / "episode.zip"
    xr.write_bytes(xr_zip(samples_dir))
    token = (serve.home.path / "token").read_text().strip()
    inbox = serve.home.settings.inbox_dir
    shots = Shots(tmp_path, "episodes")
    errors: list[str] = []
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    page.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
    page.on("console", lambda m: errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    page.set_default_timeout(15_000)
    try:
        page.goto(serve.url + "episodes")
        page.fill("#token-input", token)
        page.click("#login-button")
        expect(page.locator("#page-episodes")).to_be_visible()
        # the only error so far is the browser's own request for /favicon.ico (there is none: 404)
        assert [e for e in errors if "404 (NOT FOUND)" not in e] == [] and len(errors) <= 1, errors
        errors.clear()
        expect(page.locator("#nav a[data-page=episodes]")).to_have_class("active")
        expect(page.locator("#episodes-table tbody")).to_contain_text("No episodes yet")

        # a drop of the Pi package: its verdict, then the table with what it can train
        page.fill("#upload-tags", "kitchen")
        drop(page, package.name, package.read_bytes())
        expect(page.locator("#upload-panel")).to_have_attribute("data-state", "done")
        expect(page.locator("#upload-status")).to_contain_text("1 new")
        expect(page.locator('#upload-result li[data-episode="ep_00000_10hz"]')).to_contain_text(
            "written, ok; trains vqvae, fast_loop, mid_loop")
        assert page.locator("#upload-bar").get_attribute("style") == "width: 100%;"
        row = page.locator('#episodes-table tr[data-episode="ep_00000_10hz"]')
        expect(row.locator("td.verdict")).to_have_attribute("data-status", "ok")
        expect(row.locator("td.trainable")).to_have_attribute("data-trainable", "vqvae,fast_loop,mid_loop")
        expect(row.locator("td.tags")).to_have_text("kitchen")
        assert (inbox / "ep_00000_10hz" / "metadata.json").is_file()

        # the XR zip through the file picker: accepted with warnings, and why the loops cannot train
        page.set_input_files("#upload-input", str(xr))
        expect(page.locator("#upload-result li")).to_contain_text("follow_user_mr_v2: written, warnings; trains vqvae")
        xr_row = page.locator('#episodes-table tr[data-episode="follow_user_mr_v2"]')
        expect(xr_row.locator("td.verdict")).to_have_attribute("data-status", "warnings")
        xr_row.locator("td.verdict details.warnings summary").click()
        expect(xr_row.locator("td.verdict details.warnings")).to_contain_text("mixed_reality")
        expect(xr_row.locator("td.trainable")).to_contain_text("not fast_loop: 3 steps; its window needs 5")
        shots.take(page, "episodes-uploaded")

        # tag an episode: the table shows it, the inbox's manifest holds it
        xr_row.locator("input[name=tag]").fill("good follow")
        xr_row.locator("button", has_text="Tag").click()
        expect(xr_row.locator("td.tags")).to_contain_text("good follow")
        expect(page.locator("#flash")).to_contain_text("Tagged follow_user_mr_v2")
        manifest = json.loads((inbox / "manifest.json").read_text())
        (record,) = [e for e in manifest["episodes"] if e["episode_id"] == "follow_user_mr_v2"]
        assert record["tags"] == ["kitchen", "good follow"]  # the upload's tags field still said kitchen

        # a refused archive: the reason, and the inbox unchanged
        before = sorted(str(p) for p in inbox.rglob("*"))
        drop(page, "evil.zip", zip_of([("../evil.json", b"{}")]))
        expect(page.locator("#upload-panel")).to_have_attribute("data-state", "refused")
        expect(page.locator("#upload-status")).to_contain_text("'../evil.json': '..' component refused")
        assert sorted(str(p) for p in inbox.rglob("*")) == before
        expect(page.locator("#episodes-table tbody tr")).to_have_count(2)
        shots.take(page, "episodes-refused")
        # the browser logs the refused upload's 400 itself; nothing else went wrong
        assert [e for e in errors if "400 (BAD REQUEST)" not in e] == [], errors
    finally:
        context.close()
        shots.keep()
