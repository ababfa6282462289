"""The Mid Loop's loss and what it is measured against: copy-last and code-frequency baselines.

    loss, metrics = mid_loop_loss(model, logits, codes, mask, obs=obs, future_codes=..., future_mask=...,
                                  future_obs=..., labels=("0.5s", "1s"), training=True)

Targets (see mid_loop.py): at each horizon h of s grid steps, the code s points ahead inside the
window for every point where both are real, and the held future code beyond the window's last
point. The loss is the mean over targets of the code's negative log-likelihood, the sum of its G
groups' cross-entropies (nats per observation).

The baselines, on exactly the same targets, from counts of the training targets (count_targets,
called on training batches only; the counts are MidLoop buffers, Laplace-smoothed when read):
- copy_last: P(group code stays c_now) = the fraction of training targets of that horizon and group
  whose code stayed, the rest spread evenly over the other n_codes - 1 codes;
- code_freq: P(c) = the training frequency of c in its group, whatever the history.

Metrics (all means over targets; "_<label>" versions per horizon):
- nll, copy_last_nll, code_freq_nll: nats per observation code (lower is better);
- targets / window_targets: how many targets, and how many of them inside the window;
- accuracy / copy_last_accuracy: the fraction of group codes whose argmax is right / that stayed;
  anchor_accuracy / anchor_copy_last_accuracy on the beyond-window targets only;
- with a vector VQ-VAE, when not training: obs_mse, the squared error (normalised units, mean over
  dims) of the predicted observation (MidLoop.predicted_observation) against the real one at the
  horizon, and copy_last_obs_mse, the same for "the observation will not change" (the real current
  observation, not its reconstruction: the baseline pays no tokenizer error).

The action-conditioned world model (mid_loop.py, "World model") has its own loss and metrics,
world_model_loss below: wm_obs_mse (per step ahead wm_obs_mse_<t>s) against wm_copy_obs_mse; the
component adds wm_weight x that loss to the codes' NLL.
"""
from __future__ import annotations

import torch


class _Targets:
    """One horizon's targets, flattened over batch and points: the window's first (every point k
    whose code s points ahead is inside the window, both real), then the anchor's beyond the window
    (the last point, where future_mask says the episode still runs). `pick(x)` applies the same
    selection to any [B, K, H, ...] tensor: the logits, their argmax, the NLL of every point."""

    def __init__(self, h: int, k: int, s: int):
        self.h, self.k, self.s = h, k, s
        self.valid: torch.Tensor | None = None  # [B, K - s] bool: which window targets are real
        self.fmask: torch.Tensor | None = None  # [B] bool: which anchors have a target beyond the window
        self.target: list[torch.Tensor] = []
        self.now: list[torch.Tensor] = []
        self.obs_target: list[torch.Tensor] = []
        self.obs_now: list[torch.Tensor] = []
        self.anchor = 0  # how many of the last targets are beyond-window (anchor) targets

    def add(self, target, now, obs_target=None, obs_now=None, anchor=False):
        self.target.append(target)
        self.now.append(now)
        if obs_target is not None:
            self.obs_target.append(obs_target)
            self.obs_now.append(obs_now)
        if anchor:
            self.anchor = int(target.shape[0])

    def pick(self, x: torch.Tensor) -> torch.Tensor:
        parts: list[torch.Tensor] = []
        if self.valid is not None:
            parts.append(x[:, :self.k - self.s, self.h][self.valid])
        if self.fmask is not None:
            parts.append(x[:, -1, self.h][self.fmask])
        return torch.cat(parts) if len(parts) > 1 else parts[0]

    def cat(self):
        return (torch.cat(self.target), torch.cat(self.now),
                torch.cat(self.obs_target) if self.obs_target else None,
                torch.cat(self.obs_now) if self.obs_now else None)


def _collect(codes, mask, horizon_steps, obs, future_codes, future_mask, future_obs
             ) -> tuple[list[_Targets], torch.Tensor]:
    """Each horizon's targets, and `index` [B, K, H, G]: the code each point's logits are scored
    on at each horizon (0 where there is none: `pick` never reads those)."""
    b, k, g = codes.shape
    index = codes.new_zeros(b, k, len(horizon_steps), g)
    out = []
    for h, s in enumerate(horizon_steps):
        t = _Targets(h, k, s)
        if s < k:
            t.valid = valid = mask[:, :k - s] & mask[:, s:]
            index[:, :k - s, h] = codes[:, s:]
            t.add(codes[:, s:][valid], codes[:, :k - s][valid],
                  None if obs is None else obs[:, s:][valid], None if obs is None else obs[:, :k - s][valid])
        if future_codes is not None:
            t.fmask = fmask = torch.ones(b, dtype=torch.bool) if future_mask is None else future_mask[:, h]
            index[:, -1, h] = future_codes[:, h]
            t.add(future_codes[:, h][fmask], codes[:, -1][fmask],
                  None if future_obs is None or obs is None else future_obs[:, h][fmask],
                  None if future_obs is None or obs is None else obs[:, -1][fmask], anchor=True)
        out.append(t)
    return out, index


@torch.no_grad()
def count_targets(model, targets: list[_Targets]) -> None:
    """Add training targets to the baselines' counts (code frequencies, stays per horizon)."""
    n = model.cfg.n_codes
    for h, t in enumerate(targets):
        if not t.target:
            continue
        target, now = torch.cat(t.target), torch.cat(t.now)  # [N, G]
        for g in range(model.groups):
            model.code_counts[g] += torch.bincount(target[:, g], minlength=n).to(torch.float64)
            stayed = float((target[:, g] == now[:, g]).sum())
            model.stay_counts[h, g, 1] += stayed
            model.stay_counts[h, g, 0] += target.shape[0] - stayed


def baseline_nll(model, h: int, target: torch.Tensor, now: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-target NLL (summed over groups) of copy-last and code-frequency at horizon index h."""
    n = model.cfg.n_codes
    counts = model.code_counts.to(torch.float32)
    freq = (counts + 1.0) / (counts.sum(1, keepdim=True) + n)  # [G, n], Laplace
    stay = model.stay_counts[h].to(torch.float32)
    p_stay = (stay[:, 1] + 1.0) / (stay.sum(1) + 2.0)  # [G]
    same = target == now
    p_copy = torch.where(same, p_stay[None], (1.0 - p_stay[None]) / (n - 1))
    p_freq = freq.gather(1, target.t()).t()  # [N, G]
    return -p_copy.log().sum(1), -p_freq.log().sum(1)


def mid_loop_loss(model, logits, codes, mask, *, obs=None, future_codes=None, future_mask=None,
                  future_obs=None, labels=None, training=True) -> tuple[torch.Tensor, dict[str, float]]:
    """See the module doc. logits [B, K, H, G, n], codes [B, K, G], mask [B, K] bool, obs [B, K, D]
    (normalised; None for frames), future_codes [B, H, G], future_mask [B, H], future_obs [B, H, D]."""
    horizons = model.cfg.horizon_steps
    labels = labels or tuple(f"{s}steps" for s in horizons)
    want_obs = obs is not None and not training and model.vqvae.cfg.input == "vector"
    targets, index = _collect(codes, mask, horizons, obs if want_obs else None, future_codes, future_mask,
                              future_obs if want_obs else None)
    if training:
        count_targets(model, targets)
    metrics: dict[str, float] = {}
    overall: dict[str, list[torch.Tensor]] = {}  # per-target values of every horizon: the overall means
    total_n, window_n, nll_all = 0, 0, []
    # One log-softmax and one gather over every point: the values cross-entropy gives each target,
    # bit for bit, without a backward that scatters each horizon's picked logits into a zeroed
    # copy of the whole [B, K, H, G, n] tensor (a fifth of a step's time).
    nll_groups = -logits.log_softmax(-1).gather(-1, index.unsqueeze(-1)).squeeze(-1)  # [B, K, H, G]
    best = logits.detach().argmax(-1)  # [B, K, H, G]
    for h, (t, label) in enumerate(zip(targets, labels, strict=False)):
        if not t.target:
            continue
        target, now, obs_target, obs_now = t.cat()
        if target.shape[0] == 0:
            continue
        nll = t.pick(nll_groups).sum(1)
        nll_all.append(nll)
        copy_nll, freq_nll = baseline_nll(model, h, target, now)
        right = (t.pick(best) == target).float()
        stayed = (now == target).float()
        per = {"nll": nll.detach(), "copy_last_nll": copy_nll, "code_freq_nll": freq_nll,
               "accuracy": right.mean(1), "copy_last_accuracy": stayed.mean(1)}
        if t.anchor:
            per["anchor_accuracy"] = right[-t.anchor:].mean(1)
            per["anchor_copy_last_accuracy"] = stayed[-t.anchor:].mean(1)
        if obs_target is not None and obs_target.shape[0]:
            with torch.no_grad():
                pred = model.predicted_observation(t.pick(logits))
            per["obs_mse"] = ((pred - obs_target) ** 2).mean(1)
            per["copy_last_obs_mse"] = ((obs_now - obs_target) ** 2).mean(1)
        for key, v in per.items():
            metrics[f"{key}_{label}"] = float(v.float().mean())
            overall.setdefault(key, []).append(v.float())
        total_n += target.shape[0]
        window_n += target.shape[0] - t.anchor
    if total_n == 0:
        # e.g. every anchor within a horizon of its episode's start and end: nothing to learn from
        # this batch, which must not stop a run. A zero loss that still has a graph (backward works).
        return logits.sum() * 0.0, {"targets": 0.0, "window_targets": 0.0}
    metrics.update({key: float(torch.cat(vs).mean()) for key, vs in overall.items()})
    metrics["targets"] = float(total_n)
    metrics["window_targets"] = float(window_n)  # of them inside the window (the rest: beyond it)
    loss = torch.cat(nll_all).mean()
    return loss, metrics


def world_model_loss(model, y, obs, act, mask, grid_step_s: float | None = None
                     ) -> tuple[torch.Tensor, dict[str, float]]:
    """The action-conditioned world model's loss (mid_loop.py, "World model"): at every point k of
    the window with wm_horizon real points after it, the MSE (normalised units, mean over dims)
    of its predicted observations at k+1 .. k+M, given the actions held at k .. k+M-1.

    y [B, K, d] (the context), obs [B, K, D] normalised, act [B, K, A] held actions, mask [B, K].
    Metrics: wm_obs_mse, and per step ahead wm_obs_mse_<t>s (t = j x grid_step_s, or <j>steps);
    wm_copy_obs_mse(_<t>s), the same for "the observation will not change" (the baseline it must
    beat); wm_targets, how many points were scored. No target (windows shorter than M + 1 real
    points): a zero loss that still has a graph."""
    m = model.cfg.wm_horizon
    k = obs.shape[1]
    if k <= m:
        return y.sum() * 0.0, {"wm_targets": 0.0}
    valid = mask[:, :k - m]  # the pre-episode prefix comes first: every point after a real one is real
    now = obs[:, :k - m][valid]  # [N, D]
    target = obs.unfold(1, m, 1)[:, 1:].transpose(-1, -2)[valid]  # [N, M, D]: obs at k+1 .. k+M
    acts = act.unfold(1, m, 1)[:, :k - m].transpose(-1, -2)[valid]  # [N, M, A]: held at k .. k+M-1
    if now.shape[0] == 0:
        return y.sum() * 0.0, {"wm_targets": 0.0}
    pred = model.wm_predict(y[:, :k - m][valid], now, acts)
    err = ((pred - target) ** 2).mean(-1)  # [N, M]
    copy = ((now.unsqueeze(1) - target) ** 2).mean(-1).detach()
    loss = err.mean()
    metrics = {"wm_obs_mse": float(loss.detach()), "wm_copy_obs_mse": float(copy.mean()),
               "wm_targets": float(now.shape[0])}
    for j in range(m):
        label = f"{(j + 1) * grid_step_s:g}s" if grid_step_s else f"{j + 1}steps"
        metrics[f"wm_obs_mse_{label}"] = float(err[:, j].detach().mean())
        metrics[f"wm_copy_obs_mse_{label}"] = float(copy[:, j].mean())
    return loss, metrics
