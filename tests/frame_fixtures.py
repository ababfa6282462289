"""Small camera checkpoints for the torch-free runtime's frame tests, built in-process with random
weights in a few seconds (no dataset, no training loop):

    ckpts = camera_checkpoints(root, "grid")     # {"vq": vqvae checkpoint, "fast": fast_loop over it}
    joints_checkpoint(root)                      # a fast_loop of the same joints without a camera
    frames = moving_frames(n, seed)              # uint8 [n, 64, 64, 3]: a ball and an arm that move

The VQ-VAE's codebook is initialised as training's first step does, then replaced by encoder
outputs spread apart (farthest-point sampling): seeded at random from a few frames' outputs, a third
of the cells sat within float32 rounding of two rows (the flat background gives near-equal rows),
and torch's and NumPy's codes could not be compared; random rows are all far from the data, and
two codes won every cell. The fast_loop's keypoint scores are sharpened (the softmax follows a few
cells). Each is written
with the real checkpoint writer (manifest and all), so BrainService can serve it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

JOINTS = [("observation.robot_state.joint_positions", 2), ("observation.robot_state.joint_velocities", 2)]
VQ_CONFIGS = {
    "grid": {"layout": "grid", "patch": 4, "n_codes": 32, "channels": 8},
    "flat": {"layout": "flat", "n_codes": 32, "channels": 8, "groups": 4, "code_dim": 32},
}
FAST_SMALL = {"d_model": 16, "d_state": 32, "keypoints": 4}


def camera_spec(side: int | None = 64):
    """The joints and the camera (side None: the joints alone, a robot without a camera)."""
    from hope_models.data.features import FeatureField, FeatureGroup, FeatureSpec, FrameFeature

    obs = FeatureGroup([FeatureField(p, n) for p, n in JOINTS], mean=[0.1, -0.2, 0.0, 0.05], std=[1.0, 0.8, 2.0, 1.5])
    act = FeatureGroup([FeatureField("action.command", 2)], mean=[0.0, 0.1], std=[0.5, 0.7])
    return FeatureSpec(observation=obs, action=act,
                       frame=None if side is None else FrameFeature("observation.camera", (side, side, 3), source="blob"))


def moving_frames(n: int, seed: int = 0, side: int = 64) -> np.ndarray:
    """A grey arena with a red ball that drifts and a blue bar that turns: codes change between frames."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:side, 0:side].astype(np.float32) / side
    out = np.empty((n, side, side, 3), np.uint8)
    ball = rng.uniform(0.2, 0.8, 2)
    for t in range(n):
        ball = np.clip(ball + rng.normal(0, 0.02, 2), 0.1, 0.9)
        angle = 0.1 * t + seed
        img = np.stack([0.45 + 0.1 * xx, 0.5 + 0.05 * yy, 0.4 + 0.1 * (xx + yy) / 2], -1)
        img[(xx - ball[0]) ** 2 + (yy - ball[1]) ** 2 < 0.004] = (0.9, 0.1, 0.1)
        along = (xx - 0.5) * np.cos(angle) + (yy - 0.5) * np.sin(angle)
        across = -(xx - 0.5) * np.sin(angle) + (yy - 0.5) * np.cos(angle)
        img[(np.abs(across) < 0.03) & (along > 0) & (along < 0.35)] = (0.1, 0.2, 0.9)
        noise = rng.normal(0, 0.01, img.shape)
        out[t] = np.clip((img + noise) * 255, 0, 255).astype(np.uint8)
    return out


def _spread(points: np.ndarray, k: int) -> np.ndarray:
    """k rows of points [N, d], each the farthest from those chosen before (farthest-point
    sampling); with fewer distinct points than k, the rest are those rows plus a little noise."""
    pts = np.unique(points.astype(np.float64), axis=0)
    chosen = [0]
    dist = ((pts - pts[0]) ** 2).sum(-1)
    while len(chosen) < min(k, len(pts)):
        i = int(dist.argmax())
        chosen.append(i)
        dist = np.minimum(dist, ((pts - pts[i]) ** 2).sum(-1))
    rows = pts[chosen]
    extra = rows[np.arange(k - len(rows)) % len(rows)] + np.random.default_rng(0).normal(0, 0.3, (k - len(rows), pts.shape[1]))
    return np.concatenate([rows, extra]).astype(np.float32)


def _save(run_dir: Path, comp) -> Path:
    from hope_models.checkpoints import save_checkpoint

    return save_checkpoint(run_dir, 1, model_state=comp.model.state_dict(), config=comp.config(), state_tensors={},
                           state={})


def camera_checkpoints(root: Path, layout: str, seed: int = 0) -> dict[str, Path]:
    import torch

    from hope_models.components.build import build_component

    torch.manual_seed(seed)
    spec = camera_spec()
    vq = build_component("vqvae", spec, model_config=VQ_CONFIGS[layout])
    with torch.no_grad():  # training's first step (the init flag, a grid's background), then spread rows
        x = torch.from_numpy(moving_frames(48, seed + 100))
        vq.model(x, init_codebook=True)
        points = vq.model.groups_of(vq.model.encoder(vq.model.prepare(x)))  # [B, G, d]
        n = vq.model.cfg.n_codes
        books = [_spread(points.flatten(0, 1).numpy(), n)] if layout == "grid" else \
            [_spread(points[:, g].numpy(), n) for g in range(points.shape[1])]
        book = np.concatenate(books * (vq.model.cfg.groups if layout == "grid" else 1))
        vq.model.codebook.copy_(torch.from_numpy(book))
    vq_ckpt = _save(root / f"vq-{layout}", vq)
    fast = build_component("fast_loop", spec, model_config=FAST_SMALL, vqvae_dir=vq_ckpt)
    kp = getattr(fast.model, "keypoints", None)
    with torch.no_grad():
        if kp is not None:
            kp.score.weight.mul_(3.0)  # sharper softmax: the keypoints follow single cells
    return {"vq": vq_ckpt, "fast": _save(root / f"fast-{layout}", fast)}


def joints_checkpoint(root: Path, seed: int = 0) -> Path:
    """A fast_loop of the same joints that reads no camera."""
    import torch

    from hope_models.components.build import build_component

    torch.manual_seed(seed)
    return _save(root / "fast-joints", build_component("fast_loop", camera_spec(None), model_config=FAST_SMALL))


__all__ = ["FAST_SMALL", "JOINTS", "VQ_CONFIGS", "camera_checkpoints", "camera_spec", "joints_checkpoint",
           "moving_frames"]
