"""The Run page's pure JavaScript (webapp/static/js/metric_chart.js, run_provenance.js) under node:
the smoothing is TensorBoard's debiased EMA (the same numbers as Python's), the reference lines a
metric gets from a run's held-out figures (the Mid Loop's baselines of the same horizon, the world
model's copy baseline, the VQ-VAE gate's threshold), the elapsed-time labels of the wall-time axis
and the dotted keys of a nested config. The browser suite (tests/test_browser_run.py) checks the
drawn charts; this checks the rules on cases a short real run does not produce.

node comes with `make setup` (npm ci vendors the browser libraries); the test fails naming it when
it is missing.
"""
from __future__ import annotations

import json
import math
import shutil
import subprocess
from pathlib import Path

import pytest

JS = Path(__file__).resolve().parents[1] / "webapp" / "static" / "js"


def run_node(body: str):
    node = shutil.which("node")
    if node is None:
        pytest.fail("node is missing: `make setup` installs it (npm ci vendors the browser libraries)")
    script = (f"import * as mc from {json.dumps((JS / 'metric_chart.js').as_uri())};\n"
              f"import * as rp from {json.dumps((JS / 'run_provenance.js').as_uri())};\n"
              f"console.log(JSON.stringify({body}));")
    out = subprocess.run([node, "--input-type=module", "-e", script], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def debiased_ema(values, w):
    out, last, n = [], 0.0, 0
    for v in values:
        if not math.isfinite(v):
            out.append(None)
            continue
        n += 1
        last = last * w + (1 - w) * v
        out.append(last / (1 - w ** n) if w > 0 else v)
    return out


def test_the_smoothing_is_the_debiased_ema():
    values = [3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0, 6.0]
    got = run_node(f"[0, 0.6, 0.99].map((w) => mc.ema({json.dumps(values)}, w))")
    for w, series in zip([0, 0.6, 0.99], got):
        assert series == pytest.approx(debiased_ema(values, w), rel=1e-12)
    assert got[0] == values  # weight 0 draws the raw values
    assert got[1][0] == pytest.approx(values[0], rel=1e-12)  # debiased: the first point is the first value, not 0.4 of it


def test_reference_lines_are_the_held_out_figure_and_its_baselines():
    val = {"nll_0.5s": 1.2, "copy_last_nll_0.5s": 1.5, "code_freq_nll_0.5s": 2.1, "nll_1s": 1.4,
           "obs_mse_1s": 0.02, "copy_last_obs_mse_1s": 0.05, "wm_obs_mse": 0.3, "wm_copy_obs_mse": 0.4,
           "recon_nmse": 0.01, "loss": 0.7}
    got = run_node(
        f"Object.fromEntries([['nll_0.5s', 'mid_loop'], ['obs_mse_1s', 'mid_loop'], ['wm_obs_mse', 'mid_loop'],"
        f" ['recon_nmse', 'vqvae'], ['loss', 'fast_loop'], ['lr', 'fast_loop']].map(([m, c]) =>"
        f" [m, mc.referenceLines(m, {json.dumps(val)}, c).map((l) => [l.y, l.label])]))")
    ys = {m: [y for y, _ in lines] for m, lines in got.items()}
    assert ys["nll_0.5s"] == [1.2, 1.5, 2.1]  # not the 1 s horizon's
    assert "copy-last" in got["nll_0.5s"][1][1] and "code-frequency" in got["nll_0.5s"][2][1]
    assert ys["obs_mse_1s"] == [0.02, 0.05]
    assert ys["wm_obs_mse"] == [0.3, 0.4]
    assert ys["recon_nmse"] == [0.01, 0.05] and "gate" in got["recon_nmse"][1][1]
    assert ys["loss"] == [0.7] and ys["lr"] == []
    assert run_node("mc.referenceLines('loss', null, 'fast_loop')") == []


def test_elapsed_labels_and_flattened_config():
    assert run_node("[0, 59.6, 61, 3599, 3600, 7325].map(mc.elapsed)") == [
        "0:00", "1:00", "1:01", "59:59", "1:00:00", "2:02:05"]
    cfg = {"lr": 0.001, "model_config": {"d_model": 64, "ssm": {"blocks": 2}}, "data": "ds", "tags": [1, 2]}
    assert run_node(f"rp.flatten({json.dumps(cfg)})") == [
        ["data", "ds"], ["lr", 0.001], ["model_config.d_model", 64], ["model_config.ssm.blocks", 2], ["tags", [1, 2]]]


def test_gate_checks_read_as_one_line():
    checks = [{"check": "finite", "status": "passed", "detail": ""},
              {"check": "baselines", "status": "failed", "detail": "nll 1.6 >= copy-last 1.5"}]
    assert run_node(f"rp.checksText({json.dumps(checks)})") == "finite: passed; baselines: failed (nll 1.6 >= copy-last 1.5)"
    assert run_node("rp.checksText(null)") == "–"
