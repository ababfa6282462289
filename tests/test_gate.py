"""The promotion gate on tiny real checkpoints, and `run_trainer.py promote` (exit codes, records).

The models (promote_fixtures.build_models): fast_loops trained on 12 sim reacher demos for 150
("good") and 3 ("weak") steps, and one on synthetic data whose fields do not fit the reacher.
The reflex check runs 2 held-out episodes here (HOPE_GATE_REFLEX_EPISODES) to stay fast.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from promote_fixtures import build_models, completed_run, copy_run, poison_with_nan, write_config

import run_trainer
from registry import promotion
from registry.db import Registry
from registry.models import Model
from hope_models.promote.gate import GateError, gate_candidate, sim_task
from hope_models.promoted import checkpoint_version, read_pointer
from hope_models.settings import load_settings

ENV = {"HOPE_GATE_REFLEX_EPISODES": "2"}


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("gate")
    # The gate follows a checkpoint's data and cache paths only inside the data roots: the models'
    # datasets and caches are under root, which is therefore these tests' data root (also for the
    # CLI, through the environment the `home` fixture sets).
    ENV["HOPE_DATA_ROOTS"] = str(root)
    yield {"root": root, **build_models(root)}
    ENV.pop("HOPE_DATA_ROOTS")
    torch.set_num_threads(threads)


@pytest.fixture
def home(tmp_path, monkeypatch):
    """A fresh $HOPE_HOME for in-process CLI calls (the CLI reads the environment)."""
    h = tmp_path / "home"
    monkeypatch.setenv("HOPE_HOME", str(h))
    for k, v in ENV.items():
        monkeypatch.setenv(k, v)
    return h


def settings(**env) -> object:
    return load_settings("/nonexistent-home-for-gate-tests", env={**ENV, **env})


def cli(capsys, *argv) -> tuple[int, dict]:
    code = run_trainer.main(list(argv))
    out = capsys.readouterr().out.strip().splitlines()
    return code, (json.loads(out[-1]) if out else {})


# -- the gate itself -------------------------------------------------------------------------------

def test_candidate_val_loss_is_the_one_the_trainer_reported(models):
    """Same split, same batches, same function: the gate's number equals result.json's val loss."""
    res = gate_candidate(models["good"], None, settings=settings())
    reported = json.loads((models["good"].parent.parent / "result.json").read_text())["summary"]["val"]["loss"]
    assert res.metrics["candidate_val_loss"] == reported
    assert res.passed and res.metrics["finite"] is True
    # nothing promoted: both comparisons are skipped, and the reasons say so
    assert [c["status"] for c in res.checks] == ["passed", "skipped", "skipped"]
    assert any("nothing promoted yet" in r for r in res.reasons)
    assert res.metrics["reflex"]["task"] == "reach" and res.metrics["reflex"]["candidate_mean_return"] > 0


def test_same_model_compares_equal_on_the_same_batches(models):
    res = gate_candidate(models["good"], models["good"], settings=settings())
    assert res.passed, res.reasons
    assert res.metrics["ratio"] == 1.0
    assert res.metrics["reflex"]["candidate_mean_return"] == res.metrics["reflex"]["promoted_mean_return"]


def test_clearly_worse_val_loss_is_refused_with_the_reason(models):
    res = gate_candidate(models["weak"], models["good"], settings=settings())
    assert not res.passed
    assert res.metrics["ratio"] > 1.05
    val = next(c for c in res.checks if c["check"] == "val_loss")
    assert val["status"] == "failed" and "worse by more than 5%" in val["detail"]
    assert val["detail"] in res.reasons


def test_worse_reflex_is_refused_even_when_the_val_loss_is_tolerated(models):
    res = gate_candidate(models["weak"], models["good"], settings=settings(HOPE_GATE_VAL_TOLERANCE="100"))
    statuses = {c["check"]: c["status"] for c in res.checks}
    assert statuses == {"finite": "passed", "val_loss": "passed", "reflex": "failed"}, res.checks
    r = res.metrics["reflex"]
    assert r["candidate_mean_return"] < r["promoted_mean_return"] - 50
    assert not res.passed and len(res.reasons) == 1 and "reflex mean return" in res.reasons[0]


def test_better_candidate_passes(models):
    res = gate_candidate(models["good"], models["weak"], settings=settings())
    assert res.passed, res.reasons
    assert res.metrics["ratio"] < 1.0
    assert {c["check"]: c["status"] for c in res.checks} == {"finite": "passed", "val_loss": "passed",
                                                             "reflex": "passed"}


def test_nan_weights_are_refused_and_nothing_else_is_measured(models, tmp_path):
    bad = copy_run(models["good"], tmp_path, "nan_run")
    name = poison_with_nan(bad)
    res = gate_candidate(bad, models["good"], settings=settings())
    assert not res.passed and res.metrics["finite"] is False
    assert "non-finite" in res.reasons[0] and name in res.reasons[0]
    assert [c["status"] for c in res.checks] == ["failed", "skipped", "skipped"]


def test_a_promoted_model_that_does_not_fit_the_data_is_skipped_not_a_crash(models):
    res = gate_candidate(models["good"], models["synthetic"], settings=settings())
    assert res.passed, res.reasons
    checks = {c["check"]: c for c in res.checks}
    assert checks["val_loss"]["status"] == "skipped"
    assert "does not fit" in checks["val_loss"]["detail"] and "observation" in checks["val_loss"]["detail"]
    assert checks["reflex"]["status"] == "skipped"
    assert res.metrics["promoted_val_loss"] is None and math.isfinite(res.metrics["candidate_val_loss"])


def test_a_promoted_checkpoint_that_is_gone_is_skipped_with_the_reason(models, tmp_path):
    res = gate_candidate(models["good"], tmp_path / "pruned", settings=settings())
    assert res.passed
    assert [c["status"] for c in res.checks] == ["passed", "skipped", "skipped"]
    assert all("the promoted model cannot be loaded" in r and "pruned" in r for r in res.reasons)


def test_missing_training_data_refuses_with_the_path(models, tmp_path):
    res = gate_candidate(models["good"], models["weak"], data=tmp_path / "gone", settings=settings())
    val = next(c for c in res.checks if c["check"] == "val_loss")
    assert val["status"] == "failed" and str(tmp_path / "gone") in val["detail"]
    assert not res.passed


def test_not_a_checkpoint_is_a_gate_error(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(GateError, match="no complete checkpoint"):
        gate_candidate(tmp_path / "empty", None, settings=settings())
    with pytest.raises(GateError, match="no such"):
        gate_candidate(tmp_path / "nope", None, settings=settings())


# -- a candidate's config.json is untrusted input ---------------------------------------------------

def hostile(models, tmp_path, edit) -> Path:
    """A copy of the good candidate (outside the data root) whose config.json `edit` changed."""
    ckpt = copy_run(models["good"], tmp_path, "hostile")
    cfg = json.loads((ckpt / "config.json").read_text())
    edit(cfg)
    write_config(ckpt, cfg)
    return ckpt


@pytest.fixture
def no_data_reads(monkeypatch):
    """Fail the test if the gate opens a dataset, a spec or a cache (or makes a cache dir)."""
    import hope_models.data.cache
    import hope_models.train.dataset_dir

    def refuse(*args, **kwargs):
        raise AssertionError(f"the gate read or created {args!r}")

    monkeypatch.setattr(hope_models.data.cache, "load_or_build", refuse)
    monkeypatch.setattr(hope_models.train.dataset_dir, "dataset_dir_for", refuse)


@pytest.mark.parametrize("field", ["data", "cache_dir", "spec_path"])
def test_config_paths_outside_the_data_roots_are_refused_before_anything_is_read(models, tmp_path, no_data_reads,
                                                                                field):
    outside = tmp_path / "elsewhere"  # not under the data root (models["root"])
    outside.mkdir()
    value = {"data": str(outside), "cache_dir": str(outside / "cache"), "spec_path": "/etc/passwd"}[field]
    ckpt = hostile(models, tmp_path, lambda c: c["train"].update({field: value}))
    res = gate_candidate(ckpt, None, settings=settings())
    val = next(c for c in res.checks if c["check"] == "val_loss")
    assert not res.passed and val["status"] == "failed"
    assert f"train.{field}: {value} is outside the allowed data roots" in val["detail"]
    assert str(ckpt / "config.json") in val["detail"] and str(models["root"]) in val["detail"]
    assert list(outside.iterdir()) == []  # no cache dir was made there


def test_a_symlink_inside_the_data_root_to_outside_is_outside(models, tmp_path, no_data_reads):
    link = models["root"] / f"link-{tmp_path.name}"
    link.symlink_to(tmp_path)
    try:
        ckpt = hostile(models, tmp_path, lambda c: c["train"].update(cache_dir=str(link / "cache")))
        val = next(c for c in gate_candidate(ckpt, None, settings=settings()).checks if c["check"] == "val_loss")
        assert val["status"] == "failed" and "train.cache_dir" in val["detail"] and "outside" in val["detail"]
        assert not (tmp_path / "cache").exists()
    finally:
        link.unlink()


def test_the_promotions_own_dataset_replaces_every_path_of_config_json(models, tmp_path):
    """`promote RUN` passes the run's dataset from the registry: config.json's paths are not followed."""
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    ckpt = hostile(models, tmp_path, lambda c: c["train"].update(data="/etc", cache_dir=str(outside / "cache"),
                                                                 spec_path="/etc/passwd"))
    st = load_settings(tmp_path / "home", env=ENV)
    res = gate_candidate(ckpt, None, data=models["demos"], settings=st)
    assert res.passed, res.reasons
    assert math.isfinite(res.metrics["candidate_val_loss"]) and res.metrics["val_data"] == str(models["demos"])
    assert list(outside.iterdir()) == [] and (st.cache_dir).is_dir()  # compiled under $HOPE_HOME/cache


@pytest.mark.parametrize("train,needle", [
    ([1, 2], "'train' must be an object, got list"),
    ({"batch_size": "64"}, "train: batch_size='64' is not an integer"),
    ({"batch_size": 10**12}, "train: batch_size=1000000000000 is outside 1..65536"),
    ({"batch_size": 32, "val_batches": 10**9}, "train: val_batches=1000000000 is outside 1..1000"),
    ({"batch_size": 32, "val_fraction": {"a": [[1]]}}, "train: val_fraction={'a': [[1]]} is not a number"),
    ({"batch_size": 32, "data": 5}, "train.data: expected a path, got 5"),
    ({"batch_size": 32, "spec_path": ["nested", {"junk": 1}]}, "train.spec_path: expected a path"),
])
def test_malformed_train_values_fail_the_check_naming_the_field(models, tmp_path, no_data_reads, train, needle):
    ckpt = hostile(models, tmp_path, lambda c: c.update(train=train))
    res = gate_candidate(ckpt, None, settings=settings())
    val = next(c for c in res.checks if c["check"] == "val_loss")
    assert not res.passed and val["status"] == "failed"
    assert needle in val["detail"] and str(ckpt / "config.json") in val["detail"], val["detail"]


@pytest.mark.parametrize("edit,needle", [
    (lambda c: c["model_config"].update(d_model=10**7), "weights do not fit the model its config.json describes"),
    (lambda c: c["model_config"].update(d_state=2**40), "does not describe a usable component"),
    (lambda c: c["window"].update(k=10**12), "must be an integer in 1-4096"),
    (lambda c: c["feature_spec"].update(notes={"deep": [[["x"]]]}), "notes must be a list of strings"),
    (lambda c: c["feature_spec"]["observation"].update(mean=[3.5e38] * 6), "within float32's range"),
    ("[" * 100_000 + "]" * 100_000, "nested too deeply"),
    ('{"component": "fast_loop", "format": NaN}', "not readable JSON"),
])
def test_a_config_json_that_describes_no_usable_model_is_a_gate_error(models, tmp_path, edit, needle):
    """Huge dims are compared with the weights file before anything is allocated: an error, not the
    Pi's memory; junk is an error naming config.json, not a traceback."""
    if isinstance(edit, str):
        ckpt = copy_run(models["good"], tmp_path, "hostile")
        write_config(ckpt, edit)
    else:
        ckpt = hostile(models, tmp_path, edit)
    with pytest.raises(GateError) as err:
        gate_candidate(ckpt, None, settings=settings())
    assert needle in str(err.value) and str(ckpt) in str(err.value)


def test_sim_task_comes_from_the_dataset_metadata(models):
    from hope_models.data.cache import load_or_build

    cache, _ = load_or_build(models["demos"], models["root"] / "cache")
    assert sim_task(cache) == "reach"


# -- run_trainer.py promote -----------------------------------------------------------------------------

def test_promote_cli_promotes_refuses_and_records_why(models, home, capsys):
    code, out = cli(capsys, "promote", "--checkpoint", str(models["weak"]), "--json")
    assert code == 0 and out["promoted"] is True, out
    weak_id = out["model_id"]
    pointer = read_pointer(home, "fast_loop")
    assert pointer["version"] == checkpoint_version(models["weak"])[0] == out["version"]
    assert pointer["checkpoint"] == str(models["weak"].resolve())

    code, out = cli(capsys, "promote", "--checkpoint", str(models["good"]), "--json")
    assert code == 0 and out["promoted"] is True, out
    good_id = out["model_id"]
    assert read_pointer(home, "fast_loop")["model_id"] == good_id

    code, out = cli(capsys, "promote", "--checkpoint", str(models["weak"].parent.parent), "--json")  # a run dir
    assert code == 1 and out["promoted"] is False
    assert any("worse by more than 5%" in r for r in out["reasons"])
    assert read_pointer(home, "fast_loop")["model_id"] == good_id  # unchanged

    with Registry.open(load_settings(home, env={})) as reg, reg.session(readonly=True) as s:
        refused = s.get(Model, out["model_id"])
        assert refused.promoted_at is None and refused.gate_result["passed"] is False
        assert any("worse by more than 5%" in r for r in refused.gate_result["reasons"])
        assert refused.metrics["ratio"] > 1.05
        good = s.get(Model, good_id)
        assert good.promoted_at is not None and good.previous_model_id == weak_id
        assert s.get(Model, weak_id).demoted_at is not None


def test_promote_cli_force_and_nan(models, home, capsys, tmp_path):
    assert cli(capsys, "promote", "--checkpoint", str(models["good"]), "--json")[0] == 0
    code, out = cli(capsys, "promote", "--checkpoint", str(models["weak"]), "--force", "--json")
    assert code == 0 and out["promoted"] is True and out["forced"] is True
    bad = copy_run(models["good"], tmp_path, "nan_run")
    poison_with_nan(bad)
    code, out = cli(capsys, "promote", "--checkpoint", str(bad), "--force", "--json")
    assert code == 1 and out["promoted"] is False and out["forced"] is False
    assert any("non-finite" in r for r in out["reasons"])
    assert any("--force ignored" in r for r in out["reasons"])
    assert read_pointer(home, "fast_loop")["version"] == checkpoint_version(models["weak"])[0]
    with Registry.open(load_settings(home, env={})) as reg, reg.session(readonly=True) as s:
        row = s.get(Model, out["model_id"])
        assert row.promoted_at is None and row.metrics["finite"] is False
        assert any("non-finite" in r for r in row.gate_result["reasons"])


def test_promote_cli_by_run_id_and_usage_errors(models, home, capsys):
    st = load_settings(home, env={})
    with Registry.open(st) as reg:
        run_id = completed_run(reg, models["good"].parent.parent, data=models["demos"])
        from registry import runs
        with reg.session() as s:
            queued = runs.create_run(s, component="fast_loop", config={}, total_steps=5, run_dir="/nowhere").id
    code, out = cli(capsys, "promote", run_id, "--component", "fast_loop", "--json")
    assert code == 0 and out["run_id"] == run_id and out["promoted"] is True
    # again: already the promoted one
    code, out = cli(capsys, "promote", run_id, "--json")
    assert code == 0 and out.get("already") is True
    # --auto on a run that already has a candidate row: skipped, nothing new recorded
    code, out = cli(capsys, "promote", run_id, "--auto", "--json")
    assert code == 0 and out["promoted"] is False and "already has a candidate" in out["skipped"]

    for argv, expect in [
        (["promote", "r-missing", "--json"], "no run r-missing"),
        (["promote", queued, "--json"], "is queued; only a completed run"),
        (["promote", run_id, "--checkpoint", str(models["good"]), "--json"], "exactly one"),
        (["promote", "--json"], "exactly one"),
        (["promote", run_id, "--component", "vqvae", "--json"], "not a vqvae"),
        (["promote", "--checkpoint", str(home / "nope"), "--json"], "no such checkpoint"),
    ]:
        code, out = cli(capsys, *argv)
        assert code == 2, (argv, out)
        assert out["promoted"] is False and expect in out["error"], (argv, out)
    with Registry.open(st) as reg, reg.session(readonly=True) as s:
        assert len(promotion.history(s, "fast_loop")) == 1


def test_eval_reflex_reads_the_pointer_promote_writes(models, home, capsys):
    from hope_models.cli.eval_reflex import resolve_promoted

    cli(capsys, "promote", "--checkpoint", str(models["good"]), "--json")
    assert resolve_promoted(Path(home)) == models["good"].resolve()


# -- the reflex check after serving (registry/gating.py) -------------------------------------------

def test_a_candidate_worse_in_simulation_is_served_then_rolled_back(models, home, capsys, monkeypatch):
    """What moving the reflex check after serving costs, shown: the weak fast_loop (its val_loss let
    through) is served, then rolled back once its episodes score below the promoted one's; a
    BrainService following the pointer serves it only for the check's duration."""
    import time

    from hope_models.runtime.brain_service import BrainService

    monkeypatch.setenv("HOPE_GATE_VAL_TOLERANCE", "100")
    code, out = cli(capsys, "promote", "--checkpoint", str(models["good"]), "--json")
    assert code == 0 and out["promoted"] is True and out["after_serving"]["passed"] is True, out
    good_v, weak_v = out["version"], checkpoint_version(models["weak"])[0]
    swaps: list[tuple[str, float]] = []
    brain = BrainService(home, components=("fast_loop",), poll_s=0.02,
                         on_swap=lambda comp, version, ckpt: swaps.append((version, time.monotonic())))
    brain.start()
    try:
        code, out = cli(capsys, "promote", "--checkpoint", str(models["weak"]), "--json")
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and (not swaps or swaps[-1][0] != good_v):
            time.sleep(0.02)
    finally:
        brain.stop()
    assert code == 1 and out["promoted"] is False and out["rolled_back"] is True, out
    after = out["after_serving"]
    assert after["passed"] is False and "worse by more than the tolerance" in after["detail"]
    assert after["reflex"]["candidate_mean_return"] < after["reflex"]["promoted_mean_return"] - 50
    assert out["reasons"][0] == after["detail"]
    assert read_pointer(home, "fast_loop")["version"] == good_v
    versions = [v for v, _ in swaps]
    assert versions[0] == good_v and weak_v in versions and versions[-1] == good_v, versions
    served = next(t for v, t in swaps if v == weak_v)
    back = next(t for v, t in swaps if v == good_v and t > served)
    # served for the check's duration, then the rollback's write, one 20 ms poll and a load (margin for
    # a loaded machine)
    assert back - served <= after["seconds"] + 2.0
    with Registry.open(load_settings(home, env={})) as reg, reg.session(readonly=True) as s:
        weak = s.get(Model, out["model_id"])
        assert weak.promoted_at is None and weak.demoted_at is not None
        assert weak.gate_result["passed"] is True and weak.gate_result["after_serving"]["passed"] is False
        assert promotion.promoted(s, "fast_loop").version == good_v


def test_the_reflex_check_before_serving_when_configured(models, home, capsys, monkeypatch):
    monkeypatch.setenv("HOPE_GATE_VAL_TOLERANCE", "100")
    monkeypatch.setenv("HOPE_GATE_REFLEX_AFTER_SERVING", "0")
    assert cli(capsys, "promote", "--checkpoint", str(models["good"]), "--json")[0] == 0
    writes: list[str] = []
    real = promotion.write_pointer
    monkeypatch.setattr(promotion, "write_pointer", lambda home_, comp, obj: (writes.append(obj["version"]),
                                                                             real(home_, comp, obj)))
    code, out = cli(capsys, "promote", "--checkpoint", str(models["weak"]), "--json")
    assert code == 1 and out["promoted"] is False and "after_serving" not in out
    assert any("reflex mean return" in r for r in out["reasons"])
    assert writes == []  # never served



# -- a check interrupted after serving (registry/gating.py finish_owed_checks) ---------------------------

def serve_directly(home: Path, ckpt: Path) -> int:
    """`ckpt` recorded and served with no gate (the model a candidate replaces); its model id."""
    st = load_settings(home, env={})
    with Registry.open(st) as reg, reg.session() as s:
        model = promotion.record_candidate(s, component="fast_loop", checkpoint_path=ckpt,
                                           version=checkpoint_version(ckpt)[0], run_id=None, metrics={},
                                           gate_result={"passed": True})
        return promotion.promote(s, st, model.id).id


def promote_killed_during_the_check(home: Path, monkeypatch, capsys, ckpt: Path) -> int:
    """`promote --checkpoint ckpt` whose process dies as its reflex check after serving starts (the
    candidate is served by then); the candidate's model id, which owes the check."""
    from registry import gating

    def killed(*_args, **_kwargs):
        raise SystemExit(-9)

    with monkeypatch.context() as m:
        m.setattr(gating, "check_after_serving", killed)
        with pytest.raises(SystemExit):
            run_trainer.main(["promote", "--checkpoint", str(ckpt), "--json"])
    capsys.readouterr()
    assert read_pointer(home, "fast_loop")["checkpoint"] == str(ckpt.resolve())  # served, unchecked
    with Registry.open(load_settings(home, env={})) as reg, reg.session(readonly=True) as s:
        (owed,) = gating.owed_checks(s)
        assert owed.checkpoint_path == str(ckpt.resolve()) and "after_serving" not in owed.gate_result
        assert owed.metrics["reflex"]["after_serving"] is True
        return owed.id


def test_an_interrupted_check_of_a_worse_candidate_is_finished_and_rolls_it_back(models, home, capsys, monkeypatch):
    monkeypatch.setenv("HOPE_GATE_VAL_TOLERANCE", "100")  # the weak one's val_loss let through
    good_id = serve_directly(home, models["good"])
    weak_id = promote_killed_during_the_check(home, monkeypatch, capsys, models["weak"])

    code, out = cli(capsys, "promote", "--finish-checks", "--json")
    assert code == 1 and out["rolled_back"] is True, out
    (done,) = out["finished"]
    assert done["model_id"] == weak_id and done["rolled_back"] is True
    assert done["after_serving"]["passed"] is False and "worse by more than the tolerance" in done["after_serving"]["detail"]
    assert read_pointer(home, "fast_loop")["model_id"] == good_id
    with Registry.open(load_settings(home, env={})) as reg, reg.session(readonly=True) as s:
        weak = s.get(Model, weak_id)
        assert weak.promoted_at is None and weak.gate_result["after_serving"]["passed"] is False
        assert weak.metrics["reflex"]["candidate_mean_return"] < weak.metrics["reflex"]["promoted_mean_return"]
    assert cli(capsys, "promote", "--finish-checks", "--json") == (0, {"finished": [], "rolled_back": False})
    code, out = cli(capsys, "promote", "--finish-checks", "--checkpoint", str(models["good"]), "--json")
    assert code == 2 and "--finish-checks takes no --checkpoint" in out["error"]


def test_an_interrupted_check_of_a_better_candidate_is_finished_and_recorded(models, home, capsys, monkeypatch):
    from registry.gating import finish_owed_checks, promote_lock

    serve_directly(home, models["weak"])
    good_id = promote_killed_during_the_check(home, monkeypatch, capsys, models["good"])
    st = load_settings(home, env=ENV)  # 2 episodes
    with Registry.open(st) as reg:
        with promote_lock(home):
            code, out = finish_owed_checks(st, reg)
        assert code == 0 and out["rolled_back"] is False, out
        assert [e["model_id"] for e in out["finished"]] == [good_id] and out["finished"][0]["after_serving"]["passed"]
        with reg.session(readonly=True) as s:
            good = s.get(Model, good_id)
            assert good.promoted_at is not None and good.gate_result["after_serving"]["passed"] is True
            assert good.metrics["reflex"]["episodes"] == 2
    assert read_pointer(home, "fast_loop")["model_id"] == good_id
