"""The grid Mid Loop's loss and metrics (grid_model.py): each cell's code at each horizon against
copy-last and the code frequencies, and the joints against copy-last.

    loss, metrics = grid_loss(model, y, codes, obs, mask, future_codes=..., future_mask=...,
                              future_obs=..., labels=("0.5s", "1s"), training=True)

Code targets at a horizon of s grid steps (decoded only there, never at every point): the held
future code beyond the window at the last point (where future_mask says the episode still runs),
and the code s points ahead for the last in-window points that have one (both points real), so
score_points targets per window and horizon (all of them in-window without future codes). The
joints cost nothing per point: every in-window point with a target, and the anchor.

Metrics, per horizon ("_<label>") and over all horizons, each a mean over targets:
- nll, copy_last_nll, code_freq_nll: nats per FRAME, the sum over its G cells (as the vector Mid
  Loop sums its groups). The baselines are per cell, counted on the training targets (the model's
  code_counts [G, n] and stay_counts [H, G, 2] buffers, metrics.baseline_nll): copy-last keeps
  the cell's code with the training probability that THAT cell's code stays over the horizon;
  code frequency draws the cell's code from that cell's training frequencies. Per cell is the
  stronger baseline (a border cell that never changes costs it nearly nothing).
- accuracy / copy_last_accuracy: the fraction of cells whose argmax is right / that stayed;
  changed_accuracy: the fraction right among the cells whose code changed (copy-last's is 0).
  The model's accuracies are measured when not training only.
In training the model's nll is an unbiased estimate: every cell whose code changed is decoded,
and a stay_sample fraction of the others, weighted by its inverse (most cells hold still, and
decoding them all would be most of a step's cost); evaluation decodes every cell.
- joint_mse, copy_last_joint_mse: squared error of the predicted joints (normalised units, mean
  over dims) and of "the joints will not change".
- targets / window_targets: code targets (of them in-window); joint_targets.
A cell's predicted distribution is (1 - copy_mix) x the decoder's + copy_mix x copy-last's (the
baseline's own, from the counts): trained alone, the decoder was sure, on held-out episodes, of
changes that did not come (50 reacher camera episodes: 84 nats per frame on the cells that stayed
against copy-last's 21, which took all it won on the cells that changed). The mixture caps what a
wrong change costs at -log(copy_mix x P(stay)).
The loss: the mean over code targets of the NLL per CELL (the per-frame figure / G, so that it
sits beside the joints' MSE) + joint_weight x the joints' MSE.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from hope_models.components.mid_loop.metrics import baseline_nll


def _window_pairs(mask: torch.Tensor, s: int, last: int | None) -> tuple[torch.Tensor, torch.Tensor]:
    """(batch, point) of the in-window targets s points ahead, of the last `last` source points (None: all)."""
    k = mask.shape[1]
    lo = 0 if last is None else max(0, k - s - last)
    if s >= k or lo >= k - s:
        empty = torch.zeros(0, dtype=torch.long)
        return empty, empty
    b, p = (mask[:, lo:k - s] & mask[:, lo + s:]).nonzero(as_tuple=True)
    return b, p + lo


def _anchors(batch: int, future_mask: torch.Tensor | None, h: int) -> torch.Tensor:
    return torch.arange(batch) if future_mask is None else future_mask[:, h].nonzero(as_tuple=True)[0]


@torch.no_grad()
def count_grid_targets(model, h: int, target: torch.Tensor, now: torch.Tensor) -> None:
    """Add one horizon's training targets [N, G] to the baselines' per-cell counts."""
    g, n = model.groups, model.cfg.n_codes
    rows = (torch.arange(g) * n + target).reshape(-1)
    model.code_counts.view(-1).index_add_(0, rows, torch.ones(rows.shape[0], dtype=torch.float64))
    stayed = (target == now).sum(0).to(torch.float64)
    model.stay_counts[h, :, 1] += stayed
    model.stay_counts[h, :, 0] += target.shape[0] - stayed


def _codes_of_horizon(model, y, codes, mask, future_codes, future_mask, h, s):
    k = codes.shape[1]
    last = model.cfg.score_points - (future_codes is not None)
    wb, wp = _window_pairs(mask, s, last)  # last 0 (only the anchor's): none
    ys, now, target = [y[wb, wp]], [codes[wb, wp]], [codes[wb, wp + s]]
    if future_codes is not None:
        ab = _anchors(codes.shape[0], future_mask, h)
        ys.append(y[ab, k - 1])
        now.append(codes[ab, k - 1])
        target.append(future_codes[ab, h])
    return torch.cat(ys), torch.cat(now), torch.cat(target), int(wb.shape[0])


def _joints_of_horizon(model, y, obs, mask, future_obs, future_mask, h, s):
    k = obs.shape[1]
    wb, wp = _window_pairs(mask, s, None)
    pred = [model.joints(y[wb, wp], obs[wb, wp])[:, h]]
    now, target = [obs[wb, wp]], [obs[wb, wp + s]]
    if future_obs is not None:
        ab = _anchors(obs.shape[0], future_mask, h)
        pred.append(model.joints(y[ab, k - 1], obs[ab, k - 1])[:, h])
        now.append(obs[ab, k - 1])
        target.append(future_obs[ab, h])
    return torch.cat(pred), torch.cat(now), torch.cat(target)


def _log_copy(model, h: int, same: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """log P(target) under copy-last (metrics.baseline_nll's, per cell) where same says the code stayed."""
    stay = model.stay_counts[h].to(torch.float32)
    p = ((stay[:, 1] + 1.0) / (stay.sum(1) + 2.0))[cells]
    return torch.where(same, p.log(), ((1.0 - p) / (model.cfg.n_codes - 1)).log())


def _mixed(model, h: int, ce: torch.Tensor, same: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """The NLL of (1 - copy_mix) x the decoder's distribution + copy_mix x copy-last's, from the
    decoder's cross-entropy ce and whether each cell stayed (cells: their cell indices)."""
    eps = model.cfg.copy_mix
    if eps <= 0:
        return ce
    return -torch.logaddexp(math.log1p(-eps) - ce, math.log(eps) + _log_copy(model, h, same, cells))


def mixed_argmax(model, h: int, logits: torch.Tensor, now: torch.Tensor) -> torch.Tensor:
    """The most probable code of each cell under the mixture: the decoder's argmax, or the code now."""
    eps = model.cfg.copy_mix
    probs = logits.softmax(-1)
    p_best, best = probs.max(-1)
    if eps <= 0:
        return best
    cells = torch.arange(now.shape[-1])
    p_now = probs.gather(-1, now[..., None])[..., 0]
    copy_now = _log_copy(model, h, torch.ones_like(now, dtype=torch.bool), cells).exp()
    copy_best = _log_copy(model, h, best == now, cells).exp()
    keep = (1 - eps) * p_now + eps * copy_now >= (1 - eps) * p_best + eps * copy_best
    return torch.where(keep, now, best)


def _sampled_nll(model, ys, h, now, target, changed) -> torch.Tensor:
    """Per-target NLL [N] summed over cells, estimated from every changed cell and a stay_sample
    fraction of the others weighted by its inverse (unbiased); all cells when stay_sample is 1."""
    q = model.cfg.stay_sample
    keep = changed | (torch.rand(changed.shape) < q) if q < 1.0 else torch.ones_like(changed)
    n, g = keep.nonzero(as_tuple=True)
    ce = F.cross_entropy(model.cell_logits(ys, h, now, (n, g)), target[n, g], reduction="none")
    ce = _mixed(model, h, ce, ~changed[n, g], g)
    if q < 1.0:
        ce = ce * torch.where(changed[n, g], 1.0, 1.0 / q)
    return torch.zeros(target.shape[0], dtype=ce.dtype).index_add(0, n, ce)


def grid_loss(model, y, codes, obs, mask, *, future_codes=None, future_mask=None, future_obs=None,
              labels=None, training=True) -> tuple[torch.Tensor, dict[str, float]]:
    """See the module doc. y [B, K, d] (GridMidLoop.context), codes [B, K, G] long, obs [B, K, D]
    normalised, mask [B, K] bool, future_codes [B, H, G], future_mask [B, H], future_obs [B, H, D]."""
    horizons = model.cfg.horizon_steps
    labels = labels or tuple(f"{s}steps" for s in horizons)
    metrics: dict[str, float] = {}
    overall: dict[str, list[torch.Tensor]] = {}
    code_terms, joint_terms, window_n, total_n = [], [], 0, 0
    for h, (s, label) in enumerate(zip(horizons, labels, strict=False)):
        per: dict[str, torch.Tensor] = {}
        ys, now, target, in_window = _codes_of_horizon(model, y, codes, mask, future_codes, future_mask, h, s)
        if target.shape[0]:
            changed = target != now
            copy_nll, freq_nll = baseline_nll(model, h, target, now)
            per.update(copy_last_nll=copy_nll, code_freq_nll=freq_nll, copy_last_accuracy=(~changed).float().mean(1))
            if training:
                count_grid_targets(model, h, target, now)
                nll = _sampled_nll(model, ys, h, now, target, changed)
            else:
                logits = model.cell_logits(ys, h, now)
                ce = F.cross_entropy(logits.flatten(0, 1), target.reshape(-1), reduction="none").view(target.shape)
                nll = _mixed(model, h, ce, ~changed, torch.arange(model.groups)).sum(1)
                right = mixed_argmax(model, h, logits, now) == target  # costs about what the loss does
                per["accuracy"] = right.float().mean(1)
                if bool(changed.any()):
                    metrics[f"changed_accuracy_{label}"] = float(right[changed].float().mean())
            code_terms.append(nll / model.groups)
            per["nll"] = nll.detach()
            total_n += target.shape[0]
            window_n += in_window
        pred, jnow, jtarget = _joints_of_horizon(model, y, obs, mask, future_obs, future_mask, h, s)
        if jtarget.shape[0]:
            err = ((pred - jtarget) ** 2).mean(1)
            joint_terms.append(err)
            per.update(joint_mse=err.detach(), copy_last_joint_mse=((jnow - jtarget) ** 2).mean(1))
        for key, v in per.items():
            metrics[f"{key}_{label}"] = float(v.float().mean())
            overall.setdefault(key, []).append(v.float())
    metrics.update({key: float(torch.cat(vs).mean()) for key, vs in overall.items()})
    metrics.update(targets=float(total_n), window_targets=float(window_n),
                   joint_targets=float(sum(int(t.shape[0]) for t in joint_terms)))
    loss = y.sum() * 0.0  # no target at all (every anchor within a horizon of its episode's edges): no step lost
    if code_terms:
        loss = loss + torch.cat(code_terms).mean()
    if joint_terms:
        loss = loss + model.cfg.joint_weight * torch.cat(joint_terms).mean()
    return loss, metrics
