#!/usr/bin/env python3
"""A trained Mid Loop's figures on every episode of another dataset (episodes it never saw).

Prints figures; it is not a test. The dataset is read with the checkpoint's own normalisation
(as the gate reads a candidate's held-out batches, promote/gate.normalised_view), its frames
through the checkpoint's frozen tokenizer (a code table in the cache dir). Windows are drawn from
both of the dataset's splits (all its episodes are unseen), --batches batches of 64; the baselines
are the checkpoint's, counted on its own training targets.

    python bench/mid_loop_held_out.py CHECKPOINT DATASET CACHE_DIR [--batches 16]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from hope_models.components.build import component_from_checkpoint
from hope_models.data.cache import load_or_build
from hope_models.data.sampler import AnchorSampler
from hope_models.data.windows import make_windows
from hope_models.promote.gate import normalised_view

KEYS = ("nll", "copy_last_nll", "code_freq_nll", "joint_mse", "copy_last_joint_mse", "obs_mse", "copy_last_obs_mse")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint")
    ap.add_argument("dataset")
    ap.add_argument("cache_dir")
    ap.add_argument("--batches", type=int, default=16)
    ap.add_argument("--seed", type=int, default=11)
    args = ap.parse_args()
    torch.set_num_threads(1)
    comp = component_from_checkpoint(args.checkpoint)
    if comp.name != "mid_loop":
        raise SystemExit(f"{args.checkpoint}: a {comp.name} checkpoint, not a mid_loop")
    built, _ = load_or_build(args.dataset, args.cache_dir)
    cache = normalised_view(built, comp.spec)
    table = comp.code_table(cache, print)
    horizon = max(comp.window.horizons_s)
    n_val = max(1, args.batches // 8)
    metrics = []
    for split, n in (("train", args.batches - n_val), ("val", n_val)):
        sampler = AnchorSampler(cache, 64, seed=args.seed, horizon_s=horizon, split=split)
        for b in range(n):
            batch = make_windows(cache, sampler.batch(b), comp.window, frames=comp.wants_frames, codes=table)
            metrics.append(comp.evaluate(batch))
    mean = {k: float(np.mean([m[k] for m in metrics])) for k in metrics[0] if all(k in m for m in metrics)}
    print(f"{args.checkpoint} on {args.dataset} ({cache.n_episodes} episodes, {len(metrics)} batches of 64):")
    for label in (f"{h:g}s" for h in comp.window.horizons_s):
        got = {k: mean.get(f"{k}_{label}") for k in KEYS}
        line = [f"{label}: nll {got['nll']:.1f} vs copy-last {got['copy_last_nll']:.1f} "
                f"({1 - got['nll'] / got['copy_last_nll']:.0%} lower), code frequency {got['code_freq_nll']:.1f} "
                f"({1 - got['nll'] / got['code_freq_nll']:.0%} lower)"]
        for what, key in (("joint", "joint_mse"), ("observation", "obs_mse")):
            mse, copy = got[key], got[f"copy_last_{key}"]
            if mse is not None and copy:
                line.append(f"{what} error {mse:.3f} vs copy-last {copy:.3f} ({1 - mse / copy:.0%} lower)")
        print("  " + "; ".join(line))


if __name__ == "__main__":
    main()
