"""The Robot Editor in a real browser: the system chromium driven by Playwright, against a real
`run_trainer.py serve` (daemon, worker, BrainService) on a free port with a tmp $HOPE_HOME.

One walk through, as a user would: a wrong token is refused; the right one logs in; a short
fast_loop run is queued from the Jobs page, run.progress events move its loss chart while it runs,
it completes with a convergence summary; it is promoted; Models shows it; Inference answers with
its version, and an uploaded camera frame goes with the observation (this fast_loop reads none: the
server's 400 is shown); the reflex view reports the sim episode's return; a sequential chain is paused,
resumed and cancelled from the queue; a second run is promoted from Models and rolled back; System shows a throttle change live (a thermal zone file the test heats);
a reload on a phone-sized screen keeps the login and rebuilds the run's chart from the API.
Screenshots go to tmp_path and are copied to test-artifacts/browser/ (gitignored) for a person
to look at.

Never `playwright install`: the Makefile installs Debian's chromium (robots and CI are offline
for browser downloads). The test fails, naming the fix, when chromium or playwright is missing.
"""
from __future__ import annotations

import base64
import json
import re
import shutil
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from daemon_fixtures import Home, Proc, free_port, tiny_dataset_path
from hope_models.components.picture import png

REPO = Path(__file__).resolve().parents[1]
ARTIFACTS = REPO / "test-artifacts" / "browser"
CHROMIUM = Path("/usr/bin/chromium")
STEPS = 400  # ~15 ms a step on one thread: several seconds of live progress (5 events/s at most)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def browser():
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail("the playwright package is missing: `make setup` installs it (the dev extra)")
    if not CHROMIUM.is_file():
        pytest.fail(f"{CHROMIUM} is missing: `make setup` installs it (apt-get install chromium)")
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM),
                               args=["--no-sandbox", "--disable-background-networking", "--disable-dev-shm-usage"])
        yield b
        b.close()


class Serve:
    def __init__(self, home: Home, port: int):
        self.home = home
        self.url = f"http://127.0.0.1:{port}/"
        log = home.path / "serve.log"
        home.logs.append(log)
        home.logs.append(home.path / "logs" / "worker.log")
        self.proc = Proc("serve", [sys.executable, str(REPO / "run_trainer.py"), "serve", "--port", str(port),
                                   "--tick", "0.2"], home.env, log)

    def wait_ready(self, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not self.proc.alive():
                pytest.fail(f"serve exited with {self.proc.popen.returncode}\n{self.home.describe()}")
            try:
                with urllib.request.urlopen(self.url + "api/health", timeout=1) as r:
                    if json.load(r).get("status") == "ok":
                        return
            except OSError:
                pass
            time.sleep(0.2)
        pytest.fail(f"serve did not answer /api/health within {timeout:g} s\n{self.home.describe()}")


def serving(home: Home):
    """A ready `serve` on home, stopped (and home closed) after the test: every browser test's fixture."""
    s = Serve(home, free_port())
    try:
        s.wait_ready()
        yield s
    finally:
        s.proc.stop(timeout=30)
        home.close()


@pytest.fixture
def serve(tmp_path, tmp_path_factory):
    # a thermal zone file the test can heat (millidegrees, like /sys/class/thermal/.../temp)
    zone = tmp_path / "thermal_zone_temp"
    zone.write_text("45000\n")
    home = Home(tmp_path / "home", extra_env={"HOPE_THERMAL_ZONE": str(zone), "HOPE_ALLOW_HTTP_FORCE": "1"})
    home.zone = zone
    (home.path / "admin_token").write_text("the-robot-owners-admin-token\n")
    (home.path / "admin_token").chmod(0o600)
    shutil.copytree(tiny_dataset_path(tmp_path_factory), home.settings.datasets_dir / "ds")
    yield from serving(home)


def poll(predicate, timeout: float, what: str, home: Home | None = None) -> None:
    """Wait in Python: the page's CSP (script-src 'self') forbids Playwright's eval-based waits."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}\n" + (home.describe() if home else ""))
        time.sleep(0.1)


class Shots:
    """Full-page screenshots, numbered in the order taken; keep() copies them to
    test-artifacts/browser/<name>/ (one folder per test, replaced by its next run)."""

    def __init__(self, tmp_path: Path, name: str = "editor"):
        self.dir = tmp_path / "screenshots"
        self.dir.mkdir()
        self.name = name
        self.n = 0

    def take(self, page, name: str) -> None:
        self.n += 1
        page.screenshot(path=str(self.dir / f"{self.n:02d}-{name}.png"), full_page=True)

    def keep(self) -> None:
        out = ARTIFACTS / self.name
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True, exist_ok=True)
        for png in self.dir.glob("*.png"):
            shutil.copy2(png, out / png.name)


def test_robot_editor_end_to_end(browser, serve, tmp_path):
    from playwright.sync_api import expect

    token = (serve.home.path / "token").read_text().strip()
    shots = Shots(tmp_path)
    errors: list[str] = []
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    page.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
    page.on("console", lambda m: errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    page.set_default_timeout(20_000)
    try:
        page.goto(serve.url)
        expect(page.locator("#login")).to_be_visible()
        expect(page.locator("#vendor-missing")).to_have_count(0)

        # a wrong token is refused, with a message, and nothing is stored
        page.fill("#token-input", "not-the-token-" + "x" * 20)
        page.click("#login-button")
        expect(page.locator("#login-error")).to_contain_text("Token refused: invalid bearer token")
        expect(page.locator("#app")).to_be_hidden()
        assert page.evaluate("localStorage.getItem('hope.token')") is None
        shots.take(page, "login-refused")
        errors.clear()  # the browser logs the refused request's 401 itself

        # the right one logs in, and Socket.IO connects with it
        page.fill("#token-input", token)
        page.click("#login-button")
        expect(page.locator("#app")).to_be_visible()
        expect(page.locator("#conn")).to_have_text("live")

        # queue a short run from the Jobs page
        page.fill("#start-data", "ds")
        page.fill("#start-steps", str(STEPS))
        page.fill("#start-overrides", json.dumps({"batch_size": 8, "threads": 1, "log_every": 5, "warmup": 5,
                                                  "checkpoint_every_steps": 200, "seed": 0}))
        page.click("#start-button")
        expect(page.locator("#flash")).to_contain_text("Queued run")
        expect(page.locator("#run-detail")).to_have_attribute("data-run", re.compile(r"^r-"))
        run_id = page.get_attribute("#run-detail", "data-run")
        assert run_id in page.text_content("#flash"), run_id

        # live run.progress events move the chart while it runs (counted separately from history)
        detail = page.locator("#run-detail")
        poll(lambda: int(detail.get_attribute("data-live-points") or 0) >= 3, 60, "live progress on the chart",
             serve.home)
        shots.take(page, "jobs-running")
        expect(page.locator(f'#runs-table tr[data-run="{run_id}"]')).to_be_visible()

        # it completes, with its summary
        try:
            expect(detail).to_have_attribute("data-state", "completed", timeout=60_000)
        except AssertionError:
            pytest.fail("the run did not complete in the page\n" + serve.home.describe())
        expect(page.locator("#run-summary")).to_be_visible()
        expect(page.locator('#summary-list dd[data-key="steps"]')).to_have_text(f"{STEPS} of {STEPS}")
        expect(page.locator('#summary-list dd[data-key="loss"]')).to_contain_text("->")
        points = int(page.text_content("#chart-points"))
        assert points >= 10, f"only {points} points on the finished run's chart"
        assert int(detail.get_attribute("data-live-points")) >= 3
        shots.take(page, "jobs-completed")

        # promote it (the gate runs as a child: torch import + validation)
        page.click("#promote-run")
        expect(page.locator("#promote-result")).to_contain_text("Promoted", timeout=60_000)
        version = page.text_content("#promote-result").split()[1].rstrip(";")
        assert version.startswith(run_id), version

        # Models shows what is promoted and served
        page.click('#nav a[data-page="models"]')
        card = page.locator('#models-list [data-component="fast_loop"]')
        expect(card.locator('dd[data-key="promoted"]')).to_contain_text(version)
        expect(card.locator('dd[data-key="serving"]')).to_have_text(version)
        expect(card.locator('dd[data-key="gate"]')).to_contain_text("passed")
        shots.take(page, "models")

        # Inference: the observation is prefilled to the served size; the answer names the version
        page.click('#nav a[data-page="inference"]')
        expect(page.locator("#infer-observation")).to_have_value("0, 0, 0, 0")
        page.fill("#infer-observation", "0.1, -0.2, 0.3, 0.05")
        page.click("#infer-button")
        expect(page.locator('#infer-result dd[data-key="version"]')).to_have_text(version)
        action = page.text_content('#infer-result dd[data-key="action"]').split(", ")
        assert len(action) == 2 and all(float(a) == float(a) for a in action), action
        expect(page.locator('#infer-result dd[data-key="latency"]')).to_contain_text("ms")

        # an uploaded camera frame goes with the observation as the request's `frame` (a data: URL);
        # this fast_loop reads no camera, so the server refuses it (400) and the page says why
        frame_png = png(np.full((16, 16, 3), 90, np.uint8))
        page.set_input_files("#infer-frame", files=[{"name": "cam.png", "mimeType": "image/png", "buffer": frame_png}])
        expect(page.locator("#infer-frame-preview")).to_be_visible()
        with page.expect_response("**/api/brain/infer") as answered:
            page.click("#infer-button")
        sent = answered.value.request.post_data_json
        assert sent["frame"] == "data:image/png;base64," + base64.b64encode(frame_png).decode(), sent["frame"][:80]
        assert sent["observation"] == [0.1, -0.2, 0.3, 0.05] and sent["component"] == "fast_loop"
        assert answered.value.status == 400, answered.value.text()
        reason = answered.value.json()["error"]
        assert "frame" in reason, reason
        expect(page.locator("#infer-error")).to_have_text(f"The server answered HTTP 400: {reason}")
        expect(page.locator("#infer-result dd")).to_have_count(0)
        shots.take(page, "inference-frame-refused")
        # a phone-sized photo (a noisy 1600x1200 PNG, ~5.8 MB) is shrunk in the page to fit the API's
        # 1 MiB body: the server reads it (the same refusal), not a 413
        big = png(np.random.default_rng(0).integers(0, 256, (1200, 1600, 3), dtype=np.uint8))
        assert len(big) > 4 << 20
        page.set_input_files("#infer-frame", files=[{"name": "photo.png", "mimeType": "image/png", "buffer": big}])
        with page.expect_response("**/api/brain/infer") as answered:
            page.click("#infer-button")
        sent = answered.value.request.post_data_json
        assert sent["frame"].startswith("data:image/jpeg;base64,") and len(sent["frame"]) < 1 << 20
        assert answered.value.status == 400 and answered.value.json()["error"] == reason, answered.value.text()
        assert [e for e in errors if "400" not in e] == [], errors  # the browser logs the refused request itself
        errors.clear()
        page.click("#infer-frame-clear")
        expect(page.locator("#infer-frame-box")).to_be_hidden()

        # the reflex view: a sim episode with the promoted fast_loop, its return beside the expert's
        # and random's (this fast_loop never saw the reacher: the number is low, but it is real)
        # its first episode streams in (sim.frame, real time: 20 s) and is drawn on the canvas
        page.click("#reflex-button")
        expect(page.locator("#reflex-status")).to_contain_text("return so far", timeout=30_000)
        expect(page.locator("#reflex-frame")).to_be_visible()
        shots.take(page, "reflex-streaming")
        expect(page.locator("#reflex-status")).to_contain_text("Reflex done", timeout=60_000)
        expect(page.locator("#reflex-result")).to_have_attribute("data-state", "completed")
        drawn = int(page.get_attribute("#reflex-frame", "data-frames") or 0)
        assert drawn >= 10, f"only {drawn} frames were drawn"
        expect(page.locator('#reflex-result dd[data-key="frames"]')).to_contain_text("streamed")
        expect(page.locator('#reflex-result dd[data-key="version"]')).to_have_text(version)
        for key in ("mean return", "expert mean return", "random mean return"):
            value = page.text_content(f'#reflex-result dd[data-key="{key}"]')
            assert float(value) == float(value), f"{key}: {value!r}"
        shots.take(page, "inference")

        # a second, shorter run promoted from the Models page (forced past the gate), then rolled
        # back: the first version serves again
        page.click('#nav a[data-page="jobs"]')
        page.fill("#start-steps", "300")  # long enough that the chain below is still queued behind it
        page.click("#start-button")
        expect(detail).not_to_have_attribute("data-run", run_id)
        run2 = page.get_attribute("#run-detail", "data-run")

        # a sequential chain queued behind it (one run at a time per queue): pause, resume, cancel
        # its first member from the queue table; cancelling it cancels the rest of the chain
        page.check('input[name="mode"][value="sequential"]')
        page.fill("#start-components", "vqvae,fast_loop")
        page.click("#start-button")
        expect(page.locator("#flash")).to_contain_text("Queued sequence")
        expect(detail).not_to_have_attribute("data-run", run2)
        seq1 = detail.get_attribute("data-run")
        row = page.locator(f'#runs-table tr[data-run="{seq1}"]')
        expect(row).to_have_attribute("data-state", "queued")
        row.locator('[data-action="pause"]').click()
        expect(row).to_have_attribute("data-state", "paused")
        row.locator('[data-action="resume"]').click()
        expect(row).to_have_attribute("data-state", "queued")
        row.locator('[data-action="cancel"]').click()
        expect(row).to_have_attribute("data-state", "cancelled")
        expect(page.locator('#runs-table tr[data-state="cancelled"]')).to_have_count(2)
        shots.take(page, "jobs-sequence-cancelled")
        page.check('input[name="mode"][value="single"]')

        # a run for a queue no worker serves (serve's worker takes "pi" only): it reads as waiting
        # for a gpu worker, not as running, and Cancel ends it at once
        page.fill("#start-overrides", '{"queue": "gpu"}')
        page.fill("#start-steps", "50")
        page.click("#start-button")
        expect(detail).not_to_have_attribute("data-run", seq1)
        lonely = detail.get_attribute("data-run")
        row = page.locator(f'#runs-table tr[data-run="{lonely}"]')
        expect(row).to_have_attribute("data-state", "starting")
        expect(row.locator(".waiting")).to_contain_text("waiting for a worker on queue 'gpu'")
        expect(detail).to_have_attribute("data-state", "starting")
        expect(page.locator("#detail-waiting")).to_contain_text("waiting for a worker on queue 'gpu'")
        shots.take(page, "jobs-waiting-for-a-worker")
        row.locator('[data-action="cancel"]').click()
        expect(row).to_have_attribute("data-state", "cancelled")
        expect(page.locator("#flash")).to_contain_text(f"cancel: run {lonely} is cancelled")
        expect(page.locator("#detail-waiting")).to_be_hidden()
        page.fill("#start-overrides", "")
        page.locator(f'#runs-table tr[data-run="{run2}"] td').first.click()
        expect(detail).to_have_attribute("data-run", run2)
        try:
            expect(detail).to_have_attribute("data-state", "completed", timeout=60_000)
        except AssertionError:
            pytest.fail("the second run did not complete in the page\n" + serve.home.describe())
        points2 = int(page.text_content("#chart-points"))
        assert points2 >= 5, points2
        page.click('#nav a[data-page="models"]')
        page.select_option("#promote-run-select", run2)
        page.check("#promote-force")
        page.click("#promote-button")  # no admin token: the 403's message, nothing gated
        expect(page.locator("#promote-form-result")).to_contain_text("Not promoted: force: needs the admin token")
        assert [e for e in errors if "403" not in e] == [], errors  # the browser logs the refused request itself
        errors.clear()
        page.fill("#promote-admin", "the-robot-owners-admin-token")
        page.click("#promote-button")
        expect(page.locator("#promote-form-result")).to_contain_text(f"Promoted {run2}", timeout=60_000)
        expect(card.locator('dd[data-key="serving"]')).to_contain_text(run2)
        card.locator("[data-rollback]").click()
        expect(page.locator("#flash")).to_contain_text(f"fast_loop rolled back to {version}")
        expect(card.locator('dd[data-key="serving"]')).to_have_text(version)
        shots.take(page, "models-rolled-back")

        # System: the gauges have values; heating the thermal zone past the soft limit (75 C) is
        # pushed live (system.throttle, then system.stats) and lands in the throttle history
        page.click('#nav a[data-page="system"]')
        expect(page.locator("#mem-text")).to_contain_text("MB used")
        assert page.get_attribute("#mem-gauge", "data-value") is not None
        expect(page.locator("#temp-text")).to_have_text("45.0 °C")
        expect(page.locator("#throttle-level")).to_have_attribute("data-level", "0")
        serve.home.zone.write_text("78000\n")
        expect(page.locator("#throttle-level")).to_have_attribute("data-level", "1", timeout=15_000)
        expect(page.locator("#throttle-history li").first).to_contain_text("level 1")
        expect(page.locator("#temp-text")).to_have_text("78.0 °C", timeout=15_000)
        shots.take(page, "system-throttled")
        serve.home.zone.write_text("45000\n")
        expect(page.locator("#throttle-level")).to_have_attribute("data-level", "0", timeout=15_000)
        expect(page.locator("#throttle-history li").first).to_contain_text("level 0")
        assert not errors, "\n".join(errors)

        # a phone-sized screen, a fresh tab: the login and the selected run survive (localStorage),
        # the run's chart is rebuilt from the API
        phone = context.new_page()
        phone.set_viewport_size({"width": 390, "height": 844})
        phone.goto(serve.url + "#jobs")
        expect(phone.locator("#app")).to_be_visible()
        expect(phone.locator("#run-detail")).to_have_attribute("data-run", run2)
        expect(phone.locator("#run-detail")).to_have_attribute("data-state", "completed")
        poll(lambda: int(phone.text_content("#chart-points")) == points2, 20, "the chart rebuilt after a reload")
        width = phone.evaluate("document.documentElement.scrollWidth")
        assert width <= 390, f"the page is {width} px wide on a 390 px screen"
        shots.take(phone, "phone-jobs")

        # logging out forgets the token
        phone.click("#logout")
        expect(phone.locator("#login")).to_be_visible()
        assert phone.evaluate("localStorage.getItem('hope.token')") is None
    except BaseException:
        try:
            shots.take(page, "failure")
        except Exception:  # noqa: BLE001 - the failure itself is what matters
            pass
        raise
    finally:
        shots.keep()
        context.close()
