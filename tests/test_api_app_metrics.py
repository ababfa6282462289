"""The Continuon app's learning screens: /api/training/metrics, /api/learning/progress and
/api/training/benchmarks, in process, on registry rows whose files are real: run dirs of a VQ-VAE
and two Mid Loops trained here for a few steps (metrics.jsonl, result.json, checkpoints), real
fast_loop safetensors (brain_fixtures) and a real ingest manifest.

Every answer is also checked the way the app's Dart code reads it (learning_metrics.dart):
`MetricPoint.fromJson` (timestamp parsed as ISO 8601, value `as num?`, label `as String?`),
`LearningProgress.fromJson` (`as num?` / `as bool?`) and `TrainingBenchmark.fromJson` (`id as
String?`, `details as Map<String, dynamic>?`): a value of another type would throw in the app.
"""
from __future__ import annotations

import json
import math
import shutil
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from brain_fixtures import brain_runs
from test_api import App


# -- what the app's Dart code accepts ----------------------------------------------------------------

def dart_point(p) -> None:
    assert isinstance(p, dict) and set(p) >= {"timestamp", "value", "label"}
    assert isinstance(p["timestamp"], str) and datetime.fromisoformat(p["timestamp"]).tzinfo is not None
    assert isinstance(p["value"], (int, float)) and not isinstance(p["value"], bool) and math.isfinite(p["value"])
    assert isinstance(p["label"], str)


def dart_num_or_null(v) -> None:
    assert v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))


def dart_progress(body) -> None:
    for key in ("total_steps", "total_episodes", "learning_updates"):
        assert isinstance(body[key], int) and not isinstance(body[key], bool), key
    dart_num_or_null(body["avg_parameter_change"])
    dart_num_or_null(body["learning_rate"])
    assert isinstance(body["is_stable"], bool)


def dart_metrics(body) -> None:
    for key in ("loss_history", "curiosity_history"):
        assert isinstance(body[key], list)
        for p in body[key]:
            dart_point(p)
    dart_num_or_null(body["curiosity"])
    dart_num_or_null(body["surprise"])
    # the app merges this object with {"status": ..., "progress": ...} and casts these as maps
    assert "wavecore" not in body and "status" not in body and "progress" not in body


# -- fixtures --------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A VQ-VAE (16 codes) and two Mid Loops reading it (20 and 40 steps), trained for real."""
    from hope_models.data.synthetic import generate_dataset
    from hope_models.train.loop import TrainConfig, train

    root = tmp_path_factory.mktemp("app_metrics")
    generate_dataset(root / "ds", 1500, obs_dim=6, act_dim=2, episode_seconds=(5, 15), seed=1)

    def run(name, component, steps, model_config, vqvae_dir=None):
        r = train(TrainConfig(component=component, data=str(root / "ds"), run_dir=str(root / name), steps=steps,
                              seed=0, batch_size=16, threads=1, checkpoint_every_steps=steps, log_every=5,
                              cache_dir=str(root / "cache"), thermal_zone=None, vcgencmd=None,
                              model_config=model_config, vqvae_dir=vqvae_dir, val_batches=1))
        assert r.outcome == "completed", r.message
        return root / name, r

    vq, vq_result = run("vq", "vqvae", 20, {"n_codes": 16, "code_dim": 8, "groups": 2, "hidden": 16})
    small = {"d_model": 16, "d_state": 16, "n_layers": 1}
    mid20, _ = run("mid20", "mid_loop", 20, small, vq_result.checkpoint)
    mid40, _ = run("mid40", "mid_loop", 40, small, vq_result.checkpoint)
    return {"ds": root / "ds", "vq": vq, "mid20": mid20, "mid40": mid40}


@pytest.fixture
def settings(tmp_path):
    from hope_models.settings import load_settings

    return load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})


@pytest.fixture
def api(settings):
    a = App(settings, brain=False)
    yield a
    a.close()


T0 = datetime(2026, 11, 23, 20, 0, tzinfo=timezone.utc)


def add_run(api, src: Path | None, component: str, *, state="completed", started_min=0, finished_min=None,
            sequence=None, error=None, data=None) -> str:
    """A run row whose run dir is a copy of `src` (a run dir trained above) under $HOPE_HOME/runs."""
    from registry import runs
    from registry.models import new_run_id

    run_id = new_run_id() + component[:2]
    run_dir = Path(api.settings.runs_dir) / run_id
    if src is not None:
        shutil.copytree(src, run_dir)
    else:
        run_dir.mkdir(parents=True)
    ckpts = sorted((run_dir / "checkpoints").glob("0*")) if src is not None else []
    step = int(ckpts[-1].name) if ckpts else 7
    with api.registry.session() as s:
        run = runs.create_run(s, component=component, config={"data": data or "ds", "steps": step}, total_steps=step,
                              run_dir=str(run_dir), run_id=run_id,
                              sequence_id=sequence[0] if sequence else None,
                              sequence_index=sequence[1] if sequence else None)
        run.state, run.step, run.error_message = state, step, error
        run.last_checkpoint = str(ckpts[-1]) if ckpts else None
        run.started_at = T0 + timedelta(minutes=started_min)
        if finished_min is not None:
            run.finished_at = T0 + timedelta(minutes=finished_min)
    return run_id


def file_losses(run_dir: Path) -> list[tuple[int, float, float]]:
    """(step, wall_time, loss) of the metric records, read here without the code under test."""
    out = []
    for line in (run_dir / "metrics.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if rec["type"] == "metric" and rec.get("loss") is not None:
            out.append((rec["step"], rec["wall_time"], rec["loss"]))
    return out


def val_loss(run_dir: Path) -> float:
    return json.loads((run_dir / "result.json").read_text())["summary"]["val"]["loss"]


# -- tests -------------------------------------------------------------------------------------------

def test_before_anything_is_trained_nothing_pretends_to_be_measured(api):
    m = api.get("/api/training/metrics")
    assert m.status_code == 200
    body = m.get_json()
    dart_metrics(body)
    assert body["loss_history"] == [] and body["curiosity_history"] == []
    assert body["surprise"] is None and body["curiosity"] is None  # null, never a 0 that reads as a measurement
    p = api.get("/api/learning/progress").get_json()
    dart_progress(p)
    assert (p["total_steps"], p["total_episodes"], p["learning_updates"]) == (0, 0, 0)
    assert p["avg_parameter_change"] is None and p["learning_rate"] is None and p["is_stable"] is True
    b = api.get("/api/training/benchmarks")
    assert b.status_code == 200 and b.get_json()["benchmarks"] == []


def test_loss_history_is_the_latest_chain_thinned_evenly_with_the_newest_point(api, trained):
    add_run(api, trained["mid20"], "mid_loop", started_min=0, finished_min=5)  # older: not shown
    add_run(api, trained["vq"], "vqvae", started_min=10, finished_min=12, sequence=("seq-1", 0))
    mid = add_run(api, trained["mid40"], "mid_loop", started_min=13, state="running", sequence=("seq-1", 1))
    expected = file_losses(trained["vq"]) + file_losses(trained["mid40"])
    full = api.get("/api/training/metrics?limit=5000").get_json()
    dart_metrics(full)
    assert [p["value"] for p in full["loss_history"]] == [loss for _, _, loss in expected]
    assert [r["component"] for r in full["runs"]] == ["vqvae", "mid_loop"]
    last = full["loss_history"][-1]
    assert last["label"] == f"mid_loop · run {mid} · step {expected[-1][0]}"
    assert datetime.fromisoformat(last["timestamp"]).timestamp() == pytest.approx(expected[-1][1], abs=1e-3)
    thin = api.get("/api/training/metrics?limit=5").get_json()["loss_history"]
    n = len(expected)
    assert [p["value"] for p in thin] == [expected[round(i * (n - 1) / 4)][2] for i in range(5)]
    assert thin[0] == full["loss_history"][0] and thin[-1] == last
    assert api.get("/api/training/metrics?limit=1").get_json()["loss_history"] == [last]


def test_surprise_and_curiosity_are_the_mid_loops_validation_cross_entropy(api, trained):
    old = add_run(api, trained["mid20"], "mid_loop", started_min=0, finished_min=5)
    new = add_run(api, trained["mid40"], "mid_loop", started_min=6, finished_min=9)
    add_run(api, None, "mid_loop", state="failed", started_min=10, finished_min=11, error="killed")  # no result.json
    body = api.get("/api/training/metrics").get_json()
    dart_metrics(body)
    assert body["surprise"] == pytest.approx(val_loss(trained["mid40"]), rel=1e-12)
    # two groups of 16 codes: an observation's code is one of 16 ** 2
    assert body["curiosity"] == pytest.approx(val_loss(trained["mid40"]) / (2 * math.log(16)), rel=1e-12)
    assert body["surprise_source"]["run_id"] == new and body["surprise_source"]["n_codes"] == 16
    assert body["surprise_source"]["code_groups"] == 2
    hist = body["curiosity_history"]
    assert [p["value"] for p in hist] == pytest.approx([val_loss(trained[k]) / (2 * math.log(16))
                                                        for k in ("mid20", "mid40")])
    assert old in hist[0]["label"] and new in hist[1]["label"]
    assert hist[0]["timestamp"] == (T0 + timedelta(minutes=5)).isoformat()
    # a trained, held-out number: positive, and near chance after a few steps on random-ish codes
    assert 0.0 < body["curiosity"] < 2.0


@pytest.mark.parametrize("query", ["limit=0", "limit=-1", "limit=abc", "limit=1.5", "limit=true", "limit=5001",
                                   "limit=1e2", "limit=%201"])
def test_limit_is_checked_by_the_number_rules(api, query):
    r = api.get(f"/api/training/metrics?{query}")
    assert r.status_code == 400 and "limit" in r.get_json()["error"]


def test_unknown_query_parameters_are_refused(api):
    assert api.get("/api/training/metrics?limt=5").status_code == 400
    assert api.get("/api/learning/progress?x=1").status_code == 400
    assert api.get("/api/training/benchmarks?limit=0").status_code == 400


def _promote(api, ckpt: Path, component: str, run_id, *, promote=True, metrics=None, passed=True) -> int:
    from registry import promotion
    from hope_models.promoted import checkpoint_version

    version, _ = checkpoint_version(ckpt)
    with api.registry.session() as s:
        m = promotion.record_candidate(s, component=component, checkpoint_path=ckpt, version=version, run_id=run_id,
                                       metrics=metrics if metrics is not None else {"candidate_val_loss": 0.25},
                                       gate_result={"passed": passed, "promoted": promote, "reasons": []})
        if promote:
            promotion.promote(s, api.settings, m.id)
        return m.id


def relative_l2(a_dir: Path, b_dir: Path) -> float:
    from safetensors.numpy import load_file

    a, b = load_file(str(a_dir / "model.safetensors")), load_file(str(b_dir / "model.safetensors"))
    num = sum(float(((b[k].astype(np.float64) - a[k].astype(np.float64)) ** 2).sum()) for k in a)
    den = sum(float((a[k].astype(np.float64) ** 2).sum()) for k in a)
    return math.sqrt(num / den)


def test_progress_counts_steps_episodes_promotions_and_measures_the_weight_change(api, trained, tmp_path_factory):
    from hope_models.data.synthetic import generate_dataset
    from hope_models.rlds.ingest import ingest_paths

    inbox = api.settings.inbox_dir
    ingest_paths([trained["ds"]], inbox)
    n_inbox = json.loads((inbox / "manifest.json").read_text())["counts"]["episodes"]
    other = Path(api.settings.datasets_dir) / "other"
    generate_dataset(other.with_name("other-src"), 400, obs_dim=6, act_dim=2, episode_seconds=(5, 8), seed=9)
    ingest_paths([other.with_name("other-src")], other)
    n_other = json.loads((other / "manifest.json").read_text())["counts"]["episodes"]
    assert n_inbox > 0 and n_other > 0
    vq = add_run(api, trained["vq"], "vqvae", started_min=0, finished_min=2, data=str(inbox))  # same episodes
    mid = add_run(api, trained["mid40"], "mid_loop", started_min=3, finished_min=4, data=str(other))
    alpha = brain_runs(tmp_path_factory)["alpha30"]
    _promote(api, alpha.parent / "00000015", "fast_loop", None)
    _promote(api, alpha, "fast_loop", None)
    _promote(api, alpha, "fast_loop", None, promote=False, passed=False)  # refused: not a learning update

    p = api.get("/api/learning/progress").get_json()
    dart_progress(p)
    assert p["total_steps"] == 20 + 40
    assert p["total_episodes"] == n_inbox + n_other
    assert p["learning_updates"] == 2
    expected = relative_l2(alpha.parent / "00000015", alpha)
    assert expected > 0 and p["avg_parameter_change"] == pytest.approx(expected, rel=1e-9)
    assert p["parameter_change"] == {"fast_loop": pytest.approx(expected, rel=1e-9)}
    last_lr = [json.loads(x) for x in (trained["mid40"] / "metrics.jsonl").read_text().splitlines()]
    last_lr = [r["lr"] for r in last_lr if r["type"] == "metric"][-1]
    assert p["learning_rate"] == last_lr and p["learning_rate_run"] == mid
    assert p["is_stable"] is True and p["stability_notes"] == []
    assert vq

    add_run(api, None, "fast_loop", state="failed", started_min=5, finished_min=6,
            error="loss is nan at step 7: stopped before the optimizer step; the last good checkpoint is none")
    p = api.get("/api/learning/progress").get_json()
    dart_progress(p)
    assert p["is_stable"] is False and "loss is nan" in p["stability_notes"][0]


def test_benchmarks_are_the_gate_results_per_version(api, trained, tmp_path_factory):
    alpha = brain_runs(tmp_path_factory)["alpha30"]
    reflex = {"task": "reach", "episodes": 4, "candidate_mean_return": 812.5, "promoted_mean_return": None}
    fast = _promote(api, alpha, "fast_loop", None, metrics={"candidate_val_loss": 0.3, "reflex": reflex})
    mid_ckpt = sorted((trained["mid40"] / "checkpoints").glob("0*"))[-1]
    mid = _promote(api, mid_ckpt, "mid_loop", None, metrics={"candidate_val_loss": 2.5, "promoted_val_loss": 2.7})
    _promote(api, alpha.parent / "00000015", "fast_loop", None, promote=False, passed=False,
             metrics={"finite": False})  # nothing measured: left out
    r = api.get("/api/training/benchmarks")
    assert r.status_code == 200
    bench = r.get_json()["benchmarks"]
    assert [b["id"] for b in bench] == [f"gate-{mid}", f"gate-{fast}"]  # newest first
    for b in bench:
        assert isinstance(b["id"], str) and isinstance(b["model_version"], str) and isinstance(b["details"], dict)
        assert isinstance(b["score"], (int, float)) and datetime.fromisoformat(b["timestamp"]).tzinfo is not None
    by_id = {b["id"]: b for b in bench}
    f, m = by_id[f"gate-{fast}"], by_id[f"gate-{mid}"]
    assert f["score"] == 812.5 and f["details"]["score_kind"] == "reflex_mean_return"
    assert f["details"]["higher_is_better"] is True and f["model_version"].startswith("alpha@30:")
    assert m["score"] == 2.5 and m["details"]["score_kind"] == "val_loss" and m["details"]["promoted_val_loss"] == 2.7
    assert len(api.get("/api/training/benchmarks?limit=1").get_json()["benchmarks"]) == 1


def test_a_runs_api_object_carries_its_held_out_figures_and_baselines(api, trained):
    mid = add_run(api, trained["mid40"], "mid_loop", started_min=0, finished_min=5)
    run = api.get(f"/api/runs/{mid}").get_json()["run"]
    val = json.loads((trained["mid40"] / "result.json").read_text())["summary"]["val"]
    assert run["validation"]["loss"] == pytest.approx(val["loss"])
    for key in ("nll_0.5s", "copy_last_nll_0.5s", "code_freq_nll_1s", "obs_mse_1s", "copy_last_obs_mse_0.5s"):
        assert run["validation"][key] == pytest.approx(val[key]), key  # what the Robot Editor's summary shows
    failed = add_run(api, None, "mid_loop", state="failed", started_min=6, finished_min=7, error="killed")
    assert api.get(f"/api/runs/{failed}").get_json()["run"]["validation"] is None  # nothing was measured
