"""eval-reflex's surprise stream: the promoted Mid Loop's surprise at every grid point of the streamed
episode, as BrainService defines it, and the target jump that makes it spike.

The models (surprise_models, shared with tests/test_browser_surprise.py): 10 sim reach demos, a
fast_loop cloned from them, a vqvae (2 groups of 16 codes) and a mid_loop on its codes, a few hundred
steps each, one thread (about 30 s, built once per test run). So small a Mid Loop
only expects what it has seen: the episodes are run on a demo's seed (JUMP_SEED), whose still arm on
the target it knows, and the target jump is new to it (no demo has one). That is the claim under test:
a familiar steady state scores low, the unexpected jump high.
"""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
JUMP_SEED = 100001  # recorder.DEFAULT_SEED_BASE + 1: one of the demos' episodes
JUMP_S = 10.0
STEADY_FROM_S = 3.0  # the reach is over well before this: what follows until the jump is the steady part
SPIKE_FACTOR = 3.0
SPIKE_WITHIN_S = 1.2
GRID_EVERY = 5  # control steps per Mid Loop grid point (0.1 s / 20 ms)
STEPS = 1000


def _build(root: Path) -> None:
    import torch

    from hope_models.sim.recorder import record_dataset
    from hope_models.train.loop import TrainConfig, train

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    record_dataset(root / "demos", 10, task="reach", noise=1.0)
    ckpts = {}

    def fit(component: str, steps: int, batch: int, lr: float, mc: dict, vq: str | None = None) -> str:
        r = train(TrainConfig(component=component, data=str(root / "demos"), run_dir=str(root / "runs" / component),
                              steps=steps, seed=0, batch_size=batch, lr=lr, threads=1, checkpoint_every_steps=steps,
                              log_every=50, cache_dir=str(root / "cache"), thermal_zone=None, vcgencmd=None,
                              model_config=mc, vqvae_dir=vq, val_batches=1))
        assert r.outcome == "completed", r.message
        return str(r.checkpoint)

    try:
        ckpts["fast_loop"] = fit("fast_loop", 1000, 32, 3e-3, {"d_model": 32, "d_state": 32})
        ckpts["vqvae"] = fit("vqvae", 300, 16, 1e-3, {"n_codes": 16, "code_dim": 8, "groups": 2, "hidden": 16})
        ckpts["mid_loop"] = fit("mid_loop", 500, 16, 1e-2, {"d_model": 16, "d_state": 16, "n_layers": 2},
                                ckpts["vqvae"])
    finally:
        torch.set_num_threads(threads)
    (root / "ckpts.json").write_text(json.dumps(ckpts))


def surprise_models(tmp_path_factory) -> dict[str, Path]:
    """{"fast_loop", "vqvae", "mid_loop"}: checkpoint dirs, trained once per test run (module doc)."""
    from conftest import shared_build

    root = shared_build(tmp_path_factory, "surprise-models", _build)
    return {k: Path(v) for k, v in json.loads((root / "ckpts.json").read_text()).items()}


def promote_all(home: Path, models: dict[str, Path], components=("fast_loop", "vqvae", "mid_loop")) -> None:
    from brain_fixtures import promote_pointer

    for i, component in enumerate(components):
        promote_pointer(home, models[component], component, model_id=i + 1)


def spike_figures(records: list[dict], jump_s: float) -> dict[str, float]:
    """The figures the spike is judged by: the median of the steady part before the jump, the peak of
    the first grid points after it (within the shortest horizon, 0.5 s), and where the run's maximum is."""
    pts = [(r["t"], r["surprise"]) for r in records if r["surprise"] is not None]
    steady = [v for t, v in pts if STEADY_FROM_S <= t < jump_s]
    after = [v for t, v in pts if jump_s <= t <= jump_s + 0.5 + 1e-9]
    t_max = max(pts, key=lambda p: p[1])[0]
    return {"steady_median": statistics.median(steady), "after_peak": max(after), "t_max": t_max,
            "n_steady": len(steady)}


def assert_spike(records: list[dict], jump_s: float) -> dict[str, float]:
    f = spike_figures(records, jump_s)
    assert f["n_steady"] >= 20, f
    assert f["after_peak"] > SPIKE_FACTOR * f["steady_median"], f
    assert jump_s <= f["t_max"] <= jump_s + SPIKE_WITHIN_S, f
    return f


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    return surprise_models(tmp_path_factory)


def _home(tmp_path: Path, models, components) -> Path:
    home = tmp_path / "home"
    promote_all(home, models, components)
    return home


def _eval_reflex(home: Path, *extra: str) -> tuple[subprocess.CompletedProcess, list[dict]]:
    cmd = [sys.executable, str(REPO / "run_trainer.py"), "eval-reflex", "--checkpoint", "promoted", "--json",
           "--episodes", "1", "--seed", str(JUMP_SEED), "--stream-surprise", *extra]
    env = {**os.environ, "HOPE_HOME": str(home), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc, [json.loads(line) for line in proc.stdout.splitlines() if line.strip()]


def test_the_stream_holds_every_grid_point_and_spikes_after_the_jump(models, tmp_path):
    home = _home(tmp_path, models, ("fast_loop", "vqvae", "mid_loop"))
    # frames at 2 per simulated second (every 25 steps): most grid points are not rendered
    _, lines = _eval_reflex(home, "--target-jump-at", str(JUMP_S), "--stream-frames", "2", "--stream-size", "16",
                            "--stream-speed", "0")
    header = lines[0]["surprise_stream"]
    assert header["mid_loop"] and header["reason"] is None and header["target_jump_s"] == JUMP_S, header
    assert header["every_steps"] == GRID_EVERY and header["horizons"] == ["0.5s", "1s"], header
    records = [ln["surprise"] for ln in lines if set(ln) == {"surprise"}]
    # one record per grid point, rendered or not
    assert [r["step"] for r in records] == list(range(0, STEPS, GRID_EVERY))
    assert [ln["frame"]["step"] for ln in lines if "frame" in ln] == list(range(0, STEPS + 1, 25))
    assert [r["grid_point"] for r in records] == list(range(len(records)))
    assert all(r["t"] == pytest.approx(r["step"] * 0.02) for r in records)
    # null until a prediction made 0.5 s (5 grid points) earlier exists, then a number of nats
    assert all(r["surprise"] is None for r in records[:5])
    assert all(isinstance(r["surprise"], float) and r["surprise"] >= 0 for r in records[5:])
    assert all(r["surprise_by_horizon"]["1s"] is None for r in records[:10])
    assert all(r["surprise"] == r["surprise_by_horizon"]["0.5s"] for r in records)
    f = assert_spike(records, JUMP_S)
    print(f"\nsurprise: steady median {f['steady_median']:.2f} nats, after the jump {f['after_peak']:.2f}, "
          f"maximum at {f['t_max']:.1f} s (jump at {JUMP_S:g} s)")
    result = lines[-1]
    assert result["ok"] and result["target_jump_s"] == JUMP_S
    assert result["surprise"] == {"mid_loop": header["mid_loop"], "reason": None, "records": len(records),
                                  "non_finite": 0}


def test_the_records_are_brain_services_surprise(models, tmp_path):
    """The same ticks through BrainService (its session, the action given with each observation):
    the same surprise at every grid point. Run in-process, with the jump, so the values vary."""
    from hope_models.promote.reflex_policy import ReflexPolicy
    from hope_models.runtime.brain_service import BrainService
    from hope_models.components.mid_loop.surprise_stream import SurpriseStream, observation_values
    from hope_models.sim.evaluate import evaluate_policy

    home = _home(tmp_path, models, ("fast_loop", "vqvae", "mid_loop"))
    stream, reason = SurpriseStream.promoted(home, 0.02)
    assert reason is None
    ticks, records = [], []

    def on_tick(step, obs, action):
        ticks.append((observation_values(stream.mid.observation_fields, obs), action))
        r = stream.tick(step, obs, action)
        if r is not None:
            records.append(r)

    evaluate_policy(ReflexPolicy.from_checkpoint(models["fast_loop"]), [JUMP_SEED], "reach", steps=700,
                    target_jump_s=JUMP_S, on_tick=on_tick)
    with BrainService(home, poll_s=1.0) as brain:
        brain.check_now()
        served = []
        for i, (values, _) in enumerate(ticks):
            prev = None if i == 0 else ticks[i - 1][1].tolist()
            out = brain.infer("fast_loop", values.tolist(), session="s", action=prev)
            if i % GRID_EVERY == 0:
                served.append(out["surprise_by_horizon"])
    assert served == [r["surprise_by_horizon"] for r in records]
    assert len({round(r["surprise"], 6) for r in records[5:]}) > 10  # not a constant


def test_no_mid_loop_promoted_no_records(models, tmp_path):
    home = _home(tmp_path, models, ("fast_loop",))
    _, lines = _eval_reflex(home, "--target-jump-at", "5")
    assert lines[0] == {"surprise_stream": {"mid_loop": None, "reason": "no mid_loop promoted", "target_jump_s": 5.0}}
    assert len(lines) == 2  # the header and the result: no record
    assert lines[-1]["surprise"] == {"mid_loop": None, "reason": "no mid_loop promoted", "records": 0, "non_finite": 0}


@pytest.mark.parametrize("value", ["abc", "0", "-1", "20", "25", "nan", "inf"])
def test_a_bad_jump_time_is_exit_2_naming_the_flag(value):
    proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "eval-reflex", "--checkpoint", "x",
                           f"--target-jump-at={value}"], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode == 2, proc
    assert "--target-jump-at" in proc.stderr, proc.stderr


def test_the_jump_moves_the_target_deterministically_inside_the_reach():
    from hope_models.sim.reacher import jump_step, make_env

    assert jump_step(10.0) == 500
    for task in ("reach", "track"):
        seen = []
        for _ in range(2):
            env = make_env(task, 3, target_jump_s=1.0)
            env.reset()
            xy = []
            for _ in range(60):
                env.step([0.0, 0.0])
                xy.append(env.target_xy())
            seen.append(np.array(xy))
        a = seen[0]
        assert np.array_equal(a, seen[1])  # the seed decides where it goes
        assert np.linalg.norm(a[49] - a[48]) > 0.05, task  # step 49 -> 50: the jump (1.0 s = step 50)
        assert np.linalg.norm(a[48] - a[47]) < 0.01 and np.linalg.norm(a[51] - a[50]) < 0.01, task
        assert 0.08 - 1e-9 <= np.linalg.norm(a[49]) <= 0.20 + 1e-9, task


def test_the_api_refuses_a_jump_outside_the_episode(tmp_path):
    from test_api import App

    from hope_models.settings import load_settings

    app = App(load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""}),
              brain=False)
    try:
        for bad in (0, 25, -1, "5", True, [5]):
            r = app.post("/api/sim/reflex", {"target_jump_s": bad})
            assert r.status_code == 400 and "target_jump_s" in r.get_json()["error"], (bad, r.get_json())
        r = app.post("/api/sim/reflex", {"target_jump_s": 5})
        assert r.status_code == 409 and "no fast_loop" in r.get_json()["error"]  # valid: on to the next check
    finally:
        app.close()
