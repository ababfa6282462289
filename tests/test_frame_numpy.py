"""The torch-free runtime sees: a frame VQ-VAE's codes (flat and grid layouts) and a camera fast_loop
(a grid's codes read as keypoints, a flat one's summed) computed in NumPy equal what torch computes.

Checkpoints are built in-process with random weights (tests/frame_fixtures.py), a second each."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from frame_fixtures import camera_checkpoints, moving_frames

from hope_models.components.build import component_from_checkpoint
from hope_models.components.fast_loop.numpy_form import FastLoopNumpy, FastLoopNumpyError
from hope_models.components.vqvae.numpy_form import VQVAERuntime

TOL = 1e-5
TIE = 1e-5  # squared-distance gap (distances ~10-30) within which float32 rounding may pick either code


@pytest.fixture(scope="module", params=["grid", "flat"])
def camera(request, tmp_path_factory):
    return request.param, camera_checkpoints(tmp_path_factory.mktemp(f"cam-{request.param}"), request.param)


def _distances(tvq, frames: np.ndarray) -> np.ndarray:
    """float64 squared distances [N, G, n_codes] of torch's z_e to each group's codebook rows."""
    with torch.no_grad():
        z = tvq.groups_of(tvq.encoder(tvq.prepare(torch.from_numpy(frames)))).double().numpy()
    book = tvq.codebook.view(tvq.cfg.groups, tvq.cfg.n_codes, -1).double().numpy()
    return ((z[..., None, :] - book) ** 2).sum(-1)


def _equal_but_ties(got: np.ndarray, want: np.ndarray, dist: np.ndarray) -> None:
    """Codes equal, except where the two codes are equally near (float32 rounding picks either)."""
    differ = got != want
    assert differ.mean() < 0.02
    near = np.take_along_axis(dist, got[..., None], -1)[..., 0] - np.take_along_axis(dist, want[..., None], -1)[..., 0]
    assert (np.abs(near[differ]) < TIE).all(), np.abs(near[differ]).max()


def test_frame_codes_equal_torch_encode(camera, torch_one_thread):
    layout, ckpts = camera
    vq = VQVAERuntime.from_checkpoint(ckpts["vq"], verify_manifest=True)
    tvq = component_from_checkpoint(ckpts["vq"]).model.eval()
    assert vq.frame_shape == (64, 64, 3) and vq.vq.shared == (layout == "grid")
    rng = np.random.default_rng(1)
    frames = np.concatenate([moving_frames(40, seed=7), rng.integers(0, 256, (8, 64, 64, 3), dtype=np.uint8)])
    want = tvq.encode(torch.from_numpy(frames)).numpy()
    got = vq.vq.codes(frames)
    assert got.shape == want.shape == (48, tvq.cfg.groups)
    assert len(np.unique(want)) > 8 and len({tuple(r) for r in want.tolist()}) > 30  # codes vary
    _equal_but_ties(got, want, _distances(tvq, frames))
    assert (vq.vq.codes(frames[3]) == got[3]).all()  # one frame, no batch axis: what BrainService sends


def test_camera_fast_loop_steps_like_torch_over_many_ticks(camera, torch_one_thread):
    layout, ckpts = camera
    model = FastLoopNumpy.from_checkpoint(ckpts["fast"], verify_manifest=True)
    tmodel = component_from_checkpoint(ckpts["fast"]).model.eval()
    assert (tmodel.keypoints is not None) == (layout == "grid") and model.frame_shape == (64, 64, 3)
    ticks = 300
    frames = moving_frames(ticks, seed=11)
    obs = np.random.default_rng(2).normal(0, 1.0, (ticks, model.obs_dim)).astype(np.float32)
    codes = model.frame_codes(frames)
    # torch's step encodes each frame itself (a batch of 1); where float32 ties let the two pick
    # different codes, the comparison would test the tie, not the model: those ticks use torch's code
    tcodes = np.stack([tmodel.codes(None, torch.from_numpy(frames[t:t + 1])).numpy()[0] for t in range(ticks)])
    _equal_but_ties(codes, tcodes, _distances(tmodel.vqvae, frames))
    state, tstate = model.init_state(), tmodel.init_state(1)
    worst = 0.0
    with torch.inference_mode():
        for t in range(ticks):
            a, state = model.step(obs[t:t + 1], state, tcodes[t:t + 1])
            ta, tstate = tmodel.step(torch.from_numpy(obs[t:t + 1]), tstate, torch.from_numpy(frames[t:t + 1]))
            worst = max(worst, float(np.abs(a - ta.numpy()).max()))
        window = model.forward(obs[None, -model.window_k:], codes=tcodes[None, -model.window_k:])
    assert worst < TOL, f"max |numpy - torch| over {ticks} ticks = {worst:.2e}"
    assert np.abs(window - a).max() < TOL  # the batched path (window re-run) agrees with the ticks
    moved = tcodes[-1].copy()
    moved = np.roll(moved, 1 + moved.size // 2)  # the same codes in other cells (grid) / other groups
    b, _ = model.step(obs[-1:], model.init_state(), moved[None])
    c, _ = model.step(obs[-1:], model.init_state(), tcodes[-1:])
    assert np.abs(b - c).max() > 1e-4  # the codes reach the action


def test_a_camera_fast_loop_needs_the_frames_codes(camera):
    _, ckpts = camera
    model = FastLoopNumpy.from_checkpoint(ckpts["fast"])
    with pytest.raises(ValueError, match="reads camera frames: pass codes"):
        model.tick(np.zeros(model.obs_dim, np.float32), model.init_state())


def test_refuses_a_camera_fast_loop_whose_spec_has_another_frame(camera, tmp_path):
    import json
    import shutil

    from brain_fixtures import rewrite_manifest

    _, ckpts = camera
    ckpt = tmp_path / "fl"
    shutil.copytree(ckpts["fast"], ckpt)
    cfg = json.loads((ckpt / "config.json").read_text())
    cfg["feature_spec"]["frame"]["shape"] = [96, 96, 3]
    (ckpt / "config.json").write_text(json.dumps(cfg))
    rewrite_manifest(ckpt)
    with pytest.raises(FastLoopNumpyError, match=r"reads \[64, 64, 3\] camera frames, the feature spec's frame is "
                                                 r"\[96, 96, 3\]"):
        FastLoopNumpy.from_checkpoint(ckpt, verify_manifest=True)


def test_a_grid_tokenizer_with_a_wider_decoder_is_served(tmp_path):
    """decoder_channels widens only the decoder; the torch-free runtime must accept its tensors."""
    import torch
    from frame_fixtures import VQ_CONFIGS, _save, camera_spec

    from hope_models.components.build import build_component
    from hope_models.components.vqvae.numpy_form import VQVAERuntime

    torch.manual_seed(0)
    vq = build_component("vqvae", camera_spec(), model_config={**VQ_CONFIGS["grid"], "decoder_channels": 16})
    with torch.no_grad():
        vq.model(torch.randint(0, 256, (4, 64, 64, 3), dtype=torch.uint8), init_codebook=True)
    served = VQVAERuntime.from_checkpoint(_save(tmp_path / "vq", vq))
    assert served is not None
