"""BrainService sees: POST /api/brain/infer and the session ticks take the camera frame with the
joints (a PNG data URL as the Inference page sends it, a base64 JPEG, a raw array, lists), encode
it in NumPy and answer the camera reflex's action and the tokenizer's codes; a bad image is a 400
that says why and moves no session; a frame for a model without a camera, or none for one with, is
a 400 too."""
from __future__ import annotations

import base64
import io
import struct
import zlib

import numpy as np
import pytest
from brain_fixtures import promote_pointer
from frame_fixtures import camera_checkpoints, joints_checkpoint, moving_frames
from PIL import Image

from hope_models.components.fast_loop.numpy_form import FastLoopNumpy
from hope_models.components.vqvae.numpy_form import VQVAERuntime
from hope_models.runtime.brain_service import BrainError, BrainService

JOINTS = [0.3, -0.1, 0.5, 0.2]


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    root = tmp_path_factory.mktemp("brain-frames")
    return {**camera_checkpoints(root, "grid"), "joints": joints_checkpoint(root)}


def _raw(frame: np.ndarray) -> dict:
    return {"encoding": "raw", "shape": list(frame.shape), "data": base64.b64encode(frame.tobytes()).decode()}


def _encoded(frame: np.ndarray, fmt: str) -> str:
    buf = io.BytesIO()
    Image.fromarray(frame).save(buf, fmt)
    return base64.b64encode(buf.getvalue()).decode()


def _png_declaring(width: int, height: int) -> str:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")
    return base64.b64encode(png).decode()


def _reference(ckpts):
    """What the answers must be: the NumPy forms run by hand on the same pixels."""
    fast = FastLoopNumpy.from_checkpoint(ckpts["fast"])
    vq = VQVAERuntime.from_checkpoint(ckpts["vq"])

    def tick(frame, state):
        a, state = fast.tick(fast.normalise(np.asarray(JOINTS)), state, fast.frame_codes(frame))
        return fast.denormalise(a), state

    return fast, vq, tick


def test_session_ticks_with_frames_answer_the_reflex_and_the_codes(ckpts, tmp_path):
    home = tmp_path / "home"
    promote_pointer(home, ckpts["vq"], "vqvae")
    promote_pointer(home, ckpts["fast"], "fast_loop")
    fast, vq, tick = _reference(ckpts)
    frames = moving_frames(12, seed=5)
    with BrainService(home, components=("vqvae", "fast_loop")) as brain:
        assert brain.status()["fast_loop"]["frame_shape"] == [64, 64, 3]
        assert brain.status()["vqvae"]["frame_shape"] == [64, 64, 3]
        state = fast.init_state()
        for t, frame in enumerate(frames):
            if t == 6:  # a bad image half-way: 400, and the session's state does not move
                with pytest.raises(BrainError, match=r"frame.shape: \[32, 32, 3\], the served tokenizer reads") as err:
                    brain.infer("fast_loop", JOINTS, session="cam", frame=_raw(frame[:32, :32].copy()))
                assert err.value.status == 400
            out = brain.infer("fast_loop", JOINTS, session="cam", frame=_raw(frame))
            want, state = tick(frame, state)
            assert np.abs(np.asarray(out["action"]) - want).max() < 1e-9
            assert out["code"] == vq.vq.codes(frame).tolist() and len(out["code"]) == 256
        with pytest.raises(BrainError, match="frame is missing: .*fast_loop .* read the camera; send `frame`"):
            brain.infer("fast_loop", JOINTS, session="cam")
        # the tokenizer alone sees the frame too (its codes, no action)
        out = brain.infer("vqvae", JOINTS, frame=frames[0].tolist())
        assert out["code"] == vq.vq.codes(frames[0]).tolist()


@pytest.fixture
def api(ckpts, tmp_path):
    from test_api import App

    from hope_models.settings import load_settings

    settings = load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})
    promote_pointer(settings.home, ckpts["vq"], "vqvae")
    promote_pointer(settings.home, ckpts["fast"], "fast_loop")
    app = App(settings)
    yield app
    app.close()


def test_http_takes_a_png_data_url_a_jpeg_and_raw_pixels(api, ckpts):
    frame = moving_frames(1, seed=9)[0]
    _, vq, tick = _reference(ckpts)
    want, _ = tick(frame, FastLoopNumpy.from_checkpoint(ckpts["fast"]).init_state())
    body = {"component": "fast_loop", "observation": JOINTS}
    answers = {}
    for name, value in (("png data URL", "data:image/png;base64," + _encoded(frame, "PNG")), ("raw", _raw(frame)),
                        ("lists", frame.tolist()), ("jpeg", _encoded(frame, "JPEG"))):
        res = api.post("/api/brain/infer", {**body, "frame": value})
        assert res.status_code == 200, (name, res.get_json())
        answers[name] = res.get_json()
    for name in ("png data URL", "raw", "lists"):  # lossless: the same pixels, the same answer
        assert np.abs(np.asarray(answers[name]["action"]) - want).max() < 1e-9, name
        assert answers[name]["code"] == vq.vq.codes(frame).tolist()
    assert len(answers["jpeg"]["action"]) == 2 and len(answers["jpeg"]["code"]) == 256
    status = api.get("/api/brain").get_json()["components"]["fast_loop"]["serving"]
    assert status["frame_shape"] == [64, 64, 3]


@pytest.mark.parametrize("frame, message", [
    ({"encoding": "raw", "shape": [64, 64, 3], "data": base64.b64encode(b"\0" * 100).decode()},
     r"frame.data: 100 bytes, a \[64, 64, 3\] uint8 frame has 12288"),
    ({"encoding": "raw", "shape": [48, 48, 3], "data": ""}, r"frame.shape: \[48, 48, 3\], the served tokenizer reads"),
    (base64.b64encode(b"this is not a picture at all").decode(), "not a JPEG or PNG image"),
    (_png_declaring(5_000, 5_000), "above the limit of"),
    ("data:image/png;base64," + _png_declaring(100_000, 100_000), "PNG declares too many pixels"),
    (None, "frame is missing: .*read the camera"),
])
def test_http_bad_images_are_400_with_the_reason(api, frame, message):
    import re

    body = {"component": "fast_loop", "observation": JOINTS, "session": "s"}
    if frame is not None:
        body["frame"] = frame
    res = api.post("/api/brain/infer", body)
    assert res.status_code == 400 and re.search(message, res.get_json()["error"]), res.get_json()


def test_a_frame_for_a_model_without_a_camera_is_400(ckpts, tmp_path):
    from test_api import App

    from hope_models.settings import load_settings

    settings = load_settings(env={"HOPE_HOME": str(tmp_path / "home"), "HOPE_THERMAL_ZONE": "", "HOPE_VCGENCMD": ""})
    promote_pointer(settings.home, ckpts["joints"], "fast_loop")
    api = App(settings)
    try:
        body = {"component": "fast_loop", "observation": JOINTS}
        assert api.post("/api/brain/infer", body).status_code == 200
        res = api.post("/api/brain/infer", {**body, "frame": _raw(moving_frames(1)[0])})
        assert res.status_code == 400
        assert "frame: no served component answering this request reads a camera" in res.get_json()["error"]
        assert "send no frame" in res.get_json()["error"]
    finally:
        api.close()


def test_infer_cli_sends_a_frame_file(ckpts, tmp_path):
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    home = tmp_path / "home"
    promote_pointer(home, ckpts["vq"], "vqvae")
    promote_pointer(home, ckpts["fast"], "fast_loop")
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env["HOPE_HOME"] = str(home)
    repo = Path(__file__).resolve().parents[1]
    frame = moving_frames(1, seed=4)[0]
    png, junk = tmp_path / "camera.png", tmp_path / "notes.txt"
    Image.fromarray(frame).save(png)
    junk.write_text("not a picture")

    def infer(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, str(repo / "run_trainer.py"), "infer", "--local", "--json",
                               "--observation", json.dumps(JOINTS), *args], cwd=repo, env=env, capture_output=True,
                              text=True, timeout=120)

    proc = infer("--frame", str(png))
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    _, vq, tick = _reference(ckpts)
    want, _ = tick(frame, FastLoopNumpy.from_checkpoint(ckpts["fast"]).init_state())
    assert np.abs(np.asarray(out["action"]) - want).max() < 1e-9 and out["code"] == vq.vq.codes(frame).tolist()
    proc = infer("--frame", str(junk))
    assert proc.returncode == 2 and "not a JPEG or PNG image" in json.loads(proc.stdout)["error"], proc.stdout
    proc = infer()
    assert proc.returncode == 2 and "frame is missing" in json.loads(proc.stdout)["error"], proc.stdout


def test_a_reflex_that_reads_no_camera_does_not_replace_one_that_does(ckpts, tmp_path):
    """The robot sends what the served model reads: a swap to a model without the camera (same joints)
    would fail every request that carries a frame, so it is refused and the camera reflex keeps serving."""
    home = tmp_path / "home"
    promote_pointer(home, ckpts["fast"], "fast_loop")
    with BrainService(home, components=("fast_loop",)) as brain:
        served = brain.version("fast_loop")
        promote_pointer(home, ckpts["joints"], "fast_loop", model_id=2)
        brain.check_now()
        status = brain.status()["fast_loop"]
        assert status["version"] == served and status["frame_shape"] == [64, 64, 3]
        assert "does not fit the fast_loop being served" in status["last_error"]
        assert "+ a 64x64x3 camera frame" in status["last_error"]
        out = brain.infer("fast_loop", JOINTS, frame=_raw(moving_frames(1)[0]))
        assert out["model_version"] == served
