"""Continuous learning (daemon/continuous.py, registry/learning.py, webapp/api/learning.py) against a
real registry and a real inbox (episodes ingested by hope_models.rlds.ingest), with the host's
readings and the broker faked: each condition holds a start back and says so in the phase; a start
when all hold, with its reason recorded; no second start for the same episodes, across a restart;
the app's pause and resume through the API pause a running run and hold dispatch."""
from __future__ import annotations

import socket
from pathlib import Path

import pytest

from daemon.continuous import ContinuousLearning
from daemon.dispatch import Dispatcher
from daemon.service import Daemon
from daemon_fixtures import Home
from registry import learning, runs

HOST = socket.gethostname()
MIN_NEW = 4
COOL = {"temp_c": 50.0, "mem_available_mb": 6000.0}  # the budget is 3072 MB, thermal_soft_c 75 C


@pytest.fixture(scope="module")
def episode_dirs(tmp_path_factory) -> list[Path]:
    """~24 canonical episode dirs of 3.5-4 s at 10 Hz (obs 4, act 2): each can train every component."""
    from hope_models.data.synthetic import generate_dataset

    root = tmp_path_factory.mktemp("source") / "ds"
    generate_dataset(root, 24 * 37, obs_dim=4, act_dim=2, rates_hz=(10,), episode_seconds=(3.5, 4.0), seed=5)
    dirs = sorted(p for p in root.iterdir() if p.is_dir())
    assert len(dirs) >= 3 * MIN_NEW
    return dirs


@pytest.fixture
def home(tmp_path):
    h = Home(tmp_path / "home", extra_env={
        "HOPE_AUTO_TRAIN": "1", "HOPE_AUTO_TRAIN_MIN_NEW_EPISODES": str(MIN_NEW), "HOPE_AUTO_TRAIN_STEPS": "30",
        "HOPE_AUTO_TRAIN_COMPONENTS": "vqvae,fast_loop,mid_loop"})
    yield h
    h.close()


def hand_off(home: Home, dirs: list[Path]) -> None:
    from hope_models.intake.inbox import ingest_into_inbox

    out = ingest_into_inbox([str(d) for d in dirs], home.settings.inbox_dir, origin="test")
    assert all(r.get("action") == "written" for r in out["episodes"]), out


class Disk:
    """free_mb for the policy: the real figure unless a test lowers it."""

    def __init__(self):
        self.free: float | None = 50_000.0

    def __call__(self, _path):
        return self.free


def policy(home: Home, disk: Disk | None = None, autopromoter=None) -> ContinuousLearning:
    p = ContinuousLearning(home.settings, home.registry, local_queues=("pi",), free_mb=disk or Disk(),
                           disk_guard=Dispatcher(home.registry, home.settings).disk, autopromoter=autopromoter)
    p.start()
    return p


def status(home: Home) -> dict:
    with home.registry.session(readonly=True) as s:
        return learning.status(s, home.settings)


def chains(home: Home) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = {}
    for r in sorted(home.runs(), key=lambda r: (r["sequence_id"] or "", r["sequence_index"] or 0)):
        if r["sequence_id"]:
            out.setdefault(r["sequence_id"], []).append(r)
    return out


def complete_all(home: Home) -> None:
    with home.registry.session() as s:
        for run in runs.list_runs(s):
            if run.state not in runs.TERMINAL:
                run.state = "completed"


def test_each_condition_holds_the_start_back_and_says_so(home, episode_dirs):
    disk = Disk()
    p = policy(home, disk)
    d = p.tick(COOL)
    assert d.phase == "waiting for data" and d.data["more_needed"] == MIN_NEW and not chains(home)
    hand_off(home, episode_dirs[:MIN_NEW - 1])
    d = p.tick(COOL)
    assert d.phase == "waiting for data" and d.data["more_needed"] == 1
    assert status(home)["current_phase"] == "waiting for data (1 more)"
    hand_off(home, episode_dirs[MIN_NEW - 1:MIN_NEW])  # now enough: each host condition in turn
    for sample, level, phase in (({**COOL, "temp_c": 80.0}, 0, "waiting to cool"),
                                 (COOL, 1, "waiting to cool"),  # throttled (hysteresis) though the reading is low
                                 ({**COOL, "mem_available_mb": 1000.0}, 0, "waiting for memory")):
        d = p.tick(sample, level)
        assert d.phase == phase, d
        assert status(home)["phase"] == phase and not chains(home)
    assert "80.0 C" in p.tick({**COOL, "temp_c": 80.0}).detail
    disk.free = 100.0  # below the 200 MB margin the floor has at least
    d = p.tick(COOL)
    assert d.phase == "waiting for disk" and "100 MB free" in d.detail and not chains(home)
    disk.free = 50_000.0
    # a run queued by hand on the local queue: not idle
    other = home.enqueue(episode_dirs[0].parent, steps=10)
    assert p.tick(COOL).phase == "starting fast_loop" and set(chains(home)) == set()
    assert p.tick(COOL, 2).phase == "waiting to cool"  # dispatch starts nothing on a hot host
    with home.registry.session() as s:  # the host paused it (thermal): still not idle
        run = runs.get_run(s, other)
        run.state, run.pause_reason = "paused", "thermal"
    assert p.tick(COOL).phase == "waiting to cool"
    with home.registry.session() as s:
        runs.get_run(s, other).state = "cancelled"
    with home.registry.session() as s:  # paused from the app
        learning.pause(s)
    assert p.tick(COOL).phase == "paused" and status(home)["current_phase"] == "paused"
    with home.registry.session() as s:
        learning.resume(s)
    home.settings.auto_train = False
    assert p.tick(COOL).phase == "idle" and not chains(home)
    assert status(home)["enabled"] is False
    home.settings.auto_train = True
    d = p.tick(COOL)  # everything holds: the chain is queued
    assert d.phase == "starting vqvae" and d.sequence_id is not None
    (seq, members), = chains(home).items()
    assert [m["component"] for m in members] == ["vqvae", "fast_loop", "mid_loop"]
    assert all(m["config"]["data"] == str(home.settings.inbox_dir) and m["total_steps"] == 30 for m in members)
    reason = home.events(members[0]["id"], ["log"])[0]["payload"]
    assert reason["auto_train"]["new_episodes"] == {"vqvae": MIN_NEW, "fast_loop": MIN_NEW, "mid_loop": MIN_NEW}
    assert reason["message"].startswith(f"auto-train: {MIN_NEW} new trainable episodes in {home.settings.inbox_dir}")
    assert "50.0 C" in reason["message"] and "6000 MB memory available" in reason["message"]
    last = status(home)["last_auto_run"]
    assert last["sequence_id"] == seq and last["reason"] == reason["message"]


def test_no_second_start_for_the_same_episodes_and_a_restart_keeps_the_watermark(home, episode_dirs):
    hand_off(home, episode_dirs[:MIN_NEW + 1])
    first = policy(home).tick(COOL)
    assert first.sequence_id is not None
    complete_all(home)
    p = policy(home)  # a restarted daemon: a new policy on the same registry
    for _ in range(3):
        d = p.tick(COOL)
        assert d.phase == "waiting for data" and d.data["more_needed"] == MIN_NEW
    assert len(chains(home)) == 1
    hand_off(home, episode_dirs[MIN_NEW + 1:2 * MIN_NEW])  # one short of enough new ones
    assert p.tick(COOL).data["more_needed"] == 1
    hand_off(home, episode_dirs[2 * MIN_NEW:2 * MIN_NEW + 1])
    d = p.tick(COOL)
    assert d.sequence_id not in (None, first.sequence_id)
    assert f"since run {first.sequence_id}" in d.detail and f"{MIN_NEW} new trainable" in d.detail
    assert len(chains(home)) == 2
    complete_all(home)
    assert p.tick(COOL).phase == "waiting for data"


def test_the_auto_chain_is_not_counted_against_max_queued_runs(home, episode_dirs):
    """The cap is for the doors clients use; the daemon queues its chain only on a queue with nothing
    waiting, so a cap below the chain's length must not keep continuous learning from ever starting."""
    home.settings.max_queued_runs = 1
    hand_off(home, episode_dirs[:MIN_NEW])
    d = policy(home).tick(COOL)
    assert d.sequence_id is not None, d
    assert [m["component"] for m in chains(home)[d.sequence_id]] == ["vqvae", "fast_loop", "mid_loop"]


def test_only_components_with_enough_new_episodes_are_queued(home, episode_dirs):
    """A component whose episodes the app cannot train (no usable action, say) waits; the others go.
    A mid_loop without a vqvae in its chain reads the codes of the served VQ-VAE."""
    hand_off(home, episode_dirs[:MIN_NEW])
    ids = [r["episode_id"] for r in _manifest(home)]
    only_vision = {eid: {"vqvae"} for eid in ids}
    p = ContinuousLearning(home.settings, home.registry, inbox_reader=lambda _d: only_vision, free_mb=Disk())
    d = p.tick(COOL)
    assert [m["component"] for m in next(iter(chains(home).values()))] == ["vqvae"]
    assert d.data["new_episodes"] == {"vqvae": MIN_NEW, "fast_loop": 0, "mid_loop": 0}


def test_a_gate_at_work_holds_the_start_back(home, episode_dirs):
    hand_off(home, episode_dirs[:MIN_NEW])
    rid = home.enqueue(episode_dirs[0].parent, component="vqvae", steps=10)
    with home.registry.session() as s:
        runs.get_run(s, rid).state = "completed"
    gate = type("Gate", (), {"current_run": rid})()  # what AutoPromoter exposes while its child gates
    p = policy(home, autopromoter=gate)
    d = p.tick(COOL)
    assert d.phase == "gating vqvae" and rid in d.detail and not chains(home)
    gate.current_run = None
    assert p.tick(COOL).sequence_id is not None


def test_a_mid_loop_without_a_served_vqvae_gets_one_in_its_chain(home, episode_dirs):
    hand_off(home, episode_dirs[:MIN_NEW])
    home.settings.auto_train_components = ["vqvae"]
    p = policy(home)
    assert p.tick(COOL).sequence_id is not None  # the vqvae's watermark now holds every episode
    complete_all(home)
    home.settings.auto_train_components = ["vqvae", "mid_loop"]
    d = p.tick(COOL)  # only the mid_loop has new episodes; no VQ-VAE is served (none was gated)
    assert d.data["new_episodes"] == {"vqvae": 0, "mid_loop": MIN_NEW}
    second = chains(home)[d.sequence_id]
    assert [m["component"] for m in second] == ["vqvae", "mid_loop"]
    assert second[1]["config"]["vqvae_run"] == second[0]["id"]
    assert "vqvae added: no VQ-VAE is served" in d.detail


def test_a_chain_the_door_refuses_is_said_and_not_retried_until_the_inbox_changes(home, episode_dirs, caplog):
    home.settings.memory_budget_mb = 8  # no model fits: the door (run_request.preflight) refuses the chain
    hand_off(home, episode_dirs[:MIN_NEW])
    p = policy(home)
    d = p.tick(COOL)
    assert d.phase == "idle" and d.detail.startswith("the last auto chain could not be queued:") and not chains(home)
    assert "memory" in d.detail
    for _ in range(3):
        assert p.tick(COOL).detail.endswith("waiting for the inbox to change")
    assert sum("could not queue" in r.getMessage() for r in caplog.records) == 1
    assert status(home)["phase_detail"].startswith("the last auto chain could not be queued")
    home.settings.memory_budget_mb = 3072
    assert p.tick(COOL).phase == "idle" and not chains(home)  # same inbox: not retried
    hand_off(home, episode_dirs[MIN_NEW:MIN_NEW + 1])
    assert p.tick(COOL).sequence_id is not None


def test_an_unreadable_inbox_is_said_and_dispatch_goes_on(home, episode_dirs):
    sent = []
    home.settings.inbox_dir.mkdir(parents=True)
    (home.settings.inbox_dir / "manifest.json").write_text('{"format": "something else"}')
    rid = home.enqueue(episode_dirs[0].parent, steps=10, queue="gpu")
    daemon = Daemon(home.settings, registry=home.registry, monitor=FakeMonitor(), send=lambda *a: sent.append(a))
    daemon.start()
    daemon.tick()
    st = status(home)
    assert st["phase"] == "idle" and st["phase_detail"].startswith("the inbox cannot be read:"), st
    assert [a[0] for a in sent] == [rid]
    daemon.stop()


def _manifest(home: Home) -> list[dict]:
    import json

    return json.loads((home.settings.inbox_dir / "manifest.json").read_text())["episodes"]


class FakeMonitor:
    def __init__(self, **sample):
        self.values = {**COOL, **sample}

    def sample(self):
        return {"time": "t", "mem_total_mb": 8000.0, "mem_percent": 20.0, "cpu_percent": 3.0, "throttled": None,
                "sources": {}, **self.values}


def test_the_daemon_starts_the_chain_and_dispatches_it(home, episode_dirs):
    sent = []
    hand_off(home, episode_dirs[:MIN_NEW])
    monitor = FakeMonitor(temp_c=79.0)
    daemon = Daemon(home.settings, registry=home.registry, monitor=monitor, send=lambda *a: sent.append(a))
    daemon.start()
    daemon.tick()
    assert status(home)["current_phase"] == "waiting to cool" and sent == []
    monitor.values["temp_c"] = 55.0
    daemon.policy.level = 0  # the test's reading is below resume_c: the throttle level drops on the next sample
    daemon.tick()
    (seq, members), = chains(home).items()
    assert [(s[0], s[2]) for s in sent] == [(members[0]["id"], "pi")]
    assert home.run(members[0]["id"])["state"] == "starting"
    assert status(home)["current_phase"] == "training vqvae"
    daemon.stop()


# -- the app's pause and resume ---------------------------------------------------------------------

@pytest.fixture
def api(home):
    from webapp import create_app
    from webapp.auth import load_or_create_token

    token = load_or_create_token(home.settings)
    app, _socketio = create_app(home.settings, token=token, registry=home.registry)
    client = app.test_client()
    headers = {"authorization": f"Bearer {token}"}  # the app's lower-case header
    yield lambda method, path, **kw: getattr(client, method)(path, headers=headers, **kw)
    app.extensions["hope"].close()


def _claim(home: Home, run_id: str, pid: int):
    with home.registry.session() as s:
        run = runs.get_run(s, run_id)
        return runs.claim(s, run_id, run.celery_task_id, run.attempt, HOST, pid)


def test_pause_and_resume_from_the_app(home, api, episode_dirs):
    sent = []
    dispatcher = Dispatcher(home.registry, home.settings, send=lambda *a: sent.append(a), local_queues=("pi",))
    policy(home)  # the daemon wrote its local queues
    training = home.enqueue(episode_dirs[0].parent, steps=10)
    by_hand = home.enqueue(episode_dirs[0].parent, steps=10)
    elsewhere = home.enqueue(episode_dirs[0].parent, steps=10, queue="gpu")
    dispatcher.dispatch(0)
    _claim(home, training, 4242)
    assert api("get", "/api/training/status").get_json()["status"]["running"] is True
    assert api("get", "/api/learning/status").get_json()["current_phase"] == "training fast_loop"

    r = api("post", "/api/learning/pause")
    assert r.status_code == 200, r.get_data(as_text=True)
    out = r.get_json()
    assert out["success"] is True and out["paused_runs"] == [training]
    assert home.run(training)["desired_state"] == "pause" and home.run(training)["requested_reason"] == "user"
    assert home.run(elsewhere)["state"] == "starting"  # another host's queue is not the robot's
    again = api("post", "/api/learning/pause").get_json()  # idempotent
    assert again["success"] is True and again["paused_runs"] == [training] and again["paused_now"] == []
    with home.registry.session() as s:  # the job checkpoints and stops
        runs.finish(s, training, 4242, "paused_user", "paused", step=5, last_checkpoint=None)
    assert dispatcher.dispatch(0) == []  # held: the run queued by hand waits, and says why
    assert home.run(by_hand)["state"] == "queued" and home.run(by_hand)["waiting"] == learning.PAUSE_HOLD
    st = api("get", "/api/learning/status").get_json()
    assert st["is_paused"] is st["paused"] is True and st["current_phase"] == "paused" and st["running"] is False

    r = api("post", "/api/learning/resume")
    assert r.status_code == 200 and r.get_json() == {"success": True, "paused": False, "was_paused": True,
                                                     "resumed_runs": [training]}
    assert home.run(training)["state"] == "queued" and home.run(by_hand)["waiting"] is None
    assert api("post", "/api/learning/resume").get_json()["resumed_runs"] == []  # idempotent
    # released: the queue goes on (the resumed run queued again behind the one that waited)
    assert [d.run_id for d in dispatcher.dispatch(0)] == [by_hand]
    assert api("get", "/api/learning/status").get_json()["is_paused"] is False


def test_a_run_paused_by_hand_stays_paused_after_the_apps_resume(home, api, episode_dirs):
    mine = home.enqueue(episode_dirs[0].parent, steps=10)
    with home.registry.session() as s:
        runs.request_control(s, mine, "pause")
    assert api("post", "/api/learning/pause").get_json()["paused_runs"] == []
    assert api("post", "/api/learning/resume").get_json()["resumed_runs"] == []
    assert home.run(mine)["state"] == "paused"


def test_a_pause_survives_a_restart_and_the_daemon_keeps_holding(home, api, episode_dirs):
    """The pause lives in the registry: a restarted daemon still holds; a run someone lets go on by
    hand meanwhile (a resume that withdraws the pending pause) is paused again by the daemon's tick."""
    dispatcher = Dispatcher(home.registry, home.settings, send=lambda *a: None, local_queues=("pi",))
    rid = home.enqueue(episode_dirs[0].parent, steps=10)
    dispatcher.dispatch(0)
    _claim(home, rid, 4343)
    assert api("post", "/api/learning/pause").get_json()["paused_runs"] == [rid]
    with home.registry.session() as s:
        runs.request_control(s, rid, "resume")  # by hand, from the Jobs page
    assert home.run(rid)["desired_state"] == "run"
    home.close()  # a restart: a new daemon on the same registry
    p = policy(home)
    assert p.tick(COOL).phase == "paused"
    assert home.run(rid)["desired_state"] == "pause"
    assert api("get", "/api/learning/status").get_json()["paused"] is True
    assert api("post", "/api/learning/resume").get_json()["resumed_runs"] == [rid]
    assert home.run(rid)["desired_state"] == "run"


def test_pause_and_resume_take_no_fields(home, api):
    r = api("post", "/api/learning/pause", json={"all": True})
    assert r.status_code == 400 and "all" in r.get_json()["error"]
    assert api("get", "/api/learning/status").get_json()["paused"] is False  # nothing happened
    assert api("get", "/api/learning/status?verbose=1").status_code == 400
    r = api("post", "/api/learning/pause", data=b"", content_type="application/json")  # the app's empty body
    assert r.status_code == 200 and r.get_json()["success"] is True
