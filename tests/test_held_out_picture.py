"""The pictures a frame run leaves for the Robot Editor (train/held_out_picture.py), as a PNG in the
run dir at the end of training: a frame VQ-VAE's held-out frames over their reconstructions (none
for a vector VQ-VAE); a grid Mid Loop's held-out windows, the frame now and at each horizon its
predicted frame beside the recorded one. components/picture.py's strip, grid and spread are checked
on small arrays."""
from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from PIL import Image

from hope_models.components import picture
from hope_models.components.build import component_from_checkpoint
from hope_models.components.mid_loop.grid_metrics import mixed_argmax
from hope_models.components.mid_loop.grid_picture import ROWS, picture_anchors
from hope_models.components.mid_loop.model import previous_actions
from hope_models.components.training_base import as_tensor
from hope_models.data import synthetic as gen
from hope_models.data.cache import load_or_build
from hope_models.data.sampler import split_episodes
from hope_models.data.windows import make_windows
from hope_models.train.config import TrainConfig
from hope_models.train.held_out_picture import HELD_OUT_PICTURE, PREDICTED_PICTURE
from hope_models.train.loop import train

VAL_FRACTION = 0.5  # a handful of episodes: half of them held out, so the split is never empty


@pytest.fixture(scope="module")
def frame_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("picture")
    gen.generate_dataset(root / "ds", 400, obs_dim=4, act_dim=2, rates_hz=(10,), episode_seconds=(4, 6), seed=3,
                         frame_blobs=True)
    return root


def _train(root, name: str, model_config: dict, component: str = "vqvae", vqvae_dir: str | None = None):
    result = train(TrainConfig(component=component, data=str(root / "ds"), run_dir=str(root / name), steps=3,
                               batch_size=8, val_fraction=VAL_FRACTION, val_batches=1, model_config=model_config,
                               cache_dir=str(root / "cache"), thermal_zone=None, vcgencmd=None, threads=1,
                               vqvae_dir=vqvae_dir))
    assert result.outcome == "completed", result.message
    return result


@pytest.mark.parametrize("layout", ["flat", "grid"])
def test_a_frame_vqvae_run_leaves_held_out_frames_over_their_reconstructions(frame_data, layout):
    result = _train(frame_data, f"run-{layout}", {"input": "frame", "layout": layout})
    run = frame_data / f"run-{layout}"
    assert "val" in result.summary  # the picture comes with the held-out figures
    img = np.asarray(Image.open(io.BytesIO((run / HELD_OUT_PICTURE).read_bytes())).convert("RGB"))
    assert not [p.name for p in run.iterdir() if p.name.startswith(f".{HELD_OUT_PICTURE}")]  # no temp left
    cache, _ = load_or_build(frame_data / "ds", frame_data / "cache")
    held = split_episodes(cache, "val", VAL_FRACTION)
    assert 0 < len(held) < cache.n_episodes
    rows = picture.spread_rows(cache, held)
    assert len(rows) == picture.FRAMES
    assert set(np.searchsorted(cache.starts, rows, side="right") - 1) <= set(held.tolist())  # held-out frames only
    frames = cache.frame_rows(rows)
    s = picture.scale_for(64)
    assert img.shape == (2 * 64 * s, picture.FRAMES * 64 * s, 3)
    top = img[: 64 * s: s, ::s].reshape(64, picture.FRAMES, 64, 3).transpose(1, 0, 2, 3)
    assert np.array_equal(top, frames)  # the top row is those frames, in order
    comp = component_from_checkpoint(result.checkpoint)
    assert np.array_equal(img, comp.picture_of(frames))  # the bottom row: the trained model's reconstructions
    assert not np.array_equal(img[64 * s:], img[: 64 * s])


def test_a_vector_vqvae_run_leaves_no_picture(frame_data):
    result = _train(frame_data, "run-vector", {"input": "vector"})
    assert "val" in result.summary
    assert not (frame_data / "run-vector" / HELD_OUT_PICTURE).exists()


def _png(path) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(path.read_bytes())).convert("RGB"))


def test_a_grid_mid_loop_run_leaves_its_predicted_frames_beside_the_recorded_ones(frame_data):
    vq = _train(frame_data, "run-mid-vq", {"input": "frame", "layout": "grid", "patch": 8, "n_codes": 32,
                                           "channels": 8})
    result = _train(frame_data, "run-mid", {"d_model": 16, "d_state": 16, "cell_rank": 8, "keypoints": 4},
                    component="mid_loop", vqvae_dir=vq.checkpoint)
    run = frame_data / "run-mid"
    assert "val" in result.summary and not (run / HELD_OUT_PICTURE).exists()
    img = _png(run / PREDICTED_PICTURE)
    comp = component_from_checkpoint(result.checkpoint)
    cache, _ = load_or_build(frame_data / "ds", frame_data / "cache")
    held = split_episodes(cache, "val", VAL_FRACTION)
    anchors = picture_anchors(cache, held, comp.window)
    assert len(anchors) == ROWS and set(cache.episode_of(anchors).tolist()) <= set(held.tolist())
    s, horizons = picture.scale_for(64), comp.window.horizons_s
    assert horizons == (0.5, 1.0)
    assert img.shape == (ROWS * 64 * s, (1 + 2 * len(horizons)) * 64 * s, 3)  # now, then predicted | recorded
    cells = img[::s, ::s].reshape(ROWS, 64, 5, 64, 3).transpose(0, 2, 1, 3, 4)  # [row, column, 64, 64, 3]
    batch = make_windows(cache, anchors, comp.window, frames=True)
    assert np.array_equal(cells[:, 0], cache.frame_rows(anchors))  # the frame now
    # recorded: the dataset's frame 0.5 s and 1 s later (10 Hz: 5 and 10 steps), never a decoding
    assert np.array_equal(cells[:, 2], cache.frame_rows(anchors + 5))
    assert np.array_equal(cells[:, 4], cache.frame_rows(anchors + 10))
    # predicted: the frozen VQ-VAE's decoding of the copy-mixed argmax of each cell's code at that horizon
    model = comp.model.eval()
    with torch.no_grad():
        codes = model.codes(None, as_tensor(batch.frames))
        y = model.context(codes, previous_actions(as_tensor(batch.act)), as_tensor(batch.obs), as_tensor(batch.mask))
        for h, column in ((0, 1), (1, 3)):
            best = mixed_argmax(model, h, model.cell_logits(y[:, -1], h, codes[:, -1]), codes[:, -1])
            decoded = picture.to_uint8(model.vqvae.decode(best).permute(0, 2, 3, 1).numpy())
            assert np.array_equal(cells[:, column], decoded), h
            assert not np.array_equal(cells[:, column], cells[:, column + 1])
    assert np.array_equal(img, comp.held_out_picture(cache, held))  # the checkpoint draws the same picture


def test_grid_puts_frame_r_c_in_row_r_column_c():
    frames = np.zeros((2, 3, 2, 2, 3), np.uint8)
    frames[1, 2] = 70
    frames[0, 1] = 30
    img = picture.grid(frames, scale=2)
    assert img.shape == (8, 12, 3)
    assert (img[4:, 8:] == 70).all() and (img[:4, 4:8] == 30).all() and int(img.sum()) == 16 * 3 * 100
    with pytest.raises(ValueError, match="rows, columns"):
        picture.grid(frames[0])


def test_strip_puts_each_reconstruction_under_its_frame():
    a = np.zeros((3, 2, 2, 3), np.uint8)
    b = np.full((3, 2, 2, 3), 200, np.uint8)
    a[1] = 50
    img = picture.strip(a, b, scale=2)
    assert img.shape == (8, 12, 3)
    assert (img[:4, 4:8] == 50).all() and (img[:4, :4] == 0).all() and (img[4:] == 200).all()
    assert picture.strip(a, b).shape == (2 * 2 * 96, 3 * 2 * 96, 3)  # a 2-px frame is blown up to ~192 px
    with pytest.raises(ValueError, match="same shape"):
        picture.strip(a, b[:2])
    decoded = np.asarray(Image.open(io.BytesIO(picture.png(img))))
    assert np.array_equal(decoded, img)
