"""BrainService serving a grid Mid Loop (mid_loop/numpy_grid.py) with the camera reflex and its
tokenizer: a session's frames give the predicted joints at each horizon and, s_h grid points later,
the surprise of the cells' codes, as the NumPy form computes them by hand; the frame is encoded once
for all three (the same VQ-VAE weights); a request without a frame is a 400 naming the Mid Loop."""
from __future__ import annotations

import base64

import numpy as np
import pytest
from brain_fixtures import promote_pointer
from frame_fixtures import camera_checkpoints, moving_frames
from grid_mid_fixtures import grid_mid_checkpoint

from hope_models.components.mid_loop.numpy_form import MidLoopRuntime
from hope_models.components.mid_loop.numpy_grid import GridMidLoopNumpy
from hope_models.components.vqvae import numpy_frame
from hope_models.runtime.brain_service import BrainError, BrainService

JOINTS = np.random.default_rng(4).normal(0, 1, (128, 4))


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    root = tmp_path_factory.mktemp("brain-grid-mid")
    cam = camera_checkpoints(root, "grid")
    return {**cam, "mid": grid_mid_checkpoint(root, cam["vq"])}


def _raw(frame: np.ndarray) -> dict:
    return {"encoding": "raw", "shape": list(frame.shape), "data": base64.b64encode(frame.tobytes()).decode()}


def _expected(mid, frames, joints, actions, k_point: int, every: int):
    """By hand from the NumPy form: the prediction at grid point k_point and its surprise per horizon."""
    ticks = range(0, (k_point + 1) * every, every)
    codes = np.stack([mid.frame_vq.codes(frames[t]) for t in ticks])
    obs_n = np.stack([mid.norm.obs(joints[t]) for t in ticks])
    # a point's action input: the fast_loop's answer of the tick before it (zeros at a window's first point)
    acts = np.stack([np.zeros(mid.act_dim, np.float32) if t == 0 else mid.norm.act(actions[t - 1]) for t in ticks])

    def y_at(k: int) -> np.ndarray:
        lo = max(0, k + 1 - mid.window_k)
        a = acts[lo:k + 1].copy()
        a[0] = 0.0
        return mid.context(codes[lo:k + 1], a, obs_n[lo:k + 1])[-1]

    y = y_at(k_point)
    pred = mid.norm.raw_obs(mid.joints(y, obs_n[k_point]))
    surprise = {}
    for h, (name, s) in enumerate(zip(mid.horizon_names, mid.horizon_steps, strict=True)):
        j = k_point - s
        surprise[name] = None if j < 0 else float(-mid.observed_log_prob(y_at(j), h, codes[j], codes[k_point]).sum())
    return pred, surprise


def test_a_session_of_frames_answers_the_joints_ahead_and_the_surprise_of_the_cells(ckpts, tmp_path, monkeypatch):
    home = tmp_path / "home"
    for name in ("vq", "fast", "mid"):
        promote_pointer(home, ckpts[name], {"vq": "vqvae", "fast": "fast_loop", "mid": "mid_loop"}[name])
    mid = MidLoopRuntime.from_checkpoint(ckpts["mid"])
    encodes = []
    real = numpy_frame.FrameEncoder.encode
    monkeypatch.setattr(numpy_frame.FrameEncoder, "encode", lambda self, f: encodes.append(1) or real(self, f))
    frames = moving_frames(120, seed=3)
    ahead = []
    real_ahead = GridMidLoopNumpy.window_ahead
    monkeypatch.setattr(GridMidLoopNumpy, "window_ahead", lambda self, *a: ahead.append(1) or real_ahead(self, *a))
    with BrainService(home) as brain:
        ahead.clear()  # the load's warm-up
        status = brain.status()["mid_loop"]
        assert status["frame_shape"] == [64, 64, 3] and status["grid"] == [16, 16] and status["vqvae_matches_promoted"]
        every = 5  # the fast_loop's 20 ms ticks, the Mid Loop's 100 ms grid
        actions, answers = [], []
        for t in range(116):  # 24 grid points: the window (K=20) slides from grid point 20 on
            encodes.clear()
            out = brain.infer("fast_loop", JOINTS[t].tolist(), session="cam", frame=_raw(frames[t]))
            assert len(encodes) == 1  # the tokenizer, the reflex and the Mid Loop read one encode
            actions.append(np.asarray(out["action"]))
            answers.append(out)
        for t in (0, 25, 50, 55, 100, 105, 115):
            out, k = answers[t], t // every
            assert out["mid_tick"] == k * every and out["mid_grid_point"] == k
            pred, surprise = _expected(mid, frames, JOINTS, actions, k, every)
            got = np.asarray([out["prediction"][n] for n in mid.horizon_names])
            assert got.shape == (2, 4) and np.abs(got - pred).max() < 1e-6, t
            for name, want in surprise.items():  # null until s_h grid points of the session have passed
                value = out["surprise_by_horizon"][name]
                assert (value is None) == (want is None), (t, name)
                if want is not None:
                    assert value == pytest.approx(want, rel=1e-6) and value > 0  # float32 sums in another order
            assert out["surprise"] == out["surprise_by_horizon"]["0.5s"]
        # the ticks between grid points prepared each prediction's normalisers (numpy_grid.prepare)
        memos = list(brain._slots["mid_loop"].sessions["cam"].logp)  # the last: tick 115, a grid point
        assert all(set(m.lse) == {0, 1} for m in memos[:-1]) and not memos[-1].lse
        assert not any(m.u for m in memos)  # a decoder's hidden is kept only until its grid point
        assert len(ahead) == 23  # every next window's states were run before its grid point
        assert answers[25]["surprise"] is not None and answers[25]["surprise_by_horizon"]["1s"] is None
        assert answers[50]["surprise_by_horizon"]["1s"] is not None
        # without a session: a fresh one-point window, a prediction and never a surprise
        out = brain.infer("fast_loop", JOINTS[0].tolist(), frame=_raw(frames[0]))
        pred, _ = _expected(mid, frames, JOINTS, [], 0, every)
        assert np.abs(np.asarray([out["prediction"][n] for n in mid.horizon_names]) - pred).max() < 1e-6
        assert out["surprise"] is None


def test_a_request_without_the_frame_is_a_400_naming_the_grid_mid_loop(ckpts, tmp_path):
    home = tmp_path / "home"
    promote_pointer(home, ckpts["mid"], "mid_loop")
    with BrainService(home, components=("mid_loop",)) as brain:
        with pytest.raises(BrainError, match=r"frame is missing: mid_loop .*\(64x64x3\) read the camera") as err:
            brain.infer("mid_loop", JOINTS[0].tolist(), session="s")
        assert err.value.status == 400
        out = brain.infer("mid_loop", JOINTS[0].tolist(), session="s", frame=_raw(moving_frames(1)[0]))
        assert out["action"] is None and set(out["prediction"]) == {"0.5s", "1s"} and out["mid_grid_point"] == 0


def test_http_answers_a_frame_with_the_grid_mid_loops_fields(ckpts, tmp_path):
    from test_api import App

    from hope_models.settings import load_settings

    settings = load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})
    promote_pointer(settings.home, ckpts["fast"], "fast_loop")
    promote_pointer(settings.home, ckpts["mid"], "mid_loop")
    api = App(settings)
    try:
        body = {"component": "fast_loop", "observation": JOINTS[0].tolist(), "session": "h"}
        res = api.post("/api/brain/infer", {**body, "frame": _raw(moving_frames(1)[0])})
        assert res.status_code == 200, res.get_json()
        got = res.get_json()
        assert len(got["action"]) == 2 and len(got["prediction"]["1s"]) == 4 and got["surprise"] is None
        res = api.post("/api/brain/infer", body)
        assert res.status_code == 400 and "frame is missing" in res.get_json()["error"]
        assert "mid_loop" in res.get_json()["error"]
    finally:
        api.close()
