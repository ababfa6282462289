"""The frame VQ-VAE's grid layout at small scale: one code per cell from one shared codebook, a
decoder from the grid, a loss that weighs the small objects, and a short run that learns; plus the
linear probe of the codes. The held-out figures themselves are in docs/training.md (not asserted)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from hope_models.components.layers import tensors
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.layers import layers
from hope_models.components.vqvae.model import VQVAE, background_weights
from hope_models.components.vqvae.probe import fit_probe

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _grid(**kw) -> VQVAE:
    torch.manual_seed(0)
    cfg = {"input": "frame", "frame_shape": (32, 32, 3), "layout": "grid", "patch": 8, "groups": 16,
           "code_dim": 16 * 4, "n_codes": 16, "channels": 4, **kw}
    return VQVAE(VQVAEConfig(**cfg))


def _scenes(n: int, seed: int = 0) -> torch.Tensor:
    """n 32x32 frames: a flat dark blue floor and a 3x3 bright square somewhere on it."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n, 32, 32, 3), np.uint8)
    x[...] = (30, 60, 110)
    for i in range(n):
        r, c = rng.integers(2, 27, 2)
        x[i, r:r + 3, c:c + 3] = (250, 110, 100)
    return torch.from_numpy(x)


def test_grid_codes_are_one_per_cell_and_the_layers_match_the_model():
    vq = _grid()
    x = _scenes(5)
    out = vq(x, init_codebook=True)
    assert out.codes.shape == (5, 16) and vq.encode(x).shape == (5, 16)  # a 4x4 grid of 8-pixel cells
    assert out.z_e.shape == (5, 16 * 4) and out.recon.shape == (5, 3, 32, 32)
    assert vq.decode(vq.encode(x)).shape == (5, 3, 32, 32)
    named = {k: tuple(v.shape) for k, v in vq.named_parameters()}
    assert named == tensors(layers(vq.cfg))
    # Each cell's slice of z_e goes to its nearest row of the one shared codebook.
    z = out.z_e.detach().view(5, 16, 4)
    book = vq.codebook[:16]
    dist = ((z[:, :, None] - book[None, None]) ** 2).sum(-1)  # [5, 16 cells, 16 codes]
    chosen = dist.gather(-1, out.codes[..., None])[..., 0]
    assert torch.all(chosen <= dist.amin(-1) + 1e-6)  # (near-ties aside, the argmin)


def test_a_wider_decoder_leaves_the_encoder_as_it_was():
    narrow, wide = _grid(), _grid(decoder_channels=12)
    enc = lambda vq: {k: tuple(v.shape) for k, v in vq.named_parameters() if k.startswith("encoder.")}  # noqa: E731
    assert enc(wide) == enc(narrow)  # the robot's encode costs the same
    named = {k: tuple(v.shape) for k, v in wide.named_parameters()}
    assert named == tensors(layers(wide.cfg)) and named["decoder.1.weight"][0] == 24  # 2 x 12 at the grid
    x = _scenes(3)
    assert wide(x, init_codebook=True).recon.shape == (3, 3, 32, 32)
    with pytest.raises(ValueError, match="decoder_channels=8 is the grid layout's"):
        VQVAEConfig(input="frame", decoder_channels=8).validate()


def test_the_codebook_is_shared_by_the_cells_and_stored_once_per_cell():
    vq = _grid()
    x = _scenes(16)
    for _ in range(3):
        out = vq(x, init_codebook=True)
        vq.update_codebook(out.z_e.detach(), out.codes)
        vq.unused_steps[3] = vq.cfg.dead_after_steps  # force a restart of code 3
        assert vq.restart_dead_codes(out.z_e.detach()) >= 1
    g, n = vq.cfg.groups, vq.cfg.n_codes
    for buf in (vq.codebook, vq.ema_count, vq.ema_sum, vq.unused_steps, vq.idle_steps):
        blocks = buf.view(g, n, *buf.shape[1:])
        assert torch.equal(blocks, blocks[:1].expand_as(blocks))  # every cell's block is the same
    assert vq.codebook.shape == (g * n, 4)  # the [G * n_codes, d] table the Fast and Mid Loops read


def test_the_weighted_loss_weighs_a_small_bright_object_more_than_the_flat_floor():
    xs = _scenes(8)
    x = xs.permute(0, 3, 1, 2).float() / 255.0
    w = background_weights(x, 9.0)[:, 0]  # [8, 32, 32]
    floor = torch.tensor((30, 60, 110)).view(3, 1, 1) / 255.0
    square = (x[0] - floor).abs().amax(0) > 0.1  # frame 0's 3x3 square
    never = ((x - floor).abs().amax(1) <= 0.1).all(0)  # floor in every frame
    assert int(square.sum()) == 9 and int(never.sum()) > 900
    assert torch.all(w[0][square] == 10.0) and torch.all(w[:, never] == 1.0)
    # The same error costs 10x as much on the square as on as many floor pixels.
    e_square, e_floor = torch.zeros_like(x), torch.zeros_like(x)
    e_square[0, :, square] = 0.1
    e_floor[0, :, torch.nonzero(never)[:9, 0], torch.nonzero(never)[:9, 1]] = 0.1
    cost = [float((background_weights(x, 9.0) * e ** 2).mean()) for e in (e_square, e_floor)]
    assert cost[0] == pytest.approx(10 * cost[1])
    # It is the term the model trains on; the reported recon_loss stays the plain MSE.
    vq = _grid(fg_weight=9.0)
    out = vq(xs, init_codebook=True)
    se = (out.recon - out.target) ** 2
    torch.testing.assert_close(out.fit_loss, (background_weights(out.target, 9.0) * se).mean())
    torch.testing.assert_close(out.recon_loss, se.mean())
    assert out.fit_loss.item() > out.recon_loss.item()
    plain = _grid().forward(xs, init_codebook=True)
    assert torch.equal(plain.fit_loss, plain.recon_loss)  # fg_weight 0: the plain MSE


def test_a_short_run_on_a_few_frames_reduces_the_loss():
    vq = _grid(fg_weight=4.0)
    x = _scenes(32)
    opt = torch.optim.AdamW(vq.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        out = vq(x, init_codebook=True)
        loss = vq.loss_of(out)
        opt.zero_grad()
        loss.backward()
        opt.step()
        vq.update_codebook(out.z_e.detach(), out.codes)
        vq.restart_dead_codes(out.z_e.detach())
        losses.append(out.recon_loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_old_flat_configs_still_load_and_a_grid_must_fit_its_cells():
    cfg = VQVAEConfig(input="frame")  # a config.json from before the grid has no layout
    assert cfg.layout == "flat" and cfg.fg_weight == 0.0
    cfg.validate()
    with pytest.raises(ValueError, match="groups=4 must be the grid's 16x16=256 cells"):
        VQVAEConfig(input="frame", layout="grid").validate()
    with pytest.raises(ValueError, match="patch=6 must be a power of 2"):
        VQVAEConfig(input="frame", layout="grid", patch=6, groups=64, code_dim=64).validate()
    with pytest.raises(ValueError, match="needs input='frame'"):
        VQVAEConfig(obs_dim=6, layout="grid", groups=64, code_dim=64).validate()


def test_the_grid_configuration_is_derived_from_the_frame():
    from hope_models.components.resolve import resolve
    from hope_models.data.features import FeatureField, FeatureGroup, FeatureSpec, FrameFeature

    spec = FeatureSpec(FeatureGroup([FeatureField("observation.state", 4)]), FeatureGroup([FeatureField("action.command", 2)]),
                       FrameFeature("observation.camera", (64, 64, 3)))
    cfg = resolve("vqvae", spec, {"layout": "grid", "patch": 8}).cfg
    assert (cfg.groups, cfg.code_dim, cfg.grid_shape) == (64, 64 * 8, (8, 8))
    assert resolve("vqvae", spec, {"layout": "grid", "patch": 16, "code_dim": 16 * 8}).cfg.groups == 16


def test_the_probe_reads_a_position_back_from_codes_that_carry_it():
    rng = np.random.default_rng(0)
    n, g = 600, 8
    episode = np.repeat(np.arange(12), n // 12)
    xy = rng.uniform(-0.2, 0.2, (n, 2))
    codes = rng.integers(0, 16, (n, g))
    codes[:, 0] = np.digitize(xy[:, 0], np.linspace(-0.2, 0.2, 16)[1:-1])  # group 0: x in 16 bins
    codes[:, 1] = np.digitize(xy[:, 1], np.linspace(-0.2, 0.2, 16)[1:-1])  # group 1: y
    probe = fit_probe(codes[:480], xy[:480], episode[:480])
    assert probe.error_cm(codes[480:], xy[480:]) < 2.0  # bins of 2.7 cm
    noise = fit_probe(rng.integers(0, 16, (480, g)), xy[:480], episode[:480])
    assert noise.error_cm(rng.integers(0, 16, (120, g)), xy[480:]) > 8.0  # ~ the mean predictor
