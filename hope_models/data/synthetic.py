#!/usr/bin/env python3
"""Synthetic canonical RLDS datasets: episode dirs exactly as ingest writes them.

Used by the data-pipeline benchmark (bench/gen_dataset.py is its command line), the tests and the
data tour (examples/data_tour.py). The signals are learnable on purpose: joint positions are smooth
sinusoids, velocities their derivative, and the action is a fixed (per seed) squashed linear
function of the current state, so behaviour cloning on a generated dataset has something real to fit.

Lines are formatted with one %-template per dataset instead of json.dumps per step, because the
benchmark writes millions of steps and json.dumps is ~5x slower for float-heavy lines.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ORIGIN_REAL = "synthetic:gen_dataset"
ORIGIN_IMAGINED = "imagined:gen_dataset"
IMAGINED_TAG = "continuon.imagined"
FRAME_SHAPE = (64, 64, 3)


@dataclass
class GeneratedDataset:
    path: Path
    episodes: int
    steps: int
    imagined_episodes: int
    bytes_written: int
    seconds: float


FRAME_BLOB_URI = "blobs/step_%06d_rgb.npy"  # relative to the episode dir, as ingest writes blobs


def _step_template(n_pos: int, n_vel: int, act_dim: int, frames: bool, frame_blobs: bool = False) -> str:
    floats = lambda n: ",".join(["%.6g"] * n)  # noqa: E731 - a tiny local formatter
    image = ',"image_rgb":[%s]' if frames else ""
    if frame_blobs:  # the reference our sim recorder writes: observation.media.rgb
        h, w, _ = FRAME_SHAPE
        image += (',"media":{"rgb":{"uri":"' + FRAME_BLOB_URI + f'","width":{w},"height":{h},'
                  '"format":"npy_uint8_hwc"}}')
    return (
        '{"step_index":%d,"timestamp_ns":%d,"observation":{"robot_state":{"timestamp_nanos":%d,'
        '"joint_positions":[' + floats(n_pos) + '],"joint_velocities":[' + floats(n_vel) + '],'
        '"frame_id":"base_link"}' + image + '},"action":{"command":[' + floats(act_dim) + '],'
        '"source":"human_teleop_xr"},"reward":%.6g,"is_terminal":%s,"step_metadata":{}}'
    )


def _episode_signals(rng: np.random.Generator, n: int, rate_hz: float, n_pos: int, n_vel: int,
                     weights: np.ndarray, bias: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.arange(n) / rate_hz
    m = max(n_pos, n_vel)  # one oscillator per joint; odd obs_dim gives one extra velocity
    amp = rng.uniform(0.2, 1.0, m)
    freq = rng.uniform(0.05, 0.5, m)
    phase = rng.uniform(0, 2 * math.pi, m)
    w = 2 * math.pi * freq
    pos = (amp * np.sin(w * t[:, None] + phase))[:, :n_pos]
    vel = (amp * w * np.cos(w * t[:, None] + phase))[:, :n_vel]
    state = np.concatenate([pos, vel], axis=1)
    act = np.tanh(state @ weights + bias) + rng.normal(0, 0.01, (n, weights.shape[1]))
    return pos, vel, act


def _frame_images(pos: np.ndarray) -> list[np.ndarray]:
    # A frame whose brightness pattern follows the first joint, so a tokenizer sees change.
    h, w, c = FRAME_SHAPE
    ramp = np.linspace(0.0, 1.0, h * w * c).reshape(FRAME_SHAPE)
    return [np.clip(0.5 + 0.5 * np.sin(ramp * 6.0 + float(p) * 3.0), 0.0, 1.0) for p in pos[:, 0]]


def _frames_text(images: list[np.ndarray]) -> list[str]:
    return [",".join(["%.3g"] * img.size) % tuple(img.ravel().tolist()) for img in images]


def write_frame_blobs(ep_dir: Path, images: list[np.ndarray]) -> int:
    """Step s's frame as <ep_dir>/blobs/step_<s>_rgb.npy, uint8 [64, 64, 3]; returns bytes written."""
    (ep_dir / "blobs").mkdir(parents=True, exist_ok=True)
    total = 0
    for s, img in enumerate(images):
        path = ep_dir / (FRAME_BLOB_URI % s)
        np.save(path, np.rint(img * 255.0).astype(np.uint8), allow_pickle=False)
        total += path.stat().st_size
    return total


def generate_dataset(out_dir: str | Path, n_steps_total: int, obs_dim: int = 20, act_dim: int = 6,
                     rates_hz: tuple[float, ...] = (10, 20, 50), seed: int = 0,
                     episode_seconds: tuple[float, float] = (30.0, 90.0), imagined_fraction: float = 0.0,
                     frames: bool = False, start_unix_s: int = 1_767_225_600,
                     id_prefix: str = "ep", frame_blobs: bool = False) -> GeneratedDataset:
    """Write about n_steps_total steps (exactly, unless fewer than 2 are left over) as canonical dirs.

    Observation = robot_state.joint_positions (obs_dim // 2) + joint_velocities (the rest);
    action = action.command (act_dim). Rates cycle through rates_hz episode by episode; every
    imagined episode (the last ~imagined_fraction of them) carries origin imagined:* and the tag.
    frames adds observation.image_rgb (12288 floats in [0, 1]); frame_blobs writes each step's
    frame as blobs/step_NNNNNN_rgb.npy (uint8 [64, 64, 3]) referenced by observation.media.rgb.
    """
    if obs_dim < 2 or act_dim < 1 or n_steps_total < 2:
        raise ValueError("generate_dataset needs obs_dim >= 2, act_dim >= 1 and n_steps_total >= 2")
    if not 0.0 <= imagined_fraction <= 1.0:
        raise ValueError(f"imagined_fraction={imagined_fraction} must be within [0, 1]")
    started = time.perf_counter()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    n_pos = obs_dim // 2
    weights = rng.normal(0, 0.5, (obs_dim, act_dim)) / math.sqrt(obs_dim)
    bias = rng.normal(0, 0.1, act_dim)
    writer = _EpisodeWriter(out, rng, seed, n_pos, obs_dim - n_pos, weights, bias, frames, frame_blobs,
                            _step_template(n_pos, obs_dim - n_pos, act_dim, frames, frame_blobs))
    lengths = _plan_episodes(rng, n_steps_total, rates_hz, episode_seconds)
    n_imagined = int(round(imagined_fraction * len(lengths)))
    total_bytes = 0
    clock_ns = start_unix_s * 10**9
    for i, (n, rate) in enumerate(lengths):
        imagined = i >= len(lengths) - n_imagined
        episode_id = f"{'imag' if imagined else id_prefix}_{i:05d}_{int(rate)}hz"
        written, last_ns = writer.write(episode_id, n, rate, clock_ns, imagined)
        total_bytes += written
        clock_ns = last_ns + 5 * 10**9  # next recording starts a few seconds later
    return GeneratedDataset(out, len(lengths), sum(n for n, _ in lengths), n_imagined, total_bytes,
                            time.perf_counter() - started)


def _plan_episodes(rng: np.random.Generator, n_steps_total: int, rates_hz: tuple[float, ...],
                   episode_seconds: tuple[float, float]) -> list[tuple[int, float]]:
    """(steps, rate) per episode, planned before writing: rates cycle, lengths are drawn in seconds."""
    lengths: list[tuple[int, float]] = []
    remaining = n_steps_total
    while remaining > 0:
        rate = float(rates_hz[len(lengths) % len(rates_hz)])
        n = max(2, int(rng.uniform(*episode_seconds) * rate))
        n = min(n, remaining)
        if n < 2:  # a 1-step leftover joins the previous episode rather than making a stub
            lengths[-1] = (lengths[-1][0] + n, lengths[-1][1])
            break
        lengths.append((n, rate))
        remaining -= n
    return lengths


@dataclass
class _EpisodeWriter:
    """Writes one generated episode dir: steps (one %-template line each), metadata, frame blobs."""

    out: Path
    rng: np.random.Generator
    seed: int
    n_pos: int
    n_vel: int
    weights: np.ndarray
    bias: np.ndarray
    frames: bool
    frame_blobs: bool
    template: str

    def write(self, episode_id: str, n: int, rate: float, clock_ns: int, imagined: bool) -> tuple[int, int]:
        """(bytes written, timestamp of the last step in ns)."""
        ep_dir = self.out / episode_id
        (ep_dir / "steps").mkdir(parents=True, exist_ok=True)
        pos, vel, act = _episode_signals(self.rng, n, rate, self.n_pos, self.n_vel, self.weights, self.bias)
        period_ns = int(round(1e9 / rate))
        ts = clock_ns + np.arange(n, dtype=np.int64) * period_ns
        reward = -np.abs(act).mean(axis=1)
        images = _frame_images(pos) if (self.frames or self.frame_blobs) else None
        image_text = _frames_text(images) if self.frames else None
        total_bytes = write_frame_blobs(ep_dir, images) if self.frame_blobs else 0
        pos_l, vel_l, act_l, ts_l, rew_l = pos.tolist(), vel.tolist(), act.tolist(), ts.tolist(), reward.tolist()
        lines = []
        for s in range(n):
            values = [s, ts_l[s], ts_l[s], *pos_l[s], *vel_l[s]]
            if image_text is not None:
                values.append(image_text[s])
            if self.frame_blobs:
                values.append(s)
            values += [*act_l[s], rew_l[s], "true" if s == n - 1 else "false"]
            lines.append(self.template % tuple(values))
        text = "\n".join(lines) + "\n"
        (ep_dir / "steps" / "000000.jsonl").write_text(text, encoding="utf-8")
        meta_text = json.dumps(self.metadata(episode_id, rate, clock_ns, (n - 1) * period_ns, imagined), indent=1)
        (ep_dir / "metadata.json").write_text(meta_text, encoding="utf-8")
        return total_bytes + len(text) + len(meta_text), int(ts[-1])

    def metadata(self, episode_id: str, rate: float, start_ns: int, duration_ns: int, imagined: bool) -> dict:
        tags = ["synthetic", f"{int(rate)}hz"] + ([IMAGINED_TAG] if imagined else [])
        return {
            "schema_version": "1.1",
            "episode_id": episode_id,
            "xr_mode": "trainer",
            "control_role": "human_teleop",
            "environment_id": "synthetic",
            "robot_model": "synthetic_arm",
            "tags": tags,
            "software": {"xr_app": "gen_dataset", "continuonbrain_os": "gen_dataset", "glove_firmware": "absent"},
            "start_time_unix_ms": start_ns // 10**6,
            "duration_ms": duration_ns // 10**6,
            "provenance": {"origin": ORIGIN_IMAGINED if imagined else ORIGIN_REAL,
                           "notes": f"seed={self.seed} rate_hz={rate}"},
        }


def write_episode(dataset_dir: str | Path, episode_id: str, steps: list[dict], *,
                  origin: str = "synthetic:handmade", tags: list[str] | tuple[str, ...] = (),
                  metadata: dict | None = None) -> Path:
    """One canonical episode dir from full step dicts (observation, action, timestamp_ns, ...).

    For tests that need exact, hand-chosen values; step_index and defaults are filled in.
    """
    ep_dir = Path(dataset_dir) / episode_id
    (ep_dir / "steps").mkdir(parents=True, exist_ok=True)
    lines = []
    for i, step in enumerate(steps):
        obj = {"step_index": i, "reward": 0.0, "is_terminal": i == len(steps) - 1, "step_metadata": {}, **step}
        lines.append(json.dumps(obj))
    (ep_dir / "steps" / "000000.jsonl").write_text("\n".join(lines) + "\n", encoding="utf-8")
    meta = {"schema_version": "1.1", "episode_id": episode_id, "xr_mode": "trainer",
            "control_role": "human_teleop", "environment_id": "synthetic", "tags": list(tags),
            "software": {"xr_app": "gen_dataset", "continuonbrain_os": "gen_dataset", "glove_firmware": "absent"},
            "provenance": {"origin": origin}, **(metadata or {})}
    (ep_dir / "metadata.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")
    return ep_dir
