"""The grid Mid Loop's NumPy form (mid_loop/numpy_grid.py) against GridMidLoop in eval mode: the
context over a window, the joints at each horizon and each cell's code distribution mixed with
copy-last as grid_metrics.py mixes it; and what its checkpoint check refuses, by field."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from brain_fixtures import rewrite_manifest
from frame_fixtures import camera_checkpoints, moving_frames
from grid_mid_fixtures import grid_mid_checkpoint

from hope_models.components.build import component_from_checkpoint
from hope_models.components.mid_loop.checkpoint import MidLoopNumpyError
from hope_models.components.mid_loop.grid_metrics import _mixed
from hope_models.components.mid_loop.model import previous_actions
from hope_models.components.mid_loop.numpy_form import MidLoopNumpy, MidLoopRuntime
from hope_models.components.mid_loop.numpy_grid import GridMemo, GridMidLoopNumpy, GridPoint

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    root = tmp_path_factory.mktemp("grid-mid-numpy")
    cam = camera_checkpoints(root, "grid")
    return {**cam, "mid": grid_mid_checkpoint(root, cam["vq"])}


def _window(model, mid, length: int, seed: int):
    """A window's cells (by the NumPy encode, both models then read the same codes), joints and actions."""
    frames = moving_frames(length, seed=seed)
    rng = np.random.default_rng(seed)
    obs_n = rng.normal(0, 1, (length, model.cfg.obs_dim)).astype(np.float32)
    act_n = rng.normal(0, 1, (length, model.cfg.act_dim)).astype(np.float32)
    codes = mid.frame_vq.codes(frames)
    with torch.no_grad():
        # its own VQ-VAE's cells: torch's encode agrees but for near-ties (float32 distances within rounding)
        assert (model.codes(None, torch.from_numpy(frames)).numpy() != codes).mean() < 0.01
    return torch.from_numpy(codes), torch.from_numpy(obs_n), torch.from_numpy(act_n)


def test_the_numpy_grid_mid_loop_computes_what_torch_does(ckpts):
    model = component_from_checkpoint(ckpts["mid"]).model.eval()
    mid = MidLoopRuntime.from_checkpoint(ckpts["mid"], verify_manifest=True)
    assert isinstance(mid, GridMidLoopNumpy) and mid.groups == 256 and mid.copy_mix == pytest.approx(0.2)
    k = mid.window_k
    for length, seed in ((k, 1), (7, 2), (1, 3)):
        codes, obs, act = _window(model, mid, length, seed)
        prev = previous_actions(act[None])[0]
        with torch.no_grad():
            y = model.context(codes[None], prev[None], obs[None])[0]  # [L, d]
            joints = model.joints(y, obs)  # [L, H, D]
        y_np = mid.context(codes.numpy(), prev.numpy(), obs.numpy())
        assert np.abs(y_np - y.numpy()).max() < 1e-4, length
        assert np.abs(mid.joints(y_np, obs.numpy()) - joints.numpy()).max() < 1e-4
        last = mid.context(codes.numpy(), prev.numpy(), obs.numpy(), last_only=True)
        assert last.shape == (1, mid.d_model) and np.abs(last[0] - y.numpy()[-1]).max() < 1e-4
        later = torch.from_numpy(mid.frame_vq.codes(moving_frames(1, seed=seed + 10)[0]))  # another frame's cells
        for h in range(len(mid.horizon_steps)):
            with torch.no_grad():
                logits = model.cell_logits(y, h, codes)  # [L, G, n]
                target = later.expand_as(codes)
                ce = F.cross_entropy(logits.flatten(0, 1), target.reshape(-1), reduction="none").view(codes.shape)
                nll = _mixed(model, h, ce, target == codes, torch.arange(mid.groups))  # [L, G]
            assert np.abs(mid.cell_logits(y_np, h, codes.numpy()) - logits.numpy()).max() < 1e-4
            lp = mid.cell_log_probs(y_np, h, codes.numpy())  # [L, G, n]
            assert np.abs(np.exp(lp).sum(-1) - 1).max() < 1e-6  # a distribution over the codes (copy-last: float32)
            got = np.take_along_axis(lp, later.numpy()[None, :, None].repeat(length, 0), -1)[..., 0]
            assert np.abs(got + nll.numpy()).max() < 1e-4
            one = mid.observed_log_prob(y_np[-1], h, codes.numpy()[-1], later.numpy())
            assert np.abs(one + nll.numpy()[-1]).max() < 1e-4
            # the frame's figure is the sum over its cells: what BrainService answers as surprise,
            # decoded whole at the grid point or from the normalisers prepare() computed before it
            memo = GridMemo(y_np[-1], codes.numpy()[-1])
            target = GridPoint(later.numpy(), np.zeros(mid.d_model, np.float32), np.zeros(4, np.float32))
            whole = mid.surprises({h: memo}, target)[h]
            while mid.prepare(memo, {h: memo}):
                pass
            assert set(memo.lse) == {0, 1} and set(memo.u) == {h}  # due next for h: its hidden too
            prepared = mid.surprises({h: memo}, target)[h]
            assert not memo.u  # used once, not kept
            normalised = mid.surprises({h: memo}, target)[h]  # the normaliser alone
            for value in (-one.sum(), whole, prepared, normalised):
                assert abs(value - float(nll[-1].sum())) < 1e-3, (value, float(nll[-1].sum()))


def test_the_grid_checkpoint_is_refused_by_field(ckpts, tmp_path):
    import shutil

    from safetensors.numpy import load_file, save_file

    with pytest.raises(MidLoopNumpyError, match="a grid Mid Loop .*MidLoopRuntime.from_checkpoint picks it"):
        MidLoopNumpy.from_checkpoint(ckpts["mid"])

    def edited(name: str, config=None, tensors=None):
        d = tmp_path / name
        shutil.copytree(ckpts["mid"], d)
        if config is not None:
            obj = json.loads((d / "config.json").read_text())
            config(obj)
            (d / "config.json").write_text(json.dumps(obj))
        if tensors is not None:
            t = load_file(str(d / "model.safetensors"))
            tensors(t)
            save_file(t, str(d / "model.safetensors"), metadata={"format": "hope.checkpoint/1"})
        rewrite_manifest(d)
        return d

    cases = [
        (edited("obs", config=lambda o: o["model_config"].update(obs_dim=3)), r"model_config.obs_dim=3 is not the"),
        (edited("rank", config=lambda o: o["model_config"].update(cell_rank=0)), r"model_config.cell_rank=0 must be"),
        (edited("mix", config=lambda o: o["model_config"].update(copy_mix=1.5)), r"model_config.copy_mix=1.5 must be"),
        (edited("flat", config=lambda o: o["vqvae"]["model_config"].update(layout="flat", groups=4)), "layout is 'flat'"),
        (edited("frame", config=lambda o: o["feature_spec"]["frame"].update(shape=[32, 32, 3])),
         r"reads \[64, 64, 3\] camera frames, the feature spec's frame is \[32, 32, 3\]"),
        (edited("stay", tensors=lambda t: t.pop("stay_counts")), "stay_counts .* must be \\[2, 256, 2\\] float64, got missing"),
        (edited("neg", tensors=lambda t: t.update(stay_counts=-t["stay_counts"])), "stay_counts holds non-finite or negative"),
        (edited("cell", tensors=lambda t: t.update({"cell_out.weight": t["cell_out.weight"][:, :4].copy()})),
         "weights do not fit .*cell_out.weight"),
        (edited("nan", tensors=lambda t: t["joint_out.bias"].__setitem__(0, np.nan)), r"non-finite weights .*joint_out.bias"),
    ]
    for path, message in cases:
        with pytest.raises(MidLoopNumpyError, match=message):
            MidLoopRuntime.from_checkpoint(path, verify_manifest=True)
    with pytest.raises(MidLoopNumpyError, match="sha256"):
        MidLoopRuntime.from_checkpoint(ckpts["mid"], expected_sha256="0" * 64, verify_manifest=True)
