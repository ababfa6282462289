"""Frame streaming of the reflex (hope_models.sim.frames): the PNG writer, the JSON lines, pacing,
and a render failure that is reported rather than hidden. The eval-reflex child that streams real
rendered frames is in test_sim_reflex.py (it reuses that module's trained policy); the webapp side
(sim.frame over Socket.IO) in test_api.py."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest

from hope_models.sim.frames import FrameStream, png_bytes, png_data_url
from png_decode import decode_data_url, decode_png


def test_png_writer_round_trips_through_an_independent_decoder():
    rng = np.random.default_rng(0)
    for shape in [(1, 1, 3), (7, 13, 3), (128, 128, 3)]:
        img = rng.integers(0, 256, size=shape, dtype=np.uint8)
        assert np.array_equal(decode_png(png_bytes(img)), img)
    img = rng.integers(0, 256, size=(5, 4, 3), dtype=np.uint8)
    assert np.array_equal(decode_data_url(png_data_url(img)), img)
    with pytest.raises(ValueError, match="uint8"):
        png_bytes(np.zeros((4, 4, 3), dtype=np.float32))
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        png_bytes(np.zeros((4, 4), dtype=np.uint8))


class FakeEnv:
    def __init__(self, fail: bool = False):
        self.fail, self.renders = fail, 0

    def render(self, size):
        self.renders += 1
        if self.fail:
            raise RuntimeError("no EGL display")
        img = np.zeros((size, size, 3), dtype=np.uint8)
        img[: self.renders % size] = 200
        return img


class FakeClock:
    def __init__(self):
        self.t, self.slept = 100.0, []

    def __call__(self):
        return self.t

    def sleep(self, s):
        self.slept.append(s)
        self.t += s


def _run(stream, env, steps=100):
    for t in range(steps + 1):
        stream.on_step(env, episode=0, seed=3, step=t, return_so_far=float(t // 2), last=t == steps)


def test_frames_every_round_50_over_fps_steps_plus_the_last_paced_to_real_time():
    out, clock = io.StringIO(), FakeClock()
    stream = FrameStream(out, fps=10, size=32, speed=1.0, clock=clock, sleep=clock.sleep)
    _run(stream, FakeEnv(), steps=98)
    lines = [json.loads(x) for x in out.getvalue().splitlines()]
    steps = [x["frame"]["step"] for x in lines]
    assert steps == list(range(0, 98, 5)) + [98]
    assert stream.summary() == {"fps": 10.0, "size": 32, "speed": 1.0, "sent": len(steps), "error": None}
    last = lines[-1]["frame"]
    assert last["done"] is True and last["return_so_far"] == 49.0 and last["seed"] == 3 and last["episode"] == 0
    assert not any(x["frame"]["done"] for x in lines[:-1])
    assert decode_data_url(last["image"]).shape == (32, 32, 3)
    # the fake sim takes no time, so the stream waited: simulated time never ahead of wall time
    assert clock.t - 100.0 == pytest.approx(98 * 0.02)
    # speed 0: no waiting at all
    clock2 = FakeClock()
    _run(FrameStream(io.StringIO(), fps=10, speed=0, clock=clock2, sleep=clock2.sleep), FakeEnv())
    assert clock2.slept == []


def test_a_render_failure_is_said_once_and_no_frame_is_pretended():
    out = io.StringIO()
    env = FakeEnv(fail=True)
    stream = FrameStream(out, fps=25, speed=0)
    _run(stream, env)
    lines = [json.loads(x) for x in out.getvalue().splitlines()]
    assert len(lines) == 1 and "no EGL display" in lines[0]["frame_error"]
    assert "cannot render" in lines[0]["frame_error"]
    assert env.renders == 1  # it gave up after the first failure
    assert stream.sent == 0 and stream.error == lines[0]["frame_error"]


def test_bad_stream_settings_are_refused():
    with pytest.raises(ValueError, match="fps"):
        FrameStream(io.StringIO(), fps=0)
    with pytest.raises(ValueError, match="fps"):
        FrameStream(io.StringIO(), fps=51)
    with pytest.raises(ValueError, match="size"):
        FrameStream(io.StringIO(), fps=10, size=8)
    with pytest.raises(ValueError, match="speed"):
        FrameStream(io.StringIO(), fps=10, speed=-1)
