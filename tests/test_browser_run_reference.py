"""The Run and Compare pages on a Mid Loop and a VQ-VAE run, in a real browser on a real `serve`:
the held-out figures and their baselines as reference lines, the gate's verdicts, and two runs of
different components side by side.

The two runs are written as their trainers write them (tests/big_run.py: metrics.jsonl with the
component's own per-step figures, result.json with the held-out figures in summary.val, the
registry's own moves); the gate verdicts are the real baselines check
(hope_models/promote/baselines.py) run on those held-out figures and recorded as promotion
candidates through registry/promotion.py, as `run_trainer.py promote` records them. Training a real
Mid Loop and gating it would take minutes; the pages only read what these files and rows hold.
"""
from __future__ import annotations

import pytest

from daemon_fixtures import Home
from test_browser import Shots, browser, serving  # noqa: F401 - browser is a fixture
from test_browser_run import CHART, card, editor_page, phone_fits, rendered

pytestmark = pytest.mark.slow

HORIZONS = ("0.5s", "1s")
MID_VAL = {"loss": 15.9, "nll": 16.6,
           "nll_0.5s": 16.45, "copy_last_nll_0.5s": 19.14, "code_freq_nll_0.5s": 19.31,
           "obs_mse_0.5s": 0.534, "copy_last_obs_mse_0.5s": 0.954,
           "nll_1s": 16.8, "copy_last_nll_1s": 20.2, "code_freq_nll_1s": 19.4,
           "obs_mse_1s": 0.61, "copy_last_obs_mse_1s": 1.22}
VQ_VAL = {"loss": 0.031, "recon_nmse": 0.027, "perplexity": 96.0, "code_usage": 0.9}


def _gate_result(val: dict, min_gain: float) -> dict:
    from hope_models.components.mid_loop.held_out import mid_loop_verdict
    from hope_models.promote.gate import FAILED, GateResult

    status, detail = mid_loop_verdict(val, list(HORIZONS), True, min_gain)
    checks = [{"check": "baselines", "status": status, "detail": detail}]
    failed = [c["detail"] for c in checks if c["status"] == FAILED]
    return GateResult(not failed, failed, dict(val), checks).to_json_obj()


@pytest.fixture(scope="module")
def serve(tmp_path_factory):
    from big_run import make_big_run

    home = Home(tmp_path_factory.mktemp("run-reference") / "home")
    mid = make_big_run(home.path, steps=3000, component="mid_loop", validation=MID_VAL,
                       config={"batch_size": 16, "dropout": 0.1})
    vq = make_big_run(home.path, steps=3000, component="vqvae", validation=VQ_VAL, config={"groups": 4})
    from registry.promotion import record_candidate
    from registry.db import Registry

    registry = Registry.open(home.settings, migrate=True)
    try:  # the deployment's min gain (0.30) passes it; a stricter one (0.50) would have refused it
        for gain in (0.30, 0.50):
            with registry.session() as s:
                record_candidate(s, component="mid_loop", checkpoint_path=home.path / "runs" / mid / "checkpoints" / "00003000",
                                 version=f"mid_loop-gain-{gain}", run_id=mid, metrics=MID_VAL,
                                 gate_result=_gate_result(MID_VAL, gain))
    finally:
        registry.close()
    home.mid, home.vq = mid, vq
    yield from serving(home)


def _refs(page, metric: str) -> dict[str, float]:
    chart = page.evaluate(CHART, card(metric))
    assert chart is not None, f"no chart for {metric}"
    return {r["label"].rsplit(" ", 1)[0]: r["y"] for r in chart["refs"]}


def test_reference_lines_gate_verdicts_and_two_components_compared(browser, serve, tmp_path):
    from playwright.sync_api import expect

    mid, vq = serve.home.mid, serve.home.vq
    shots = Shots(tmp_path, "run-reference")
    with editor_page(browser, serve, shots) as (page, errors):
        page.goto(serve.url + f"#run/{mid}")
        rendered(page, mid)
        for metric in ("nll_0.5s", "obs_mse_1s"):
            page.check(f'#run-metric-picker input[value="{metric}"]')
        rendered(page, mid)
        expect(page.locator(card("obs_mse_1s"))).to_have_count(1)
        # each chart's dashed lines are the held-out figure and the baselines of its own horizon
        assert _refs(page, "nll_0.5s") == {"held-out nll_0.5s": 16.45, "copy-last baseline (held-out)": 19.14,
                                           "code-frequency baseline (held-out)": 19.31}
        assert _refs(page, "obs_mse_1s") == {"held-out obs_mse_1s": 0.61, "copy-last baseline (held-out)": 1.22}

        # the gate's verdicts on this run, with the figures its check gave
        rows = page.locator("#run-gate tbody tr")
        expect(rows).to_have_count(2)
        expect(page.locator('#run-gate tr[data-verdict="passed"]')).to_have_count(1)
        expect(page.locator('#run-gate tr[data-verdict="refused"]')).to_have_count(1)
        expect(page.locator('#run-gate tr[data-verdict="refused"]')).to_contain_text("copy-last")
        refused = page.locator('#run-gate tr[data-verdict="refused"]').text_content()
        assert refused.count("held-out 0.5s") == 1, refused  # the check's detail, not again as a reason
        expect(page.locator("#run-gate")).to_contain_text("mid_loop-gain-0.5")
        shots.take(page, "mid-loop-reference-lines")

        page.goto(serve.url + f"#run/{vq}")
        rendered(page, vq)
        page.check('#run-metric-picker input[value="recon_nmse"]')
        rendered(page, vq)
        expect(page.locator(card("recon_nmse"))).to_have_count(1)
        refs = _refs(page, "recon_nmse")
        assert refs["held-out recon_nmse"] == 0.027 and refs["gate: at most 0.05"] == 0.05, refs
        expect(page.locator("#run-gate")).to_contain_text("Not gated yet")

        page.goto(serve.url + f"#compare/{mid},{vq}")
        rendered(page, f"{mid},{vq}", "compare")
        chart = page.evaluate(CHART, card("loss", "compare"))
        assert {d["run"] for d in chart["datasets"]} == {mid, vq}
        for d in chart["datasets"]:  # decimated for drawing, the whole run's range still there
            assert d["data"][0]["x"] == 1 and d["data"][-1]["x"] == 3000, (d["run"], d["kind"], len(d["data"]))
        expect(page.locator('#compare-summary tr[data-key="component"] td')).to_have_text(["mid_loop", "vqvae"])
        expect(page.locator('#compare-diff tr[data-key="component"] td')).to_have_text(["mid_loop", "vqvae"])
        expect(page.locator('#compare-diff tr[data-key="batch_size"] td')).to_have_text(["16", "32"])
        expect(page.locator('#compare-diff tr[data-key="seed"]')).to_have_count(0)
        shots.take(page, "compare-mid-loop-vqvae")
        assert not errors, "\n".join(errors)
        phone_fits(browser, serve, f"#run/{mid}", shots, "mid-loop-phone", "run", mid)
