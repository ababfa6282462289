"""The VQ-VAE on 64x64 camera frames: held-out PSNR, codebook health, and a strip of originals vs
reconstructions for docs/training.md.

1. records --episodes reacher demonstrations with frames (sim-demos --frames, DART noise 1.0,
   --steps each) and --play play episodes (sim-demos --policy play: the arm swept around) into
   --out/demos, unless they are there already. Many short episodes, because every episode puts the
   target somewhere else: 16 episodes of 300 steps taught the VQ-VAE 16 target positions, and on
   held-out episodes it drew the arm and the target where it had seen them (normalised MSE 1.26:
   worse than the mean frame);
2. trains the vqvae component on them with the real trainer (the feature spec has the frame, so
   the VQ-VAE reads frames), --train-steps steps;
3. measures it on the validation split (the episodes the trainer held out, the batches the gate
   scores): recon_nmse, psnr_db, perplexity, code_usage;
4. writes --strip (default docs/img/vqvae-frames.png): the first frame of every 25th step of the
   first held-out episode, originals on the top row, reconstructions below, upscaled (the
   trainer's picture: components/picture.py).

    .venv/bin/python bench/vqvae_frames.py --out /tmp/vqvae_frames       # ~20 min on 2 cores

It prints figures; it is not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="work dir (demos, cache, run)")
    p.add_argument("--episodes", type=int, default=60)
    p.add_argument("--play", type=int, default=40, help="play episodes (exploration) besides the demos")
    p.add_argument("--steps", type=int, default=100, help="control steps per episode")
    p.add_argument("--train-steps", type=int, default=4000)
    p.add_argument("--strip", type=Path, default=REPO / "docs" / "img" / "vqvae-frames.png")
    p.add_argument("--frames-in-strip", type=int, default=8)
    args = p.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")

    import numpy as np
    import torch

    from hope_models.components.build import component_from_checkpoint
    from hope_models.components.picture import png
    from hope_models.data.cache import load_or_build
    from hope_models.data.sampler import split_episodes
    from hope_models.sim.recorder import record_dataset
    from hope_models.train.loop import TrainConfig, train
    from hope_models.train.validation import ValidationSetup, validation_metrics

    demos = args.out / "demos"
    if not demos.is_dir():
        record_dataset(demos, args.episodes, task="reach", noise=1.0, frames=True, steps=args.steps)
        if args.play:
            record_dataset(demos, args.play, task="reach", policy="play", frames=True, steps=args.steps)
    result = train(TrainConfig(component="vqvae", data=str(demos), run_dir=str(args.out / "run"),
                               steps=args.train_steps, cache_dir=str(args.out / "cache"), thermal_zone=None,
                               vcgencmd=None, log_every=100))
    if result.outcome != "completed":
        print(f"training ended {result.outcome}: {result.message}", file=sys.stderr)
        return 1
    comp = component_from_checkpoint(result.checkpoint)
    cache, _ = load_or_build(demos, args.out / "cache", None)
    setup = ValidationSetup(batch_size=64, val_fraction=0.1, batches=8)
    val = validation_metrics(comp, cache, setup)

    episode = int(split_episodes(cache, "val", 0.1)[0])
    start, end = int(cache.starts[episode]), int(cache.ends[episode])
    rows = np.linspace(start, end - 1, args.frames_in_strip).astype(np.int64)
    originals = np.ascontiguousarray(cache.frame_rows(rows))
    model = comp.model.eval()
    with torch.no_grad():
        codes = model.encode(torch.from_numpy(originals))
    args.strip.parent.mkdir(parents=True, exist_ok=True)
    args.strip.write_bytes(png(comp.picture_of(originals)))
    figures = {k: val[k] for k in ("recon_nmse", "psnr_db", "perplexity", "code_usage") if k in val}
    figures.update({"episodes": cache.n_episodes, "frames": cache.n_steps, "train_steps": args.train_steps,
                    "held_out_episodes": len(split_episodes(cache, "val", 0.1)), "strip": str(args.strip),
                    "strip_codes": codes.tolist()})
    print(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
