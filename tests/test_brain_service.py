"""BrainService: serving the promoted fast_loop, following promotions and rollbacks without a restart.

Hot reload under load (a thread calling infer in a tight loop while a new model is promoted: 0
failures, the version switches exactly once, p99 during the swap <= 3x the normal p99), checkpoints
that do not fit refused while the old model keeps serving, recurrent sessions, input validation with
the HTTP status each error maps to, the once-per-version first-inference hook, and that the service
never imports torch.
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from brain_fixtures import brain_runs, overflowing_copy, promote_pointer, rewrite_manifest
from hope_models.promoted import checkpoint_version, pointer_path
from hope_models.runtime.brain_service import MAX_ABS_OBSERVATION, BrainError, BrainService
from hope_models.components.fast_loop.numpy_act import FastLoopNumpyAct

REPO = Path(__file__).resolve().parents[1]
OBS6 = [0.1, -0.2, 0.3, 0.05, -0.4, 0.2]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return brain_runs(tmp_path_factory)


@pytest.fixture
def home(tmp_path) -> Path:
    h = tmp_path / "home"
    h.mkdir()
    return h


class Recorder:
    def __init__(self):
        self.swaps, self.errors, self.firsts = [], [], []
        self.lock = threading.Lock()

    def kwargs(self) -> dict:
        return {"on_swap": lambda *a: self._add(self.swaps, a), "on_error": lambda *a: self._add(self.errors, a),
                "on_first_inference": lambda *a: self._add(self.firsts, a)}

    def _add(self, where, item):
        with self.lock:
            where.append(item)


def wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.01)


def version(ckpt: Path) -> str:
    return checkpoint_version(ckpt)[0]


# -- serving and following the pointer --------------------------------------------------------------

def test_nothing_promoted_is_503_then_serves_and_follows_a_promotion_within_1s(runs, home):
    rec = Recorder()
    with BrainService(home, **rec.kwargs()) as brain:
        with pytest.raises(BrainError, match="no promoted fast_loop") as err:
            brain.infer("fast_loop", OBS6)
        assert err.value.status == 503
        assert brain.status()["fast_loop"]["version"] is None

        promote_pointer(home, runs["alpha15"])
        wait_for(lambda: brain.version("fast_loop") == version(runs["alpha15"]), 1.0, "the first promotion")
        out = brain.infer("fast_loop", OBS6)
        assert out["model_version"] == version(runs["alpha15"])
        assert len(out["action"]) == 2 and all(isinstance(v, float) and np.isfinite(v) for v in out["action"])
        assert 0 < out["latency_ms"] < 100

        promote_pointer(home, runs["alpha30"], model_id=2)
        started = time.monotonic()
        wait_for(lambda: brain.version("fast_loop") == version(runs["alpha30"]), 1.0, "the second promotion")
        noticed = time.monotonic() - started
        assert brain.infer("fast_loop", OBS6)["model_version"] == version(runs["alpha30"])
        st = brain.status()["fast_loop"]
        assert st["checkpoint"] == str(runs["alpha30"].resolve()) and st["last_error"] is None
        assert st["pointer_version"] == version(runs["alpha30"]) and st["obs_dim"] == 6 and st["act_dim"] == 2
        assert st["loaded_at"] and st["observation_fields"][0].startswith("observation.robot_state.joint_positions")
    assert [s[1] for s in rec.swaps] == [version(runs["alpha15"]), version(runs["alpha30"])]
    assert rec.errors == []
    print(f"\nnew pointer noticed and swapped in {noticed * 1000:.0f} ms")


def test_loads_what_is_promoted_at_start_and_answers_like_the_checkpoint(runs, home):
    promote_pointer(home, runs["alpha30"])
    model = FastLoopNumpyAct.from_checkpoint(runs["alpha30"])
    with BrainService(home) as brain:  # no wait: start() loads synchronously
        got = brain.infer("fast_loop", OBS6)
    want, _ = model.act(OBS6, model.init_state())
    assert np.allclose(got["action"], want, atol=1e-6)


SWAP_ATTEMPTS = 3


def _swap_under_load(runs, home) -> tuple[float, float]:
    """One swap with a client in a loop: no failure and exactly one switch (asserted); returns the
    client's p99 latency (s) in the 0.8 s before the promotion and from it to 0.2 s after the switch."""
    old, new = version(runs["alpha15"]), version(runs["alpha30"])
    promote_pointer(home, runs["alpha15"])
    results: list[tuple[float, float, str]] = []  # (t, client-side latency s, version)
    failures: list[str] = []
    stop = threading.Event()
    with BrainService(home, poll_s=0.1) as brain:
        def client():
            rng = np.random.default_rng(0)
            obs = rng.normal(0, 1, (512, 6)).tolist()
            i = 0
            while not stop.is_set():
                t0 = time.perf_counter()
                try:
                    out = brain.infer("fast_loop", obs[i % 512], session="robot")
                except Exception as exc:  # any failure counts, whatever its type
                    failures.append(repr(exc))
                    continue
                finally:
                    i += 1
                results.append((t0, time.perf_counter() - t0, out["model_version"]))

        thread = threading.Thread(target=client)
        thread.start()
        try:
            time.sleep(1.0)
            promoted_at = time.perf_counter()
            promote_pointer(home, runs["alpha30"], model_id=2)
            wait_for(lambda: results and results[-1][2] == new, 2.0, "responses from the new version")
            switched_at = next(t for t, _, v in results if v == new)
            time.sleep(0.3)
        finally:
            stop.set()
            thread.join(10)
    assert failures == []
    versions = [v for _, _, v in results]
    switches = sum(1 for a, b in zip(versions, versions[1:]) if a != b)
    assert versions[0] == old and versions[-1] == new and switches == 1, "the version must switch exactly once"
    normal = np.array([lat for t, lat, _ in results if promoted_at - 0.8 <= t < promoted_at])
    during = np.array([lat for t, lat, _ in results if promoted_at <= t <= switched_at + 0.2])
    assert len(normal) > 200 and len(during) > 100
    p99_normal, p99_swap = float(np.percentile(normal, 99)), float(np.percentile(during, 99))
    print(f"\n{len(results)} requests, 0 failed; p99 normal {p99_normal * 1e3:.3f} ms, during the swap "
          f"{p99_swap * 1e3:.3f} ms (max {during.max() * 1e3:.2f} ms); noticed+loaded in "
          f"{(switched_at - promoted_at) * 1e3:.0f} ms")
    return p99_normal, p99_swap


def test_hot_reload_under_load(runs, home):
    """A client in a loop while a new model is promoted: no failure, exactly one switch, and the swap
    does not stall requests (p99 during it <= 3x the normal p99). A stall the swap causes comes back
    at every swap; a burst of load from another process on this shared machine, landing on the
    0.2 s the swap is measured over, does not: so the swap is measured again, up to SWAP_ATTEMPTS
    times, and every attempt must serve without a failure and switch once."""
    figures = []
    for _ in range(SWAP_ATTEMPTS):
        p99_normal, p99_swap = _swap_under_load(runs, home)
        figures.append((p99_normal, p99_swap))
        if p99_swap <= 3 * p99_normal:
            return
    raise AssertionError(f"every swap stalled requests: (p99 normal, p99 during the swap) in s: {figures}")


def test_rollback_is_followed_and_sessions_reset_on_a_version_change(runs, home):
    promote_pointer(home, runs["alpha15"])
    model15 = FastLoopNumpyAct.from_checkpoint(runs["alpha15"])
    model30 = FastLoopNumpyAct.from_checkpoint(runs["alpha30"])
    with BrainService(home) as brain:
        for _ in range(3):
            brain.infer("fast_loop", OBS6, session="s")
        promote_pointer(home, runs["alpha30"], model_id=2)
        wait_for(lambda: brain.version("fast_loop") == model30.version, 1.0, "the promotion")
        assert brain.status()["fast_loop"]["sessions"] == 0
        first = brain.infer("fast_loop", OBS6, session="s")  # a fresh state on the new weights
        want, _ = model30.act(OBS6, model30.init_state())
        assert np.allclose(first["action"], want, atol=1e-6)
        promote_pointer(home, runs["alpha15"], model_id=1)  # what a rollback writes
        wait_for(lambda: brain.version("fast_loop") == model15.version, 1.0, "the rollback")
        out = brain.infer("fast_loop", OBS6, session="s")
        want, _ = model15.act(OBS6, model15.init_state())
        assert out["model_version"] == model15.version and np.allclose(out["action"], want, atol=1e-6)


# -- refusals: the old model keeps serving -------------------------------------------------------------

def _nan_copy(src: Path, dst: Path) -> Path:
    from safetensors.numpy import load_file, save_file

    shutil.copytree(src, dst)
    tensors = load_file(str(dst / "model.safetensors"))
    tensors["out.weight"][:] = np.nan
    save_file(tensors, str(dst / "model.safetensors"), metadata={"format": "hope.checkpoint/1", "step": "30"})
    rewrite_manifest(dst)  # a consistent checkpoint: the NaN check itself must refuse it
    return dst


def test_checkpoints_that_do_not_fit_are_refused_while_the_old_one_serves(runs, home, tmp_path):
    rec = Recorder()
    good = version(runs["alpha15"])
    promote_pointer(home, runs["alpha15"])
    nan_ckpt = _nan_copy(runs["alpha30"], tmp_path / "nan" / "checkpoints" / "00000030")
    cases = [
        ("another robot", lambda: promote_pointer(home, runs["other"], model_id=3),
         r"does not fit the fast_loop being served .*joint_positions\[4\].*still serving"),
        ("not a fast_loop", lambda: promote_pointer(home, runs["vq"], model_id=4),
         r"component is 'vqvae'.*still serving"),
        ("NaN weights", lambda: promote_pointer(home, nan_ckpt, model_id=5), r"non-finite weights .*out.weight"),
        ("sha mismatch", lambda: _pointer_with_sha(home, runs["alpha30"], "ab" * 32), r"does not match the promoted"),
        ("corrupt pointer", lambda: pointer_path(home, "fast_loop").write_text("{not json"), r"not valid JSON"),
        ("torn checkpoint", lambda: _torn(home, runs["alpha30"], tmp_path), r"not a complete checkpoint"),
    ]
    with BrainService(home, poll_s=0.05, **rec.kwargs()) as brain:
        for what, act, pattern in cases:
            n_errors = len(rec.errors)
            act()
            wait_for(lambda: len(rec.errors) > n_errors, 2.0, f"the refusal of {what}")
            msg = brain.status()["fast_loop"]["last_error"]
            assert rec.errors[-1] == ("fast_loop", msg)
            assert re.search(pattern, msg), f"{what}: {msg}"
            assert good in msg, f"{what}: the error should say what is still served: {msg}"
            out = brain.infer("fast_loop", OBS6)
            assert out["model_version"] == good, what
        promote_pointer(home, runs["alpha30"], model_id=6)  # a good one again: taken, the error cleared
        wait_for(lambda: brain.version("fast_loop") == version(runs["alpha30"]), 1.0, "the good promotion")
        assert brain.status()["fast_loop"]["last_error"] is None
    assert [s[1] for s in rec.swaps] == [good, version(runs["alpha30"])]


def _pointer_with_sha(home: Path, ckpt: Path, sha: str) -> None:
    from hope_models.promoted import write_pointer

    obj = promote_pointer(home, ckpt)
    write_pointer(home, "fast_loop", {**obj, "sha256": sha, "model_id": 7})


def _torn(home: Path, src: Path, tmp_path: Path) -> None:
    dst = tmp_path / "torn" / "checkpoints" / "00000030"
    shutil.copytree(src, dst)
    promote_pointer(home, dst, model_id=8)  # the pointer's sha is the intact file's ...
    data = (dst / "training_state.safetensors").read_bytes()
    (dst / "training_state.safetensors").write_bytes(data[: len(data) // 2])  # ... but the dir is damaged


def test_a_refused_first_checkpoint_means_503_with_the_reason(runs, home):
    promote_pointer(home, runs["vq"])
    with BrainService(home) as brain:
        with pytest.raises(BrainError, match="refused: .*component is 'vqvae'") as err:
            brain.infer("fast_loop", OBS6)
        assert err.value.status == 503


# -- sessions ----------------------------------------------------------------------------------------

def test_sessions_keep_state_reset_and_are_bounded(runs, home):
    promote_pointer(home, runs["alpha30"])
    model = FastLoopNumpyAct.from_checkpoint(runs["alpha30"])
    rng = np.random.default_rng(5)
    obs = rng.normal(0, 1, (12, 6))
    with BrainService(home, max_sessions=3) as brain:
        state = model.init_state()
        for t, x in enumerate(obs):  # a session is the recurrent policy; another session is independent
            got = brain.infer("fast_loop", x.tolist(), session="a")
            want, state = model.act(x, state)
            assert np.allclose(got["action"], want, atol=1e-6), t
            other = brain.infer("fast_loop", x.tolist(), session="b")
        stateless = brain.infer("fast_loop", obs[-1].tolist())
        fresh, _ = model.act(obs[-1], model.init_state())
        assert np.allclose(stateless["action"], fresh, atol=1e-6) and stateless["session"] is None
        assert not np.allclose(got["action"], fresh, atol=1e-4)  # the session's history mattered
        reset = brain.infer("fast_loop", obs[-1].tolist(), session="a", reset=True)
        assert np.allclose(reset["action"], fresh, atol=1e-6)
        assert other["session"] == "b"
        for name in ("c", "d"):  # 4 sessions, at most 3 kept
            brain.infer("fast_loop", OBS6, session=name)
        assert brain.status()["fast_loop"]["sessions"] == 3
        # "b" was the least recently used ("a" was used since, by the reset): evicted, it starts afresh
        again = brain.infer("fast_loop", obs[0].tolist(), session="b")
        first, _ = model.act(obs[0], model.init_state())
        assert np.allclose(again["action"], first, atol=1e-6)


# -- input validation ----------------------------------------------------------------------------------

@pytest.mark.parametrize("args,status,pattern", [
    (("world_model", OBS6), 404, "unknown component 'world_model'"),
    ((None, OBS6), 404, "unknown component"),
    (("fast_loop", OBS6[:5]), 400, r"has 5 values, .* needs 6 \(observation.robot_state.joint_positions\[0\]"),
    (("fast_loop", OBS6 + [1.0]), 400, "has 7 values"),
    (("fast_loop", OBS6[:5] + [float("nan")]), 400, r"observation\[5\] = nan is not finite"),
    (("fast_loop", OBS6[:5] + [float("inf")]), 400, "not finite"),
    (("fast_loop", OBS6[:5] + [10 ** 400]), 400, "too large"),
    # finite doubles that float32 cannot hold (they answered NaN): refused with the range
    (("fast_loop", OBS6[:5] + [3.5e38]), 400, r"observation\[5\] = 3.5e\+38 is outside the accepted range "
                                               r"\[-1e\+06, 1e\+06\]"),
    (("fast_loop", [-1.5e6] + OBS6[1:]), 400, r"observation\[0\] = -1.5e\+06 is outside the accepted range"),
    (("fast_loop", OBS6[:5] + ["1.0"]), 400, r"observation\[5\] = '1.0' is not a number"),
    (("fast_loop", OBS6[:5] + [True]), 400, "is not a number"),
    (("fast_loop", OBS6[:5] + [[1.0]]), 400, "is not a number"),
    (("fast_loop", {"x": 1.0}), 400, "must be a list of numbers, got dict"),
    (("fast_loop", "0.1,0.2"), 400, "must be a list of numbers, got str"),
    (("fast_loop", []), 400, "empty"),
    (("fast_loop", [0.0] * 5000), 400, "at most 4096"),
    (("fast_loop", OBS6, 7), 400, "session must be a string"),
    (("fast_loop", OBS6, "x" * 200), 400, "session must be a string of 1 to 128"),
    (("fast_loop", OBS6, "s", "yes"), 400, "reset must be true or false"),
])
def test_bad_input_is_a_brain_error_with_its_status(runs, home, args, status, pattern):
    promote_pointer(home, runs["alpha30"])
    brain = BrainService(home)
    brain.check_now()  # loads without starting a thread
    with pytest.raises(BrainError, match=pattern) as err:
        brain.infer(*args)
    assert err.value.status == status
    assert brain.infer("fast_loop", OBS6)["model_version"]  # and the service is fine afterwards


def test_observations_at_the_range_limit_answer_finite_actions(runs, home):
    promote_pointer(home, runs["alpha30"])
    brain = BrainService(home)
    brain.check_now()
    for edge in (MAX_ABS_OBSERVATION, -MAX_ABS_OBSERVATION):
        out = brain.infer("fast_loop", [edge] * 6, session="edge")
        assert all(np.isfinite(out["action"])), out


def test_a_non_finite_answer_is_a_500_and_never_poisons_the_session(runs, home, tmp_path):
    """A model that computes NaN from a valid observation (weights that overflow float32 on it):
    the request gets a 500 naming the version, no NaN; the session's state is not committed, so
    its next tick answers exactly what a session that never saw the bad observation answers."""
    ckpt, mean0 = overflowing_copy(runs["alpha30"], tmp_path / "ovf" / "checkpoints" / "00000030")
    promote_pointer(home, ckpt)
    normal = [[mean0] + OBS6[1:], [mean0, 0.5, -0.3, 0.1, 0.2, -0.1], [mean0, -0.1, 0.0, 0.3, 0.1, 0.4]]
    bad = [1e6] + OBS6[1:]  # in range: a fault of the model, not of the request
    brain = BrainService(home)
    brain.check_now()
    first = brain.infer("fast_loop", normal[0], session="arm")
    for session in ("arm", None):
        with pytest.raises(BrainError, match=rf"{re.escape(version(ckpt))} computed a non-finite action") as err:
            brain.infer("fast_loop", bad, session=session)
        assert err.value.status == 500 and "nan" not in str(err.value).lower()
    after = [brain.infer("fast_loop", x, session="arm")["action"] for x in normal[1:]]
    fresh = [brain.infer("fast_loop", x, session="ref")["action"] for x in normal]
    assert [first["action"], *after] == fresh  # exactly: the bad tick left nothing behind
    assert fresh[1] != brain.infer("fast_loop", normal[1])["action"]  # (the state does matter)
    assert all(np.isfinite(a).all() for a in fresh)
    assert brain.status()["fast_loop"]["non_finite"] == 2


def test_constructor_refuses_components_it_cannot_serve(home):
    with pytest.raises(ValueError, match="no inference runtime for \\['world_model'\\]"):
        BrainService(home, components=("fast_loop", "world_model"))
    with pytest.raises(ValueError, match="poll_s"):
        BrainService(home, poll_s=5)


# -- hooks -----------------------------------------------------------------------------------------------

def test_first_inference_fires_once_per_version_and_hooks_cannot_break_requests(runs, home):
    rec = Recorder()
    promote_pointer(home, runs["alpha15"])
    brain = BrainService(home, **rec.kwargs())
    brain.on_swap = lambda *a: 1 / 0  # the webapp replaces hooks after construction: read at call time
    with brain:
        for _ in range(5):
            brain.infer("fast_loop", OBS6)
        assert brain.wait_hooks(5)  # the hook runs on its own thread: a request never waits for it
        assert len(rec.firsts) == 1
        comp, ver, ckpt, when = rec.firsts[0]
        assert (comp, ver, ckpt) == ("fast_loop", version(runs["alpha15"]), str(runs["alpha15"].resolve()))
        assert when.tzinfo is not None and abs(when.timestamp() - time.time()) < 5
        brain.on_first_inference = lambda *a: (_ for _ in ()).throw(RuntimeError("hook down"))
        promote_pointer(home, runs["alpha30"], model_id=2)
        wait_for(lambda: brain.version("fast_loop") == version(runs["alpha30"]), 1.0, "the promotion")
        assert brain.infer("fast_loop", OBS6)["model_version"] == version(runs["alpha30"])  # hook raised: fine
        assert brain.wait_hooks(5)
        brain.on_first_inference = rec.kwargs()["on_first_inference"]
        brain.infer("fast_loop", OBS6)
        assert brain.wait_hooks(5)
    assert len(rec.firsts) == 1  # the second version's first inference already went (to the raising hook)


# -- memory: the service never imports torch ---------------------------------------------------------------

def test_serving_never_imports_torch(runs, home):
    promote_pointer(home, runs["alpha30"])
    code = f"""
import json, sys
from hope_models.runtime.brain_service import BrainService
with BrainService({str(home)!r}) as brain:
    out = brain.infer("fast_loop", {OBS6!r}, session="s")
print(json.dumps({{"version": out["model_version"], "torch": "torch" in sys.modules}}))
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got == {"version": version(runs["alpha30"]), "torch": False}


# -- run_trainer.py infer -------------------------------------------------------------------------------

def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _infer_cli(home: Path, *args: str, port: int | None = None) -> subprocess.CompletedProcess:
    import os

    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    port = port or _free_port()
    # infer asks the inference port; this test's server answers every route on one port
    env.update(HOPE_HOME=str(home), HOPE_HOST="127.0.0.1", HOPE_PORT=str(_free_port()), HOPE_INFERENCE_PORT=str(port))
    return subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "infer", *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)


def test_infer_cli_local(runs, home):
    obs = json.dumps(OBS6)
    proc = _infer_cli(home, "--local", "--observation", obs)
    assert proc.returncode == 1 and "no promoted fast_loop" in proc.stderr, proc.stderr
    promote_pointer(home, runs["alpha30"])
    proc = _infer_cli(home, "--local", "--observation", obs, "--json")
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    model = FastLoopNumpyAct.from_checkpoint(runs["alpha30"])
    want, _ = model.act(OBS6, model.init_state())
    assert out["model_version"] == model.version and out["via"] == "local"
    assert np.allclose(out["action"], want, atol=1e-6) and out["latency_ms"] > 0
    proc = _infer_cli(home, "--local", "--observation", obs)
    assert proc.returncode == 0 and f"version {model.version}" in proc.stdout and "latency" in proc.stdout
    for bad, pattern in (("[0.1, 0.2]", "has 2 values"), ("[0.1, NaN, 0, 0, 0, 0]", "not finite"),
                         ('"0.1,0.2"', "list of numbers"), ("[0.1,", "not valid JSON")):
        proc = _infer_cli(home, "--local", "--observation", bad, "--json")
        assert proc.returncode == 2, (bad, proc.stderr)
        assert pattern in json.loads(proc.stdout)["error"], (bad, proc.stdout)


def test_infer_cli_says_when_no_service_answers(runs, home):
    from hope_models.settings import load_settings
    from webapp.auth import load_or_create_token

    promote_pointer(home, runs["alpha30"])
    proc = _infer_cli(home, "--observation", json.dumps(OBS6))
    assert proc.returncode == 1 and "no API token" in proc.stderr and "serve" in proc.stderr, proc.stderr
    load_or_create_token(load_settings(home, env={}))
    port = _free_port()
    proc = _infer_cli(home, "--observation", json.dumps(OBS6), port=port)
    assert proc.returncode == 1, proc.stderr
    assert f"nothing answers at http://127.0.0.1:{port}" in proc.stderr
    assert "run_trainer.py serve" in proc.stderr and "--local" in proc.stderr


def test_infer_cli_asks_the_running_webapp(runs, home):
    from werkzeug.serving import make_server

    from hope_models.settings import load_settings
    from webapp import create_app
    from webapp.auth import load_or_create_token

    promote_pointer(home, runs["alpha30"])
    settings = load_settings(home, env={})
    token = load_or_create_token(settings)
    model = FastLoopNumpyAct.from_checkpoint(runs["alpha30"])
    with BrainService(home) as brain:
        app, _ = create_app(settings, token=token, brain=brain)
        server = make_server("127.0.0.1", 0, app, threaded=True)
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            port = server.server_port
            state = model.init_state()
            for tick in range(2):  # the session lives in the service: the 2nd call continues the 1st
                proc = _infer_cli(home, "--observation", json.dumps(OBS6), "--session", "cli", "--json", port=port)
                assert proc.returncode == 0, proc.stderr
                out = json.loads(proc.stdout)
                want, state = model.act(OBS6, state)
                assert out["via"] == "http" and out["model_version"] == model.version and out["session"] == "cli"
                assert np.allclose(out["action"], want, atol=1e-6), tick
            proc = _infer_cli(home, "--component", "world_model", "--observation", json.dumps(OBS6), port=port)
            assert proc.returncode == 2 and "unknown component" in proc.stderr, proc.stderr
            proc = _infer_cli(home, "--observation", "[1, 2]", port=port)
            assert proc.returncode == 2 and "has 2 values" in proc.stderr, proc.stderr
            (home / "token").write_text("x" * 43 + "\n")
            proc = _infer_cli(home, "--observation", json.dumps(OBS6), port=port)
            assert proc.returncode == 2 and "refused the token" in proc.stderr, proc.stderr
        finally:
            server.shutdown()
            thread.join(5)
