"""The picture a frame VQ-VAE run leaves for the Robot Editor (train/held_out_picture.py): at the end
of training, held-out frames over their reconstructions, as a PNG in the run dir; none for a vector
VQ-VAE. components/picture.py's strip and spread are checked on small arrays."""
from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from hope_models.components import picture
from hope_models.components.build import component_from_checkpoint
from hope_models.data import synthetic as gen
from hope_models.data.cache import load_or_build
from hope_models.data.sampler import split_episodes
from hope_models.train.config import TrainConfig
from hope_models.train.held_out_picture import HELD_OUT_PICTURE
from hope_models.train.loop import train

VAL_FRACTION = 0.5  # a handful of episodes: half of them held out, so the split is never empty


@pytest.fixture(scope="module")
def frame_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("picture")
    gen.generate_dataset(root / "ds", 400, obs_dim=4, act_dim=2, rates_hz=(10,), episode_seconds=(4, 6), seed=3,
                         frame_blobs=True)
    return root


def _train(root, name: str, model_config: dict):
    result = train(TrainConfig(component="vqvae", data=str(root / "ds"), run_dir=str(root / name), steps=3,
                               batch_size=8, val_fraction=VAL_FRACTION, val_batches=1, model_config=model_config,
                               cache_dir=str(root / "cache"), thermal_zone=None, vcgencmd=None, threads=1))
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
