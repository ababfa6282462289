"""The reflex view's surprise chart in a real browser: chromium driven by Playwright against a real
`run_trainer.py serve` whose $HOPE_HOME has a fast_loop, a vqvae and a mid_loop promoted (the tiny
models of tests/test_eval_reflex_surprise.py, trained on sim demos).

The reflex runs on a demo's seed with the target moved at JUMP_S; the episode streams in real time
(20 s) and the page plots the Mid Loop's surprise as the polls bring it. The test reads the Chart.js
instance's data (Chart.getChart on the canvas), not the DOM text: the points plotted must spike after
the jump (the same figures as the stream test: > 3x the steady median, the maximum within 1.2 s
after the jump). Then, with the mid_loop pointer removed, a second run shows "no mid_loop promoted"
instead of the chart. A screenshot at desktop width goes to test-artifacts/browser/.
"""
from __future__ import annotations

import shutil

import pytest

from daemon_fixtures import Home
from test_browser import ARTIFACTS, browser, poll, serving  # noqa: F401 - browser is a fixture
from test_eval_reflex_surprise import JUMP_S, JUMP_SEED, assert_spike, promote_all, surprise_models

pytestmark = pytest.mark.slow

CHART_DATA = """() => {
  const chart = Chart.getChart(document.querySelector('#reflex-surprise-chart'));
  return chart ? {points: chart.data.datasets[0].data, jump: chart.options.plugins.jumpMarker.t} : null;
}"""


@pytest.fixture
def serve_with_mid(tmp_path, tmp_path_factory):
    models = surprise_models(tmp_path_factory)
    home = Home(tmp_path / "home")
    promote_all(home.path, models)
    yield from serving(home)


def _records(page) -> int:
    return int(page.get_attribute("#reflex-surprise", "data-records") or 0)


def test_the_reflex_view_plots_the_surprise_spike_after_a_target_jump(browser, serve_with_mid, tmp_path):
    from playwright.sync_api import expect

    serve = serve_with_mid
    errors: list[str] = []
    context = browser.new_context(viewport={"width": 1280, "height": 900})
    page = context.new_page()
    page.on("pageerror", lambda exc: errors.append(f"pageerror: {exc}"))
    page.on("console", lambda m: errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    page.set_default_timeout(20_000)
    shot = tmp_path / "reflex-surprise.png"
    try:
        page.goto(serve.url)
        page.fill("#token-input", (serve.home.path / "token").read_text().strip())
        page.click("#login-button")
        expect(page.locator("#app")).to_be_visible()
        errors.clear()  # the first load's /favicon.ico 404 (test_browser.py clears it with the refused login)
        page.click('#nav a[data-page="inference"]')
        page.fill("#reflex-seed", str(JUMP_SEED))
        page.check("#reflex-jump")
        page.fill("#reflex-jump-s", f"{JUMP_S:g}")
        page.click("#reflex-button")

        # live: points are on the chart while the episode still runs (it plays in real time)
        expect(page.locator("#reflex-status")).to_contain_text("return so far", timeout=30_000)
        poll(lambda: _records(page) >= 30, 30, "surprise records on the chart", serve.home)
        live = page.evaluate(CHART_DATA)
        assert "Reflex done" not in page.text_content("#reflex-status")
        assert live["points"] and live["jump"] == JUMP_S, live
        expect(page.locator("#reflex-surprise-latest")).to_contain_text("mid_loop@")
        expect(page.locator("#reflex-frame")).to_be_visible()
        expect(page.locator("#reflex-surprise-none")).to_be_hidden()

        expect(page.locator("#reflex-status")).to_contain_text("Reflex done", timeout=60_000)
        expect(page.locator("#reflex-result")).to_have_attribute("data-state", "completed")
        assert _records(page) == 200  # every grid point of the 1000-step episode (0.1 s)
        data = page.evaluate(CHART_DATA)
        points = data["points"]
        assert len(points) == 195, len(points)  # the first 5 have no prediction 0.5 s back yet
        ts = [p["x"] for p in points]
        assert ts == sorted(ts) and ts[0] == pytest.approx(0.5) and ts[-1] == pytest.approx(19.9)
        f = assert_spike([{"t": p["x"], "surprise": p["y"]} for p in points], JUMP_S)
        print(f"\nchart: steady median {f['steady_median']:.2f} nats, after the jump {f['after_peak']:.2f}, "
              f"maximum at {f['t_max']:.1f} s (jump at {JUMP_S:g} s)")
        expect(page.locator('#reflex-result dd[data-key="frames"]')).to_contain_text("streamed")
        page.locator("#reflex-form").screenshot(path=str(shot))
        assert not errors, "\n".join(errors)

        # without a mid_loop the view says so instead of drawing a chart
        (serve.home.path / "promoted" / "mid_loop.json").unlink()
        page.uncheck("#reflex-jump")
        page.click("#reflex-button")
        expect(page.locator("#reflex-surprise-none")).to_have_text("no mid_loop promoted", timeout=30_000)
        expect(page.locator("#reflex-surprise .chart-box")).to_be_hidden()
        assert not errors, "\n".join(errors)
    finally:
        if shot.is_file():  # beside test_browser.py's screenshots (it clears the dir when it runs)
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            shutil.copy2(shot, ARTIFACTS / "reflex-surprise.png")
        context.close()
