"""A small grid Mid Loop checkpoint for the torch-free runtime's tests, built in-process with random
weights over frame_fixtures' grid VQ-VAE (no dataset, no training loop):

    ckpts = camera_checkpoints(root, "grid")                  # frame_fixtures: {"vq", "fast"}
    mid = grid_mid_checkpoint(root, ckpts["vq"])              # a grid mid_loop reading that VQ-VAE
    model = GridMidLoop as built (grid_mid_model(ckpts["vq"])) # the torch model, for comparisons

Its copy-last counts (stay_counts) are random, as if counted on training targets, so the mixture
the runtime reads is not the uniform one of an untrained model; its keypoint scores are sharpened
(the softmax follows a few cells, as a trained one does). Written with the real checkpoint writer.
"""
from __future__ import annotations

from pathlib import Path

MID_SMALL = {"d_model": 32, "d_state": 16, "n_layers": 2, "keypoints": 4, "cell_rank": 8, "copy_mix": 0.2}


def grid_mid_component(vq_ckpt: Path, seed: int = 0, model_config: dict | None = None):
    import torch
    from frame_fixtures import camera_spec

    from hope_models.components.build import build_component

    torch.manual_seed(seed)
    comp = build_component("mid_loop", camera_spec(), model_config={**MID_SMALL, **(model_config or {})},
                           vqvae_dir=vq_ckpt)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        comp.model.keypoints.score.weight.mul_(3.0)
        comp.model.stay_counts.copy_(torch.randint(0, 50, comp.model.stay_counts.shape, generator=gen).double())
        comp.model.code_counts.copy_(torch.randint(0, 50, comp.model.code_counts.shape, generator=gen).double())
    return comp


def grid_mid_checkpoint(root: Path, vq_ckpt: Path, seed: int = 0, model_config: dict | None = None,
                        name: str = "mid-grid") -> Path:
    from hope_models.checkpoints import save_checkpoint

    comp = grid_mid_component(vq_ckpt, seed, model_config)
    return save_checkpoint(root / name, 1, model_state=comp.model.state_dict(), config=comp.config(),
                           state_tensors={}, state={})


__all__ = ["MID_SMALL", "grid_mid_checkpoint", "grid_mid_component"]
