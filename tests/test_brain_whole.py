"""BrainService serving all three promoted components (vqvae, fast_loop, mid_loop), torch-free.

The NumPy VQ-VAE and Mid Loop equal torch's; one request answers the action, the vqvae's code, the
Mid Loop's prediction (raw units) and surprise (docs/training.md "Surprise at inference"), checked
against the definition computed by hand; a jump in the observation makes the surprise spike; each
component hot-swaps under load with no failed request; refused checkpoints keep the old one serving.
"""
from __future__ import annotations

import json
import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from brain_fixtures import brain_runs, brain_whole_runs, promote_pointer, rewrite_manifest
from hope_models.promoted import checkpoint_version
from hope_models.runtime.brain_service import BrainError, BrainService
from hope_models.components.fast_loop.numpy_form import FastLoopNumpy
from hope_models.components.mid_loop.numpy_form import MidLoopNumpy
from hope_models.components.vqvae.numpy_form import VQVAERuntime

OBS6 = [0.1, -0.2, 0.3, 0.05, -0.4, 0.2]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return {**brain_runs(tmp_path_factory), **brain_whole_runs(tmp_path_factory)}


@pytest.fixture
def home(tmp_path) -> Path:
    h = tmp_path / "home"
    h.mkdir()
    return h


def version(ckpt: Path) -> str:
    return checkpoint_version(ckpt)[0]


def wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not (value := predicate()):
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.01)
    return value


def promote_all(home: Path, runs, vq="vq_a", fast="alpha30", mid="mid_a") -> None:
    for component, name in (("vqvae", vq), ("fast_loop", fast), ("mid_loop", mid)):
        if name is not None:
            promote_pointer(home, runs[name], component)


# -- 1. NumPy == torch ----------------------------------------------------------------------------------

def test_numpy_vqvae_and_mid_loop_equal_torch(runs):
    import torch

    from hope_models.components.build import component_from_checkpoint

    rng = np.random.default_rng(0)
    vq, tvq = VQVAERuntime.from_checkpoint(runs["vq_a"]), component_from_checkpoint(runs["vq_a"]).model.eval()
    obs = rng.normal(0, 1.5, (3000, 6)).astype(np.float32)
    probs = rng.dirichlet(np.ones(16), (500, 2)).astype(np.float32)
    with torch.inference_mode():
        want = tvq.encode(torch.from_numpy(obs)).numpy()
        dec = tvq.decode(torch.from_numpy(want)).numpy()
        exp = tvq.decode_expected(torch.from_numpy(probs)).numpy()
    got = vq.vq.codes(obs)
    assert len({tuple(r) for r in want.tolist()}) > 10  # the comparison means something only if codes vary
    assert (got == want).all()
    assert np.abs(vq.vq.decode(want) - dec).max() < 1e-5
    assert np.abs(vq.vq.decode_expected(probs) - exp).max() < 1e-5

    mid, tmid = MidLoopNumpy.from_checkpoint(runs["mid_a"]), component_from_checkpoint(runs["mid_a"]).model.eval()
    assert (mid.vq.codes(obs) == tmid.codes(torch.from_numpy(obs)).numpy()).all()
    for length in (1, 7, mid.window_k):
        codes = rng.integers(0, mid.n_codes, (1, length, mid.groups))
        act = rng.normal(0, 1, (1, length, mid.act_dim)).astype(np.float32)
        with torch.inference_mode():
            tl = tmid(torch.from_numpy(codes), torch.from_numpy(act)).numpy()[0]
            tp = tmid.predicted_observation(torch.from_numpy(tl[-1])).numpy()
        logits = mid.forward(mid.rows(codes[0]), act[0])
        assert logits.shape == tl.shape and np.abs(logits - tl).max() < 1e-4, length
        last = mid.forward(mid.rows(codes[0]), act[0], last_only=True)[-1]
        assert np.abs(last - tl[-1]).max() < 1e-4
        assert np.abs(mid.prediction_n(mid.log_probs(last)) - tp).max() < 1e-4
        state = mid.init_state()  # the stepped form from a fresh state is the same window
        for i in range(length):
            stepped, state = mid.step(mid.rows(codes[0, i]), act[0, i], state)
        assert np.abs(stepped - tl[-1]).max() < 1e-4


# -- 2. the whole answer ----------------------------------------------------------------------------------

def test_infer_answers_action_code_prediction_surprise_and_versions(runs, home):
    promote_all(home, runs)
    fast = FastLoopNumpy.from_checkpoint(runs["alpha30"])
    mid, vq = MidLoopNumpy.from_checkpoint(runs["mid_a"]), VQVAERuntime.from_checkpoint(runs["vq_a"])
    rng = np.random.default_rng(1)
    obs = rng.normal(0, 0.5, (60, 6)).tolist()
    with BrainService(home) as brain:
        st = brain.status()
        assert st["mid_loop"]["vqvae_matches_promoted"] is True and st["fast_loop"]["vqvae_matches_promoted"] is None
        assert st["mid_loop"]["horizons"] == ["0.5s", "1s"] and st["mid_loop"]["grid_step_s"] == pytest.approx(0.1)
        outs = [brain.infer("fast_loop", o, session="s") for o in obs]
        state = fast.init_state()
        for o, out in zip(obs, outs):  # the action is the fast_loop's, unchanged by the other components
            a, state = fast.tick(fast.normalise(np.asarray(o)), state)
            assert np.allclose(out["action"], fast.denormalise(a), atol=1e-6)
        assert outs[0]["versions"] == {"vqvae": version(runs["vq_a"]), "fast_loop": version(runs["alpha30"]),
                                       "mid_loop": version(runs["mid_a"])}
        assert outs[0]["model_version"] == version(runs["alpha30"])
        for o, out in zip(obs, outs):
            assert out["code"] == vq.codes_of(np.asarray(o)).tolist() and len(out["code"]) == 2
            assert set(out["prediction"]) == {"0.5s", "1s"}
            assert all(len(v) == 6 and np.isfinite(v).all() for v in out["prediction"].values())
        # grid points every 5 ticks (0.1 s / 0.02 s); between them the latest values again
        assert [o["mid_tick"] for o in outs[:11]] == [0] * 5 + [5] * 5 + [10]
        assert [o["mid_grid_point"] for o in outs[:11]] == [0] * 5 + [1] * 5 + [2]
        assert all(o["surprise"] is None for o in outs[:25]) and outs[25]["surprise"] is not None
        assert outs[45]["surprise_by_horizon"]["1s"] is None and outs[50]["surprise_by_horizon"]["1s"] > 0
        # the definition by hand: at grid point 5, -log P(code at 5) under the 0.5 s prediction of point 0
        codes = [mid.codes_of(np.asarray(obs[5 * k])) for k in range(6)]
        acts = [np.zeros(2)] + [np.asarray(outs[5 * k - 1]["action"]) for k in range(1, 6)]
        logp0 = mid.log_probs(mid.forward(mid.rows(codes[0])[None], np.zeros((1, 2), np.float32))[-1])
        assert outs[25]["surprise"] == pytest.approx(-logp0[0, [0, 1], codes[5]].sum(), rel=1e-6)
        window = mid.forward(np.stack([mid.rows(c) for c in codes]),
                             np.stack([np.zeros(2, np.float32)] + [mid.norm.act(a) for a in acts[1:]]))[-1]
        want = mid.prediction(mid.log_probs(window))
        assert np.allclose(outs[25]["prediction"]["0.5s"], want[0], atol=1e-6)
        # the client's `action` (the one it actually took) is the Mid Loop's input when given
        given = [brain.infer("fast_loop", o, session="g", action=[0.9, -0.9]) for o in obs[:6]]
        assert given[5]["prediction"] != outs[5]["prediction"] and given[5]["action"] == outs[5]["action"]
        with pytest.raises(BrainError, match="action must be a list of 2 numbers"):
            brain.infer("fast_loop", OBS6, session="g", action=[1.0])
        stateless = brain.infer("mid_loop", OBS6)
        assert stateless["surprise"] is None and stateless["mid_grid_point"] == 0 and stateless["action"] is not None


def test_fast_loop_only_is_unchanged_and_missing_components_are_clear(runs, home, tmp_path):
    promote_pointer(home, runs["alpha30"])
    fast = FastLoopNumpy.from_checkpoint(runs["alpha30"])
    with BrainService(home) as brain:
        out = brain.infer("fast_loop", OBS6, session="s")
        a, _ = fast.tick(fast.normalise(np.asarray(OBS6)), fast.init_state())
        assert np.allclose(out["action"], fast.denormalise(a), atol=1e-6)
        assert out["code"] is None and out["prediction"] is None and out["surprise"] is None
        assert out["versions"] == {"vqvae": None, "fast_loop": version(runs["alpha30"]), "mid_loop": None}
        with pytest.raises(BrainError, match="no promoted mid_loop to serve yet") as exc:
            brain.infer("mid_loop", OBS6)
        assert exc.value.status == 503
    other = tmp_path / "other"
    other.mkdir()
    promote_all(other, runs, fast=None)
    with BrainService(other) as brain:  # no fast_loop: what can be answered is, the action is null
        out = brain.infer("mid_loop", OBS6, session="s")
        assert out["action"] is None and len(out["code"]) == 2 and out["prediction"] is not None
        assert out["model_version"] == version(runs["mid_a"])
        with pytest.raises(BrainError, match="no promoted fast_loop to serve yet") as exc:
            brain.infer("fast_loop", OBS6)
        assert exc.value.status == 503


# -- 3. surprise spikes when the world jumps ------------------------------------------------------------

def test_surprise_spikes_after_a_jump(runs, home):
    promote_all(home, runs, mid="mid_b")
    steady, jumped = np.zeros(6), np.array([1.2, -1.0, 0.9, 0.0, 0.0, 0.0])  # normalised-ish joint positions
    with BrainService(home) as brain:
        outs = [brain.infer("fast_loop", steady.tolist(), session="s") for _ in range(200)]  # 40 grid points
        outs += [brain.infer("fast_loop", jumped.tolist(), session="s") for _ in range(50)]
    assert outs[199]["code"] != outs[200]["code"], "the jump must change the code, or the test means nothing"
    steady_s = [outs[t]["surprise"] for t in range(100, 200, 5)]  # grid points 20-39: the window is all steady
    spike = outs[200]["surprise"]  # grid point 40: the first after the jump, scored by point 35's prediction
    assert outs[200]["mid_grid_point"] == 40
    print(f"\nsteady surprise median {np.median(steady_s):.3f} max {max(steady_s):.3f} nats; after the jump "
          f"{spike:.3f} nats")
    # measured: steady 2.90-2.98 nats, the spike 4.7 (a 200-step model, not sharp: uniform would be
    # 2 ln 16 = 5.5). Clearly higher = at least 1 nat above the steady maximum, e times less likely.
    assert spike > max(steady_s) + 1.0
    later = [outs[t]["surprise"] for t in range(225, 250, 5)]  # predicted after the jump: the model adapts
    assert min(later) < spike


# -- 4. hot swap of each component under load --------------------------------------------------------------

def test_each_component_hot_swaps_under_load(runs, home):
    promote_all(home, runs, fast="alpha15")
    failures, seen = [], []
    stop = threading.Event()
    with BrainService(home, poll_s=0.05) as brain:
        def client(n):
            rng = np.random.default_rng(n)
            obs = rng.normal(0, 0.5, (256, 6)).tolist()
            i = 0
            while not stop.is_set():
                try:
                    out = brain.infer("fast_loop", obs[i % 256], session=f"robot-{n}")
                    seen.append(out["versions"])
                    assert out["prediction"] is not None and len(out["code"]) == 2
                except Exception as exc:  # any failure counts, whatever its type
                    failures.append(repr(exc))
                i += 1

        threads = [threading.Thread(target=client, args=(n,)) for n in range(3)]
        for t in threads:
            t.start()
        try:
            for component, name in (("vqvae", "vq_b"), ("fast_loop", "alpha30"), ("mid_loop", "mid_b")):
                time.sleep(0.3)
                promote_pointer(home, runs[name], component, model_id=2)
                want = version(runs[name])
                wait_for(lambda: seen and seen[-1][component] == want, 3.0, f"{component} -> {name}")
            time.sleep(0.2)
            st = brain.status()
        finally:
            stop.set()
            for t in threads:
                t.join(10)
    assert failures == []
    assert seen[0] == {"vqvae": version(runs["vq_a"]), "fast_loop": version(runs["alpha15"]),
                       "mid_loop": version(runs["mid_a"])}
    assert seen[-1] == {"vqvae": version(runs["vq_b"]), "fast_loop": version(runs["alpha30"]),
                        "mid_loop": version(runs["mid_b"])}
    assert len(seen) > 300
    assert all(st[c]["last_error"] is None for c in st)
    assert st["mid_loop"]["vqvae_matches_promoted"] is False  # mid_b reads vq_a, vq_b is promoted


# -- 5. refused checkpoints --------------------------------------------------------------------------------

def _edited(src: Path, dst: Path, edit) -> Path:
    from safetensors.numpy import load_file, save_file

    shutil.copytree(src, dst)
    tensors = load_file(str(dst / "model.safetensors"))
    edit(tensors)
    save_file(tensors, str(dst / "model.safetensors"), metadata={"format": "hope.checkpoint/1"})
    rewrite_manifest(dst)
    return dst


def test_refused_mid_loop_and_vqvae_keep_the_old_one_serving(runs, home, tmp_path):
    promote_all(home, runs, fast=None)
    mid_v, vq_v = version(runs["mid_a"]), version(runs["vq_a"])

    def nan(t):
        t["head.weight"] = np.full_like(t["head.weight"], np.nan)

    def world_model(t):  # a world model's extra heads: ignored, never a reason to refuse
        t["wm_head.weight"] = np.ones((3, 3), np.float32)

    nan_mid = _edited(runs["mid_a"], tmp_path / "nan_mid", nan)
    wm_mid = _edited(runs["mid_a"], tmp_path / "wm_mid", world_model)
    bad_vq = shutil.copytree(runs["vq_a"], tmp_path / "bad_vq")
    (bad_vq / "model.safetensors").write_bytes(b"\x00" * 64)
    rewrite_manifest(bad_vq)
    with BrainService(home, poll_s=0.05) as brain:
        def refused(component, ckpt, pattern, still):
            promote_pointer(home, ckpt, component, model_id=3)
            err = wait_for(lambda: pattern in (brain.status()[component]["last_error"] or "")
                           and brain.status()[component]["last_error"], 3.0, f"{component} refused: {pattern}")
            assert f"still serving {still}" in err and str(ckpt) in err, err
            assert brain.infer("mid_loop", OBS6, session="s")["versions"][component] == still

        refused("mid_loop", runs["mid8"], "does not fit", mid_v)
        refused("mid_loop", nan_mid, "non-finite weights", mid_v)
        refused("vqvae", runs["vq8"], "does not fit", vq_v)
        refused("vqvae", bad_vq, "safetensors", vq_v)
        promote_pointer(home, wm_mid, "mid_loop", model_id=4)
        wait_for(lambda: brain.status()["mid_loop"]["version"] == version(wm_mid), 3.0, "the wm_* checkpoint")
        assert brain.status()["mid_loop"]["last_error"] is None
    assert json.loads((home / "promoted" / "mid_loop.json").read_text())["checkpoint"] == str(wm_mid.resolve())


# -- over HTTP ---------------------------------------------------------------------------------------------

def test_post_infer_answers_the_whole_fields_and_takes_the_action(runs, tmp_path):
    from hope_models.settings import load_settings
    from test_api import App

    settings = load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})
    promote_all(settings.home, runs)
    api = App(settings)
    try:
        body = {"component": "fast_loop", "observation": OBS6, "session": "http", "action": [0.1, -0.1]}
        out = api.post("/api/brain/infer", body).get_json()
        assert {"action", "code", "prediction", "surprise", "surprise_by_horizon", "mid_tick", "mid_grid_point",
                "versions"} <= set(out)
        assert len(out["code"]) == 2 and set(out["prediction"]) == {"0.5s", "1s"}
        bad = api.post("/api/brain/infer", {**body, "action": [0.1]})
        assert bad.status_code == 400 and "action must be a list of 2 numbers" in bad.get_json()["error"]
        bad = api.post("/api/brain/infer", {**body, "action": ["x", 1]})
        assert bad.status_code == 400
    finally:
        api.close()


def test_infer_cli_prints_code_prediction_and_surprise_and_checks_action(runs, home):
    import os
    import subprocess
    import sys

    promote_all(home, runs)
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env["HOPE_HOME"] = str(home)
    repo = Path(__file__).resolve().parents[1]

    def infer(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, str(repo / "run_trainer.py"), "infer", "--local", *args], cwd=repo,
                              env=env, capture_output=True, text=True, timeout=120)

    obs = json.dumps([0.1, -0.2, 0.3, 0.05, -0.4, 0.2])
    proc = infer("--observation", obs, "--action", "[0.1, -0.1]")
    assert proc.returncode == 0, proc.stderr
    assert "code [" in proc.stdout and "prediction +0.5s: [" in proc.stdout and "prediction +1s: [" in proc.stdout
    assert "surprise: none yet" in proc.stdout  # one tick of a fresh session: no prediction is due
    out = json.loads(infer("--observation", obs, "--json").stdout)
    assert len(out["code"]) == 2 and set(out["prediction"]) == {"0.5s", "1s"} and out["surprise"] is None
    proc = infer("--observation", obs, "--action", "[0.1, NaN]", "--json")
    assert proc.returncode == 2 and json.loads(proc.stdout)["error"].startswith("--action"), proc.stdout
