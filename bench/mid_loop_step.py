#!/usr/bin/env python3
"""A Mid Loop training step over a grid frame tokenizer against one over vector codes, on one thread.

Prints figures; it is not a test. Both at batch 32, K=20, horizons 5 and 10 grid steps, AdamW,
forward + loss + backward + step on random inputs (no data loading):
  - vector: the default vector VQ-VAE (4 groups x 128 codes) over a 6-d observation, with the
    action-conditioned world model (wm_*), as the reacher's state Mid Loop trains;
  - grid: a 16x16 grid of one shared 256-code codebook (the camera tokenizer's layout) and 4 joints,
    the codes a fixed background per window with 12 cells of a moving thing (~9 % of the cells
    change over 5 steps, about what the reacher's camera codes do: 11 %).

    python bench/mid_loop_step.py [--steps 20] [--model-config '{"score_points": 4}']
"""
from __future__ import annotations

import argparse
import json
import time

import torch

from hope_models.components.mid_loop.grid_metrics import grid_loss
from hope_models.components.mid_loop.grid_model import GridMidLoop
from hope_models.components.mid_loop.metrics import mid_loop_loss, world_model_loss
from hope_models.components.mid_loop.model import MidLoop, MidLoopConfig, previous_actions
from hope_models.components.vqvae.model import VQVAE, VQVAEConfig

B, K, HORIZONS = 32, 20, (5, 10)


def _vector_step():
    vq = VQVAE(VQVAEConfig(input="vector", obs_dim=6))
    vq(torch.randn(256, 6), init_codebook=True)
    m = MidLoop(MidLoopConfig(act_dim=2, n_codes=128, horizon_steps=HORIZONS), vq)
    opt = torch.optim.AdamW([p for p in m.parameters() if p.requires_grad], 1e-3)
    obs, act, fobs = torch.randn(B, K, 6), torch.randn(B, K, 2), torch.randn(B, len(HORIZONS), 6)
    mask, fmask = torch.ones(B, K, dtype=torch.bool), torch.ones(B, len(HORIZONS), dtype=torch.bool)

    def step():
        codes, fc = m.codes(obs), m.codes(fobs)
        y = m.context(codes, previous_actions(act), mask)
        loss, _ = mid_loop_loss(m, m.heads(y), codes, mask, obs=obs, future_codes=fc, future_mask=fmask,
                                future_obs=fobs)
        wm, _ = world_model_loss(m, y, obs, act, mask, 0.1)
        opt.zero_grad()
        (loss + wm).backward()
        opt.step()
    return step


def _grid_step(overrides: dict):
    vq = VQVAE(VQVAEConfig(input="frame", layout="grid", patch=4, n_codes=256, channels=16, groups=256,
                           code_dim=2048))
    m = GridMidLoop(MidLoopConfig(act_dim=2, n_codes=256, obs_dim=4, horizon_steps=HORIZONS, **overrides), vq)
    opt = torch.optim.AdamW([p for p in m.parameters() if p.requires_grad], 1e-3)
    codes = torch.randint(0, 256, (B, 1, 256)).repeat(1, K + max(HORIZONS), 1)
    for k in range(codes.shape[1]):
        for j in range(12):
            codes[:, k, (3 * k + j * 16) % 256] = 7
    fc = torch.stack([codes[:, K - 1 + s] for s in HORIZONS], 1)
    codes = codes[:, :K].contiguous()
    obs, act, fobs = torch.randn(B, K, 4), torch.randn(B, K, 2), torch.randn(B, len(HORIZONS), 4)
    mask, fmask = torch.ones(B, K, dtype=torch.bool), torch.ones(B, len(HORIZONS), dtype=torch.bool)

    def step():
        y = m.context(codes, previous_actions(act), obs, mask)
        loss, _ = grid_loss(m, y, codes, obs, mask, future_codes=fc, future_mask=fmask, future_obs=fobs)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return step


def _ms(step, n: int) -> float:
    for _ in range(3):
        step()
    t = time.perf_counter()
    for _ in range(n):
        step()
    return (time.perf_counter() - t) / n * 1000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--model-config", default="{}", help="overrides of the grid Mid Loop's MidLoopConfig")
    args = ap.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    vector, grid = _ms(_vector_step(), args.steps), _ms(_grid_step(json.loads(args.model_config)), args.steps)
    print(f"mid_loop step at batch {B}, K={K}, 1 thread: vector codes {vector:.1f} ms, grid codes {grid:.1f} ms "
          f"({grid / vector:.2f}x)")


if __name__ == "__main__":
    main()
