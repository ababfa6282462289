"""GET /api/runs/<id>/series (webapp/api/run_series.py, hope_models/train/metric_series.py): the
list of series, each series' points against read_metrics' own rules (resume, non-finite values,
strings, booleans, a damaged line), `after`, a live run's growth and a replaced file, every bad
parameter, and the time a 100k-step run takes cold and warm."""
from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import pytest

from big_run import make_big_run
from run_page_fixtures import RunPageApp


def _add_run(api: RunPageApp, lines: list[str]) -> tuple[str, Path]:
    from registry import runs

    with api.registry.session() as s:
        run = runs.create_run(s, component="fast_loop", config={"data": "x", "steps": 10}, total_steps=10,
                              run_dir=str(Path(api.settings.runs_dir) / "pending"))
        rid = run.id
        run.run_dir = str(Path(api.settings.runs_dir) / rid)
    run_dir = Path(api.settings.runs_dir) / rid
    run_dir.mkdir(parents=True)
    (run_dir / "metrics.jsonl").write_text("".join(line + "\n" for line in lines))
    return rid, run_dir


def _metric(step: int, **values) -> str:
    return json.dumps({"type": "metric", "step": step, "wall_time": 1000.0 + step, **values})


def _resume(step: int) -> str:
    return json.dumps({"type": "event", "kind": "resume", "wall_time": 0, "payload": {"step": step}})


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    a = RunPageApp(tmp_path_factory.mktemp("series") / "home")
    yield a
    a.close()


def _reference(run_dir: Path, name: str, after: int = -1) -> dict[str, list]:
    """The points by read_metrics' rules, computed the slow way."""
    from hope_models.train.metrics import read_metrics

    out = {"step": [], "wall_time": [], "value": []}
    for r in read_metrics(run_dir):
        v = r.get(name)
        if r.get("type") == "metric" and type(v) in (int, float) and math.isfinite(v) and r["step"] > after:
            out["step"].append(r["step"])
            out["wall_time"].append(r["wall_time"])
            out["value"].append(float(v))
    return out


def test_series_follow_the_metrics_rules(api):
    lines = [_metric(s, loss=10.0 / s, lr=1e-3 * s, note="warm", flag=True) for s in range(1, 41)]
    lines[4] = _metric(5, loss=None, lr=5e-3)  # a NaN loss is written as null
    lines.append('{"type": "metric", "step": 41, "wall_time": 1041.0, "loss": NaN, "acc": 0.5}')
    lines.append('{"type": "metric", "step": 4')  # a damaged line in the middle (a torn write)
    lines.append(_resume(30))  # steps 31..41 are trained again
    lines += [_metric(s, loss=1.0 / s, lr=2e-3, temp_c=None) for s in range(31, 51)]
    rid, run_dir = _add_run(api, lines)

    listed = api.get(f"/api/runs/{rid}/series").get_json()
    assert listed["records"] == 50
    assert [s["name"] for s in listed["series"]] == ["loss", "lr"]  # acc's only record was dropped
    loss = listed["series"][0]
    assert loss == {"name": "loss", "points": 49, "first_step": 1, "last_step": 50, "last": 1.0 / 50}

    got = api.get(f"/api/runs/{rid}/series?names=loss,lr,acc,never_seen").get_json()
    assert got["run_id"] == rid and got["last_step"] == 50
    assert got["series"]["loss"] == _reference(run_dir, "loss")
    assert got["series"]["lr"] == _reference(run_dir, "lr")
    assert 5 not in got["series"]["loss"]["step"] and 5 in got["series"]["lr"]["step"]
    assert got["series"]["loss"]["step"] == sorted(set(got["series"]["loss"]["step"]))
    assert got["series"]["acc"] == got["series"]["never_seen"] == {"step": [], "wall_time": [], "value": []}

    after = api.get(f"/api/runs/{rid}/series?names=loss&after=45").get_json()
    assert after["series"]["loss"] == _reference(run_dir, "loss", after=45)
    assert after["series"]["loss"]["step"] == [46, 47, 48, 49, 50]


def test_a_live_run_is_read_as_it_grows_and_a_replaced_file_again(api):
    rid, run_dir = _add_run(api, [_metric(s, loss=1.0) for s in range(1, 11)])
    path = run_dir / "metrics.jsonl"
    assert api.get(f"/api/runs/{rid}/series?names=loss").get_json()["last_step"] == 10
    with open(path, "a") as f:
        f.write(_metric(11, loss=2.0) + "\n" + _metric(12, loss=3.0)[:20])  # the last line not complete yet
    got = api.get(f"/api/runs/{rid}/series?names=loss&after=10").get_json()
    assert got["series"]["loss"]["step"] == [11] and got["last_step"] == 11
    with open(path, "a") as f:
        f.write(_metric(12, loss=3.0)[20:] + "\n" + _resume(11) + "\n" + _metric(12, loss=4.0) + "\n")
    got = api.get(f"/api/runs/{rid}/series?names=loss&after=10").get_json()
    assert got["series"]["loss"]["step"] == [11, 12] and got["series"]["loss"]["value"] == [2.0, 4.0]
    # replaced (a new inode, shorter): read again from the start
    tmp = run_dir / "new.jsonl"
    tmp.write_text(_metric(1, loss=9.0) + "\n")
    os.replace(tmp, path)
    got = api.get(f"/api/runs/{rid}/series?names=loss").get_json()
    assert got["series"]["loss"]["value"] == [9.0] and got["last_step"] == 1


def test_a_run_without_metrics_has_no_series(api):
    rid, run_dir = _add_run(api, [])
    (run_dir / "metrics.jsonl").unlink()
    assert api.get(f"/api/runs/{rid}/series").get_json() == {"run_id": rid, "records": 0, "series": []}
    got = api.get(f"/api/runs/{rid}/series?names=loss").get_json()
    assert got["last_step"] is None and got["series"]["loss"]["step"] == []


@pytest.mark.parametrize("query, status, text", [
    ("names=", 400, "names"),
    ("names=,,", 400, "names"),
    ("names=" + ",".join(f"m{i}" for i in range(13)), 400, "at most 12"),
    ("names=loss;drop", 400, "names"),
    ("names=" + "x" * 101, 400, "names"),
    ("names=l%C3%B6ss", 400, "names"),
    ("names=loss&after=-1", 400, "after"),
    ("names=loss&after=1.5", 400, "after"),
    ("names=loss&after=abc", 400, "after"),
    ("after=3", 400, "after"),
    ("name=loss", 400, "name"),
])
def test_bad_parameters_are_named(api, query, status, text):
    rid, _ = _add_run(api, [_metric(1, loss=1.0)])
    r = api.get(f"/api/runs/{rid}/series?{query}")
    assert r.status_code == status, r.get_json()
    assert text in r.get_json()["error"]


def test_unknown_run_and_no_token(api):
    r = api.get("/api/runs/r-nope/series?names=loss")
    assert r.status_code == 404 and "r-nope" in r.get_json()["error"]
    assert api.client.get("/api/runs/r-nope/series").status_code == 401


def test_100k_steps_answer_fast(tmp_path):
    """The run page's loss chart of a 100k-step run: < 2 s the first time (parse + answer), < 0.5 s
    after that, on the 2-core dev box when it is not loaded (1.3-1.5 s and 0.15-0.25 s measured);
    make_big_run's 100k records in < 10 s (1.4-1.9 s). A loaded box (other tests running) slows
    everything, so each budget is scaled by how much slower than its unloaded 0.9 s the plain
    parse of /metrics (read_metrics) runs around the measurement, best of (at most) two rounds."""
    from hope_models.train.metric_series import clear_cache
    from hope_models.train.metrics import read_metrics

    def load() -> float:
        t0 = time.perf_counter()
        read_metrics(Path(api.settings.runs_dir) / rid)
        return max(1.0, (time.perf_counter() - t0) / 0.9)

    home = tmp_path / "home"
    t0 = time.perf_counter()
    rid = make_big_run(home, steps=100_000)
    made = time.perf_counter() - t0
    (home / "runs" / rid / "metrics.columns").unlink()  # the parse, as for a run still training
    api = RunPageApp(home)
    try:
        assert api.get(f"/api/runs/{rid}").status_code == 200  # the app's own first-request costs
        rounds = []
        for _ in range(2):
            clear_cache()
            before = load()
            t0 = time.perf_counter()
            r = api.get(f"/api/runs/{rid}/series?names=loss")
            cold = time.perf_counter() - t0
            t0 = time.perf_counter()
            r2 = api.get(f"/api/runs/{rid}/series?names=loss")
            warm = time.perf_counter() - t0
            factor = (before + load()) / 2
            assert len(r.get_json()["series"]["loss"]["step"]) == 100_000 and r2.data == r.data
            rounds.append((cold / factor, warm / factor, cold, warm, factor))
            print(f"make_big_run {made:.2f} s, cold {cold:.2f} s, warm {warm:.3f} s, load factor {factor:.2f}")
            if cold / factor < 2.0 and warm / factor < 0.5:
                break  # the second round is for a load spike in the first
        cold_scaled, warm_scaled = min(x[0] for x in rounds), min(x[1] for x in rounds)
        assert cold_scaled < 2.0 and warm_scaled < 0.5 and made < 10.0 * max(x[4] for x in rounds), rounds
    finally:
        api.close()
