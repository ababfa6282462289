"""The run registry: state machine, control requests, dispatch order, the worker's claim/finish
protocol, recovery, and SQLite under several writing processes."""
from __future__ import annotations

import itertools
import json
import subprocess
import sys
import textwrap
from datetime import datetime, timedelta, timezone

import pytest
from sqlalchemy.exc import IntegrityError, StatementError

from registry import runs
from registry.db import Registry, RegistryError, db_path
from registry.models import Model, Run, new_run_id, utcnow
from registry.runs import RunError
from hope_models.settings import load_settings

REPO = __import__("pathlib").Path(__file__).resolve().parents[1]


@pytest.fixture
def settings(tmp_path):
    return load_settings(tmp_path / "home", env={})


@pytest.fixture
def reg(settings):
    registry = Registry.open(settings)
    yield registry
    registry.close()


@pytest.fixture(scope="module")
def shared_reg(tmp_path_factory):
    """One registry for the large parametrised tables (each case makes its own runs)."""
    registry = Registry.open(load_settings(tmp_path_factory.mktemp("shared") / "home", env={}))
    yield registry
    registry.close()


def make(s, component="vqvae", **kw) -> Run:
    kw.setdefault("config", {"threads": 1})
    kw.setdefault("total_steps", 40)
    kw.setdefault("run_dir", "/tmp/hope-test-run")
    return runs.create_run(s, component=component, **kw)


def force(run: Run, state: str, **fields) -> Run:
    """Put a run straight into a state (test setup only; the API never skips transitions)."""
    run.state = state
    for k, v in fields.items():
        setattr(run, k, v)
    return run


def states_of(s, run_id):
    return [(e.payload["from"], e.payload["state"]) for e in runs.run_events(s, run_id, kinds=["state"])]


def dispatch_and_claim(s, run: Run, task="t-1", pid=4242) -> Run:
    runs.mark_dispatched(s, run, task)
    claimed = runs.claim(s, run.id, task, run.attempt, "host-a", pid)
    assert claimed is not None
    return claimed


# --- opening -------------------------------------------------------------------------------

def test_open_creates_home_and_db_with_pragmas(settings):
    assert not db_path(settings).exists()
    with Registry.open(settings) as reg:
        assert db_path(settings) == settings.home / "hope.db" and db_path(settings).is_file()
        with reg.engine.connect() as c:
            assert c.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
            assert c.exec_driver_sql("PRAGMA busy_timeout").scalar() == 30000
            assert c.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
            assert c.exec_driver_sql("PRAGMA synchronous").scalar() == 1  # NORMAL


def test_open_without_migrate_refuses_an_empty_database(settings):
    with pytest.raises(RegistryError, match="hope.db.*not set up"):
        Registry.open(settings, migrate=False)
    Registry.open(settings).close()
    Registry.open(settings, migrate=False).close()  # migrated once: fine


def test_session_rolls_back_on_error(reg):
    with pytest.raises(RuntimeError):
        with reg.session() as s:
            rid = make(s).id
            raise RuntimeError("boom")
    with reg.session(readonly=True) as s:
        with pytest.raises(RunError, match=f"no run {rid} .*run_trainer.py status"):
            runs.get_run(s, rid)


def test_session_objects_usable_after_commit(reg):
    with reg.session() as s:
        run = make(s)
    assert run.state == "queued" and run.created_at.tzinfo is not None  # expire_on_commit=False


# --- create / list / events -----------------------------------------------------------------

def test_create_run_defaults_and_json(reg):
    with reg.session() as s:
        run = make(s, config={"data": "/d", "lr": 1e-3, "vqvae_run": None}, dataset_fingerprint="fp")
    with reg.session(readonly=True) as s:
        run = runs.get_run(s, run.id)
        obj = run.to_json_obj()
    assert run.id.startswith("r-") and len(run.id) == len("r-20250101-120000-abcdef")
    assert obj["state"] == "queued" and obj["step"] == 0 and obj["total_steps"] == 40
    assert obj["queue"] == "pi" and obj["priority"] == 0 and obj["attempt"] == 1 and obj["max_attempts"] == 3
    assert obj["desired_state"] == "run" and obj["throttle_level"] == 0 and obj["error"] is None
    assert obj["config"] == {"data": "/d", "lr": 1e-3, "vqvae_run": None}
    assert datetime.fromisoformat(obj["created_at"]).utcoffset() == timedelta(0)
    assert obj["queued_at"] == obj["created_at"] and obj["started_at"] is None
    json.dumps(obj)  # everything in it is JSON
    required = {"id", "component", "state", "step", "total_steps", "pause_reason", "desired_state",
                "throttle_level", "attempt", "max_attempts", "queue", "priority", "sequence_id",
                "sequence_index", "loss", "steps_per_s", "error", "last_checkpoint", "run_dir",
                "created_at", "started_at", "finished_at", "config"}
    assert required <= obj.keys()


@pytest.mark.parametrize(
    "kw, match",
    [
        ({"component": "brain"}, "component 'brain'"),
        ({"total_steps": 0}, "total_steps"),
        ({"total_steps": 2.5}, "total_steps"),
        ({"queue": "GPU box"}, "queue 'GPU box'"),
        ({"queue": ""}, "queue"),
        ({"priority": "high"}, "priority"),
        ({"max_attempts": 0}, "max_attempts"),
        ({"run_dir": ""}, "run_dir"),
        ({"config": [1, 2]}, "config must be a JSON object"),
        ({"config": {"lr": float("nan")}}, "config is not JSON"),
        ({"config": {"p": object()}}, "config is not JSON"),
        ({"sequence_id": "q-1"}, "sequence_id and sequence_index"),
        ({"sequence_id": "q-1", "sequence_index": -1}, "sequence_index"),
    ],
)
def test_create_run_validates(shared_reg, kw, match):
    kw = {"component": "vqvae", **kw}
    with shared_reg.session() as s:
        with pytest.raises(RunError, match=match) as err:
            make(s, run_id="r-fixed-id", **kw)
    assert "r-fixed-id" in str(err.value)  # every message names the run


def test_create_run_refuses_duplicate_id(reg):
    with reg.session() as s:
        make(s, run_id="r-dup")
    with reg.session() as s:
        with pytest.raises(RunError, match="r-dup already exists"):
            make(s, run_id="r-dup")


def test_new_run_id_format():
    rid = new_run_id(datetime(2025, 3, 4, 5, 6, 7, tzinfo=timezone.utc))
    assert rid.startswith("r-20250304-050607-") and len(rid.rsplit("-", 1)[1]) == 6
    assert new_run_id() != new_run_id()


def test_naive_datetimes_are_refused(reg):
    with pytest.raises(StatementError, match="naive datetime"):
        with reg.session() as s:
            run = make(s)
            run.heartbeat_at = datetime.now()  # no tzinfo
            s.flush()


def test_list_runs_newest_first_and_filters(reg):
    with reg.session() as s:
        base = utcnow()
        ids = []
        for i in range(4):
            run = make(s)
            run.created_at = base + timedelta(seconds=i)
            ids.append(run.id)
        runs.request_control(s, ids[1], "cancel")
    with reg.session(readonly=True) as s:
        assert [r.id for r in runs.list_runs(s)] == ids[::-1]
        assert [r.id for r in runs.list_runs(s, limit=2)] == ids[:1:-1]
        assert [r.id for r in runs.list_runs(s, states=["cancelled"])] == [ids[1]]
        with pytest.raises(RunError, match="unknown state"):
            runs.list_runs(s, states=["done"])


def test_events_api(reg):
    with reg.session() as s:
        a, b = make(s).id, make(s).id
        runs.add_event(s, a, "progress", {"step": 1, "loss": float("nan"), "eta_s": float("inf")})
        runs.add_event(s, b, "log", {"level": "info", "message": "hi"})
        runs.add_event(s, a, "metric", {"val_loss": 0.5})
        with pytest.raises(RunError, match=f"run {a}: event kind 'bogus'"):
            runs.add_event(s, a, "bogus", {})
        with pytest.raises(RunError, match="no run r-missing"):
            runs.add_event(s, "r-missing", "log", {"message": "x"})
    with reg.session(readonly=True) as s:
        every = runs.events_after(s, 0)
        assert [e.id for e in every] == sorted(e.id for e in every) and len(every) == 5  # 2 created + 3
        assert [e.kind for e in runs.events_after(s, every[2].id)] == ["log", "metric"]
        assert len(runs.events_after(s, 0, limit=2)) == 2
        assert [e.kind for e in runs.run_events(s, a)] == ["state", "progress", "metric"]
        progress = runs.run_events(s, a, kinds=["progress"])
        assert progress[0].payload == {"step": 1, "loss": None, "eta_s": None}  # no NaN in JSON
        assert runs.run_events(s, a, after_id=progress[0].id)[0].kind == "metric"
        obj = progress[0].to_json_obj()
        assert obj["run_id"] == a and obj["kind"] == "progress" and obj["time"].endswith("+00:00")


# --- the state machine table ----------------------------------------------------------------

ALL_PAIRS = list(itertools.product(runs.STATES, runs.STATES))


@pytest.mark.parametrize("old, new", ALL_PAIRS, ids=[f"{a}->{b}" for a, b in ALL_PAIRS])
def test_transition_table(shared_reg, old, new):
    allowed = new in runs.ALLOWED[old]
    with shared_reg.session() as s:
        run = force(make(s), old, desired_state="pause", requested_reason="user", worker_pid=7,
                    worker_host="h", throttle_level=2, pause_reason="user" if old == "paused" else None)
        before = len(runs.run_events(s, run.id))
        if not allowed:
            with pytest.raises(RunError, match=f"run {run.id}: cannot go from {old} to {new}"):
                runs.transition(s, run, new, reason="thermal")
            assert run.state == old and len(runs.run_events(s, run.id)) == before
            return
        runs.transition(s, run, new, reason="thermal", message="why")
        assert run.state == new
        ev = runs.run_events(s, run.id)[-1]
        assert ev.kind == "state" and ev.payload == {"state": new, "from": old, "reason": "thermal", "message": "why"}
        assert (run.finished_at is not None) == (new in runs.TERMINAL)
        assert run.pause_reason == ("thermal" if new == "paused" else None)
        if old in runs.ACTIVE and new not in runs.ACTIVE:  # the child's claim and the served request are cleared
            assert (run.worker_pid, run.worker_host, run.desired_state, run.requested_reason, run.throttle_level) \
                == (None, None, "run", None, 0)
        if (old, new) == ("starting", "running"):  # claimed: what the dispatch set (throttle level) is kept
            assert run.throttle_level == 2
        if new == "queued":
            assert run.desired_state == "run" and run.queued_at >= run.created_at
        if new == "failed":
            assert run.error_message == "why"


def test_transition_table_is_the_documented_one():
    assert runs.ALLOWED == {
        "queued": {"starting", "cancelled", "paused"},
        "starting": {"running", "queued", "cancelled", "paused"},
        "running": {"paused", "completed", "failed", "cancelled", "interrupted", "queued"},
        "paused": {"queued", "cancelled"},
        "interrupted": {"queued", "failed", "cancelled"},
        "completed": set(), "failed": set(), "cancelled": set(),
    }
    assert runs.TERMINAL == {"completed", "failed", "cancelled"} and runs.ACTIVE == {"starting", "running"}


def test_transition_refuses_unknown_state_and_pause_without_reason(reg):
    with reg.session() as s:
        run = make(s)
        with pytest.raises(RunError, match="unknown state 'done'"):
            runs.transition(s, run, "done")
        with pytest.raises(RunError, match="pause reason None"):
            runs.transition(s, run, "paused")


# --- request_control ------------------------------------------------------------------------

# (state, desired_state, action) -> (state, desired_state, requested_reason, pause_reason) or an error match
CONTROL_TABLE = [
    ("queued", "run", "cancel", ("cancelled", "run", None, None)),
    ("queued", "run", "pause", ("paused", "run", None, "user")),
    ("queued", "run", "resume", ("queued", "run", None, None)),
    # sent to its queue, no child yet: done at once, like a queued run
    ("starting", "run", "cancel", ("cancelled", "run", None, None)),
    ("starting", "run", "pause", ("paused", "run", None, "user")),
    ("starting", "run", "resume", ("starting", "run", None, None)),
    ("running", "run", "cancel", ("running", "cancel", "user", None)),
    ("running", "run", "pause", ("running", "pause", "user", None)),
    ("running", "run", "resume", ("running", "run", None, None)),
    ("running", "pause", "resume", ("running", "run", None, None)),
    ("running", "pause", "cancel", ("running", "cancel", "user", None)),
    ("running", "cancel", "cancel", ("running", "cancel", "user", None)),
    ("running", "cancel", "pause", "a cancel is already requested"),
    ("running", "cancel", "resume", "a cancel is already requested"),
    ("paused", "run", "cancel", ("cancelled", "run", None, None)),
    ("paused", "run", "pause", ("paused", "run", None, "thermal")),
    ("paused", "run", "resume", ("queued", "run", None, None)),
    ("interrupted", "run", "cancel", ("cancelled", "run", None, None)),
    ("interrupted", "run", "pause", "interrupted and about to be requeued"),
    ("interrupted", "run", "resume", ("interrupted", "run", None, None)),
    ("completed", "run", "cancel", "is completed; nothing to cancel"),
    ("failed", "run", "pause", "is failed; nothing to pause"),
    ("cancelled", "run", "resume", "is cancelled; nothing to resume"),
]


@pytest.mark.parametrize("state, desired, action, expected", CONTROL_TABLE,
                         ids=[f"{a}/{b}/{c}" for a, b, c, _ in CONTROL_TABLE])
def test_request_control_table(shared_reg, state, desired, action, expected):
    with shared_reg.session() as s:
        run = force(make(s), state, desired_state=desired,
                    requested_reason="user" if desired != "run" else None,
                    pause_reason="thermal" if state == "paused" else None,
                    worker_pid=99 if state == "running" else None)
        rid = run.id
    if isinstance(expected, str):
        with shared_reg.session() as s:
            with pytest.raises(RunError, match=f"run {rid}.*{expected}"):
                runs.request_control(s, rid, action)
        return
    with shared_reg.session() as s:
        runs.request_control(s, rid, action)
    with shared_reg.session(readonly=True) as s:
        run = runs.get_run(s, rid)
        assert (run.state, run.desired_state, run.requested_reason, run.pause_reason) == expected
        logs = runs.run_events(s, rid, kinds=["log"])
        assert len(logs) == 1 and action in logs[0].payload["message"]  # each request is recorded
        if expected[0] != state:
            assert states_of(s, rid)[-1] == (state, expected[0])


def test_request_control_unknown_action_and_run(reg):
    with reg.session() as s:
        rid = make(s).id
        with pytest.raises(RunError, match=f"run {rid}: action 'stop'"):
            runs.request_control(s, rid, "stop")
        with pytest.raises(RunError, match="no run r-nope"):
            runs.request_control(s, "r-nope", "cancel")


# --- next_dispatchable ------------------------------------------------------------------------

def _queued(s, n, **kw):
    base = utcnow() - timedelta(hours=1)
    out = []
    for i in range(n):
        run = make(s, **kw)
        run.queued_at = base + timedelta(seconds=i)
        out.append(run)
    return out


def test_dispatch_fifo_then_priority(reg):
    with reg.session() as s:
        a, b, c = _queued(s, 3)
        assert runs.next_dispatchable(s, "pi").id == a.id
        c.priority = 5
        assert runs.next_dispatchable(s, "pi").id == c.id
        b.priority = 5
        assert runs.next_dispatchable(s, "pi").id == b.id  # same priority: older queued_at first
        b.priority = -1
        c.priority = 0
        assert runs.next_dispatchable(s, "pi").id == a.id


def test_dispatch_one_active_per_queue(reg):
    with reg.session() as s:
        a, b = _queued(s, 2)
        g = make(s, queue="gpu")
        dispatch_and_claim(s, runs.next_dispatchable(s, "pi"), task="t-a")
        assert runs.next_dispatchable(s, "pi") is None  # a runs
        assert runs.next_dispatchable(s, "gpu").id == g.id  # other queues are independent
        assert runs.next_dispatchable(s, "nothing-here") is None
        runs.request_control(s, b.id, "pause")
        runs.finish(s, a.id, 4242, "completed", "done", step=40, last_checkpoint=None)
    with reg.session() as s:
        assert runs.get_run(s, a.id).state == "completed"
        assert runs.next_dispatchable(s, "pi") is None  # b is paused, not queued
        runs.request_control(s, b.id, "resume")
        assert runs.next_dispatchable(s, "pi").id == b.id


def test_dispatch_requeued_run_keeps_its_place_user_resume_goes_to_the_back(reg):
    with reg.session() as s:
        a, b, c = _queued(s, 3)
        run = dispatch_and_claim(s, runs.next_dispatchable(s, "pi"))
        assert run.id == a.id
        runs.mark_interrupted(s, run, "worker died")  # knocked out by the system: still first in line
        assert runs.next_dispatchable(s, "pi").id == a.id
        run = dispatch_and_claim(s, a, task="t-2")
        runs.request_shutdown(s, run)
        runs.finish(s, a.id, 4242, "paused_user", "stopped", step=3, last_checkpoint="c")
        assert runs.next_dispatchable(s, "pi").id == a.id
        run = dispatch_and_claim(s, a, task="t-3")
        runs.finish(s, a.id, 4242, "paused_memory", "memory", step=4, last_checkpoint="c")
        runs.transition(s, a, "queued", reason="memory", message="memory available again")
        assert runs.next_dispatchable(s, "pi").id == a.id
        runs.request_control(s, a.id, "pause")
        runs.request_control(s, a.id, "resume")  # the user's resume: behind b and c
        assert runs.next_dispatchable(s, "pi").id == b.id
        runs.request_control(s, b.id, "cancel")
        runs.request_control(s, c.id, "cancel")
        assert runs.next_dispatchable(s, "pi").id == a.id


def _chain(s, n=3, queue="pi"):
    seq = "q-test-" + new_run_id()
    out = []
    for i, comp in enumerate(["vqvae", "fast_loop", "mid_loop"][:n]):
        out.append(make(s, component=comp, sequence_id=seq, sequence_index=i, queue=queue))
    return seq, out


def test_dispatch_chain_in_order(reg):
    with reg.session() as s:
        seq, (v, f, m) = _chain(s)
        assert [r.id for r in runs.sequence_runs(s, seq)] == [v.id, f.id, m.id]
        other = make(s)  # queued after the chain
        for expected in (v, f, m, other):
            run = runs.next_dispatchable(s, "pi")
            assert run.id == expected.id
            dispatch_and_claim(s, run, task=f"t-{run.id}")
            assert runs.next_dispatchable(s, "pi") is None
            runs.finish(s, run.id, 4242, "completed", "ok", step=40, last_checkpoint="c")


def test_dispatch_chain_waits_for_paused_predecessor_and_lets_others_pass(reg):
    with reg.session() as s:
        seq, (v, f, m) = _chain(s)
        other = make(s)
        run = dispatch_and_claim(s, runs.next_dispatchable(s, "pi"))
        assert run.id == v.id
        runs.finish(s, v.id, 4242, "paused_memory", "memory", step=10, last_checkpoint="c")
        # v is paused: f and m must wait, the unrelated run may go
        assert runs.next_dispatchable(s, "pi").id == other.id
        assert runs.get_run(s, f.id).state == "queued"


@pytest.mark.parametrize("outcome", ["failed", "cancelled"])
def test_dispatch_chain_cancelled_after_failed_predecessor(reg, outcome):
    with reg.session() as s:
        seq, (v, f, m) = _chain(s)
        other = make(s)
        dispatch_and_claim(s, runs.next_dispatchable(s, "pi"))
        runs.finish(s, v.id, 4242, outcome, "nan loss", step=3, last_checkpoint=None)
        assert runs.next_dispatchable(s, "pi").id == other.id
        f_run, m_run = runs.get_run(s, f.id), runs.get_run(s, m.id)
        assert f_run.state == "cancelled" and m_run.state == "cancelled"
        assert f_run.error_message == f"previous run {v.id} in sequence {seq} ended {outcome}"
        assert m_run.error_message == f"previous run {f.id} in sequence {seq} ended cancelled"
        assert states_of(s, f.id)[-1] == ("queued", "cancelled")


def test_cancelling_a_chain_member_that_has_not_started_cancels_the_rest_at_once(reg):
    with reg.session() as s:
        seq, (v, f, m) = _chain(s)
        blocker = dispatch_and_claim(s, make(s, queue="pi"))  # the queue is busy: nothing dispatches
        runs.request_control(s, v.id, "cancel")
        assert [runs.get_run(s, r.id).state for r in (v, f, m)] == ["cancelled"] * 3
        assert runs.get_run(s, f.id).error_message == f"previous run {v.id} in sequence {seq} ended cancelled"
        assert runs.get_run(s, blocker.id).state == "running"
        # a later member cancelled on its own leaves the ones before it alone
        seq2, (v2, f2, m2) = _chain(s)
        runs.request_control(s, f2.id, "cancel")
        assert [runs.get_run(s, r.id).state for r in (v2, f2, m2)] == ["queued", "cancelled", "cancelled"]


def test_dispatch_chain_member_with_missing_predecessor_is_cancelled(reg):
    with reg.session() as s:
        orphan = make(s, sequence_id="q-orphan", sequence_index=1)
        assert runs.next_dispatchable(s, "pi") is None
        assert runs.get_run(s, orphan.id).state == "cancelled"
        assert "does not exist" in orphan.error_message


# --- worker protocol: dispatch, claim, heartbeat, finish ---------------------------------------

def test_claim_refuses_stale_tasks(reg):
    with reg.session() as s:
        run = make(s)
        rid = run.id
        assert runs.claim(s, rid, "t-1", 1, "h", 1) is None  # not dispatched yet
        runs.mark_dispatched(s, run, "t-1")
        assert run.heartbeat_at is not None and run.celery_task_id == "t-1" and run.started_at is None
    with reg.session() as s:
        assert runs.claim(s, rid, "t-0", 1, "h", 1) is None  # another task id
        assert runs.claim(s, rid, "t-1", 2, "h", 1) is None  # another attempt
        runs.resend(s, runs.get_run(s, rid), "t-2")  # never picked up: re-sent
        assert runs.claim(s, rid, "t-1", 1, "h", 1) is None  # the old delivery arrives late
        claimed = runs.claim(s, rid, "t-2", 1, "host-b", 321)
        assert claimed is not None and claimed.worker_pid == 321 and claimed.worker_host == "host-b"
        assert claimed.started_at is not None
        assert runs.claim(s, rid, "t-2", 1, "host-b", 322) is None  # a second delivery of the same task
        with pytest.raises(RunError, match="only a starting .* run can be re-sent"):
            runs.resend(s, claimed, "t-3")
    with reg.session(readonly=True) as s:
        run = runs.get_run(s, rid)
        assert run.worker_pid == 321 and run.celery_task_id == "t-2"
        logs = [e.payload["message"] for e in runs.run_events(s, rid, kinds=["log"])]
        assert any("re-sent as task t-2" in m for m in logs) and any("claimed by pid 321" in m for m in logs)


def test_a_sent_run_is_starting_until_a_child_claims_it_and_says_what_it_waits_for(reg):
    with reg.session() as s:
        first, behind = make(s, queue="gpu"), make(s, queue="gpu")
        runs.mark_dispatched(s, first, "t-1")
        assert first.state == "starting" and first.dispatched_at is not None and first.worker_pid is None
        obj = first.to_json_obj()
        assert obj["state"] == "starting" and obj["dispatched_at"] == first.dispatched_at.isoformat()
        assert obj["waiting"].startswith(f"waiting for a worker on queue 'gpu' since "
                                         f"{first.dispatched_at:%Y-%m-%d %H:%M:%S} UTC")
        assert "start one with: run_trainer.py worker -Q gpu" in obj["waiting"]
        # it holds its queue, and the run behind it says why it does not start
        assert runs.next_dispatchable(s, "gpu") is None
        held = {o["id"]: o["waiting"] for o in runs.to_json(s, [first, behind])}
        assert held[behind.id] == (f"behind run {first.id}, waiting for a worker on queue 'gpu' "
                                   "(one run per queue at a time)")
        runs.resend(s, first, "t-2")  # a re-send keeps the time it has waited since
        assert first.state == "starting" and first.to_json_obj()["waiting"] == obj["waiting"]
        claimed = runs.claim(s, first.id, "t-2", 1, "gpu-box", 77)
        assert claimed.state == "running" and claimed.to_json_obj()["waiting"] is None
        assert states_of(s, first.id)[-2:] == [("queued", "starting"), ("starting", "running")]
        assert runs.to_json(s, [behind])[0]["waiting"] == (f"behind run {first.id}, running on queue 'gpu' "
                                                           "(one run per queue at a time)")


def test_cancel_of_a_starting_run_ends_it_at_once_and_its_task_is_refused(reg):
    with reg.session() as s:
        run, nxt = make(s, queue="gpu"), make(s, queue="gpu")
        rid = run.id
        runs.mark_dispatched(s, run, "t-1")
    with reg.session() as s:
        cancelled = runs.request_control(s, rid, "cancel")
        assert cancelled.state == "cancelled" and cancelled.finished_at is not None
        assert cancelled.error_message == "cancelled by user" and cancelled.to_json_obj()["waiting"] is None
        assert "cancelled before a worker took it (task t-1" in runs.run_events(s, rid, kinds=["log"])[-1].payload["message"]
        assert runs.next_dispatchable(s, "gpu").id == nxt.id  # the queue is free again
    with reg.session() as s:  # a worker comes up later and takes the old message
        assert runs.claim(s, rid, "t-1", 1, "gpu-box", 78) is None
        assert runs.get_run(s, rid).state == "cancelled" and runs.get_run(s, rid).worker_pid is None


def test_pause_of_a_starting_run_is_at_once_and_resume_sends_it_again(reg):
    with reg.session() as s:
        run = make(s)
        rid = run.id
        runs.mark_dispatched(s, run, "t-1", throttle_level=1)
        runs.request_control(s, rid, "pause")
        assert (run.state, run.pause_reason, run.throttle_level) == ("paused", "user", 0)
        assert runs.claim(s, rid, "t-1", 1, "h", 1) is None
        runs.request_control(s, rid, "resume")
        runs.mark_dispatched(s, runs.next_dispatchable(s, "pi"), "t-2")
        assert runs.claim(s, rid, "t-1", 1, "h", 1) is None and runs.claim(s, rid, "t-2", 1, "h", 1) is not None


def test_heartbeat_is_pid_guarded(reg):
    with reg.session() as s:
        run = dispatch_and_claim(s, make(s), pid=50)
        first = run.heartbeat_at
        rid = run.id
    with reg.session() as s:
        assert runs.heartbeat(s, rid, 50, step=7, loss=1.25, steps_per_s=float("nan"), last_checkpoint="ck7")
        assert not runs.heartbeat(s, rid, 51, step=99)
        with pytest.raises(RunError, match="heartbeat fields \\['eta'\\]"):
            runs.heartbeat(s, rid, 50, eta=3)
    with reg.session(readonly=True) as s:
        run = runs.get_run(s, rid)
        assert (run.step, run.loss, run.steps_per_s, run.last_checkpoint) == (7, 1.25, None, "ck7")
        assert run.heartbeat_at > first


# (outcome, desired_state, requested_reason, throttle_level) -> (state, pause_reason, attempt)
FINISH_TABLE = [
    ("completed", "run", None, 0, ("completed", None)),
    ("failed", "run", None, 0, ("failed", None)),
    ("cancelled", "cancel", "user", 0, ("cancelled", None)),
    ("paused_memory", "run", None, 0, ("paused", "memory")),
    ("paused_user", "pause", "user", 0, ("paused", "user")),
    ("paused_user", "pause", "user", 2, ("paused", "user")),
    ("paused_user", "run", None, 2, ("paused", "thermal")),
    ("paused_user", "pause", None, 0, ("paused", "user")),
    ("paused_user", "pause", "shutdown", 0, ("queued", None)),
    ("paused_user", "pause", "shutdown", 2, ("queued", None)),
    ("completed", "pause", "shutdown", 0, ("completed", None)),
]


@pytest.mark.parametrize("outcome, desired, requested, level, expected", FINISH_TABLE,
                         ids=[f"{o}/{d}/{r}/{lv}" for o, d, r, lv, _ in FINISH_TABLE])
def test_finish_mapping(shared_reg, outcome, desired, requested, level, expected):
    with shared_reg.session() as s:
        run = dispatch_and_claim(s, make(s), pid=77)
        run.desired_state, run.requested_reason, run.throttle_level = desired, requested, level
        rid = run.id
    with shared_reg.session() as s:
        assert runs.finish(s, rid, 78, outcome, "msg", step=12, last_checkpoint="ck") is None  # stale pid
    with shared_reg.session(readonly=True) as s:
        assert runs.get_run(s, rid).state == "running"  # untouched
    with shared_reg.session() as s:
        out = runs.finish(s, rid, 77, outcome, "the message", step=12, last_checkpoint="ck-12")
        assert out is not None
    with shared_reg.session(readonly=True) as s:
        run = runs.get_run(s, rid)
        assert (run.state, run.pause_reason) == expected
        assert run.step == 12 and run.last_checkpoint == "ck-12" and run.attempt == 1
        assert run.worker_pid is None and run.desired_state == "run" and run.throttle_level == 0
        assert run.error_message == ("the message" if outcome in ("failed", "cancelled") else None)
        last = runs.run_events(s, rid, kinds=["state"])[-1].payload
        assert last["from"] == "running" and last["state"] == expected[0]
        if expected[0] == "queued":
            assert last["message"] == "stopped by shutdown; resumes on next start" and last["reason"] == "shutdown"
        if expected[0] in runs.TERMINAL:
            assert run.finished_at is not None
        # a finished run cannot be finished again
        assert runs.finish(s, rid, 77, "completed", "again", step=40, last_checkpoint=None) is None


def test_finish_refuses_unknown_outcome(reg):
    with reg.session() as s:
        rid = dispatch_and_claim(s, make(s)).id
        with pytest.raises(RunError, match=f"run {rid}: outcome 'done'"):
            runs.finish(s, rid, 4242, "done", "", step=1, last_checkpoint=None)


def test_request_shutdown_then_finish_requeues(reg):
    with reg.session() as s:
        run = dispatch_and_claim(s, make(s))
        with pytest.raises(RunError, match="only a running run"):
            runs.request_shutdown(s, make(s))
        runs.request_shutdown(s, run)
        assert (run.desired_state, run.requested_reason) == ("pause", "shutdown")
        runs.finish(s, run.id, 4242, "paused_user", "paused", step=5, last_checkpoint="c5")
        assert run.state == "queued" and run.attempt == 1 and run.step == 5
        assert runs.next_dispatchable(s, "pi").id == run.id


def test_shutdown_requeue_then_redispatch_same_attempt(reg):
    with reg.session() as s:
        run = dispatch_and_claim(s, make(s), task="t-1")
        runs.transition(s, run, "queued", reason="shutdown", message="lost task")
        assert run.attempt == 1 and run.worker_pid is None
        runs.mark_dispatched(s, run, "t-2")
        assert runs.claim(s, run.id, "t-1", 1, "h", 5) is None
        assert runs.claim(s, run.id, "t-2", 1, "h", 5) is not None


# --- recovery ---------------------------------------------------------------------------------

def test_mark_interrupted_retries_then_gives_up(reg):
    with reg.session() as s:
        run = make(s, max_attempts=3)
        rid = run.id
        for attempt in (1, 2):
            run = dispatch_and_claim(s, runs.next_dispatchable(s, "pi"), task=f"t-{attempt}", pid=100 + attempt)
            assert run.attempt == attempt
            runs.mark_interrupted(s, run, f"worker pid {100 + attempt} is gone")
            assert run.state == "queued" and run.attempt == attempt + 1 and run.worker_pid is None
        run = dispatch_and_claim(s, runs.next_dispatchable(s, "pi"), task="t-3", pid=103)
        assert runs.claim(s, rid, "t-2", 2, "h", 1) is None  # an old attempt's task is stale
        runs.mark_interrupted(s, run, "heartbeat 45 s old")
        assert run.state == "failed" and run.attempt == 3
        assert run.error_message == "gave up after 3 attempts: heartbeat 45 s old"
        assert runs.next_dispatchable(s, "pi") is None
        assert states_of(s, rid) == [
            (None, "queued"),
            ("queued", "starting"), ("starting", "running"), ("running", "interrupted"), ("interrupted", "queued"),
            ("queued", "starting"), ("starting", "running"), ("running", "interrupted"), ("interrupted", "queued"),
            ("queued", "starting"), ("starting", "running"), ("running", "interrupted"), ("interrupted", "failed"),
        ]
        msgs = [e.payload["message"] for e in runs.run_events(s, rid, kinds=["state"])]
        assert "attempt 2 of 3 after: worker pid 101 is gone" in msgs


def test_mark_interrupted_only_from_running(reg):
    with reg.session() as s:
        run = make(s)
        with pytest.raises(RunError, match="cannot go from queued to interrupted"):
            runs.mark_interrupted(s, run, "x")


# --- models table -----------------------------------------------------------------------------

def test_one_promoted_model_per_component(reg):
    now = utcnow()
    with reg.session() as s:
        rid = make(s).id
        s.add_all([
            Model(component="vqvae", checkpoint_path="/a", run_id=rid, metrics={"loss": 1.0}, promoted_at=now),
            Model(component="vqvae", checkpoint_path="/b", metrics=None),
            Model(component="vqvae", checkpoint_path="/c"),
            Model(component="fast_loop", checkpoint_path="/d", promoted_at=now),
        ])
    with pytest.raises(IntegrityError, match="UNIQUE constraint failed: models.component"):
        with reg.session() as s:
            s.add(Model(component="vqvae", checkpoint_path="/e", promoted_at=now))
    with reg.session() as s:  # demote, then promote another: fine
        old = s.query(Model).filter(Model.component == "vqvae", Model.promoted_at.is_not(None)).one()
        old.promoted_at = None
        s.flush()
        s.query(Model).filter(Model.checkpoint_path == "/b").one().promoted_at = now
    with reg.session(readonly=True) as s:
        promoted = s.query(Model).filter(Model.promoted_at.is_not(None)).order_by(Model.component).all()
        assert [(m.component, m.checkpoint_path) for m in promoted] == [("fast_loop", "/d"), ("vqvae", "/b")]
        assert s.query(Model).filter(Model.checkpoint_path == "/b").one().to_json_obj()["metrics"] is None


def test_foreign_keys_enforced(reg):
    with pytest.raises(IntegrityError, match="FOREIGN KEY"):
        with reg.session() as s:
            s.add(Model(component="vqvae", checkpoint_path="/x", run_id="r-missing"))


# --- several processes ------------------------------------------------------------------------

WRITER = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from hope_models.settings import load_settings
    from registry.db import Registry
    from registry import runs
    home, rid, n, tag = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4]
    reg = Registry.open(load_settings(home, env={}), migrate=False)
    go = Path(home) / "go"
    while not go.exists():
        time.sleep(0.005)
    for i in range(n):
        with reg.session() as s:  # read-modify-write: lost updates or "database is locked" if unsafe
            run = runs.get_run(s, rid)
            run.step = run.step + 1
            runs.add_event(s, rid, "log", {"message": f"{tag} {i}"})
        with reg.session(readonly=True) as s:
            runs.list_runs(s, limit=5)
    print("torch" in sys.modules)
    """
)


def test_concurrent_writers_from_two_processes(settings, reg):
    with reg.session() as s:
        rid = make(s).id
    n = 150
    procs = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(settings.home), rid, str(n), tag],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for tag in ("a", "b")
    ]
    (settings.home / "go").touch()
    outs = [p.communicate(timeout=60) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, f"writer failed:\n{err}"
        assert out.strip() == "False", "the registry must not import torch"
    with reg.session(readonly=True) as s:
        assert runs.get_run(s, rid).step == 2 * n  # no lost update
        logs = runs.run_events(s, rid, kinds=["log"])
        assert len(logs) == 2 * n
        assert {e.payload["message"].split()[0] for e in logs} == {"a", "b"}


def test_registry_modules_do_not_import_torch():
    code = "import sys; import registry.db, registry.models, registry.runs; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_threads_share_one_registry(reg):
    """The worker child writes from its main thread and a heartbeat thread through one Registry."""
    import threading

    with reg.session() as s:
        rid = dispatch_and_claim(s, make(s), pid=11).id
    errors: list[BaseException] = []

    def work(n: int) -> None:
        try:
            for i in range(n):
                with reg.session() as s:
                    runs.add_event(s, rid, "progress", {"step": i})
                    assert runs.heartbeat(s, rid, 11, step=i)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(60,)) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors, errors
    with reg.session(readonly=True) as s:
        assert len(runs.run_events(s, rid, kinds=["progress"])) == 180
