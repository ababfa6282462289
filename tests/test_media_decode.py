"""hope_models.media: each format decodes to what Pillow / PyAV / numpy give directly (with the
same area resize), JPEG goes through draft mode, videos give frames by time, and every bad file
(truncated, a declared bomb, audio only, wrong dtype, empty, random bytes) is a MediaError naming
the file with no warning escaping.

Inputs follow what the robot writes (continuonbrain/recording/camera_episode_recorder.py):
480x640 frames, JPEG at quality 85, np.save of uint8 [H, W, 3] arrays and of uint16 [H, W]
depth in millimetres.
"""
from __future__ import annotations

import struct
import subprocess
import sys
import textwrap
import warnings
import zlib
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image, ImageFile

from hope_models.media import MediaError, VideoFrames, area_resize, decode_still, floats_to_uint8, probe, sniff
from hope_models.media.image import read_image

REPO = Path(__file__).resolve().parents[1]
OUT = (64, 64)
COLOURS = [(230, 20, 20), (20, 230, 20), (20, 20, 230), (230, 230, 20), (20, 230, 230), (230, 20, 230),
           (128, 128, 128), (250, 250, 250)]


def scene(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Camera-like content (gradients, edges, noise), not flat colour: JPEG has work to do."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.stack([x / w * 255, y / h * 255, (x + y) / (w + h) * 255], axis=2)
    img[h // 4: h // 2, w // 3: w // 2] = (200, 40, 90)
    img += rng.normal(0, 12, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def pil_box(img: Image.Image, hw=OUT) -> np.ndarray:
    return np.asarray(img.resize((hw[1], hw[0]), Image.Resampling.BOX))


def strict(fn, *args, **kwargs):
    """Call with every warning an error: nothing may escape as a warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return fn(*args, **kwargs)


def media_error(fn, *args, **kwargs) -> str:
    with pytest.raises(MediaError) as info:
        strict(fn, *args, **kwargs)
    return str(info.value)


# -- sniff and probe ------------------------------------------------------------------------------

def write_jpeg(path: Path, arr: np.ndarray, quality: int = 85) -> Path:
    Image.fromarray(arr).save(path, "JPEG", quality=quality)
    return path


def test_sniff_reads_magic_bytes_not_names(tmp_path):
    arr = scene(48, 64)
    write_jpeg(tmp_path / "a.png", arr)  # a JPEG under a PNG name
    Image.fromarray(arr).save(tmp_path / "b.jpg", "PNG")
    with open(tmp_path / "c.bin", "wb") as f:
        np.save(f, arr)
    (tmp_path / "empty.jpg").write_bytes(b"")
    (tmp_path / "noise.npy").write_bytes(np.random.default_rng(1).bytes(300))
    assert sniff(tmp_path / "a.png") == "jpeg"
    assert sniff(tmp_path / "b.jpg") == "png"
    assert sniff(tmp_path / "c.bin") == "npy"
    assert sniff(tmp_path / "empty.jpg") == "empty"
    assert sniff(tmp_path / "noise.npy") is None
    # decoded as what they are
    assert np.array_equal(decode_still(tmp_path / "b.jpg", OUT), pil_box(Image.fromarray(arr)))
    assert probe(tmp_path / "a.png").format == "JPEG"


def test_probe_reads_headers(tmp_path):
    write_jpeg(tmp_path / "f.jpg", scene(480, 640))
    np.save(tmp_path / "d.npy", np.zeros((480, 640), np.uint16))
    Image.fromarray(np.zeros((30, 40), np.uint16)).save(tmp_path / "d.png")
    info = probe(tmp_path / "f.jpg")
    assert (info.format, info.height, info.width, info.channels, info.dtype) == ("JPEG", 480, 640, 3, "uint8")
    assert info.describe(OUT) == "JPEG 480x640 -> 64x64"
    assert probe(tmp_path / "d.npy").describe((48, 64)) == "NPY 480x640 -> 48x64"
    assert (probe(tmp_path / "d.npy").channels, probe(tmp_path / "d.npy").dtype) == (1, "uint16")
    assert probe(tmp_path / "d.png").dtype == "uint16"
    video = make_video(tmp_path / "v.mp4", "libx264", n=3)
    assert (probe(video).format, probe(video).height, probe(video).width) == ("MP4", 48, 64)
    assert probe(make_video(tmp_path / "v.webm", "libvpx-vp9", n=3)).format == "WEBM"


# -- stills ---------------------------------------------------------------------------------------

def test_jpeg_equals_pillow_draft_plus_area_resize(tmp_path):
    arr = scene(480, 640)
    path = write_jpeg(tmp_path / "f.jpg", arr)
    got = strict(decode_still, path, OUT)
    ref = Image.open(path)
    ref.draft("RGB", (64, 64))
    assert ref.size == (160, 120)  # 480 // 64 = 7: 1/8 would be 60 high, under 64; 1/4 it is
    assert got.dtype == np.uint8 and got.shape == (64, 64, 3)
    assert np.array_equal(got, pil_box(ref.convert("RGB")))
    # Against a full-size decode: libjpeg's scaled IDCT is not a box filter of the full decode,
    # so levels differ a little; the picture is the same.
    full = pil_box(Image.open(path).convert("RGB")).astype(int)
    diff = np.abs(got.astype(int) - full)
    assert diff.mean() < 1.5 and np.percentile(diff, 99) <= 6, (diff.mean(), diff.max())


def test_jpeg_is_decoded_in_draft_mode_at_a_reduced_size(tmp_path):
    path = write_jpeg(tmp_path / "big.jpg", scene(960, 1280))
    with open(path, "rb") as f:
        # 1280/64 = 20, 960/64 = 15: libjpeg's largest scale 1/8 -> 160x120, never 1280x960
        assert read_image(f, "jpeg", str(path), OUT, "rgb", 50_000_000).size == (160, 120)
    with open(path, "rb") as f:
        # an output near the native size gets no reduction
        assert read_image(f, "jpeg", str(path), (700, 1000), "rgb", 50_000_000).size == (1280, 960)
    grey = tmp_path / "grey.jpg"
    Image.fromarray(scene(960, 1280)[:, :, 0]).save(grey, "JPEG", quality=85)
    got = decode_still(grey, OUT)
    assert got.shape == (64, 64, 3) and np.array_equal(got[:, :, 0], got[:, :, 2])


@pytest.mark.parametrize("mode", ["RGB", "RGBA", "L", "LA", "P"])
def test_png_modes_become_rgb_like_pillow_converts_them(tmp_path, mode):
    base = Image.fromarray(scene(120, 160))
    img = base.convert(mode) if mode != "LA" else base.convert("L").convert("LA")
    if mode == "RGBA":
        alpha = Image.fromarray(np.tile(np.arange(160, dtype=np.uint8), (120, 1)))
        img.putalpha(alpha)
    path = tmp_path / f"f_{mode}.png"
    img.save(path)
    got = strict(decode_still, path, OUT)
    assert got.dtype == np.uint8 and got.shape == (64, 64, 3)
    # the alpha is dropped, not composited: colour values are what the file stores
    assert np.array_equal(got, pil_box(Image.open(path).convert("RGB")))


def test_png_16bit_grey_is_depth_in_millimetres(tmp_path):
    mm = np.full((128, 128), 1500, np.uint16)
    mm[:, 64:] = 2500
    mm[::2, ::2] = 0  # a quarter of the readings missing
    mm[0:2, 0:2] = 0  # one output pixel with no reading at all
    path = tmp_path / "depth.png"
    Image.fromarray(mm).save(path)
    got = strict(decode_still, path, OUT, kind="depth")
    assert got.dtype == np.float32 and got.shape == (64, 64, 1)
    # 2x2 blocks: the mean of the readings present, 0 where none is
    blocks = mm.astype(np.float64).reshape(64, 2, 64, 2).transpose(0, 2, 1, 3).reshape(64, 64, 4) / 1000
    count = (blocks > 0).sum(axis=2)
    ref = np.where(count > 0, blocks.sum(axis=2) / np.maximum(count, 1), 0.0)
    assert np.allclose(got[:, :, 0], ref, atol=1e-6), np.abs(got[:, :, 0] - ref).max()
    assert got[0, 0, 0] == 0.0 and got[1, 1, 0] == pytest.approx(1.5) and got[1, 40, 0] == pytest.approx(2.5)
    assert "depth" in media_error(decode_still, path, OUT)  # colour from a depth PNG is refused
    assert "not a depth image" in media_error(decode_still, write_jpeg(tmp_path / "c.jpg", scene(64, 64)), OUT,
                                              kind="depth")


def test_npy_colour_frames(tmp_path):
    rgb = scene(480, 640)  # taken as RGB: a BGR array from the OAK-D stays in its order
    np.save(tmp_path / "rgb.npy", rgb)
    assert np.array_equal(strict(decode_still, tmp_path / "rgb.npy", OUT), pil_box(Image.fromarray(rgb)))
    rgba = np.dstack([rgb, np.full(rgb.shape[:2], 7, np.uint8)])
    np.save(tmp_path / "rgba.npy", rgba)
    assert np.array_equal(decode_still(tmp_path / "rgba.npy", OUT), pil_box(Image.fromarray(rgb)))
    grey = rgb[:, :, 1]
    for name, arr in (("g2.npy", grey), ("g3.npy", grey[:, :, None])):
        np.save(tmp_path / name, arr)
        assert np.array_equal(decode_still(tmp_path / name, OUT), pil_box(Image.fromarray(np.dstack([grey] * 3))))
    floats = (rgb / 255.0).astype(np.float32)
    np.save(tmp_path / "f.npy", floats)
    assert np.array_equal(decode_still(tmp_path / "f.npy", OUT), pil_box(Image.fromarray(np.rint(floats * 255).astype(np.uint8))))
    np.save(tmp_path / "fortran.npy", np.asfortranarray(rgb))
    assert np.array_equal(decode_still(tmp_path / "fortran.npy", OUT), pil_box(Image.fromarray(rgb)))
    np.save(tmp_path / "big_endian.npy", rgb.astype(">f4") / 255)
    assert decode_still(tmp_path / "big_endian.npy", OUT).shape == (64, 64, 3)
    np.save(tmp_path / "over.npy", floats * 2)
    assert "expected [0, 1]" in media_error(decode_still, tmp_path / "over.npy", OUT)
    # the native size is any size: no resize when it already is the output size
    np.save(tmp_path / "small.npy", rgb[:64, :64])
    assert np.array_equal(decode_still(tmp_path / "small.npy", OUT), rgb[:64, :64])


def test_npy_depth_frames(tmp_path):
    mm = np.random.default_rng(3).integers(500, 5000, (480, 640)).astype(np.uint16)
    np.save(tmp_path / "mm.npy", mm)  # what the recorder writes for depth
    got = strict(decode_still, tmp_path / "mm.npy", OUT, kind="depth")
    ref = np.asarray(Image.fromarray(mm.astype(np.float32) / 1000).resize((64, 64), Image.Resampling.BOX))
    assert got.dtype == np.float32 and got.shape == (64, 64, 1)
    assert np.allclose(got[:, :, 0], ref, rtol=1e-6)  # no zeros: the plain box mean
    metres = (mm.astype(np.float32) / 1000)[:, :, None]
    np.save(tmp_path / "m.npy", metres)
    assert np.allclose(decode_still(tmp_path / "m.npy", OUT, kind="depth"), got, rtol=1e-6)
    assert "kind='depth'" in media_error(decode_still, tmp_path / "mm.npy", OUT)
    np.save(tmp_path / "rgb.npy", scene(48, 64))
    assert "not a depth image" in media_error(decode_still, tmp_path / "rgb.npy", OUT, kind="depth")


def test_area_resize_dtypes_and_caller_errors():
    rgb = scene(100, 50)
    assert np.array_equal(area_resize(rgb, (10, 5)), pil_box(Image.fromarray(rgb), (10, 5)))
    depth = np.full((100, 50, 1), 2.0, np.float32)
    assert area_resize(depth, (10, 5)).dtype == np.float32
    with pytest.raises(ValueError, match="uint8 \\[h, w, 3\\] or float32"):
        area_resize(rgb.astype(np.float64), (10, 5))
    with pytest.raises(ValueError, match="out_hw"):
        area_resize(rgb, (0, 5))
    assert floats_to_uint8(np.array([0.0, 0.5, 1.0], np.float32)).tolist() == [0, 128, 255]
    # depth: zeros, NaN and negatives are no reading, left out of the mean
    holes = np.full((4, 4, 1), 3.0, np.float32)
    holes[0, 0], holes[0, 1], holes[1, 0] = 0.0, np.nan, -1.0
    holes[2:, 2:] = 0.0
    assert area_resize(holes, (2, 2))[:, :, 0].tolist() == [[3.0, 3.0], [3.0, 0.0]]


def test_probe_reads_only_the_header(tmp_path):
    """A JPEG cut after its header probes fine (nothing decoded) and fails to decode."""
    data = write_jpeg(tmp_path / "f.jpg", scene(480, 640)).read_bytes()
    (tmp_path / "cut.jpg").write_bytes(data[:2000])
    assert strict(probe, tmp_path / "cut.jpg").describe(OUT) == "JPEG 480x640 -> 64x64"
    assert "truncated" in media_error(decode_still, tmp_path / "cut.jpg", OUT)


# -- videos ---------------------------------------------------------------------------------------

def make_video(path: Path, codec: str, n: int = 8, fps: int = 10, hw=(48, 64)) -> Path:
    """n frames, frame i a solid COLOURS[i], at fps frames per second."""
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=fps)
        stream.height, stream.width = hw
        stream.pix_fmt = "yuv420p"
        for i in range(n):
            frame = av.VideoFrame.from_ndarray(np.full((*hw, 3), COLOURS[i % len(COLOURS)], np.uint8),
                                               format="rgb24")
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def make_audio_only(path: Path, codec: str) -> Path:
    with av.open(str(path), "w") as out:
        stream = out.add_stream(codec, rate=48000)
        for i in range(10):
            frame = av.AudioFrame.from_ndarray(np.zeros((1, 960), np.float32) + i * 0.01, format="flt",
                                               layout="mono")
            frame.sample_rate = 48000
            frame.pts = i * 960
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return path


def nearest_colour(frame: np.ndarray) -> int:
    mean = frame.reshape(-1, 3).mean(axis=0)
    return int(np.argmin([np.abs(mean - c).sum() for c in COLOURS]))


@pytest.mark.parametrize("name,codec", [("h264.mp4", "libx264"), ("vp8.webm", "libvpx"), ("vp9.webm", "libvpx-vp9")])
def test_frames_at_picks_the_frame_by_time(tmp_path, name, codec):
    path = make_video(tmp_path / name, codec)
    # frames at 0.0, 0.1, ..., 0.7 s: the last at or before t, the first before it, the last after the end
    times = [-0.5, 0.0, 0.05, 0.1, 0.1499, 0.2, 0.3, 0.35, 0.6 - 1e-3, 0.7, 0.71, 30.0]
    expected = [0, 0, 0, 1, 1, 2, 3, 3, 5, 7, 7, 7]
    with VideoFrames(path) as video:
        assert video.info.format == ("MP4" if name.endswith(".mp4") else "WEBM")
        assert (video.info.height, video.info.width, video.info.channels) == (48, 64, 3)
        assert video.duration_s is None or 0.7 <= video.duration_s <= 0.9
        got = strict(lambda: list(video.frames_at(times, (12, 16))))
        assert [nearest_colour(f) for f in got] == expected
        assert all(f.shape == (12, 16, 3) and f.dtype == np.uint8 for f in got)
        # again from the start (the file is reopened), and each frame is its own array
        again = list(video.frames_at([0.3], (12, 16)))
        assert nearest_colour(again[0]) == 3
        got[0][:] = 0
        assert nearest_colour(got[1]) == 0
        with pytest.raises(ValueError, match="non-decreasing"):
            list(video.frames_at([0.2, 0.1], (12, 16)))
        # a depth camera pointing at a video is the data's fault: a MediaError naming the file
        assert "holds colour frames, not depth" in media_error(video.frames_at, [0.0], (12, 16), kind="depth")
        with pytest.raises(ValueError, match="kind 'ir'"):
            video.frames_at([0.0], (12, 16), kind="ir")


def test_video_frames_equal_pyav_decode_plus_area_resize(tmp_path):
    path = tmp_path / "scene.mp4"
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=30)
        stream.height, stream.width, stream.pix_fmt = 240, 320, "yuv420p"
        for i in range(6):
            for packet in stream.encode(av.VideoFrame.from_ndarray(scene(240, 320, seed=i), format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    with av.open(str(path)) as container:
        frames = list(container.decode(video=0))
        pts0, base = frames[0].pts, Fraction(frames[0].time_base)
        ref = [(float((f.pts - pts0) * base), pil_box(f.to_image(), (60, 80))) for f in frames]
    assert len(ref) == 6
    times = [t for t, _ in ref]
    with VideoFrames(path) as video:
        got = list(video.frames_at(times, (60, 80)))
    for (t, want), have in zip(ref, got, strict=True):
        assert np.array_equal(have, want), t


def test_video_frames_hold_no_whole_video():
    """A few hundred 640x480 frames through frames_at: RSS stays near a baseline taken in the same
    process after the first frames; holding the decoded frames (the control at the end) would not."""
    script = textwrap.dedent("""
        import sys, tempfile, os
        import av, numpy as np, psutil
        from hope_models.media import VideoFrames
        N, H, W = 300, 480, 640
        tmp = tempfile.mkdtemp()
        path = os.path.join(tmp, "long.mp4")
        rng = np.random.default_rng(0)
        base = rng.integers(0, 255, (H, W, 3), dtype=np.uint8)
        with av.open(path, "w") as out:
            s = out.add_stream("libx264", rate=30)
            s.height, s.width, s.pix_fmt = H, W, "yuv420p"
            s.options = {"preset": "ultrafast"}
            for i in range(N):
                for p in s.encode(av.VideoFrame.from_ndarray(np.roll(base, i * 3, axis=1), format="rgb24")):
                    out.mux(p)
            for p in s.encode():
                out.mux(p)
        proc = psutil.Process()
        times = [i / 30 for i in range(N)]
        with VideoFrames(path) as video:
            it = video.frames_at(times, (64, 64))
            for _ in range(10):
                next(it)
            baseline = proc.memory_info().rss
            peak, count = baseline, 10
            for frame in it:
                count += 1
                peak = max(peak, proc.memory_info().rss)
        # control: the same frames held decoded, as a decoder that kept the video would
        held = []
        with av.open(path) as c:
            for f in c.decode(video=0):
                held.append(f.to_ndarray(format="rgb24"))
        control = proc.memory_info().rss - baseline
        print(count, peak - baseline, control)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-3000:]
    count, growth, control = (int(x) for x in proc.stdout.split())
    assert count == 300
    limit = 40 * 2**20  # 300 RGB frames are 276 MB; one is 0.9 MB
    assert control > limit, f"the control held {control / 2**20:.0f} MB: the measure cannot tell"
    assert growth < limit, f"RSS grew {growth / 2**20:.1f} MB while streaming 300 frames"


# -- bad media ------------------------------------------------------------------------------------

def png_declaring(width: int, height: int) -> bytes:
    """A small PNG whose IHDR declares width x height RGB (with a correct CRC) over a tiny IDAT."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\x00" * 1000))
            + chunk(b"IEND", b""))


@pytest.mark.parametrize("width,height,why", [
    (100_000, 100_000, "declares too many pixels"),  # above twice Pillow's limit: its error
    (10_000, 10_000, "declares too many pixels"),  # between Pillow's limit and twice it: its warning
    (8_000, 8_000, "max_pixels"),  # under Pillow's limit, over ours
])
def test_png_bomb_is_refused_before_decoding(tmp_path, width, height, why):
    path = tmp_path / "bomb.png"
    path.write_bytes(png_declaring(width, height))
    assert len(path.read_bytes()) < 200
    for call in (lambda: decode_still(path, OUT), lambda: probe(path)):
        message = media_error(call)
        assert str(path) in message and why in message, message


def test_no_pillow_global_is_changed(tmp_path):
    pixels, truncated = Image.MAX_IMAGE_PIXELS, ImageFile.LOAD_TRUNCATED_IMAGES
    filters = list(warnings.filters)
    path = tmp_path / "bomb.png"
    path.write_bytes(png_declaring(10_000, 10_000))
    media_error(decode_still, path, OUT)
    decode_still(write_jpeg(tmp_path / "ok.jpg", scene(48, 64)), OUT)
    assert (Image.MAX_IMAGE_PIXELS, ImageFile.LOAD_TRUNCATED_IMAGES) == (pixels, truncated)
    assert warnings.filters == filters


def test_max_pixels_applies_to_npy_and_video(tmp_path):
    np.save(tmp_path / "big.npy", np.zeros((100, 100, 3), np.uint8))
    assert "max_pixels" in media_error(decode_still, tmp_path / "big.npy", OUT, max_pixels=5000)
    video = make_video(tmp_path / "v.mp4", "libx264", n=2)
    assert "max_pixels" in media_error(VideoFrames, video, max_pixels=1000)
    assert "max_pixels" in media_error(probe, video, max_pixels=1000)


def test_bad_media_is_a_media_error_naming_the_file(tmp_path):
    rng = np.random.default_rng(7)
    good = write_jpeg(tmp_path / "good.jpg", scene(480, 640)).read_bytes()
    cases: dict[str, tuple[bytes, str]] = {
        "truncated.jpg": (good[: len(good) // 2], "truncated"),
        "empty.jpg": (b"", "empty file (0 bytes)"),
        "noise.jpg": (rng.bytes(5000), "not a known media file"),
        "bad_header.jpg": (b"\xff\xd8\xff" + rng.bytes(5000), "undecodable JPEG"),
        "bad_png.png": (b"\x89PNG\r\n\x1a\n" + rng.bytes(500), "undecodable PNG"),
        "pickled.npy": (b"", "Python objects"),
    }
    for name, (data, why) in cases.items():
        if name == "pickled.npy":
            np.save(tmp_path / name, np.array([{"a": 1}], dtype=object), allow_pickle=True)
        else:
            (tmp_path / name).write_bytes(data)
        for kind in ("rgb", "depth"):
            message = media_error(decode_still, tmp_path / name, OUT, kind=kind, where="blobs/x.jpg")
            assert f"blobs/x.jpg ({tmp_path / name})" in message and why in message, (name, message)
    assert "empty file (0 bytes)" in media_error(VideoFrames, tmp_path / "empty.jpg")
    assert "not a video" in media_error(VideoFrames, tmp_path / "good.jpg")
    assert "file not found" in media_error(probe, tmp_path / "missing.jpg", where="blobs/m.jpg")


@pytest.mark.parametrize("dtype", ["int64", "float64", "bool", "int16", "complex64"])
def test_npy_of_a_wrong_dtype_names_it(tmp_path, dtype):
    path = tmp_path / f"{dtype}.npy"
    np.save(path, np.ones((48, 64, 3), dtype=dtype))
    for call in (lambda: decode_still(path, OUT), lambda: decode_still(path, OUT, kind="depth"),
                 lambda: probe(path)):
        message = media_error(call)
        assert str(path) in message and f"dtype {dtype}" in message and "accepted: uint8" in message, message


def test_npy_of_a_wrong_shape_or_size(tmp_path):
    np.save(tmp_path / "stack.npy", np.zeros((4, 48, 64, 3), np.uint8))
    assert "not one frame" in media_error(decode_still, tmp_path / "stack.npy", OUT)
    np.save(tmp_path / "cut.npy", np.zeros((48, 64, 3), np.uint8))
    data = (tmp_path / "cut.npy").read_bytes()
    (tmp_path / "cut.npy").write_bytes(data[:-100])
    assert "truncated" in media_error(decode_still, tmp_path / "cut.npy", OUT)


@pytest.mark.parametrize("name,codec", [("audio.mp4", "aac"), ("audio.webm", "libopus")])
def test_audio_only_video_is_refused(tmp_path, name, codec):
    path = make_audio_only(tmp_path / name, codec)
    assert sniff(path) == name.split(".")[1]
    for call in (lambda: VideoFrames(path, where="blobs/a"), lambda: probe(path, where="blobs/a")):
        message = media_error(call)
        assert f"blobs/a ({path})" in message and "no video stream (streams: audio)" in message, message


def test_broken_video_bytes(tmp_path):
    good = make_video(tmp_path / "v.mp4", "libx264").read_bytes()
    (tmp_path / "cut.mp4").write_bytes(good[:40])
    (tmp_path / "noise.webm").write_bytes(b"\x1a\x45\xdf\xa3" + np.random.default_rng(2).bytes(4000))
    for name in ("cut.mp4", "noise.webm"):
        message = media_error(VideoFrames, tmp_path / name)
        assert str(tmp_path / name) in message, message
    assert "VideoFrames" in media_error(decode_still, tmp_path / "v.mp4", OUT)
