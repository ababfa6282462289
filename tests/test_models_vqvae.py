"""VQ-VAE: data-driven init, EMA codebook, usage/perplexity, dead-code restart, buffers in safetensors."""
from __future__ import annotations

import pytest
import torch
from safetensors.torch import load_file, save_file

from hope_models.components.vqvae.model import VQVAE, VQVAEConfig


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _vq(**kw) -> VQVAE:
    torch.manual_seed(0)
    return VQVAE(VQVAEConfig(**{"obs_dim": 8, "n_codes": 16, "code_dim": 4, "hidden": 32, "groups": 1, **kw}))


def _rows_in(rows: torch.Tensor, pool: torch.Tensor) -> bool:
    """Every row of rows is exactly (bitwise) one of the rows of pool."""
    return bool((rows[:, None, :] == pool[None, :, :]).all(-1).any(1).all())


def test_first_training_batch_seeds_the_codebook_and_evaluation_does_not():
    vq = _vq()
    x = torch.randn(64, 8)
    vq(x)  # an evaluation pass: no init
    assert int(vq.initialized) == 0 and (vq.codebook == 0).all()
    out = vq(x, init_codebook=True)
    assert int(vq.initialized) == 1
    z = vq.encoder(x).detach()
    assert _rows_in(vq.codebook, z)  # every row is one of this batch's encoder outputs
    assert len(torch.unique(vq.codebook, dim=0)) == 16
    assert torch.equal(vq.ema_sum, vq.codebook) and (vq.ema_count == 1).all()
    assert torch.equal(out.codes, vq.nearest(z))
    before = vq.codebook.clone()
    vq(torch.randn(64, 8) * 5, init_codebook=True)  # only the first batch seeds
    assert torch.equal(vq.codebook, before)


def test_fewer_outputs_than_codes_still_gives_distinct_rows():
    vq = _vq()
    vq(torch.randn(5, 8), init_codebook=True)
    assert len(torch.unique(vq.codebook, dim=0)) == 16


def test_ema_update_matches_the_formula_with_laplace_smoothing():
    vq = _vq(ema_decay=0.9, eps=1e-5)
    x = torch.randn(32, 8)
    vq(x, init_codebook=True)
    z = vq.encoder(x).detach()
    codes = vq.nearest(z)
    count0, sum0 = vq.ema_count.clone(), vq.ema_sum.clone()
    vq.update_codebook(z, codes)
    onehot = torch.nn.functional.one_hot(codes[:, 0], 16).float()  # one group: codes [B, 1]
    count = 0.9 * count0 + 0.1 * onehot.sum(0)
    total = 0.9 * sum0 + 0.1 * onehot.t() @ z
    n = count.sum()
    smoothed = (count + 1e-5) / (n + 16 * 1e-5) * n
    torch.testing.assert_close(vq.ema_count, count)
    torch.testing.assert_close(vq.codebook, total / smoothed[:, None])
    used = onehot.sum(0) > 0
    assert (vq.unused_steps[used] == 0).all() and (vq.unused_steps[~used] == 1).all()


def test_encode_is_pure_and_matches_forward():
    vq = _vq()
    x = torch.randn(20, 8)
    out = vq(x, init_codebook=True)
    state = {k: v.clone() for k, v in vq.state_dict().items()}
    codes = vq.encode(x)
    assert codes.dtype == torch.long and codes.shape == (20, 1)
    assert torch.equal(codes, out.codes)
    assert all(torch.equal(state[k], v) for k, v in vq.state_dict().items())
    assert vq.decode(codes).shape == (20, 8)


def test_perplexity_and_usage():
    vq = _vq()
    one = vq.code_stats(torch.zeros(10, 1, dtype=torch.long))
    assert one["perplexity"] == pytest.approx(1.0) and one["batch_code_usage"] == pytest.approx(1 / 16)
    four = vq.code_stats(torch.arange(4).repeat(5)[:, None])
    assert four["perplexity"] == pytest.approx(4.0) and four["batch_code_usage"] == pytest.approx(0.25)
    vq.idle_steps.fill_(vq.cfg.dead_after_steps)
    vq.idle_steps[:3] = 0
    assert vq.code_stats(torch.tensor([[3], [3]]))["code_usage"] == pytest.approx(4 / 16)


def _restart_scenario(seed: int):
    vq = _vq(dead_after_steps=3)
    x = torch.randn(64, 8)
    vq(x, init_codebook=True)
    with torch.no_grad():
        vq.codebook[10:] = 1e3  # six codes nobody is near: they will go unused
        vq.ema_sum[10:] = 1e3
    z = vq.encoder(x).detach()
    for _ in range(3):
        codes = vq.nearest(z)
        assert not (codes >= 10).any()
        vq.update_codebook(z, codes)
    assert (vq.unused_steps[10:] >= 3).all()
    torch.manual_seed(seed)
    n = vq.restart_dead_codes(z)
    return vq, z, n


def test_dead_codes_are_restarted_from_encoder_outputs_and_then_used():
    vq, z, n = _restart_scenario(seed=1)
    assert n >= 6 and int(vq.restarts) == n
    assert _rows_in(vq.codebook[10:], z)  # re-seeded from current encoder outputs
    assert (vq.unused_steps[10:] == 0).all()
    codes = vq.nearest(z)
    revived = torch.unique(codes[codes >= 10])
    assert len(revived) >= 1  # at least one revived code now wins points
    usage_before = vq.code_stats(codes[:0])["code_usage"]  # restarted but not yet used: not "in use"
    vq.update_codebook(z, codes)
    assert (vq.unused_steps[revived] == 0).all()
    assert vq.code_stats(codes[:0])["code_usage"] == pytest.approx(usage_before + len(revived) / 16)
    assert vq.restart_dead_codes(z) == 0  # nothing is dead right after a restart


def test_restarts_draw_from_torchs_global_rng():
    a, _, _ = _restart_scenario(seed=1)
    b, _, _ = _restart_scenario(seed=1)
    c, _, _ = _restart_scenario(seed=2)
    assert torch.equal(a.codebook, b.codebook)
    assert not torch.equal(a.codebook, c.codebook)


def test_codebook_state_is_in_buffers_and_survives_safetensors(tmp_path):
    vq, z, _ = _restart_scenario(seed=3)
    names = dict(vq.named_buffers())
    for key in ("codebook", "ema_count", "ema_sum", "unused_steps", "idle_steps", "initialized", "restarts"):
        assert key in names
    save_file(vq.state_dict(), str(tmp_path / "vq.safetensors"))
    fresh = _vq(dead_after_steps=3)
    fresh.load_state_dict(load_file(str(tmp_path / "vq.safetensors")))
    for k, v in vq.state_dict().items():
        assert torch.equal(fresh.state_dict()[k], v), k
    x = torch.randn(16, 8)
    assert torch.equal(fresh.encode(x), vq.encode(x))


def test_frame_input_shapes_and_errors():
    torch.manual_seed(0)
    vq = VQVAE(VQVAEConfig(input="frame", n_codes=8, code_dim=8, groups=2, channels=8))
    frames = torch.randint(0, 256, (3, 64, 64, 3), dtype=torch.uint8)
    out = vq(frames, init_codebook=True)
    assert out.recon.shape == (3, 3, 64, 64) and out.codes.shape == (3, 2)
    assert vq.decode(vq.encode(frames)).shape == (3, 3, 64, 64)
    with pytest.raises(ValueError, match="frames must be"):
        vq.encode(torch.zeros(3, 32, 32, 3, dtype=torch.uint8))
    with pytest.raises(ValueError, match="frame_shape"):
        VQVAE(VQVAEConfig(input="frame", frame_shape=(60, 60, 3)))
    with pytest.raises(ValueError, match="obs_dim"):
        VQVAE(VQVAEConfig(input="vector", obs_dim=0))


def test_groups_quantise_each_slice_against_its_own_codebook():
    """Two groups: each half of z_e picks its nearest row among its own group's rows; decode puts the
    two rows side by side; the EMA moves each row towards the slices assigned to it; a dead code is
    re-seeded from its own group's slice."""
    torch.manual_seed(3)
    vq = _vq(groups=2, dead_after_steps=2)
    x = torch.randn(48, 8)
    vq(x, init_codebook=True)
    z = vq.encoder(x).detach()
    codes = vq.nearest(z)
    assert codes.shape == (48, 2) and int(codes.max()) < 16
    book = vq.codebook.view(2, 16, 2)
    for g in range(2):
        want = torch.cdist(z[:, 2 * g:2 * g + 2], book[g]).argmin(1)
        assert torch.equal(codes[:, g], want)
    assert torch.equal(vq.quantised(codes), torch.cat([book[0][codes[:, 0]], book[1][codes[:, 1]]], 1))
    probs = torch.nn.functional.one_hot(codes, 16).float()
    torch.testing.assert_close(vq.decode_expected(probs), vq.decode(codes))
    sum0 = vq.ema_sum.clone()
    vq.update_codebook(z, codes)
    for g in range(2):
        c = int(codes[0, g])
        members = z[codes[:, g] == c, 2 * g:2 * g + 2]
        torch.testing.assert_close(vq.ema_sum[16 * g + c], 0.99 * sum0[16 * g + c] + 0.01 * members.sum(0))
    vq.unused_steps[16 + 5] = 2  # a dead code of group 1
    vq.restart_dead_codes(z)
    assert _rows_in(vq.codebook[16 + 5:16 + 6], z[:, 2:4])
    stats = vq.code_stats(codes)
    assert 1.0 <= stats["perplexity"] <= 16.0 and 0 < stats["batch_code_usage"] <= 1


def test_groups_must_divide_the_code_width():
    with pytest.raises(ValueError, match="groups=3 must be >= 1 and divide code_dim=4"):
        _vq(groups=3)
