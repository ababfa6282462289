"""The frame VQ-VAE on the reacher's camera observation, measured on held-out episodes: the share of
the pixel variance it keeps, its PSNR, and how well a linear probe reads the target's and the
fingertip's positions back from its codes (cm). For docs/training.md.

1. records --train-episodes camera episodes from --train-seed and --held-episodes from --held-seed
   (record_dataset(observation="camera", noise=1.0), full 1000-step episodes unless --episode-steps)
   into --train / --held, unless they are there already;
2. trains the vqvae component on --train with the real trainer (--steps, --model-config, one torch
   thread), and reports its wall time and steps/s;
3. encodes and decodes every frame of every --held episode: variance_kept = 1 - the squared error
   over the held-out frames' per-pixel variance (summed over pixels), psnr_db = 10 log10(1 / MSE)
   on [0, 1] pixels;
4. the probe (components/vqvae/probe.py): codes of --probe-frames training frames -> the target's and
   the fingertip's xy (hope_models/sim/positions.py: from the simulator, never in the observation),
   scored on every held-out frame; beside it the error of always answering the training mean;
5. writes --strip (a row of held-out frames over their reconstructions, upscaled: the trainer's
   picture, components/picture.py) if given.
--checkpoint skips 1-2 and measures a trained checkpoint (e.g. on another held-out set).

    MUJOCO_GL=egl .venv/bin/python bench/vqvae_grid.py --train /tmp/cam/train --held /tmp/cam/held \\
        --out /tmp/cam/grid --steps 3000 --model-config '{"layout": "grid", "fg_weight": 10}'

It prints figures (JSON); it is not a test.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _episodes(root: Path) -> list[Path]:
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")
                  and (p / "metadata.json").is_file())


def _load(root: Path, every: int = 1):
    """Frames [N, H, W, 3] uint8, target and fingertip xy [N, 2] (m), episode index [N] of a recorded dir."""
    import numpy as np

    from hope_models.sim.positions import episode_positions

    frames, targets, tips, episode = [], [], [], []
    for i, ep in enumerate(_episodes(root)):
        blobs = sorted((ep / "blobs").glob("step_*_rgb.npy"))[::every]
        target, tip = episode_positions(ep)
        if len(sorted((ep / "blobs").glob("step_*_rgb.npy"))) != len(target):
            raise RuntimeError(f"{ep}: {len(target)} steps but another number of frames")
        frames.append(np.stack([np.load(b) for b in blobs]))
        targets.append(target[::every])
        tips.append(tip[::every])
        episode.append(np.full(len(blobs), i))
    return (np.concatenate(frames), np.concatenate(targets), np.concatenate(tips), np.concatenate(episode))


def _codes_and_error(model, frames, chunk: int = 256):
    """All codes [N, G] and the summed squared error of the reconstructions on [0, 1] pixels."""
    import numpy as np
    import torch

    codes, se = [], 0.0
    with torch.no_grad():
        for i in range(0, len(frames), chunk):
            x = torch.from_numpy(frames[i:i + chunk])
            c = model.encode(x)
            se += float(((model.decode(c).clamp(0, 1) - model.prepare(x)) ** 2).sum())
            codes.append(c.numpy())
    return np.concatenate(codes), se


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--train", type=Path, required=True, help="training episodes (recorded here if missing)")
    p.add_argument("--held", type=Path, required=True, help="held-out episodes (recorded here if missing)")
    p.add_argument("--out", type=Path, required=True, help="run dir and cache go here")
    p.add_argument("--train-episodes", type=int, default=30)
    p.add_argument("--train-seed", type=int, default=300000)
    p.add_argument("--held-episodes", type=int, default=20)
    p.add_argument("--held-seed", type=int, default=900000)
    p.add_argument("--episode-steps", type=int, default=1000)
    p.add_argument("--steps", type=int, default=3000, help="training steps")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch threads of the training (the measuring uses one)")
    p.add_argument("--model-config", type=json.loads, default={}, help="the vqvae's model_config (JSON)")
    p.add_argument("--probe-frames", type=int, default=4000, help="training frames the probe is fitted on")
    p.add_argument("--strip", type=Path, default=None)
    p.add_argument("--checkpoint", type=Path, default=None,
                   help="measure this trained checkpoint dir (run/checkpoints/<step>) instead of training")
    args = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")

    import numpy as np
    import torch

    from hope_models.components.build import component_from_checkpoint
    from hope_models.components.vqvae.probe import distance_cm, fit_probe
    from hope_models.sim.recorder import record_dataset
    from hope_models.train.loop import TrainConfig, train

    for root, n, seed in ((args.train, args.train_episodes, args.train_seed), (args.held, args.held_episodes, args.held_seed)):
        if not root.is_dir():
            record_dataset(root, n, seed=seed, observation="camera", noise=1.0, steps=args.episode_steps)
    figures: dict = {}
    checkpoint = args.checkpoint
    if checkpoint is None:
        t0 = time.monotonic()
        result = train(TrainConfig(component="vqvae", data=str(args.train), run_dir=str(args.out / "run"),
                                   steps=args.steps, lr=args.lr, seed=args.seed, model_config=args.model_config,
                                   cache_dir=str(args.out / "cache"), thermal_zone=None, vcgencmd=None,
                                   log_every=100, threads=args.threads))
        wall = time.monotonic() - t0
        if result.outcome != "completed":
            print(f"training ended {result.outcome}: {result.message}", file=sys.stderr)
            return 1
        checkpoint = Path(result.checkpoint)
        figures.update({"train_steps": args.steps, "train_wall_s": round(wall), "steps_per_s": round(args.steps / wall, 2)})
    torch.set_num_threads(1)
    component = component_from_checkpoint(checkpoint)
    model = component.model.eval()
    frames, target, tip, _ = _load(args.held)
    codes, se = _codes_and_error(model, frames)
    x = frames.astype(np.float64) / 255.0
    variance = float(x.var(0).sum()) * len(x)  # the squared error of answering the mean frame
    mse = se / x.size
    figures.update({"checkpoint": str(checkpoint), "model": model.describe(),
                    "params": sum(q.numel() for q in model.parameters()),
                    "held_out_episodes": len(_episodes(args.held)), "held_out_frames": len(frames),
                    "variance_kept": 1.0 - se / variance, "psnr_db": 10.0 * math.log10(1.0 / mse)})
    n_train = len(_episodes(args.train)) * args.episode_steps
    tr_frames, tr_target, tr_tip, tr_episode = _load(args.train, every=max(1, n_train // args.probe_frames))
    tr_codes, _ = _codes_and_error(model, tr_frames)
    for name, train_xy, held_xy in (("target", tr_target, target), ("fingertip", tr_tip, tip)):
        probe = fit_probe(tr_codes, train_xy, tr_episode, max_fit=args.probe_frames)
        figures[f"probe_{name}_cm"] = probe.error_cm(codes, held_xy)
        figures[f"mean_{name}_cm"] = distance_cm(np.broadcast_to(train_xy.mean(0), held_xy.shape), held_xy)
    if args.strip is not None:
        from hope_models.components.picture import png

        rows = np.linspace(0, len(frames) - 1, 10).astype(np.int64)
        args.strip.parent.mkdir(parents=True, exist_ok=True)
        args.strip.write_bytes(png(component.picture_of(frames[rows])))
        figures["strip"] = str(args.strip)
    print(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
