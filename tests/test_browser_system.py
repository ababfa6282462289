"""The System and Workers pages in a real browser (chromium driven by Playwright) against a real
`run_trainer.py serve` whose daemon samples the host every second (HOPE_SYSTEM_SAMPLE_S=1) and
whose worker beats every second (HOPE_WORKER_HEARTBEAT_S=1).

System: the registry is seeded, before serve starts, with a minute of samples ending now (with a
throttle level change in it); the daemon refills its ring from them, so the page's charts hold
that minute as the API serves it, gain live system.stats points within seconds, and the
temperature chart follows a thermal zone file the test writes.
Workers: serve's own worker is online on queue "pi"; a short real fast_loop run shows as its
current job (a link to #run/<id>) and is gone once it finished; a run on a queue no worker serves
highlights that queue with the command that starts one. The page reloads every heartbeat while it
is visible and stops while it is hidden.
Screenshots of both pages at 1280 px and 390 px go to test-artifacts/browser/system/; at 390 px
the pages do not scroll sideways.
"""
from __future__ import annotations

import json
import re
import shutil
import time
import urllib.request
from datetime import datetime, timedelta, timezone

import pytest

from daemon_fixtures import Home, tiny_dataset_path
from test_browser import Shots, browser, poll, serving  # noqa: F401 - browser is a fixture

pytestmark = pytest.mark.slow

SEED_S = 70          # seeded seconds of history, one sample a second, ending now
THROTTLED_AT = 30    # the seeded samples from here to THROTTLED_AT + 9 are at throttle level 1
RUN_STEPS = 300

CHART = "(sel) => Chart.getChart(document.querySelector(sel)).data.datasets[0].data.map((p) => [p.x, p.y])"


def _seed(home: Home) -> list[dict]:
    from registry.system_samples import record_samples

    end = datetime.now(timezone.utc).replace(microsecond=0)
    samples = [{"time": (end - timedelta(seconds=SEED_S - i)).isoformat(),
                "mem_percent": 40.0 + (i % 7), "mem_used_mb": 1600.0 + i, "mem_available_mb": 2400.0 - i,
                "mem_total_mb": 4000.0, "temp_c": 50.0 + (i % 3), "cpu_percent": float(i % 50),
                "throttle_level": 1 if THROTTLED_AT <= i < THROTTLED_AT + 10 else 0}
               for i in range(SEED_S + 1)]
    with home.registry.session() as s:
        record_samples(s, samples)
    return samples


@pytest.fixture(scope="module")
def serve(tmp_path_factory):
    root = tmp_path_factory.mktemp("system")
    zone = root / "thermal_zone_temp"
    zone.write_text("45000\n")
    home = Home(root / "home", extra_env={"HOPE_THERMAL_ZONE": str(zone), "HOPE_SYSTEM_SAMPLE_S": "1",
                                          "HOPE_WORKER_HEARTBEAT_S": "1"})
    home.zone = zone
    home.seeded = _seed(home)
    home.close()  # serve migrates and writes from its own process
    shutil.copytree(tiny_dataset_path(tmp_path_factory), home.settings.datasets_dir / "ds")
    yield from serving(home)


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    s = Shots(tmp_path_factory.mktemp("shots"), "system")
    yield s
    s.keep()


@pytest.fixture(scope="module")
def page(browser, serve):
    from playwright.sync_api import expect

    context = browser.new_context(viewport={"width": 1280, "height": 900})
    p = context.new_page()
    p.errors = []
    p.on("pageerror", lambda exc: p.errors.append(f"pageerror: {exc}"))
    p.on("console", lambda m: p.errors.append(f"console.{m.type}: {m.text}") if m.type == "error" else None)
    p.set_default_timeout(20_000)
    p.goto(serve.url)
    p.fill("#token-input", (serve.home.path / "token").read_text().strip())
    p.click("#login-button")
    expect(p.locator("#app")).to_be_visible()
    expect(p.locator("#conn")).to_have_text("live")
    p.errors.clear()  # the first load's /favicon.ico 404
    yield p
    context.close()


def _api(serve, path: str) -> dict:
    token = (serve.home.path / "token").read_text().strip()
    req = urllib.request.Request(serve.url + path.lstrip("/"), headers={"Authorization": f"Bearer {token}"})
    with urllib.request.urlopen(req, timeout=10) as r:
        return json.load(r)


def _ms(iso: str) -> int:
    return (datetime.fromisoformat(iso) - datetime(1970, 1, 1, tzinfo=timezone.utc)) // timedelta(milliseconds=1)


def _no_sideways_scroll(page) -> None:
    width = page.evaluate("() => [document.documentElement.scrollWidth, window.innerWidth]")
    assert width[0] <= width[1], f"the page scrolls sideways at {width[1]} px: {width[0]} px wide"


def _samples(page) -> int:
    return int(page.get_attribute("#system-charts", "data-samples") or 0)


def test_system_page_plots_the_last_hour_and_live_samples(page, serve, shots):
    from playwright.sync_api import expect

    page.click('#nav a[data-page="system"]')
    poll(lambda: _samples(page) >= SEED_S, 15, "the seeded minute on the charts", serve.home)
    # the points loaded from the history, without the live ones (a system.stats sample is not
    # necessarily one the ring kept), read in one go
    mem = page.evaluate("""() => {
      const box = document.querySelector('#system-charts');
      const data = Chart.getChart(document.querySelector('#system-mem-chart')).data.datasets[0].data;
      return data.slice(0, data.length - Number(box.dataset.liveSamples)).map((p) => [p.x, p.y]);
    }""")
    api = _api(serve, "/api/system/history?seconds=3600")
    assert api["source"] == "daemon" and api["interval_s"] == 1.0, {k: api[k] for k in ("source", "interval_s")}

    # the chart holds the hour the API serves (and nothing else): same times, same values
    plotted = {x: y for x, y in mem}
    served = {_ms(s["time"]): s["mem_percent"] for s in api["samples"] if s["mem_percent"] is not None}
    assert set(plotted) <= set(served), sorted(set(plotted) - set(served))[:5]
    assert {x: served[x] for x in served if mem[0][0] <= x <= mem[-1][0]} == plotted
    assert min(served) == mem[0][0], "the oldest sample the API serves is not on the chart"
    assert mem[-1][0] - mem[0][0] >= 60_000, f"the chart spans {(mem[-1][0] - mem[0][0]) / 1000} s"
    for s in serve.home.seeded:  # every seeded sample is a point
        assert plotted.get(_ms(s["time"])) == s["mem_percent"], s
    throttle = dict(page.evaluate(CHART, "#system-throttle-chart"))
    assert throttle[_ms(serve.home.seeded[THROTTLED_AT]["time"])] == 1
    expect(page.locator("#throttle-history")).to_contain_text("sampled change")
    expect(page.locator("#system-sampling")).to_contain_text("One sample every 1.0 s")
    expect(page.locator("#system-temp-none")).to_be_hidden()

    # live system.stats samples are appended within a few seconds, and the temperature chart
    # follows the thermal zone (61.5 °C: below the soft limit, no throttling; no seeded or earlier
    # sample has it, so its point is a live one)
    before = _samples(page)
    serve.home.zone.write_text("61500\n")
    poll(lambda: page.evaluate(CHART, "#system-temp-chart")[-1][1] == 61.5, 15,
         "the new temperature on the chart", serve.home)
    assert int(page.get_attribute("#system-charts", "data-live-samples") or 0) >= 1
    assert _samples(page) > before
    last = page.evaluate(CHART, "#system-mem-chart")[-1][0]
    assert last > _ms(serve.home.seeded[-1]["time"])
    expect(page.locator("#temp-text")).to_have_text("61.5 °C")
    shots.take(page, "system-desktop")
    page.set_viewport_size({"width": 390, "height": 844})
    time.sleep(0.3)  # Chart.js resizes on the next frame
    _no_sideways_scroll(page)
    shots.take(page, "system-phone")
    page.set_viewport_size({"width": 1280, "height": 900})
    assert not page.errors, page.errors


def test_a_throttle_change_while_the_system_page_loads_stays_in_its_history(page, serve):
    """The page's history is loaded after two requests; a system.throttle event that lands while
    the sampled hour is still on its way is kept, not wiped by the load it raced (the load's own
    samples predate the change and no run is active to have recorded it, so nothing else would
    bring it back)."""
    from playwright.sync_api import expect

    held = []

    def hold(route):  # the hour as the server had it before the change, answered later
        held.append((route, route.fetch()))

    page.click('#nav a[data-page="workers"]')
    expect(page.locator("#throttle-level")).to_have_attribute("data-level", "0")
    loads = lambda: int(page.get_attribute("#page-system", "data-loaded") or 0)  # noqa: E731
    seen = loads()
    page.route(re.compile(r"/api/system/history\?"), hold)
    try:
        page.click('#nav a[data-page="system"]')
        # the route handler runs only while Playwright is called, hence the page's own wait
        poll(lambda: page.wait_for_timeout(100) or held, 15, "the System page asking for its hour", serve.home)
        entries = page.locator("#throttle-history li").count()
        serve.home.zone.write_text("78000\n")  # past the soft limit (75 C): level 1
        expect(page.locator("#throttle-level")).to_have_attribute("data-level", "1", timeout=15_000)
        poll(lambda: page.locator("#throttle-history li").count() > entries, 15,
             "the system.throttle event in the history", serve.home)
        route, response = held[0]
        route.fulfill(response=response)
        poll(lambda: loads() > seen, 15, "the System page's load to finish", serve.home)
        first = page.locator("#throttle-history li").first
        expect(first).to_contain_text("level 1")
        expect(first).not_to_contain_text("sampled change")
    finally:
        page.unroute(re.compile(r"/api/system/history\?"))
        for route, response in held[1:]:
            route.fulfill(response=response)
        serve.home.zone.write_text("45000\n")
    expect(page.locator("#throttle-level")).to_have_attribute("data-level", "0", timeout=15_000)
    assert not page.errors, page.errors


def _current_href(page) -> str | None:
    link = page.locator('#workers-table tr[data-state="online"] td[data-key="current"] a.run-link')
    return link.first.get_attribute("href") if link.count() else None


def test_workers_page_shows_the_worker_its_job_and_a_queue_without_worker(page, serve, shots):
    from playwright.sync_api import expect

    page.click('#nav a[data-page="workers"]')
    row = page.locator("#workers-table tbody tr[data-worker]").filter(
        has=page.locator('td[data-key="queues"] .tag', has_text="pi"))
    expect(row.first).to_have_attribute("data-state", "online")
    expect(row.first.locator('td[data-key="last_seen"]')).to_have_text(re.compile(r"^(just now|\d+ s ago)$"))
    assert "last heartbeat" in row.first.locator('td[data-key="last_seen"] .ago').get_attribute("title")
    expect(row.first.locator('td[data-key="current"]')).to_have_text("idle")
    expect(page.locator('#queues-table tr[data-queue="pi"] td[data-key="workers_online"]')).to_have_text("1")

    run_id = serve.home.enqueue(serve.home.settings.datasets_dir / "ds", steps=RUN_STEPS)
    poll(lambda: _current_href(page) == f"#run/{run_id}", 60, f"run {run_id} as the worker's current job",
         serve.home)
    expect(row.first.locator('td[data-key="current"]')).to_contain_text("fast_loop")
    shots.take(page, "workers-running")

    poll(lambda: serve.home.run(run_id)["state"] in ("completed", "failed", "cancelled"), 90,
         f"run {run_id} to finish", serve.home)
    assert serve.home.run(run_id)["state"] == "completed", serve.home.describe()
    expect(row.first.locator('td[data-key="current"]')).to_have_text("idle", timeout=15_000)

    # a run on a queue no worker serves: the queue is highlighted with the command to start one
    serve.home.enqueue(serve.home.settings.datasets_dir / "ds", steps=RUN_STEPS, queue="gpu")
    stalled = page.locator('#queues-table tr[data-queue="gpu"]')
    expect(stalled).to_have_attribute("data-stalled", "1", timeout=15_000)
    expect(page.locator("#queues-hint")).to_contain_text("run_trainer.py worker --queue gpu")
    expect(page.locator('#queues-table tr[data-queue="pi"]')).to_have_attribute("data-stalled", "0")
    # reloaded every heartbeat (1 s) while visible, not at all while hidden
    loads = lambda: int(page.get_attribute("#page-workers", "data-loaded") or 0)  # noqa: E731
    seen = loads()
    poll(lambda: loads() >= seen + 2, 10, "the Workers page reloading every heartbeat", serve.home)
    page.click('#nav a[data-page="system"]')
    time.sleep(1.2)  # a reload already in flight when the page was hidden may still land
    hidden_at = loads()
    time.sleep(2.0)
    assert loads() == hidden_at, "the Workers page kept reloading while hidden"
    page.click('#nav a[data-page="workers"]')
    expect(page.locator('#queues-table tr[data-queue="gpu"]')).to_have_attribute("data-stalled", "1")
    shots.take(page, "workers-desktop")
    page.set_viewport_size({"width": 390, "height": 844})
    _no_sideways_scroll(page)
    shots.take(page, "workers-phone")
    assert not page.errors, page.errors
