"""The Mid Loop's loss scores each target through one log-softmax and one gather over every point
(components/mid_loop/metrics.py): it must give, bit for bit, what cross-entropy of each horizon's
picked logits gives (the direct form, written out below): the loss, its gradient and every metric,
with a masked prefix, futures past the episode's end and a horizon longer than the window."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from hope_models.components.mid_loop.metrics import mid_loop_loss
from hope_models.components.mid_loop.model import MidLoop, MidLoopConfig
from hope_models.components.vqvae.model import VQVAE, VQVAEConfig

B, K, G, N = 6, 8, 3, 16
HORIZONS = (2, 5, 9)  # the last one is beyond the window: anchor targets only


def _model() -> MidLoop:
    torch.manual_seed(0)
    vq = VQVAE(VQVAEConfig(obs_dim=5, n_codes=N, code_dim=6, hidden=16, groups=G))
    vq(torch.randn(64, 5), init_codebook=True)
    return MidLoop(MidLoopConfig(act_dim=2, n_codes=N, horizon_steps=HORIZONS, wm_horizon=0), vq)


def _batch():
    g = torch.Generator().manual_seed(1)
    codes = torch.randint(0, N, (B, K, G), generator=g)
    mask = torch.ones(B, K, dtype=torch.bool)
    mask[0, :3] = False  # windows that start before their episode
    mask[1, :K - 1] = False
    future = torch.randint(0, N, (B, len(HORIZONS), G), generator=g)
    fmask = torch.rand(B, len(HORIZONS), generator=g) > 0.3
    obs = torch.randn(B, K, 5, generator=g)
    fobs = torch.randn(B, len(HORIZONS), 5, generator=g)
    logits = torch.randn(B, K, len(HORIZONS), G, N, generator=g) * 3
    return codes, mask, future, fmask, obs, fobs, logits


def _direct_nll(logits, codes, mask, future, fmask):
    """Cross-entropy of each horizon's picked logits, window targets first, then the anchor's."""
    per = []
    for h, s in enumerate(HORIZONS):
        lg, target = [], []
        if s < K:
            valid = mask[:, :K - s] & mask[:, s:]
            lg.append(logits[:, :K - s, h][valid])
            target.append(codes[:, s:][valid])
        lg.append(logits[:, -1, h][fmask[:, h]])
        target.append(future[:, h][fmask[:, h]])
        lg, target = torch.cat(lg), torch.cat(target)
        per.append(F.cross_entropy(lg.flatten(0, 1), target.flatten(), reduction="none").view(target.shape).sum(1))
    return per


def test_loss_gradient_and_nll_equal_cross_entropy_of_the_picked_logits():
    model = _model()
    codes, mask, future, fmask, obs, fobs, logits = _batch()
    mine = logits.clone().requires_grad_(True)
    loss, m = mid_loop_loss(model, mine, codes, mask, future_codes=future, future_mask=fmask, training=True)
    loss.backward()
    direct = logits.clone().requires_grad_(True)
    per = _direct_nll(direct, codes, mask, future, fmask)
    want = torch.cat(per).mean()
    want.backward()
    assert torch.equal(loss.detach(), want.detach())
    assert torch.equal(mine.grad, direct.grad)
    for h, nll in enumerate(per):
        label = f"{HORIZONS[h]}steps"
        assert m[f"nll_{label}"] == float(nll.detach().mean())
    assert m["targets"] == sum(int(p.shape[0]) for p in per)
    # points no target reads get no gradient at all
    assert torch.equal(mine.grad[0, :3], torch.zeros_like(mine.grad[0, :3]))


def test_accuracies_and_decoded_errors_read_the_picked_points():
    model = _model().eval()
    codes, mask, future, fmask, obs, fobs, logits = _batch()
    _, m = mid_loop_loss(model, logits, codes, mask, obs=obs, future_codes=future, future_mask=fmask,
                         future_obs=fobs, training=False)
    s, h = HORIZONS[0], 0
    valid = mask[:, :K - s] & mask[:, s:]
    lg = torch.cat([logits[:, :K - s, h][valid], logits[:, -1, h][fmask[:, h]]])
    target = torch.cat([codes[:, s:][valid], future[:, h][fmask[:, h]]])
    assert m[f"accuracy_{s}steps"] == float((lg.argmax(-1) == target).float().mean(1).mean())
    anchor = int(fmask[:, h].sum())
    assert m[f"anchor_accuracy_{s}steps"] == float((lg[-anchor:].argmax(-1) == target[-anchor:]).float().mean(1).mean())
    with torch.no_grad():
        pred = model.predicted_observation(lg)
    obs_target = torch.cat([obs[:, s:][valid], fobs[:, h][fmask[:, h]]])
    assert m[f"obs_mse_{s}steps"] == float(((pred - obs_target) ** 2).mean(1).mean())
