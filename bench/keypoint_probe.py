"""How well a camera fast_loop's keypoints say where the target and the fingertip are, held out:
for each keypoint a linear map from its (x, y) to the position (metres, the simulator's answer,
never an input: hope_models/sim/positions.py), fit on the first 40 episodes of a reach camera
dataset and scored on the next 10, every 25th step. Prints the 3 best points' mean error in cm and
the error of always guessing the mean. A diagnostic of the drawing (docs/reflex.md), not a test.

    .venv/bin/python bench/keypoint_probe.py RUN_OR_CHECKPOINT_DIR DATASET_DIR
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from hope_models.components.build import component_from_checkpoint
from hope_models.sim.positions import episode_positions

EVERY = 25  # steps between the frames read: 40 a 1000-step episode


def _checkpoint(path: Path) -> Path:
    if (path / "checkpoints").is_dir():
        steps = [p for p in (path / "checkpoints").iterdir() if p.name.isdigit()]
        return max(steps, key=lambda p: int(p.name))
    return path


def _episode(model, ep: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    target, tip = episode_positions(ep)
    idx = np.arange(0, len(target), EVERY)
    frames = np.stack([np.load(ep / "blobs" / f"step_{i:06d}_rgb.npy") for i in idx])
    with torch.no_grad():
        where, _ = model.keypoints.locate(model.vqvae.encode(torch.from_numpy(frames)))
    return where.numpy(), target[idx], tip[idx]


def _errors(where_fit, y_fit, where_test, y_test) -> tuple[list[float], float]:
    out = []
    for c in range(where_fit.shape[1]):
        w, *_ = np.linalg.lstsq(np.c_[where_fit[:, c], np.ones(len(where_fit))], y_fit, rcond=None)
        pred = np.c_[where_test[:, c], np.ones(len(where_test))] @ w
        out.append(float(100 * np.linalg.norm(pred - y_test, axis=1).mean()))
    mean_guess = float(100 * np.linalg.norm(y_fit.mean(0) - y_test, axis=1).mean())
    return sorted(out)[:3], mean_guess


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("data", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(1)
    ckpt = _checkpoint(args.checkpoint)
    model = component_from_checkpoint(ckpt).model.eval()
    if getattr(model, "keypoints", None) is None:
        raise SystemExit(f"{ckpt}: not a fast_loop reading a grid VQ-VAE's codes as keypoints")
    episodes = sorted(p for p in args.data.iterdir() if (p / "metadata.json").is_file())[:50]
    if len(episodes) < 50:
        raise SystemExit(f"{args.data}: {len(episodes)} episodes; the probe fits on 40 and scores on 10")
    parts = [_episode(model, ep) for ep in episodes]
    fit = [np.concatenate([p[i] for p in parts[:40]]) for i in range(3)]
    test = [np.concatenate([p[i] for p in parts[40:]]) for i in range(3)]
    result = {"checkpoint": str(ckpt)}
    for name, i in (("target", 1), ("fingertip", 2)):
        best, guess = _errors(fit[0], fit[i], test[0], test[i])
        result[name] = {"best_points_cm": [round(v, 2) for v in best], "mean_guess_cm": round(guess, 2)}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
