"""Promotion records and pointers (registry/promotion.py, hope_models/promoted.py), rollback,
the loop-closure record, the promotion settings, and the daemon's AutoPromoter with real promote
children on a tiny trained fast_loop."""
from __future__ import annotations

import json
import threading
import time
from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy import select

from promote_fixtures import completed_run, train_fast_loop

import run_trainer
from registry import promotion
from registry import runs
from daemon.autopromote import LOG_FILE, AutoPromoter, describe
from registry.db import Registry
from registry.models import Model, Run, utcnow
from hope_models.promoted import (
    PointerError, checkpoint_version, pointer_path, read_pointer, remove_pointer, write_pointer,
)
from hope_models.settings import SettingsError, load_settings

SHA = "ab" * 32


def pointer(**over) -> dict:
    obj = {"component": "fast_loop", "checkpoint": "/abs/run/checkpoints/00000010", "version": "run@10:abababababab",
           "sha256": SHA, "model_id": 1, "run_id": None, "promoted_at": "2026-01-01T00:00:00+00:00"}
    obj.update(over)
    return obj


def make_ckpt(home: Path, name: str, value: float, step: int = 10) -> Path:
    """A complete (manifest-verified) checkpoint whose weights differ by `value`."""
    import torch

    from hope_models.checkpoints import save_checkpoint

    return save_checkpoint(home / "runs" / name, step, model_state={"w": torch.full((4,), float(value))},
                           config={"component": "fast_loop"}, state_tensors={"x": torch.zeros(1)}, state={})


@pytest.fixture
def reg(tmp_path):
    st = load_settings(tmp_path / "home", env={})
    with Registry.open(st) as registry:
        yield st, registry


def candidate(s, ckpt: Path, run_id: str | None = None) -> Model:
    return promotion.record_candidate(s, component="fast_loop", checkpoint_path=ckpt,
                                      version=checkpoint_version(ckpt)[0], run_id=run_id,
                                      metrics={"candidate_val_loss": 0.1}, gate_result={"passed": True})


# -- pointers -------------------------------------------------------------------------------------

def test_pointer_round_trip_and_atomic_replace(tmp_path):
    assert read_pointer(tmp_path, "fast_loop") is None
    path = write_pointer(tmp_path, "fast_loop", pointer())
    assert path == pointer_path(tmp_path, "fast_loop") == tmp_path / "promoted" / "fast_loop.json"
    assert read_pointer(tmp_path, "fast_loop") == pointer()
    write_pointer(tmp_path, "fast_loop", pointer(model_id=2, run_id="r-1"))
    assert read_pointer(tmp_path, "fast_loop")["model_id"] == 2
    assert [p.name for p in (tmp_path / "promoted").iterdir()] == ["fast_loop.json"]  # no temp files left
    assert remove_pointer(tmp_path, "fast_loop") is True and remove_pointer(tmp_path, "fast_loop") is False
    assert read_pointer(tmp_path, "fast_loop") is None


def test_readers_never_see_a_half_written_pointer(tmp_path):
    write_pointer(tmp_path, "fast_loop", pointer())
    errors, seen, stop = [], set(), threading.Event()

    def reader():
        while not stop.is_set():
            try:
                seen.add(read_pointer(tmp_path, "fast_loop")["model_id"])
            except Exception as exc:  # noqa: BLE001 - any failure is the finding
                errors.append(exc)

    t = threading.Thread(target=reader)
    t.start()
    for i in range(300):
        write_pointer(tmp_path, "fast_loop", pointer(model_id=i, version=f"run@{i}:" + "c" * 12))
    stop.set()
    t.join()
    assert errors == [] and len(seen) > 1


@pytest.mark.parametrize("content, match", [
    (b"{not json", "not valid JSON"),
    (b"[1, 2]", "must be a JSON object"),
    (json.dumps({k: v for k, v in pointer().items() if k != "sha256"}).encode(), "'sha256' is missing"),
    (json.dumps(pointer(model_id="7")).encode(), "'model_id' must be int"),
    (json.dumps(pointer(model_id=True)).encode(), "'model_id' must be int"),
    (json.dumps(pointer(checkpoint="runs/x")).encode(), "absolute path"),
    (json.dumps(pointer(sha256="xyz")).encode(), "64 lowercase hex"),
    (json.dumps(pointer(component="vqvae")).encode(), "expected 'fast_loop'"),
])
def test_a_corrupt_pointer_is_an_error_naming_the_file(tmp_path, content, match):
    path = pointer_path(tmp_path, "fast_loop")
    path.parent.mkdir(parents=True)
    path.write_bytes(content)
    with pytest.raises(PointerError, match=match) as info:
        read_pointer(tmp_path, "fast_loop")
    assert str(path) in str(info.value)


def test_pointer_component_names_cannot_escape_the_dir(tmp_path):
    for bad in ("../etc", "fast_loop.json", "", "A", "a/b"):
        with pytest.raises(PointerError, match="not a valid component name"):
            pointer_path(tmp_path, bad)
    with pytest.raises(PointerError, match="names component"):
        write_pointer(tmp_path, "vqvae", pointer())


def test_checkpoint_version_names_run_step_and_sha(tmp_path):
    from hope_models.durable import file_sha256

    ckpt = make_ckpt(tmp_path, "my-run", 1.0, step=20)
    version, sha = checkpoint_version(ckpt)
    assert sha == file_sha256(ckpt / "model.safetensors")
    assert version == f"my-run@20:{sha[:12]}"
    with pytest.raises(PointerError, match="model.safetensors: not found"):
        checkpoint_version(tmp_path)


# -- promote / rollback in the registry ---------------------------------------------------------------

def test_promote_demote_and_roll_back_through_the_history(reg):
    st, registry = reg
    home = st.home
    a, b, c = (make_ckpt(home, n, v) for n, v in (("ra", 1), ("rb", 2), ("rc", 3)))
    with registry.session() as s:
        ma, mb, mc = candidate(s, a), candidate(s, b), candidate(s, c)
        assert promotion.promoted(s, "fast_loop") is None
        promotion.promote(s, st, ma.id)
        promotion.promote(s, st, mb.id)
        promotion.promote(s, st, mc.id)
        ids = (ma.id, mb.id, mc.id)
    with registry.session(readonly=True) as s:
        ma, mb, mc = (s.get(Model, i) for i in ids)
        assert promotion.promoted(s, "fast_loop").id == mc.id
        assert (ma.previous_model_id, mb.previous_model_id, mc.previous_model_id) == (None, ma.id, mb.id)
        assert ma.demoted_at is not None and mb.demoted_at is not None and mc.demoted_at is None
        assert [m.id for m in promotion.history(s, "fast_loop")] == [mc.id, mb.id, ma.id]
        assert [m.id for m in promotion.history(s, "fast_loop", limit=1)] == [mc.id]
    p = read_pointer(home, "fast_loop")
    assert p["model_id"] == ids[2] and p["version"] == checkpoint_version(c)[0]
    assert p["checkpoint"] == str(c.resolve()) and p["sha256"] == checkpoint_version(c)[1]

    with registry.session() as s:
        assert promotion.rollback(s, st, "fast_loop").id == ids[1]
    assert read_pointer(home, "fast_loop")["version"] == checkpoint_version(b)[0]
    with registry.session() as s:
        assert promotion.rollback(s, st, "fast_loop").id == ids[0]
        assert s.get(Model, ids[2]).promoted_at is None and s.get(Model, ids[1]).demoted_at is not None
    assert read_pointer(home, "fast_loop")["model_id"] == ids[0]
    with registry.session() as s, pytest.raises(promotion.PromotionError, match="first one promoted"):
        promotion.rollback(s, st, "fast_loop")
    with registry.session() as s, pytest.raises(promotion.PromotionError, match="nothing to roll back"):
        promotion.rollback(s, st, "vqvae")
    with registry.session() as s, pytest.raises(promotion.PromotionError, match="no model 999"):
        promotion.promote(s, st, 999)


def test_a_failed_pointer_write_rolls_the_promotion_back(reg, monkeypatch):
    st, registry = reg
    a, b = make_ckpt(st.home, "ra", 1), make_ckpt(st.home, "rb", 2)
    with registry.session() as s:
        ma, mb = candidate(s, a), candidate(s, b)
        promotion.promote(s, st, ma.id)
        ids = ma.id, mb.id

    def broken(*args, **kwargs):
        raise PointerError("/x/promoted/fast_loop.json: cannot write: No space left on device")

    monkeypatch.setattr(promotion, "write_pointer", broken)
    with registry.session() as s:
        with pytest.raises(promotion.PromotionError, match="rolled back: .*No space left"):
            promotion.promote(s, st, ids[1])
        # the savepoint undid the demotion too, inside this very transaction
        assert promotion.promoted(s, "fast_loop").id == ids[0]
    with registry.session(readonly=True) as s:
        assert promotion.promoted(s, "fast_loop").id == ids[0]
        assert s.get(Model, ids[0]).demoted_at is None and s.get(Model, ids[1]).previous_model_id is None
    assert read_pointer(st.home, "fast_loop")["model_id"] == ids[0]


def test_promote_refuses_a_checkpoint_that_changed_or_vanished(reg):
    import shutil

    st, registry = reg
    a, b = make_ckpt(st.home, "ra", 1), make_ckpt(st.home, "rb", 2)
    with registry.session() as s:
        ma, mb = candidate(s, a), candidate(s, b)
        ids = ma.id, mb.id
    make_ckpt(st.home, "ra", 5)  # same run and step, other weights: not what was gated
    with registry.session() as s, pytest.raises(promotion.PromotionError, match="gate it again"):
        promotion.promote(s, st, ids[0])
    shutil.rmtree(b)
    with registry.session() as s, pytest.raises(promotion.PromotionError, match="no longer exists"):
        promotion.promote(s, st, ids[1])
    assert read_pointer(st.home, "fast_loop") is None


def test_sync_pointer_repairs_a_missing_or_corrupt_pointer(reg):
    st, registry = reg
    a = make_ckpt(st.home, "ra", 1)
    with registry.session() as s:
        promotion.promote(s, st, candidate(s, a).id)
    good = read_pointer(st.home, "fast_loop")
    pointer_path(st.home, "fast_loop").write_text("garbage")
    with registry.session() as s:
        assert promotion.sync_pointer(s, st, "fast_loop") == good
        assert promotion.sync_pointer(s, st, "vqvae") is None
    assert read_pointer(st.home, "fast_loop") == good


def test_loop_closure_is_recorded_once_per_run(reg):
    st, registry = reg
    a = make_ckpt(st.home, "ra", 1)
    run_id = completed_run(registry, a.parent.parent)
    with registry.session() as s:
        m = candidate(s, a, run_id)
        version = m.version
        finished = s.get(Run, run_id).finished_at
    when = finished + timedelta(seconds=12.5)
    with registry.session() as s:
        assert promotion.record_first_inference(s, "nobody@1:000000000000", when) is None
        run = promotion.record_first_inference(s, version, when)
        assert run.id == run_id and run.loop_closure_s == 12.5
    with registry.session() as s:  # later inferences (by path this time) change nothing
        run = promotion.record_first_inference(s, str(a), when + timedelta(seconds=100))
        assert run.loop_closure_s == 12.5 and run.first_inference_at == when
        obj = run.to_json_obj()
        assert obj["loop_closure_s"] == 12.5 and obj["first_inference_at"] == when.isoformat()
        events = [e.payload["message"] for e in runs.run_events(s, run_id, kinds=["log"])]
        assert sum("first inference on" in m and "12.5 s" in m for m in events) == 1
    with registry.session() as s, pytest.raises(promotion.PromotionError, match="naive"):
        promotion.record_first_inference(s, version, when.replace(tzinfo=None))


def test_a_tokenizers_loop_closes_when_it_is_loaded(reg):
    """A vqvae's codes are in every answer once BrainService loads it, whoever asks: its loop closure
    is the time to being loaded, not the wait for a fast_loop that reads it; a fast_loop's is not."""
    st, registry = reg
    ckpts = {c: make_ckpt(st.home, f"r{c}", 2) for c in ("vqvae", "fast_loop")}
    ids = {comp: completed_run(registry, ckpt.parent.parent, component=comp) for comp, ckpt in ckpts.items()}
    versions = {}
    with registry.session() as s:
        for comp, ckpt in ckpts.items():
            m = promotion.record_candidate(s, component=comp, checkpoint_path=ckpt, version=f"{comp}@2:0123456789ab",
                                           run_id=ids[comp], metrics={}, gate_result={"passed": True})
            versions[comp] = m.version
        finished = s.get(Run, ids["vqvae"]).finished_at
    with registry.session() as s:
        assert promotion.record_loaded(s, str(ckpts["fast_loop"]), finished + timedelta(seconds=1)) is None
        run = promotion.record_loaded(s, str(ckpts["vqvae"]), finished + timedelta(seconds=0.75))
        assert run.id == ids["vqvae"] and run.loop_closure_s == 0.75
        assert promotion.record_loaded(s, versions["vqvae"], finished + timedelta(seconds=9)) is None  # once
    with registry.session() as s:  # its first answer later records when, and keeps the closure
        run = promotion.record_first_inference(s, versions["vqvae"], finished + timedelta(seconds=300))
        assert run.loop_closure_s == 0.75 and run.first_inference_at == finished + timedelta(seconds=300)
        assert s.get(Run, ids["fast_loop"]).loop_closure_s is None
        events = [e.payload["message"] for e in runs.run_events(s, ids["vqvae"], kinds=["log"])]
        assert sum("loaded by BrainService: loop closure 0.8 s" in m for m in events) == 1, events


# -- run_trainer.py rollback -----------------------------------------------------------------------------

def test_rollback_cli(reg, monkeypatch, capsys):
    st, registry = reg
    monkeypatch.setenv("HOPE_HOME", str(st.home))
    a, b = make_ckpt(st.home, "ra", 1), make_ckpt(st.home, "rb", 2)
    with registry.session() as s:
        ma, mb = candidate(s, a), candidate(s, b)
        promotion.promote(s, st, ma.id)
        promotion.promote(s, st, mb.id)
        ids = ma.id, mb.id
    assert run_trainer.main(["rollback", "fast_loop", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["rolled_back"] is True and out["model"]["id"] == ids[0] and out["demoted"]["id"] == ids[1]
    assert out["model"]["promoted"] is True and out["demoted"]["demoted_at"] is not None
    assert read_pointer(st.home, "fast_loop")["model_id"] == ids[0]
    assert run_trainer.main(["rollback", "fast_loop", "--json"]) == 2
    out = json.loads(capsys.readouterr().out)
    assert out["rolled_back"] is False and "first one promoted" in out["error"]
    assert run_trainer.main(["rollback", "mid_loop"]) == 2
    assert "nothing to roll back" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        run_trainer.main(["rollback", "brain"])  # argparse: not a component
    assert info.value.code == 2


# -- settings ---------------------------------------------------------------------------------------------

def test_promotion_settings_from_env_and_config(tmp_path):
    s = load_settings(tmp_path, env={})
    assert (s.auto_promote, s.gate_val_tolerance, s.gate_reflex_tolerance, s.gate_reflex_episodes) == \
        (True, 0.05, 50.0, 5)
    (tmp_path / "config.toml").write_text("auto_promote = false\ngate_val_tolerance = 0.1\n")
    s = load_settings(tmp_path, env={"HOPE_GATE_REFLEX_EPISODES": "3"})
    assert (s.auto_promote, s.gate_val_tolerance, s.gate_reflex_episodes) == (False, 0.1, 3)
    assert load_settings(tmp_path, env={"HOPE_AUTO_PROMOTE": "yes"}).auto_promote is True
    for env, match in [({"HOPE_AUTO_PROMOTE": "maybe"}, "HOPE_AUTO_PROMOTE.*not a valid bool"),
                       ({"HOPE_GATE_VAL_TOLERANCE": "-0.1"}, "must be >= 0"),
                       ({"HOPE_GATE_REFLEX_EPISODES": "0"}, "must be >= 1"),
                       ({"HOPE_GATE_REFLEX_TOLERANCE": "inf"}, "not a valid float")]:
        with pytest.raises(SettingsError, match=match):
            load_settings(tmp_path, env=env)


# -- auto-promotion ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A sim-demo fast_loop (40 steps) and a 2-step one that the gate refuses after it."""
    import torch

    from hope_models.sim.recorder import record_dataset

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("auto")
    record_dataset(root / "demos", 12, task="reach", noise=1.0, steps=200)
    out = {"demos": root / "demos", "good": train_fast_loop(root, "good", 150, root / "demos"),
           "weak": train_fast_loop(root, "weak", 2, root / "demos")}
    torch.set_num_threads(threads)
    return out


def wait_outcome(promoter: AutoPromoter, run_id: str, timeout: float = 120.0) -> dict:
    """Tick until the child gating run_id has been collected; its outcome."""
    deadline = time.monotonic() + timeout
    while (promoter.last_outcome or {}).get("run_id") != run_id:
        assert time.monotonic() < deadline, f"the promote child of {run_id} did not finish"
        time.sleep(0.2)
        promoter.tick()
    return promoter.last_outcome


def log_messages(registry, run_id: str) -> list[str]:
    with registry.session(readonly=True) as s:
        return [e.payload["message"] for e in runs.run_events(s, run_id, kinds=["log"])]


def test_auto_promoter_gates_completed_runs_one_at_a_time(trained, tmp_path, monkeypatch):
    monkeypatch.delenv("HOPE_GATE_REFLEX_EPISODES", raising=False)  # the child gets it from the daemon's settings
    st = load_settings(tmp_path / "home", env={"HOPE_GATE_REFLEX_EPISODES": "2"})
    with Registry.open(st) as registry:
        old = completed_run(registry, trained["good"].parent.parent, data=trained["demos"])  # before the promoter
        time.sleep(0.01)
        promoter = AutoPromoter(st, registry)
        promoter.tick()
        assert not promoter.busy  # the old run is not gated
        time.sleep(0.01)
        good = completed_run(registry, trained["good"].parent.parent, data=trained["demos"])
        weak = completed_run(registry, trained["weak"].parent.parent, data=trained["demos"])
        started = time.monotonic()
        promoter.tick()
        assert time.monotonic() - started < 1.0  # spawning does not wait for the gate
        assert promoter.busy and promoter.current_run == good
        promoter.tick()
        assert promoter.current_run == good  # one at a time
        outcome = wait_outcome(promoter, good)
        assert outcome["exit_code"] == 0 and outcome["promoted"] is True, outcome
        assert promoter.current_run == weak  # the tick that collected one started the next
        outcome = wait_outcome(promoter, weak)
        assert outcome["exit_code"] == 1 and outcome["promoted"] is False, outcome
        promoter.tick()
        assert not promoter.busy

        with registry.session(readonly=True) as s:
            good_model = promotion.promoted(s, "fast_loop")
            assert good_model.run_id == good and good_model.gate_result["mode"] == "auto"
            assert good_model.metrics["reflex"]["episodes"] == 2
            weak_model = s.scalars(select(Model).where(Model.run_id == weak)).one()
            assert weak_model.promoted_at is None
            assert s.scalars(select(Model).where(Model.run_id == old)).first() is None
        assert read_pointer(st.home, "fast_loop")["run_id"] == good
        assert any(m.startswith("auto-promote: promoted fast_loop") for m in log_messages(registry, good))
        refused = [m for m in log_messages(registry, weak) if m.startswith("auto-promote: the gate refused")]
        assert refused and "worse" in refused[0]
        text = (st.home / "logs" / LOG_FILE).read_text()
        assert f"run {good}: auto-promote: promoted" in text and f"run {weak}: auto-promote: the gate refused" in text
        assert not list((st.home / "logs").glob(".promote-*"))


def test_auto_promoter_off_and_close(trained, tmp_path):
    st = load_settings(tmp_path / "home", env={"HOPE_AUTO_PROMOTE": "0"})
    with Registry.open(st) as registry:
        promoter = AutoPromoter(st, registry, clock=lambda: utcnow() - timedelta(hours=1))
        run_id = completed_run(registry, trained["good"].parent.parent)
        promoter.tick()
        assert not promoter.busy  # auto_promote is off
        st.auto_promote = True
        promoter.tick()
        assert promoter.busy and promoter.current_run == run_id
        pid = promoter._proc.pid
        promoter.close()
        assert not promoter.busy
        import os
        with pytest.raises(ProcessLookupError):
            os.kill(pid, 0)
        assert "gate stopped" in (st.home / "logs" / LOG_FILE).read_text()


def test_describe_outcomes():
    assert describe(2, None)[0] == "error" and "without a result" in describe(2, None)[1]
    level, msg = describe(1, {"component": "fast_loop", "version": "v", "model_id": 3, "reasons": ["worse"]})
    assert level == "warning" and "refused fast_loop v (model 3): worse" in msg
    assert describe(2, {"promoted": False, "error": "no run x"})[1] == "auto-promote: could not gate: no run x"
    after = {"passed": False, "detail": "reflex mean return 12.0 vs the promoted model's 900.0"}
    level, msg = describe(1, {"component": "fast_loop", "version": "v", "model_id": 4, "promoted": False,
                              "rolled_back": True, "reasons": [after["detail"]], "after_serving": after})
    assert level == "warning" and "served fast_loop v (model 4), then rolled it back: reflex mean return 12.0" in msg
    level, msg = describe(0, {"component": "fast_loop", "version": "w", "model_id": 5, "promoted": True, "reasons": [],
                              "after_serving": {"passed": True, "detail": "reflex mean return 950.0"}})
    assert level == "info" and msg.endswith("promoted fast_loop w (model 5); after serving: reflex mean return 950.0")


# -- a reflex check after serving that a dead process left owed (registry/gating.py) --------------------------

def served_owing_the_check(s, st, ckpt: Path, run_id: str | None = None, **gate) -> Model:
    """A candidate recorded and served the way promote_candidate does it, with its reflex check
    deferred, and then nothing more: its process died before the check's verdict was recorded."""
    model = promotion.record_candidate(
        s, component="fast_loop", checkpoint_path=ckpt, version=checkpoint_version(ckpt)[0], run_id=run_id,
        metrics={"reflex": {"task": "reach", "after_serving": True, "episodes": 2}},
        gate_result={"passed": True, "promoted": True, "forced": False, "reasons": ["reflex: checked after serving"],
                     "checks": [{"check": "finite", "status": "passed", "detail": "every weight is finite"},
                                {"check": "reflex", "status": "deferred", "detail": "reflex: checked after serving"}],
                     "mode": "auto", **gate})
    return promotion.promote(s, st, model.id)


def test_which_served_models_owe_their_check(reg, monkeypatch):
    from registry import gating

    st, registry = reg
    a, b, c = (make_ckpt(st.home, n, v) for n, v in (("ra", 1), ("rb", 2), ("rc", 3)))
    with registry.session() as s:
        promotion.promote(s, st, candidate(s, a).id)
        owed_b = served_owing_the_check(s, st, b).id
        assert [m.id for m in gating.owed_checks(s)] == [owed_b]
        promotion.rollback(s, st, "fast_loop")  # no longer served: nothing owed
        assert gating.owed_checks(s) == []
        served_owing_the_check(s, st, c, forced=True)  # a forced promotion never runs the check
        assert gating.owed_checks(s) == []
        checked = served_owing_the_check(s, st, b, after_serving={"passed": True})
        assert gating.owes_check(checked) is False

    def not_called(*_args, **_kwargs):
        raise AssertionError("the check ran for a model that no longer owes it")

    monkeypatch.setattr(gating, "check_after_serving", not_called)
    assert gating.finish_check(st, registry, owed_b) is None  # read again: demoted meanwhile
    assert gating.finish_owed_checks(st, registry) == (0, {"finished": [], "rolled_back": False})


def test_a_failed_check_whose_rollback_fails_is_still_recorded(reg):
    """Otherwise the check stays owed and runs again at every start of the service."""
    import shutil

    from registry import gating

    st, registry = reg
    a, b = make_ckpt(st.home, "ra", 1), make_ckpt(st.home, "rb", 2)  # b: not a fast_loop its check can load
    with registry.session() as s:
        promotion.promote(s, st, candidate(s, a).id)
        b_id = served_owing_the_check(s, st, b).id
    shutil.rmtree(a)  # the model to roll back to is gone
    code, out = gating.finish_owed_checks(st, registry)
    assert code == 0 and out["finished"][0]["rolled_back"] is False, out
    with registry.session(readonly=True) as s:
        assert promotion.promoted(s, "fast_loop").id == b_id and gating.owed_checks(s) == []
        assert s.get(Model, b_id).gate_result["after_serving"]["passed"] is False


def test_auto_promotion_finishes_an_owed_check_when_the_lock_is_free(tmp_path):
    import os
    import signal

    from registry.gating import promote_lock

    st = load_settings(tmp_path / "home", env={"HOPE_AUTO_PROMOTE": "0"})  # it runs with auto_promote off too
    with Registry.open(st) as registry:
        a = make_ckpt(st.home, "ra", 1)
        b = make_ckpt(st.home, "rb", 2)  # not a fast_loop its check can load: it fails, and b is rolled back
        run_b = completed_run(registry, b.parent.parent)
        with registry.session() as s:
            a_id = promotion.promote(s, st, candidate(s, a).id).id
            b_id = served_owing_the_check(s, st, b, run_id=run_b).id
        promoter = AutoPromoter(st, registry)
        run_c = completed_run(registry, make_ckpt(st.home, "rc", 3).parent.parent)  # a run to gate next
        st.auto_promote = True
        with promote_lock(st.home, wait=False) as mine:  # the check may be running in the lock's holder
            assert mine
            promoter.tick()
            assert not promoter.busy
        promoter.tick()  # the served unchecked model before the next run's gate
        assert promoter.busy and promoter.current_run == run_b and "--finish-checks" in promoter._argv
        os.killpg(promoter._proc.pid, signal.SIGKILL)  # the finishing child dies too
        promoter._proc.wait()
        promoter.tick()
        assert promoter.last_outcome["model_ids"] == [b_id]
        assert promoter.current_run == run_c and "--finish-checks" not in promoter._argv  # not started again
        promoter.close()
        assert any("was not finished" in m and "killed by signal 9" in m for m in log_messages(registry, run_b))

        st.auto_promote = False

        fresh = AutoPromoter(st, registry)  # the next start of the service
        fresh.tick()
        assert fresh.busy
        deadline = time.monotonic() + 120
        while fresh.busy:
            assert time.monotonic() < deadline, "the --finish-checks child did not finish"
            time.sleep(0.1)
            fresh.tick()
        assert fresh.last_outcome["exit_code"] == 1 and fresh.last_outcome["rolled_back"] is True, fresh.last_outcome
        messages = log_messages(registry, run_b)
    assert read_pointer(st.home, "fast_loop")["model_id"] == a_id
    assert any("reflex check after serving was interrupted" in m for m in messages)
    assert any(f"(model {b_id}), interrupted after it was served, ran now: failed, rolled back" in m for m in messages)
    assert "ran now: failed, rolled back" in (st.home / "logs" / LOG_FILE).read_text()
