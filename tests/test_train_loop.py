"""The training loop with a stand-in component: metrics, control, guards, NaN, exact resume in-process."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from hope_models.data.synthetic import generate_dataset
from hope_models import checkpoints as ckpt
from hope_models.train.contract import OUTCOME_EXIT_CODES, ControlCommand
from hope_models.train.guards import MemoryGuard
from hope_models.train.loop import LossHistory, TrainConfig, TrainSetupError, lr_at, train
from hope_models.train.metrics import read_metrics
from hope_models.train.thermal import ThermalGovernor
from test_train_loop_standin import assert_bitwise_equal, factory, weights

STEPS = 60


@pytest.fixture(scope="module")
def ds(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("loop")
    generate_dataset(root / "ds", 3000, obs_dim=6, act_dim=2, episode_seconds=(3, 9), seed=1)
    return root


def cfg_for(ds: Path, run_dir: Path, **kw) -> TrainConfig:
    base = dict(component="fast_loop", data=str(ds / "ds"), run_dir=str(run_dir), steps=STEPS, seed=3,
                batch_size=16, lr=3e-3, threads=1, checkpoint_every_steps=20, log_every=5,
                cache_dir=str(ds / "cache"), thermal_zone=None, vcgencmd=None, control_interval_s=0.0)
    base.update(kw)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def reference(ds, tmp_path_factory) -> dict[str, torch.Tensor]:
    run = tmp_path_factory.mktemp("ref")
    r = train(cfg_for(ds, run), component_factory=factory())
    assert r.outcome == "completed"
    return weights(run)


class StopAt:
    """Control that asks for `desired` from step `at` on, and optionally a throttle."""

    def __init__(self, at: int | None = None, desired: str = "pause", throttle: float = 0.0):
        self.at, self.desired, self.throttle, self.polls = at, desired, throttle, []

    def poll(self, step: int) -> ControlCommand:
        self.polls.append(step)
        if self.at is not None and step >= self.at:
            return ControlCommand(desired=self.desired)
        return ControlCommand(throttle=self.throttle)


def test_completed_run_logs_metrics_checkpoints_and_summary(ds, tmp_path, reference):
    events: list[tuple[str, dict]] = []
    r = train(cfg_for(ds, tmp_path, keep_last=2), emit=lambda k, p: events.append((k, p)),
              component_factory=factory())
    assert r.outcome == "completed" and r.exit_code == 0 and r.steps == STEPS and r.resumed_from is None
    assert r.checkpoint == str(tmp_path / "checkpoints" / f"{STEPS:08d}")
    assert [s for s, _ in ckpt.list_step_dirs(tmp_path)] == [60, 40]  # keep_last=2
    assert_bitwise_equal(weights(tmp_path), reference)  # same config, same weights
    s = r.summary
    assert s["last10_mean"] < 0.7 * s["first10_mean"] and s["slope"] < 0 and s["val"]["loss"] > 0
    assert r.first_loss > r.final_loss and r.peak_rss_mb > 50
    metrics = [m for m in read_metrics(tmp_path) if m["type"] == "metric"]
    assert [m["step"] for m in metrics] == list(range(5, STEPS + 1, 5))
    for key in ("loss", "lr", "grad_norm", "steps_per_s", "rss_mb", "temp_c", "throttle_level", "throttle",
                "pred_std"):
        assert key in metrics[-1], key
    assert metrics[-1]["throttle_level"] == "normal" and metrics[-1]["temp_c"] is None
    assert (tmp_path / "metrics.mcap").stat().st_size > 0
    kinds = [k for k, _ in events]
    assert kinds.count("metric") == len(metrics) and kinds.count("checkpoint") == 3
    progress = [p for k, p in events if k == "progress"]
    assert progress[-1]["step"] == STEPS and progress[-1]["total"] == STEPS and progress[-1]["eta_s"] == 0
    assert set(progress[0]) == {"step", "total", "loss", "steps_per_s", "eta_s", "rss_mb"}
    saved = json.loads((tmp_path / "result.json").read_text())
    assert saved["outcome"] == "completed" and saved["steps"] == STEPS
    # re-running a finished job does nothing and says so
    again = train(cfg_for(ds, tmp_path), component_factory=factory())
    assert again.outcome == "completed" and again.resumed_from == STEPS and again.final_loss == r.final_loss


@pytest.mark.parametrize("desired,outcome", [("pause", "paused_user"), ("cancel", "cancelled")])
def test_control_pause_or_cancel_checkpoints_then_resume_is_bitwise_exact(ds, tmp_path, reference, desired,
                                                                          outcome):
    r = train(cfg_for(ds, tmp_path), StopAt(23, desired), component_factory=factory())
    assert r.outcome == outcome and r.exit_code == OUTCOME_EXIT_CODES[outcome] and r.steps == 23
    assert "step 23" in r.message
    assert ckpt.list_step_dirs(tmp_path)[0][0] == 23 and r.checkpoint.endswith("00000023")
    r2 = train(cfg_for(ds, tmp_path), component_factory=factory())
    assert r2.outcome == "completed" and r2.resumed_from == 23 and r2.steps == STEPS
    assert_bitwise_equal(weights(tmp_path), reference)


def test_control_is_polled_at_most_every_interval(ds, tmp_path):
    c = StopAt()
    train(cfg_for(ds, tmp_path, control_interval_s=3600.0), c, component_factory=factory())
    assert c.polls == [0]


def test_throttle_sleeps_its_fraction_of_the_step(ds, tmp_path, monkeypatch):
    import hope_models.train.loop as loop_mod
    sleeps: list[float] = []
    monkeypatch.setattr(loop_mod.time, "sleep", lambda s: sleeps.append(s))
    r = train(cfg_for(ds, tmp_path, steps=20), StopAt(throttle=0.5), component_factory=factory())
    assert r.outcome == "completed"
    # throttle 0.5: half of each step's wall time asleep -> sleep == the previous step's compute time
    assert len(sleeps) == 19 and all(0 < s < 5 for s in sleeps)


def test_nan_loss_fails_naming_the_step_and_keeps_the_last_good_checkpoint(ds, tmp_path):
    r = train(cfg_for(ds, tmp_path), component_factory=factory(nan_at_call=33))
    assert r.outcome == "failed" and r.exit_code == 1
    assert "step 33" in r.message and "nan" in r.message and "00000020" in r.message
    assert r.steps == 32 and r.checkpoint.endswith("00000020")
    assert [s for s, _ in ckpt.list_step_dirs(tmp_path)] == [20]
    loaded = ckpt.load_latest(tmp_path)
    assert all(torch.isfinite(v).all() for v in loaded.model.values())


def test_memory_guard_soft_limit_pauses_then_resume_is_exact(ds, tmp_path, reference):
    mb = 1 << 20
    readings = iter([100 * mb] * 30 + [950 * mb] * 1000)  # RSS jumps past 90% of 1000 MB
    guard = MemoryGuard(1000, rss_fn=lambda: next(readings))
    r = train(cfg_for(ds, tmp_path, memory_budget_mb=1000), component_factory=factory(), memory_guard=guard)
    assert r.outcome == "paused_memory" and r.exit_code == 3
    assert "950 MB" in r.message and "1000 MB" in r.message
    paused_at = r.steps
    assert 0 < paused_at < STEPS and ckpt.load_latest(tmp_path).step == paused_at
    events = [m for m in read_metrics(tmp_path) if m.get("kind") == "memory"]
    assert events and events[0]["payload"]["rss_mb"] == 950
    r2 = train(cfg_for(ds, tmp_path), component_factory=factory())
    assert r2.outcome == "completed" and r2.resumed_from == paused_at
    assert_bitwise_equal(weights(tmp_path), reference)


def test_thermal_hot_checkpoints_waits_until_cool_and_matches_the_reference(ds, tmp_path, reference):
    zone = tmp_path / "temp"
    zone.write_text("50000\n")
    slept: list[float] = []

    def cool_down(seconds):  # the governor's wait: the SoC cools a little every poll
        slept.append(seconds)
        zone.write_text(f"{max(60.0, 85.0 - 6 * len(slept)) * 1000:.0f}\n")

    class HeatAt(StopAt):
        heated = False

        def poll(self, step):
            if step == 25 and not self.heated:  # the SoC heats up once, before step 26
                self.heated = True
                zone.write_text("85000\n")
            return super().poll(step)

    events: list[tuple[str, dict]] = []
    gov = ThermalGovernor(zone, None, sleep_fn=cool_down, poll_s=0.5, sample_interval_s=0.0,
                          emit=lambda k, p: events.append((k, p)))
    r = train(cfg_for(ds, tmp_path / "run"), HeatAt(), emit=lambda k, p: events.append((k, p)),
              component_factory=factory(), thermal=gov)
    assert r.outcome == "completed"
    thermal = [p for k, p in events if k == "throttle"]
    assert [p["event"] for p in thermal if p["event"] != "level"] == ["wait_start", "wait_end"]
    assert thermal[-1]["ended_by"] == "cool" and len(slept) >= 3
    assert any(k == "checkpoint" and p["step"] == 25 for k, p in events)
    assert_bitwise_equal(weights(tmp_path / "run"), reference)


def test_thermal_slow_sleeps_a_fraction_of_the_step(ds, tmp_path, monkeypatch):
    import hope_models.train.loop as loop_mod
    zone = tmp_path / "temp"
    zone.write_text("78.5\n")  # halfway between soft 75 and hard 82 -> fraction 0.25
    sleeps: list[float] = []
    monkeypatch.setattr(loop_mod.time, "sleep", lambda s: sleeps.append(s))
    gov = ThermalGovernor(zone, None, sample_interval_s=0.0)
    r = train(cfg_for(ds, tmp_path / "run", steps=20), component_factory=factory(), thermal=gov)
    assert r.outcome == "completed" and len(sleeps) == 19  # every step but the first (no timing yet)
    metrics = [m for m in read_metrics(tmp_path / "run") if m["type"] == "metric"]
    assert metrics[-1]["throttle_level"] == "slow" and metrics[-1]["temp_c"] == 78.5


def test_resume_with_other_settings_is_refused(ds, tmp_path):
    train(cfg_for(ds, tmp_path, steps=20), component_factory=factory())
    with pytest.raises(TrainSetupError, match=r"seed: 3 in the run dir, 4 now"):
        train(cfg_for(ds, tmp_path, steps=40, seed=4), component_factory=factory())


@pytest.mark.parametrize("file,edit,match", [
    ("config.json", lambda c: c.update(train=["not", "an", "object"]), r"config.json: 'train' must be an object"),
    ("config.json", lambda c: c.update(train={"seed": {"deep": [[3]]}}), r"seed: \{'deep'.* in the run dir, 3 now"),
    ("training_state.json", lambda s: s["rng"].update(numpy="junk"), r"cannot resume from it: TypeError"),
])
def test_resume_from_a_checkpoint_with_malformed_json_is_a_clear_error(ds, tmp_path, file, edit, match):
    """A run dir's checkpoint JSON is read as untrusted input: wrong types are a TrainSetupError
    naming the checkpoint, never a traceback (an unreadable newest checkpoint is skipped on load)."""
    from brain_fixtures import rewrite_manifest

    train(cfg_for(ds, tmp_path, steps=20), component_factory=factory())
    last = ckpt.latest_complete(tmp_path)
    obj = json.loads((last / file).read_text())
    edit(obj)
    (last / file).write_text(json.dumps(obj))
    rewrite_manifest(last)
    with pytest.raises(TrainSetupError, match=match):
        train(cfg_for(ds, tmp_path, steps=40), component_factory=factory())


def test_setup_errors_name_the_problem(ds, tmp_path):
    with pytest.raises(TrainSetupError, match="no such file"):
        train(cfg_for(ds, tmp_path, data=str(tmp_path / "missing")), component_factory=factory())
    with pytest.raises(TrainSetupError, match="--component 'nope'"):
        train(cfg_for(ds, tmp_path, component="nope"))
    with pytest.raises(TrainSetupError, match="estimated .* exceeds the budget of 100 MB"):
        train(cfg_for(ds, tmp_path, memory_budget_mb=100), component_factory=factory())
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.md").write_text("no episodes here")
    with pytest.raises(TrainSetupError, match=f"--data {empty}"):
        train(cfg_for(ds, tmp_path, data=str(empty)), component_factory=factory())
    with pytest.raises(TrainSetupError, match="steps=0"):
        train(cfg_for(ds, tmp_path, steps=0), component_factory=factory())


def test_single_episode_file_as_data(ds, tmp_path):
    ep = sorted(p for p in (ds / "ds").iterdir() if p.is_dir())[0]
    steps_file = tmp_path / "one_episode.jsonl"
    steps_file.write_text((ep / "steps" / "000000.jsonl").read_text())
    r = train(cfg_for(ds, tmp_path / "run", data=str(steps_file), steps=10), component_factory=factory())
    assert r.outcome == "completed"


def test_schedule_is_a_pure_function_of_the_step():
    cfg = TrainConfig(component="fast_loop", data="x", run_dir="y", steps=1000, lr=1e-3, warmup=100,
                      min_lr_ratio=0.1)
    assert lr_at(50, cfg) == pytest.approx(5e-4) and lr_at(100, cfg) == pytest.approx(1e-3)
    assert lr_at(1000, cfg) == pytest.approx(1e-4)
    assert lr_at(550, cfg) == pytest.approx(1e-4 + 0.9e-3 * 0.5)
    short = TrainConfig(component="fast_loop", data="x", run_dir="y", steps=50, warmup=100)
    assert lr_at(5, short) == pytest.approx(short.lr)  # warmup capped at a tenth of the run


def test_loss_history_keeps_head_tail_and_a_bounded_curve():
    h = LossHistory(stride=10, max_points=64)
    for s in range(1, 5001):
        h.add(s, 1.0 / s)
    steps = [s for s, _ in h.points]
    assert steps[:10] == list(range(1, 11)) and steps[-10:] == list(range(4991, 5001))
    assert len(steps) <= 64 and steps == sorted(steps)
    assert all(s <= 10 or s % h.stride == 0 or s > 4990 for s in steps)
    again = LossHistory.from_json_obj(json.loads(json.dumps(h.to_json_obj())))
    assert again.points == h.points and math.isclose(again.first(), 1.0)


def test_time_based_checkpoints_do_not_change_the_math(ds, tmp_path, reference):
    events: list[tuple[str, dict]] = []
    r = train(cfg_for(ds, tmp_path, checkpoint_every_steps=10_000, checkpoint_every_s=1e-9, keep_last=100),
              emit=lambda k, p: events.append((k, p)), component_factory=factory())
    assert r.outcome == "completed"
    assert [p["step"] for k, p in events if k == "checkpoint"] == list(range(1, STEPS + 1))
    assert_bitwise_equal(weights(tmp_path), reference)


def test_an_error_inside_a_step_fails_the_job_and_keeps_the_last_checkpoint(ds, tmp_path):
    from test_train_loop_standin import StandIn

    class Broken(StandIn):
        def after_step(self, step):
            if step == 27:
                raise RuntimeError("codebook exploded")

    events: list[tuple[str, dict]] = []
    r = train(cfg_for(ds, tmp_path), emit=lambda k, p: events.append((k, p)),
              component_factory=lambda name, spec, **kw: Broken(spec))
    assert r.outcome == "failed" and "RuntimeError: codebook exploded" in r.message and "step 27" in r.message
    assert r.checkpoint.endswith("00000020") and ckpt.load_latest(tmp_path).step == 20
    assert any(k == "log" and p["level"] == "error" and "Traceback" in p["message"] for k, p in events)


def test_a_second_job_in_the_same_run_dir_is_refused_while_the_first_runs(ds, tmp_path):
    class SecondJob(StopAt):
        def poll(self, step):
            if step == 5 and not hasattr(self, "err"):
                try:
                    train(cfg_for(ds, tmp_path), component_factory=factory())
                except TrainSetupError as exc:
                    self.err = str(exc)
            return super().poll(step)

    c = SecondJob()
    assert train(cfg_for(ds, tmp_path, steps=10), c, component_factory=factory()).outcome == "completed"
    assert "in use by another training job" in c.err and f"pid {__import__('os').getpid()}" in c.err
    # released afterwards
    assert train(cfg_for(ds, tmp_path, steps=12), component_factory=factory()).resumed_from == 10


def test_a_model_that_cannot_fit_is_refused_from_its_config_before_it_is_built(ds, tmp_path, monkeypatch):
    """The pre-flight estimate runs on the configuration (resolve.resolve, estimate_from_config):
    a model_config too big for the budget never reaches build_component, whose allocations were
    what took the memory, and leaves no run dir behind; nor does a model_config with a typo."""
    from hope_models.components import build as components

    def build_nothing(*args, **kwargs):
        raise AssertionError("the model was built before the pre-flight looked at its configuration")

    monkeypatch.setattr(components, "build_component", build_nothing)
    run_dir = tmp_path / "run"
    with pytest.raises(TrainSetupError, match=r"fast_loop: estimated .* exceeds the budget of 3072 MB"):
        train(cfg_for(ds, run_dir, model_config={"d_model": 4096}, memory_budget_mb=3072))
    with pytest.raises(TrainSetupError, match=r"cannot build fast_loop: model_config for fast_loop: unknown key"):
        train(cfg_for(ds, run_dir, model_config={"d_modle": 64}))
    assert not run_dir.exists()
