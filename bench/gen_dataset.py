#!/usr/bin/env python3
"""Write a synthetic canonical RLDS dataset (hope_models.data.synthetic) from the shell.

    python bench/gen_dataset.py OUT_DIR --steps 500000
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hope_models.data.synthetic import generate_dataset  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description="write a synthetic canonical RLDS dataset")
    p.add_argument("out_dir")
    p.add_argument("--steps", type=int, default=10_000)
    p.add_argument("--obs-dim", type=int, default=20)
    p.add_argument("--act-dim", type=int, default=6)
    p.add_argument("--rates", default="10,20,50", help="comma-separated step rates in Hz")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--imagined-fraction", type=float, default=0.0)
    p.add_argument("--frames", action="store_true", help="add observation.image_rgb (64x64x3 floats)")
    p.add_argument("--frame-blobs", action="store_true",
                   help="write each step's frame as blobs/step_NNNNNN_rgb.npy, referenced by observation.media.rgb")
    a = p.parse_args(argv)
    rates = tuple(float(r) for r in a.rates.split(","))
    g = generate_dataset(a.out_dir, a.steps, a.obs_dim, a.act_dim, rates, a.seed,
                         imagined_fraction=a.imagined_fraction, frames=a.frames,
                         frame_blobs=a.frame_blobs)
    print(f"{g.path}: {g.episodes} episodes ({g.imagined_episodes} imagined), {g.steps} steps, "
          f"{g.bytes_written / 1e6:.1f} MB in {g.seconds:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
