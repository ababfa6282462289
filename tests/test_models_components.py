"""The three components on generated data: loss goes down, checkpoints round-trip, bad ones are refused.

The Adam loops here are deliberately minimal (the trainer is tested on its own): sampler batch b ->
make_windows -> component.loss -> backward -> step -> after_step.
"""
from __future__ import annotations

import copy
import json
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from hope_models.data.cache import load_or_build
from hope_models.data.spec_request import spec_from_json_obj
from hope_models.data.sampler import AnchorSampler
from hope_models.data.synthetic import generate_dataset
from hope_models.data.windows import make_windows
from hope_models.durable import file_sha256
from hope_models.components.build import (
    CheckpointError, build_component, component_from_checkpoint, load_model_weights,
)


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    root = tmp_path_factory.mktemp("vec")
    generate_dataset(root / "ds", 3000, obs_dim=20, act_dim=6, seed=0)
    c, _ = load_or_build(root / "ds", root / "cache")
    return c


@pytest.fixture(scope="module")
def frame_cache(tmp_path_factory):
    root = tmp_path_factory.mktemp("frames")
    generate_dataset(root / "ds", 600, obs_dim=20, act_dim=6, seed=1, episode_seconds=(10, 20), frame_blobs=True)
    c, _ = load_or_build(root / "ds", root / "cache")
    assert c.spec.frame is not None
    return c


def _batches(comp, cache, batch_size: int, seed: int = 0):
    w = comp.window
    sampler = AnchorSampler(cache, batch_size, seed=seed, horizon_s=max(w.horizons_s, default=0.0))
    b = 0
    while True:
        yield make_windows(cache, sampler.batch(b), w, frames=comp.wants_frames)
        b += 1


def _train(comp, cache, steps=100, batch_size=32, lr=3e-3, seed=0, opt=None, start=0):
    """Minimal Adam loop; returns (losses, last metrics, optimizer)."""
    if opt is None:
        opt = torch.optim.Adam([p for p in comp.model.parameters() if p.requires_grad], lr=lr)
    losses, metrics = [], {}
    batches = _batches(comp, cache, batch_size, seed)
    for _ in range(start):
        next(batches)
    for step in range(start, start + steps):
        loss, metrics = comp.loss(next(batches))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        comp.after_step(step)
        losses.append(loss.item())
    return losses, metrics, opt


def _ratio(losses):
    return float(np.mean(losses[-10:]) / np.mean(losses[:10]))


def _save(comp, d: Path) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    save_file(comp.model.state_dict(), str(d / "model.safetensors"))
    (d / "config.json").write_text(json.dumps(comp.config(), indent=1), encoding="utf-8")
    return d


@pytest.fixture(scope="module")
def vq_ckpt(cache, tmp_path_factory):
    torch.manual_seed(0)
    comp = build_component("vqvae", cache.spec, data_fingerprint=cache.fingerprint)
    _train(comp, cache, steps=100)
    return _save(comp, tmp_path_factory.mktemp("vq") / "checkpoints" / "100")


# -- loss goes down ------------------------------------------------------------------------------

def test_vqvae_loss_decreases_and_the_codebook_is_used(cache):
    torch.manual_seed(0)
    comp = build_component("vqvae", cache.spec)
    assert not comp.wants_frames and comp.window.k == 1
    losses, m, _ = _train(comp, cache)
    assert _ratio(losses) < 0.7, losses[:10] + losses[-10:]
    assert m["perplexity"] > 4 and m["batch_code_usage"] > 0.05 and 0 < m["code_usage"] <= 1
    assert m["recon_loss"] < np.mean(losses[:10])


def test_frame_vqvae_loss_decreases(frame_cache):
    torch.manual_seed(0)
    comp = build_component("vqvae", frame_cache.spec, model_config={"n_codes": 32})
    assert comp.wants_frames and comp.model.cfg.input == "frame"
    losses, m, _ = _train(comp, frame_cache, batch_size=16)
    assert _ratio(losses) < 0.7, losses[:10] + losses[-10:]
    assert m["perplexity"] >= 1.0


def test_fast_loop_loss_decreases(cache):
    torch.manual_seed(0)
    comp = build_component("fast_loop", cache.spec)
    assert comp.window.k == 5 and comp.window.duration_s == pytest.approx(0.1)
    losses, m, _ = _train(comp, cache)
    assert _ratio(losses) < 0.7, losses[:10] + losses[-10:]
    assert m["mse"] < 0.5 * m["mean_action_mse"]  # beats always predicting the mean action


def test_fast_loop_with_codes_loss_decreases_and_the_vqvae_stays_frozen(cache, vq_ckpt):
    torch.manual_seed(0)
    comp = build_component("fast_loop", cache.spec, vqvae_dir=vq_ckpt)
    frozen = {k: v.clone() for k, v in comp.model.vqvae.state_dict().items()}
    losses, _, _ = _train(comp, cache)
    assert _ratio(losses) < 0.7, losses[:10] + losses[-10:]
    for k, v in comp.model.vqvae.state_dict().items():
        assert torch.equal(v, frozen[k]), f"frozen VQ-VAE changed: {k}"


def test_mid_loop_loss_decreases_and_beats_copying_the_last_code(cache, vq_ckpt):
    torch.manual_seed(0)
    comp = build_component("mid_loop", cache.spec, vqvae_dir=vq_ckpt)
    assert comp.window.scale == "mid" and comp.window.horizons_s == (0.5, 1.0)
    assert comp.model_config.horizon_steps == (5, 10)
    losses, m, _ = _train(comp, cache)
    assert _ratio(losses) < 0.7, losses[:10] + losses[-10:]
    assert m["anchor_accuracy"] >= 0 and m["targets"] > m["window_targets"] > 0
    val = next(_batches(comp, cache, 64, seed=99))
    ev = comp.evaluate(val)
    assert {"loss", "accuracy", "copy_last_accuracy", "anchor_accuracy", "anchor_copy_last_accuracy"} <= set(ev)
    assert ev["accuracy"] > ev["copy_last_accuracy"]


def test_mid_loop_with_a_frame_vqvae_learns_from_in_window_and_future_frame_targets(frame_cache, tmp_path):
    torch.manual_seed(0)
    vq = build_component("vqvae", frame_cache.spec, model_config={"n_codes": 16, "channels": 8})
    _train(vq, frame_cache, steps=5, batch_size=16)
    comp = build_component("mid_loop", frame_cache.spec, vqvae_dir=_save(vq, tmp_path / "vq"))
    assert comp.wants_frames
    losses, m, _ = _train(comp, frame_cache, steps=3, batch_size=4)
    assert all(np.isfinite(losses)) and m["targets"] > m["window_targets"] > 0
    assert "anchor_accuracy" in m  # the beyond-window targets: codes of the batch's future_frames


# -- determinism and exact continuation ----------------------------------------------------------

def test_vqvae_training_continues_exactly_from_saved_state(cache, tmp_path):
    """All codebook state is in buffers: save at step 15, rebuild, continue = 30 straight steps."""
    cfg = {"n_codes": 64, "dead_after_steps": 4}

    def fresh():
        torch.manual_seed(5)
        return build_component("vqvae", cache.spec, model_config=cfg)

    straight = fresh()
    _train(straight, cache, steps=30, batch_size=16)
    assert int(straight.model.restarts) > 0  # the restart path ran inside the compared stretch

    first = fresh()
    _, _, opt = _train(first, cache, steps=15, batch_size=16)
    _save(first, tmp_path / "ck")
    opt_state, rng = copy.deepcopy(opt.state_dict()), torch.get_rng_state()
    torch.manual_seed(12345)  # the process moves on; only the saved state may matter
    resumed = component_from_checkpoint(tmp_path / "ck")
    opt2 = torch.optim.Adam([p for p in resumed.model.parameters() if p.requires_grad], lr=3e-3)
    opt2.load_state_dict(opt_state)
    torch.set_rng_state(rng)
    _train(resumed, cache, steps=15, batch_size=16, opt=opt2, start=15)
    a, b = straight.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


# -- config.json and checkpoints -----------------------------------------------------------------

def test_config_is_json_with_dims_window_spec_and_vqvae_reference(cache, vq_ckpt):
    torch.manual_seed(0)
    comp = build_component("fast_loop", cache.spec, vqvae_dir=vq_ckpt, data_fingerprint=cache.fingerprint)
    cfg = json.loads(json.dumps(comp.config()))
    assert cfg == comp.config()
    assert cfg["component"] == "fast_loop" and cfg["data_fingerprint"] == cache.fingerprint
    assert cfg["model_config"]["obs_dim"] == 20 and cfg["model_config"]["act_dim"] == 6
    assert cfg["model_config"]["n_codes"] == 128
    assert cfg["window"] == {"scale": "fast", "duration_s": 0.1, "k": 5, "horizons_s": []}
    assert spec_from_json_obj(cfg["feature_spec"]).obs_dim == 20
    ref = cfg["vqvae"]
    assert Path(ref["path"]) == vq_ckpt.resolve()
    assert ref["weights_sha256"] == file_sha256(vq_ckpt / "model.safetensors")
    assert len(ref["config_sha256"]) == 64 and ref["model_config"]["n_codes"] == 128
    assert 0 < cfg["params"]["trainable"] < cfg["params"]["total"] < 500_000


@pytest.mark.parametrize("name", ["vqvae", "fast_loop", "mid_loop"])
def test_checkpoint_round_trip(name, cache, vq_ckpt, tmp_path):
    vq_copy = tmp_path / "vq_copy"
    shutil.copytree(vq_ckpt, vq_copy)
    torch.manual_seed(0)
    comp = build_component(name, cache.spec, vqvae_dir=None if name == "vqvae" else vq_copy)
    _train(comp, cache, steps=3, batch_size=8)
    ck = _save(comp, tmp_path / "checkpoints" / "3")
    shutil.rmtree(vq_copy)  # a fast/mid checkpoint carries its frozen VQ-VAE: the source dir is not needed
    torch.manual_seed(999)  # a different init: everything must come from the files
    back = component_from_checkpoint(ck)
    assert back.name == name and back.config() == comp.config()
    for k, v in comp.model.state_dict().items():
        assert torch.equal(back.model.state_dict()[k], v), k
    batch = next(_batches(comp, cache, 16, seed=7))
    assert back.evaluate(batch) == comp.evaluate(batch)
    if name == "fast_loop":  # inference rebuilds it from the files: the stepped form is the same too
        obs = torch.from_numpy(batch.obs[:2].copy())
        with torch.no_grad():
            s1, s2 = comp.model.init_state(2), back.model.init_state(2)
            for t in range(obs.shape[1]):
                a1, s1 = comp.model.step(obs[:, t], s1)
                a2, s2 = back.model.step(obs[:, t], s2)
        assert torch.equal(a1, a2)


def _edit_config(ck: Path, edit) -> None:
    obj = json.loads((ck / "config.json").read_text())
    edit(obj)
    (ck / "config.json").write_text(json.dumps(obj))


def test_checkpoints_whose_config_does_not_fit_are_refused(cache, tmp_path):
    torch.manual_seed(0)
    comp = build_component("fast_loop", cache.spec)
    ck = _save(comp, tmp_path / "ck")

    _edit_config(ck, lambda o: o["model_config"].update(obs_dim=21))
    with pytest.raises(CheckpointError, match=r"config.json.*obs_dim=21 does not fit.*obs_dim=20"):
        component_from_checkpoint(ck)

    _save(comp, ck)
    _edit_config(ck, lambda o: o["model_config"].update(d_model=64))  # config fine, weights are 128 wide
    with pytest.raises(CheckpointError, match=r"model.safetensors: weights do not fit.*shape"):
        component_from_checkpoint(ck)

    _save(comp, ck)
    _edit_config(ck, lambda o: o.update(component="planner"))
    with pytest.raises(CheckpointError, match="component 'planner'"):
        component_from_checkpoint(ck)

    _save(comp, ck)
    _edit_config(ck, lambda o: o["model_config"].update(n_codes=128))  # codes without a VQ-VAE
    with pytest.raises(CheckpointError, match="n_codes"):
        component_from_checkpoint(ck)

    (ck / "config.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="config.json: not readable JSON"):
        component_from_checkpoint(ck)
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    with pytest.raises(CheckpointError, match="looks like a run dir"):
        component_from_checkpoint(run)


class _Trap:
    """Unpickling this would create the marker file: proof that nothing was unpickled."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_pickle_checkpoints_are_refused_without_unpickling(cache, tmp_path):
    torch.manual_seed(0)
    comp = build_component("fast_loop", cache.spec)
    ck = _save(comp, tmp_path / "ck")
    marker = tmp_path / "unpickled"
    (ck / "model.safetensors").write_bytes(pickle.dumps({"w": _Trap(marker)}))
    with pytest.raises(CheckpointError, match=r"model.safetensors: not a valid safetensors file.*pickle"):
        component_from_checkpoint(ck)
    assert not marker.exists()

    torch.save(comp.model.state_dict(), ck / "model.safetensors")  # torch.save's zip format
    with pytest.raises(CheckpointError, match="pickle"):
        component_from_checkpoint(ck)

    _save(comp, ck)
    data = (ck / "model.safetensors").read_bytes()
    (ck / "model.safetensors").write_bytes(data[: len(data) // 2])  # truncated
    with pytest.raises(CheckpointError, match="not a valid safetensors file"):
        load_model_weights(comp.model, ck / "model.safetensors")
    (ck / "model.safetensors").unlink()
    with pytest.raises(CheckpointError, match="weights file not found"):
        component_from_checkpoint(ck)


# -- building: clear errors ----------------------------------------------------------------------

def test_build_errors_name_the_parameter(cache, vq_ckpt, tmp_path):
    with pytest.raises(ValueError, match="mid_loop needs vqvae_dir"):
        build_component("mid_loop", cache.spec)
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['d_modle'\]"):
        build_component("fast_loop", cache.spec, model_config={"d_modle": 64})
    with pytest.raises(ValueError, match="obs_dim=12 does not fit"):
        build_component("fast_loop", cache.spec, model_config={"obs_dim": 12})
    with pytest.raises(ValueError, match="vqvae_dir is for fast_loop and mid_loop"):
        build_component("vqvae", cache.spec, vqvae_dir=vq_ckpt)
    with pytest.raises(ValueError, match="horizons_s: 0.25 s is not a whole number"):
        build_component("mid_loop", cache.spec, vqvae_dir=vq_ckpt, model_config={"window": {"horizons_s": [0.25]}})
    with pytest.raises(ValueError, match="input='frame' but the feature spec has no frame"):
        build_component("vqvae", cache.spec, model_config={"input": "frame"})
    with pytest.raises(ValueError, match="component 'planner'"):
        build_component("planner", cache.spec)
    with pytest.raises(ValueError, match="d_model=.*must be an integer"):
        build_component("fast_loop", cache.spec, model_config={"d_model": "big"})

    torch.manual_seed(0)
    fast = build_component("fast_loop", cache.spec)
    fast_ck = _save(fast, tmp_path / "fast")
    with pytest.raises(ValueError, match="holds a fast_loop checkpoint, not a vqvae"):
        build_component("mid_loop", cache.spec, vqvae_dir=fast_ck)
    untrained = _save(build_component("vqvae", cache.spec), tmp_path / "untrained")
    with pytest.raises(ValueError, match="never trained"):
        build_component("fast_loop", cache.spec, vqvae_dir=untrained)

    small = build_component("fast_loop", cache.spec, model_config={"window": {"duration_s": 0.06, "k": 3},
                                                                    "d_model": 32})
    assert small.window.k == 3 and small.model.cfg.d_model == 32
    assert small.model.cfg.window_k == 3  # the policy's window follows the training window
    with pytest.raises(ValueError, match="window_k=4 does not fit.*window_k=5"):
        build_component("fast_loop", cache.spec, model_config={"window_k": 4})
    mid = build_component("mid_loop", cache.spec, vqvae_dir=vq_ckpt,
                          model_config={"window": {"duration_s": 4.0, "k": 40, "horizons_s": [0.3, 2.0]}})
    assert mid.model_config.horizon_steps == (3, 20)
