#!/usr/bin/env python3
"""Camera-frame decoding benchmark (hope_models.media): frames/s on one core, and the peak RSS of
a long video decoded frame by frame.

Prints figures; it is not a test. One run:
  1. generates, in a temp dir, --frames 640x480 JPEGs (quality 85, camera-like content: gradients,
     shapes, texture, sensor noise; what the robot's recorder writes with cv2), the same frames as
     480x640x3 uint8 .npy files, a 10 s 30 fps 640x480 H.264 video of them, and a --minutes long
     one (18000 frames for 10 minutes; the time its generation took is printed),
  2. in a subprocess pinned to ONE core (os.sched_setaffinity), decodes every still with
     decode_still to --out-hw (64x64) and the 10 s video with VideoFrames.frames_at, each against a
     BASELINE measured in the same process: the full-size decode a naive loader does
     (Image.open().convert("RGB"), np.load, the video's frames as full RGB arrays), with the same
     area resize,
  3. in a fresh pinned subprocess, decodes the long video into 64x64 frames and reports its peak
     RSS (VmHWM) and the growth over the RSS right after opening the video,
  4. in a fresh pinned subprocess, builds the training cache of that video as one episode (one
     step per frame, as a producer recording a session writes it) and reports its peak RSS,
  5. prints a table and PASS/FAIL for >= 1000 JPEG frames/s on one core and < 200 MB for the build.

    python bench/frames.py [--frames 200] [--minutes 10] [--out-hw 64 64] [--out DIR] [--keep]

The lead's cache build can reuse measure_video_rss(path, out_hw) (a dict of figures) and
pinned_child(kind, *args) (the same measure in a fresh process on one core).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from hope_models.media import VideoFrames, area_resize, decode_still  # noqa: E402 (after the sys.path setup)

H, W, FPS = 480, 640, 30
MB = 1 << 20


def pin_one_core() -> int:
    """Run on one core only (the lowest this process may use); returns it."""
    core = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {core})
    return core


def peak_rss() -> int:
    """The process's peak RSS in bytes since it was started (VmHWM). Not ru_maxrss: that one
    survives exec, so a child started from a big parent reports the parent's peak."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def _rss() -> int:
    import psutil

    return psutil.Process().memory_info().rss


# -- inputs ---------------------------------------------------------------------------------------

def camera_frame(i: int, rng: np.random.Generator) -> np.ndarray:
    """A camera-like 480x640 RGB frame: lit gradient, a few objects, texture, sensor noise; the
    scene pans with i so consecutive frames differ as a moving robot's do."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    x = x + 4 * i
    img = np.empty((H, W, 3), np.float32)
    img[..., 0] = 90 + 60 * np.sin(x / 140) + 0.1 * y
    img[..., 1] = 110 + 50 * np.cos(y / 90) + 20 * np.sin((x + y) / 60)
    img[..., 2] = 70 + 0.15 * y + 30 * np.sin(x / 33) * np.cos(y / 47)
    floor = y > 300
    img[floor] = img[floor] * 0.6 + 40 * (((x[floor] // 40 + y[floor] // 40) % 2)[:, None])  # tiled floor
    for k in range(4):
        cy, cx, r = 120 + 60 * k, (150 * k + 5 * i) % W, 30 + 10 * k
        disk = (y - cy) ** 2 + (x % W - cx) ** 2 < r * r
        img[disk] = (40 + 50 * k, 200 - 40 * k, 90 + 30 * k)
    img += rng.normal(0, 3.0, img.shape)  # sensor noise
    return np.clip(img, 0, 255).astype(np.uint8)


def write_stills(work: Path, n: int) -> tuple[list[Path], list[Path], float]:
    from PIL import Image

    rng = np.random.default_rng(0)
    jpegs, npys, total = [], [], 0
    for i in range(n):
        frame = camera_frame(i, rng)
        jpeg, npy = work / f"f{i:04d}.jpg", work / f"f{i:04d}.npy"
        Image.fromarray(frame).save(jpeg, "JPEG", quality=85)
        np.save(npy, frame)
        jpegs.append(jpeg)
        npys.append(npy)
        total += jpeg.stat().st_size
    return jpegs, npys, total / n


def write_video(path: Path, frames: int) -> float:
    """An H.264 640x480 30 fps video panning over the scene; returns the seconds it took."""
    import av

    started = time.perf_counter()
    rng = np.random.default_rng(1)
    base = [camera_frame(i, rng) for i in range(8)]  # a few frames, rolled: generating each costs more than encoding
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=FPS)
        stream.height, stream.width, stream.pix_fmt = H, W, "yuv420p"
        stream.options = {"preset": "veryfast", "crf": "23"}
        for i in range(frames):
            frame = np.roll(base[i % len(base)], 3 * i, axis=1)
            for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                out.mux(packet)
        for packet in stream.encode():
            out.mux(packet)
    return time.perf_counter() - started


# -- measures (run in a pinned child) -------------------------------------------------------------

def _rate(fn, items: list, min_s: float = 2.0) -> float:
    """Items per second of fn over the items, repeated until at least min_s has passed."""
    done, started = 0, time.perf_counter()
    while True:
        for item in items:
            fn(item)
        done += len(items)
        elapsed = time.perf_counter() - started
        if elapsed >= min_s:
            return done / elapsed


def measure_stills(jpeg_dir: str, out_h: str, out_w: str) -> dict:
    from PIL import Image

    out_hw = (int(out_h), int(out_w))
    jpegs = sorted(Path(jpeg_dir).glob("*.jpg"))
    npys = sorted(Path(jpeg_dir).glob("*.npy"))

    def full_jpeg(p: Path) -> np.ndarray:
        with Image.open(p) as img:
            return area_resize(np.asarray(img.convert("RGB")), out_hw)

    def full_npy(p: Path) -> np.ndarray:
        return area_resize(np.load(p, allow_pickle=False), out_hw)

    diffs = np.stack([np.abs(decode_still(p, out_hw).astype(int) - full_jpeg(p).astype(int)) for p in jpegs[:20]])
    return {"core": pin_one_core(),
            "jpeg": _rate(lambda p: decode_still(p, out_hw), jpegs),
            "jpeg_full": _rate(full_jpeg, jpegs),
            "npy": _rate(lambda p: decode_still(p, out_hw), npys),
            "npy_full": _rate(full_npy, npys),
            "draft_vs_full": [float(diffs.mean()), float(np.percentile(diffs, 99)), int(diffs.max())]}


def measure_video(path: str, out_h: str, out_w: str) -> dict:
    import av

    core = pin_one_core()
    out_hw = (int(out_h), int(out_w))
    with av.open(path) as c:
        n = c.streams.video[0].frames
    times = [i / FPS for i in range(n)]
    started = time.perf_counter()
    with VideoFrames(path) as video:
        got = sum(1 for _ in video.frames_at(times, out_hw))
    ours = got / (time.perf_counter() - started)
    # the decode alone, no conversion: what frames_at cannot beat
    started = time.perf_counter()
    with av.open(path) as c:
        c.streams.video[0].thread_count = 1
        decoded = sum(1 for _ in c.decode(video=0))
    decode_only = decoded / (time.perf_counter() - started)
    return {"core": core, "frames": got, "video": ours, "decode_only": decode_only}


def measure_video_rss(path: str | os.PathLike, out_hw: tuple[int, int]) -> dict:
    """Decode every frame of a video into out_hw frames: frames, seconds, peak RSS (VmHWM, the
    whole process) and its growth over the RSS right after the video was opened, in MB."""
    import av

    with av.open(str(path)) as c:
        stream = c.streams.video[0]
        n = stream.frames or int(float(stream.duration * stream.time_base) * FPS)
    times = [i / FPS for i in range(n)]
    started = time.perf_counter()
    with VideoFrames(path) as video:
        opened = _rss()
        got = 0
        for _ in video.frames_at(times, out_hw):
            got += 1
    seconds = time.perf_counter() - started
    peak = peak_rss()
    return {"frames": got, "seconds": seconds, "peak_rss_mb": peak / MB, "opened_rss_mb": opened / MB,
            "growth_mb": (peak - opened) / MB}


def child_rss(path: str, out_h: str, out_w: str) -> dict:
    core = pin_one_core()
    return {"core": core, **measure_video_rss(path, (int(out_h), int(out_w)))}


def write_video_episode(work: Path, video: Path, frames: int) -> Path:
    """A dataset of one episode as a producer that records a session video writes it: one step per
    video frame (30 Hz joints and command), every step naming the same file."""
    ep = work / "video_ds" / "session"
    ep.mkdir(parents=True, exist_ok=True)
    os.link(video, ep / "session.mp4")  # a hard link: the episode dir must hold its files itself
    steps = [{"observation": {"robot_state": {"joint_positions": [np.sin(i / 90), np.cos(i / 70), 0.1]},
                              "egocentric_video": {"uri": "session.mp4"}},
              "action": {"command": [np.sin(i / 50), 0.2]}, "timestamp_ns": 1_000_000_000 + i * 1_000_000_000 // FPS}
             for i in range(frames)]
    (ep / "episode.json").write_text(json.dumps({"metadata": {"episode_id": "session"}, "steps": steps}))
    return ep.parent


def child_cache(dataset: str, cache_root: str) -> dict:
    """The whole cache build of a video episode (hope_models.data.cache.load_or_build: spec
    inference, every frame decoded and resized, the arrays written), as `dataset` runs it."""
    from hope_models.data.cache import load_or_build

    core = pin_one_core()
    started = time.perf_counter()
    cache, _info = load_or_build(dataset, cache_root)
    seconds = time.perf_counter() - started
    frames = 0 if cache.frames is None else int(cache.frames.shape[0])
    return {"core": core, "frames": frames, "seconds": seconds, "peak_rss_mb": peak_rss() / MB}


CHILDREN = {"stills": measure_stills, "video": measure_video, "rss": child_rss, "cache": child_cache}


def pinned_child(kind: str, *args: str) -> dict:
    """One measure in a fresh process of its own (pinned to one core there): its JSON result."""
    proc = subprocess.run([sys.executable, __file__, "_child", kind, *args], capture_output=True, text=True,
                          cwd=REPO)
    if proc.returncode != 0:
        raise SystemExit(f"bench child {kind} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- the run --------------------------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=200, help="distinct 640x480 stills (JPEG and .npy each)")
    p.add_argument("--minutes", type=float, default=10.0, help="length of the long video for the RSS figure")
    p.add_argument("--out-hw", type=int, nargs=2, default=[64, 64], metavar=("H", "W"))
    p.add_argument("--out", help="work dir (default: a temp dir)")
    p.add_argument("--keep", action="store_true", help="keep the generated files")
    a = p.parse_args(argv)
    out_h, out_w = str(a.out_hw[0]), str(a.out_hw[1])
    work = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="hope-frames-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        started = time.perf_counter()
        jpegs, _npys, jpeg_bytes = write_stills(work, a.frames)
        print(f"wrote {a.frames} JPEGs (mean {jpeg_bytes / 1024:.0f} KiB, quality 85) and .npy files "
              f"in {time.perf_counter() - started:.1f} s", flush=True)
        short = work / "short.mp4"
        print(f"wrote a 10 s H.264 video in {write_video(short, 10 * FPS):.1f} s", flush=True)
        long_video = work / "long.mp4"
        n_long = int(round(a.minutes * 60 * FPS))
        gen_s = write_video(long_video, n_long)
        print(f"wrote a {a.minutes:g} min H.264 video ({n_long} frames, {long_video.stat().st_size / MB:.0f} MB) "
              f"in {gen_s:.0f} s", flush=True)
        stills = pinned_child("stills", str(work), out_h, out_w)
        video = pinned_child("video", str(short), out_h, out_w)
        rss = pinned_child("rss", str(long_video), out_h, out_w)
        cache = pinned_child("cache", str(write_video_episode(work, long_video, n_long)), str(work / "cache"))
        _report(a, stills, video, rss, cache)
    finally:
        if a.keep:
            print(f"kept {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    return 0


def _report(a, stills: dict, video: dict, rss: dict, cache: dict) -> None:
    hw = f"{a.out_hw[0]}x{a.out_hw[1]}"
    print()
    print(f"one core (core {stills['core']}), 640x480 -> {hw}, frames/s")
    print(f"{'':36s} {'ours':>10s} {'baseline':>10s} {'ratio':>7s}")
    for label, ours, base, what in (
            ("JPEG q85 (draft mode)", stills["jpeg"], stills["jpeg_full"], "full-size decode"),
            ("480x640x3 uint8 .npy", stills["npy"], stills["npy_full"], "np.load"),
            ("H.264 30 fps (frames_at)", video["video"], video["decode_only"], "decode only")):
        print(f"{label:36s} {ours:>10,.0f} {base:>10,.0f} {ours / base:>6.2f}x  (baseline: {what})")
    mean, p99, top = stills["draft_vs_full"]
    print(f"JPEG draft vs full-size decode, |diff| over 20 frames: mean {mean:.2f}, 99th percentile {p99:.0f}, "
          f"max {top} levels")
    print(f"{a.minutes:g} min H.264 640x480 -> {hw}: {rss['frames']} frames in {rss['seconds']:.0f} s "
          f"({rss['frames'] / rss['seconds']:,.0f} frames/s), peak RSS {rss['peak_rss_mb']:.0f} MB, "
          f"{rss['growth_mb']:+.1f} MB over the RSS after opening ({rss['opened_rss_mb']:.0f} MB)")
    print(f"cache build of that video as one {rss['frames']}-step episode (load_or_build, default 64x64): "
          f"{cache['frames']} frames in {cache['seconds']:.0f} s, peak RSS {cache['peak_rss_mb']:.0f} MB "
          f"(target < 200) {'PASS' if cache['peak_rss_mb'] < 200 else 'FAIL'}")
    verdict = "PASS" if stills["jpeg"] >= 1000 else "FAIL"
    print(f"JPEG frames/s on one core: {stills['jpeg']:,.0f} (target >= 1000) {verdict}")


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "_child":
        print(json.dumps(CHILDREN[sys.argv[2]](*sys.argv[3:])))
        sys.exit(0)
    sys.exit(main())
