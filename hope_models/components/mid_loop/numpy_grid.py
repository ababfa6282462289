"""The grid Mid Loop (grid_model.GridMidLoop) in NumPy: a K-point window of a camera's cell codes, the
joints and the previous actions -> the joints at each horizon and each cell's code distribution.

    model = GridMidLoopNumpy(...)                  # numpy_form.MidLoopRuntime.from_checkpoint picks it
    codes = model.frame_vq.codes(frame)           # its OWN frozen VQ-VAE's cell codes [G] of a uint8 frame
    y = model.context(codes [L, G], prev_act_n [L, A], obs_n [L, D])     # [L, d], L <= K (last_only: [1, d])
    model.joints(y, obs_n)                        # [..., H, D] normalised joints at each horizon
    model.cell_log_probs(y [d], h, codes_now [G]) # [G, n] log P of each cell's code s_h points later

The arithmetic is grid_model.py's in eval mode (dropout the identity), float32 like torch
(tests/test_mid_loop_numpy_grid.py checks it within 1e-4): the input of a point is
keypoints(codes) (components/numpy_keypoints.py, CodeKeypoints with reader "policy") + the mean
over cells of code_in[code] + act_in(previous action) + obs_in(joints); SSMStack over the window
(numpy_ssm.py) and ln_f give y. The shared cell decoder of horizon h: z_g = cell_ctx(y)[h] +
cell_pos[g] + cell_code[c_g], u = z + GatedMLP(LN(z)), logits = cell_out(u). Each cell's
distribution is then mixed with copy-last's as the loss and the metrics read it (grid_metrics.py,
copy_mix): P = (1 - copy_mix) P_decoder + copy_mix P_copy, P_copy keeping the cell's code with the
training probability (stay_counts, +1/+2 smoothed) that that cell's code stays over the horizon
and spreading the rest over the other codes. code_counts is not read.

Serving (mid_loop/serving.py) keeps, per grid point, the point's input without its action
(point()), runs the window's last point only (predict(): the joints per horizon in raw units,
and what a later surprise needs, y and the codes now: GridMemo), and scores a horizon's cells when
its target arrives (surprises(): the horizons due at a point in one pass), so no [K, H, G, n]
tensor is made. Neither the [G, n] logits' normaliser of each cell nor the decoder's hidden
depends on the target, and the next window's points but its last are known a grid step ahead, so
the control ticks between grid points (4 of 5 at 20 ms / 100 ms) do that work, one step a tick
(prepare(), then window_ahead() and ahead_step()): the newest prediction's normalisers, the
hidden of the predictions the next grid point scores, the blocks' states over the next window's
first K-1 points (numpy_ssm.advance: a block's SSM, then its MLP, a stage a tick). The grid point then runs its new point through one recurrent step a block and reads one
row of cell_out per cell (a [G, r] product instead of the decoder, [G, r] x [r, n] and G x n
exponentials). A session with no tick between grid points, or a step not yet done, takes the
whole of it at the grid point (the same figures). Memory per session: G floats a horizon a
prediction (2 KB at 256 cells) for the longest horizon's points, the hidden [G, r] of the
predictions due at the next grid point (32 KB a horizon at rank 32, dropped once scored) and
n_layers x d_state floats of states. Torch-free.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.components.mid_loop.checkpoint import grid_frame
from hope_models.components.mid_loop.config import MidLoopConfig
from hope_models.components.mid_loop.numpy_ssm import (
    SSMBlockNumpy,
    WindowAhead,
    advance,
    run_window,
    step_last,
    window_ahead,
)
from hope_models.components.numpy_keypoints import KeypointsNumpy
from hope_models.components.numpy_layers import Linear, NormMLP, layer_norm
from hope_models.components.vqvae.numpy_form import Normaliser, VQVAENumpy
from hope_models.data.features import FeatureSpec


@dataclass(eq=False)
class GridMemo:
    """What a grid point predicted, for the surprise s_h points later: the context and the codes
    then; per horizon, once prepare() has computed them, each cell's log-normaliser [G] and, on
    the tick before the grid point that scores it, the decoder's hidden [G, r] (dropped once used)."""
    y: np.ndarray
    now: np.ndarray
    lse: dict[int, np.ndarray] = field(default_factory=dict)
    u: dict[int, np.ndarray] = field(default_factory=dict)


@dataclass(frozen=True)
class GridPoint:
    """What a session's window keeps of one grid point: its codes, its input without the action, its joints."""
    codes: np.ndarray  # [G] cell codes of the frame
    x: np.ndarray  # [d]: keypoints + mean code embedding + obs_in(joints)
    obs_n: np.ndarray  # [D] normalised joints


def horizon_fields(model: Any, config: dict[str, Any]) -> None:
    """The window and horizons of a checked mid_loop config, as attributes both forms answer with."""
    mc, window = config["model_config"], config["window"]
    model.horizon_steps = [int(s) for s in mc["horizon_steps"]]
    model.window_k = int(window["k"])
    model.grid_step_s = float(window["duration_s"]) / model.window_k
    model.horizons_s = [s * model.grid_step_s for s in model.horizon_steps]
    model.horizon_names = [f"{round(h, 6):g}s" for h in model.horizons_s]  # "0.5s", "1s"


class GridMidLoopNumpy:
    """One grid mid_loop checkpoint, runnable on windows of grid points. Immutable after load."""

    name = "mid_loop"

    def status_fields(self) -> dict:
        """What BrainService.status() adds for this component: the shape of its answer."""
        return {"horizons": self.horizon_names, "grid_step_s": self.grid_step_s, "window_k": self.window_k,
                "groups": self.groups, "n_codes": self.n_codes, "grid": list(self.grid), "copy_mix": self.copy_mix}

    def __init__(self, *, checkpoint: Path, config: dict[str, Any], spec: FeatureSpec,
                 tensors: dict[str, np.ndarray], sha256: str, version: str):
        self.checkpoint, self.config, self.spec, self.sha256, self.version = checkpoint, config, spec, sha256, version
        mc, t = config["model_config"], tensors
        frame = grid_frame(config)
        assert frame is not None, "checkpoint.check_config has checked that this Mid Loop reads a grid"
        horizon_fields(self, config)
        self.obs_dim, self.act_dim = spec.obs_dim, spec.act_dim
        self.n_codes, self.n_layers, self.cell_rank = int(mc["n_codes"]), int(mc["n_layers"]), int(mc["cell_rank"])
        self.copy_mix = float(mc.get("copy_mix", MidLoopConfig.copy_mix))
        self.observation_fields = [(f.path, f.size) for f in spec.observation.fields]
        self.action_fields = [(f.path, f.size) for f in spec.action.fields]
        # it reads the request's camera frame: a replacement must read the same size of frame
        self.frame_shape: tuple[int, ...] = tuple(frame.frame_shape)
        self.fit_fields = (self.observation_fields, self.action_fields, self.frame_shape)
        self.vqvae_sha256 = config["vqvae"].get("weights_sha256")
        self.frame_vq = VQVAENumpy(t, groups=frame.groups, n_codes=self.n_codes, prefix="vqvae.", decoder=False,
                                   frame=frame)
        self.groups, self.grid = frame.groups, tuple(frame.grid_shape)
        self.norm = Normaliser(spec)

        def lin(name: str) -> Linear:
            return Linear(np.ascontiguousarray(t[f"{name}.weight"].T), t[f"{name}.bias"])

        self._kp = KeypointsNumpy(t, "keypoints", self.grid)
        self._code_in = t["code_in.weight"]  # [n, d], shared by every cell
        self._act_in, self._obs_in = lin("act_in"), lin("obs_in")
        self._blocks = [SSMBlockNumpy(t, f"ssm.blocks.{i}", self.window_k) for i in range(self.n_layers)]
        self._lnf_w, self._lnf_b = t["ssm.ln_f.weight"], t["ssm.ln_f.bias"]
        self.d_model = d = self._code_in.shape[1]
        self._mean = np.full(d, 1.0 / d, np.float32)
        self._mean_r = np.full(self.cell_rank, 1.0 / self.cell_rank, np.float32)
        r, h = self.cell_rank, len(self.horizon_steps)
        ctx = lin("cell_ctx")
        self._cell_ctx = [Linear(np.ascontiguousarray(ctx.w_t[:, i * r:(i + 1) * r]), ctx.b[i * r:(i + 1) * r])
                          for i in range(h)]
        self._cell_pos, self._cell_code = t["cell_pos.weight"], t["cell_code.weight"]  # [G, r], [n, r]
        self._cell_mlp = NormMLP.fold(t, "cell_ln", "cell_mlp")
        self._cell_out = lin("cell_out")  # [r, n]
        self._cell_v = np.ascontiguousarray(t["cell_out.weight"])  # [n, r]: a code's row
        self._joint_out = lin("joint_out")  # [d, H * D]
        # copy-last's per-cell log-probabilities, as grid_metrics._log_copy computes them (float32)
        stay = t["stay_counts"].astype(np.float32)  # [H, G, 2]: [changed, stayed]
        p = (stay[..., 1] + np.float32(1.0)) / (stay.sum(-1) + np.float32(2.0))
        self._log_stay = np.log(p).astype(np.float64)
        self._log_move = np.log((np.float32(1.0) - p) / np.float32(self.n_codes - 1)).astype(np.float64)

    # -- the window ----------------------------------------------------------------------------------
    def point_inputs(self, codes: np.ndarray, obs_n: np.ndarray) -> np.ndarray:
        """Cell codes [..., G], normalised joints [..., D] -> the points' inputs without the action [..., d]."""
        codes = np.asarray(codes)
        flat = codes.reshape(-1, self.groups)
        # the mean of the cells' embeddings as a histogram of codes times the table (GridMidLoop._inputs)
        hist = np.stack([np.bincount(c, minlength=self.n_codes) for c in flat]).astype(np.float32)
        hist *= np.float32(1.0 / self.groups)
        x = self._kp(codes)
        x += hist.dot(self._code_in).reshape(x.shape)
        x += self._obs_in(np.asarray(obs_n, np.float32))
        return x

    def _context(self, x: np.ndarray, last_only: bool) -> np.ndarray:
        if not 0 < x.shape[0] <= self.window_k:
            raise ValueError(f"a window holds 1 to {self.window_k} grid points, got {x.shape[0]}")
        y = layer_norm(run_window(self._blocks, x, self._mean, last_only), self._mean)
        y *= self._lnf_w
        y += self._lnf_b
        return y

    def context(self, codes: np.ndarray, prev_act_n: np.ndarray, obs_n: np.ndarray,
                last_only: bool = False) -> np.ndarray:
        """A window from a zero state: codes [L, G], normalised previous actions [L, A] (zeros at the
        first point), normalised joints [L, D] -> y [L, d] (last_only: [1, d])."""
        x = self.point_inputs(codes, obs_n)
        x += self._act_in(np.asarray(prev_act_n, np.float32))
        return self._context(x, last_only)

    def joints(self, y: np.ndarray, obs_n: np.ndarray) -> np.ndarray:
        """Context [..., d], joints now [..., D] -> the joints at each horizon [..., H, D] (normalised)."""
        delta = self._joint_out(y).reshape(*y.shape[:-1], len(self.horizon_steps), self.obs_dim)
        return np.asarray(obs_n, np.float32)[..., None, :] + delta

    def cell_logits(self, y: np.ndarray, h: int, now: np.ndarray) -> np.ndarray:
        """Context [..., d], horizon index h, codes now [..., G] -> logits [..., G, n_codes] of each
        cell's code s_h grid points later (GridMidLoop.cell_logits)."""
        return self._cell_out(self._hidden(self._cell_ctx[h](y), now))

    def _hidden(self, ctx: np.ndarray, now: np.ndarray) -> np.ndarray:
        """The shared cell decoder's last hidden u [..., G, r] from a horizon's context ctx [..., r]
        and the codes now [..., G]."""
        z = ctx[..., None, :] + self._cell_pos + self._cell_code[now]  # [..., G, r]
        z += self._cell_mlp(layer_norm(z, self._mean_r))
        return z

    def cell_log_probs(self, y: np.ndarray, h: int, now: np.ndarray) -> np.ndarray:
        """log P of every code of every cell [..., G, n] (float64): the decoder's mixed with copy-last's."""
        z = self.cell_logits(y, h, now).astype(np.float64)
        z -= z.max(-1, keepdims=True)
        z -= np.log(np.exp(z).sum(-1, keepdims=True))
        eps = self.copy_mix
        if eps <= 0:
            return z
        copy = np.broadcast_to(self._log_move[h][:, None], z.shape).copy()  # [..., G, n]
        np.put_along_axis(copy, np.asarray(now)[..., None], np.broadcast_to(self._log_stay[h], now.shape)[..., None],
                          -1)
        return np.logaddexp(math.log1p(-eps) + z, math.log(eps) + copy)

    def observed_log_prob(self, y: np.ndarray, h: int, now: np.ndarray, later: np.ndarray) -> np.ndarray:
        """log P [G] (float64) of each cell's code `later` under the distribution predicted from
        (y [d], now [G]) for horizon h; only those G entries of the mixture are computed."""
        return self._observed([(GridMemo(y, now), h)], later)[0]

    def _cells(self, due: list[tuple[GridMemo, int]]) -> np.ndarray:
        """The shared cell decoder's last hidden u [M, G, r] of several (prediction, horizon)."""
        return self._hidden(np.stack([self._cell_ctx[h](m.y) for m, h in due]), np.stack([m.now for m, _ in due]))

    def _log_norm(self, logits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each cell's max [M, G] and log sum exp(logits - max) [M, G], float32 like torch's
        cross-entropy, shifted by the max first (logits is overwritten)."""
        top = logits.max(-1)
        logits -= top[..., None]
        np.exp(logits, out=logits)
        return top, np.log(logits.sum(-1))

    def _observed(self, due: list[tuple[GridMemo, int]], later: np.ndarray) -> np.ndarray:
        """observed_log_prob of several (prediction, horizon) at once [M, G] (float64): one decoder
        pass over M x G cells. Where prepare() has computed the normaliser (and the decoder's
        hidden u), only one row of cell_out per cell is read; else the whole [G, n] logits."""
        u = [m.u.pop(h, None) for m, h in due]  # a hidden is used once: not kept past its grid point
        missing = [i for i, v in enumerate(u) if v is None]
        if missing:
            for i, v in zip(missing, self._cells([due[i] for i in missing]), strict=True):
                u[i] = v
        hidden = np.stack(u)  # [M, G, r]
        if all(h in m.lse for m, h in due):
            picked = np.einsum("mgr,gr->mg", hidden, self._cell_v[later]) + self._cell_out.b[later]
            lp = picked.astype(np.float64) - np.stack([m.lse[h] for m, h in due])
        else:
            logits = self._cell_out(hidden)  # [M, G, n]
            picked = np.take_along_axis(logits, np.broadcast_to(later, logits.shape[:-1])[..., None], -1)[..., 0]
            top, lse = self._log_norm(logits)
            lp = (picked - top).astype(np.float64) - lse
        eps = self.copy_mix
        if eps <= 0:
            return lp
        hs = [h for _, h in due]
        copy = np.where(later == np.stack([m.now for m, _ in due]), self._log_stay[hs], self._log_move[hs])
        return np.logaddexp(math.log1p(-eps) + lp, math.log(eps) + copy)

    def prepare(self, newest: GridMemo, due_next: dict[int, GridMemo]) -> bool:
        """One step of the next grid points' surprise, on a tick between grid points (serving.py):
        the newest prediction's normalisers (every horizon at once), else the decoder's hidden of
        the predictions the next grid point scores (due_next: {h: memo}). False when nothing is left."""
        todo = [(newest, h) for h in range(len(self.horizon_steps)) if h not in newest.lse]
        if todo:
            u = self._cells(todo)
            top, lse = self._log_norm(self._cell_out(u))
            for i, (memo, h) in enumerate(todo):
                memo.lse[h] = (top[i] + lse[i]).astype(np.float64)
                if due_next.get(h) is memo:
                    memo.u[h] = u[i]
            return True
        todo = [(m, h) for h, m in due_next.items() if h not in m.u]
        if todo:
            for (memo, h), u in zip(todo, self._cells(todo), strict=True):
                memo.u[h] = u
            return True
        return False

    def window_ahead(self, points: list[GridPoint], acts_n: np.ndarray) -> WindowAhead:
        """The next window but its last point (points, their normalised previous actions, zeros at
        the first) -> the blocks' SSM states after them, the first stage done (ahead_step() does
        the others, one a call: a block's SSM, its MLP): predict() then runs the new point alone, one recurrent step a
        block (the same sums as the window's parallel form)."""
        if points:
            x = np.stack([p.x for p in points])
            x += self._act_in(np.asarray(acts_n, np.float32))
        else:
            x = np.zeros((0, self.d_model), np.float32)
        ahead = window_ahead(self._blocks, x)
        advance(self._blocks, ahead, self._mean)
        return ahead

    def ahead_step(self, ahead: WindowAhead) -> bool:
        """One more stage of a window_ahead() -> whether all are done."""
        return advance(self._blocks, ahead, self._mean)

    def _step_last(self, x: np.ndarray, ahead: np.ndarray) -> np.ndarray:
        """The window's last point [d] from the states of the points before it -> y [d] (after ln_f)."""
        y = layer_norm(step_last(self._blocks, x, ahead, self._mean), self._mean)
        y *= self._lnf_w
        y += self._lnf_b
        return y

    # -- what serving.py calls -------------------------------------------------------------------
    def point(self, values: np.ndarray, codes: np.ndarray | None) -> GridPoint:
        """A grid point from the raw joints [D] and the frame's cell codes [G] (by frame_vq)."""
        if codes is None:
            raise ValueError(f"{self.version} reads the camera: a grid point needs the frame's codes")
        obs_n = self.norm.obs(values)
        return GridPoint(np.asarray(codes), self.point_inputs(codes, obs_n), obs_n)

    def predict(self, points: list[GridPoint], acts_n: np.ndarray,
                ahead: WindowAhead | None = None) -> tuple[np.ndarray, Any, bool]:
        """The window's last point -> (joints per horizon [H, D] raw units float64, what surprises()
        reads later, finite). ahead: window_ahead() of points[:-1], acts_n[:-1] (then only the
        last point is run)."""
        if ahead is None:
            x = np.stack([p.x for p in points])
            x += self._act_in(np.asarray(acts_n, np.float32))
            y = self._context(x, last_only=True)[-1]
        else:
            while not self.ahead_step(ahead):  # a grid point before the ticks between finished it
                pass
            y = self._step_last(points[-1].x + self._act_in(np.asarray(acts_n[-1], np.float32)), ahead.states)
        pred = self.norm.raw_obs(self.joints(y, points[-1].obs_n))
        return pred, GridMemo(y, points[-1].codes), bool(np.isfinite(pred).all() and np.isfinite(y).all())

    def surprises(self, due: dict[int, Any], point: GridPoint) -> dict[int, float]:
        """{horizon index: what predict() returned s_h points ago} -> {h: -sum over the cells of
        log P(the point's code) under that horizon's distribution} (nats), all decoded in one pass."""
        if not due:
            return {}
        lp = self._observed([(memo, h) for h, memo in due.items()], point.codes)
        return {h: float(-v) for h, v in zip(due, lp.sum(-1), strict=True)}

    def warm(self) -> None:
        """A full window, a one-point one and a surprise, so the first request after a swap pays no first-call costs."""
        codes = self.frame_vq.codes(np.zeros(self.frame_shape, np.uint8))
        p = self.point(np.zeros(self.obs_dim), codes)
        acts = np.zeros((self.window_k, self.act_dim), np.float32)
        _, memo, _ = self.predict([p] * self.window_k, acts)
        self.predict([p], acts[:1])
        self.predict([p] * self.window_k, acts, self.window_ahead([p] * (self.window_k - 1), acts[1:]))
        every = dict.fromkeys(range(len(self.horizon_steps)), memo)
        self.surprises(every, p)
        while self.prepare(memo, every):
            pass
        self.surprises(every, p)

    def describe_observation(self, limit: int = 12) -> str:
        names = self.spec.observation.dim_names()
        return ", ".join(names[:limit]) + (f", ... ({len(names) - limit} more)" if len(names) > limit else "")

    def __repr__(self) -> str:
        return (f"GridMidLoopNumpy({self.version}, {'x'.join(map(str, self.grid))} cells x {self.n_codes} codes + "
                f"joints {self.obs_dim} + act {self.act_dim}, K={self.window_k}, horizons {self.horizon_names}, "
                f"copy_mix {self.copy_mix:g})")


__all__ = ["GridMemo", "GridMidLoopNumpy", "GridPoint", "horizon_fields"]
