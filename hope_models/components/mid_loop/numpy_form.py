"""The Mid Loop in NumPy: a K-point window of codes and previous actions -> code logits per horizon.

    model = MidLoopNumpy.from_checkpoint(ckpt, expected_sha256=..., verify_manifest=True)
    rows = model.rows_of(raw_observation)                 # its own VQ-VAE's codes, as code_in rows [G]
    logits = model.forward(rows_window [L, G], prev_act_n [L, A])    # [L, H, G, n_codes], L <= K
    logits = model.forward(..., last_only=True)           # [1, H, G, n]: what serving needs
    model.prediction(logits[-1])                          # [H, obs_dim] expected observation, raw units
    ahead = model.window_ahead(points[:-1], acts[:-1])    # serving: the window but its last point,
    model.ahead_step(ahead)                               #   a stage a call on the ticks between grid points,
    model.predict(points, acts, ahead)                    #   then the last point alone (the same sums)

The arithmetic is hope_models/components/mid_loop/model.py and SSMStack/SSMBlock/DiagonalSSM in
hope_models/components/ssm.py, float32 (tests/test_brain_whole.py checks forward against MidLoop.forward in eval
mode within 1e-4): x = code_in(rows).sum(G) + act_in(prev_act); per block u = LN1(x),
h_t = sum_{s<=t} a^(t-s) g (B u_s) (the parallel form over the window, from a zero state),
x += C h + D u, x += GatedMLP(LN2(x)); then ln_f and the head. Dropout is the identity at
inference. The checkpoint's own frozen VQ-VAE (tensors vqvae.*) encodes observations and decodes
the prediction: a Mid Loop carries the VQ-VAE it was trained with. A Mid Loop over a grid frame
VQ-VAE is numpy_grid.py's GridMidLoopNumpy; MidLoopRuntime (RUNTIME) loads either. code_counts/stay_counts (the
baselines' statistics) and any `wm_*` tensor (a world model's action-conditioned heads) are not
read. What is refused, and why, is hope_models/components/mid_loop/checkpoint.py's.

Why the window form and not step(): the stepped SSMStack remembers everything since init_state
(mid_loop.py), while training saw K-point windows, so each prediction is computed from the
session's last K grid points (bench/inference.py measures forward against re-stepping K points:
docs/benchmarks.md). step() is kept for that comparison and the tests. Torch-free.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.components.mid_loop.checkpoint import MidLoopNumpyError, grid_frame, read_mid_loop
from hope_models.components.mid_loop.numpy_grid import GridMidLoopNumpy
from hope_models.components.mid_loop.numpy_ssm import (
    SSMBlockNumpy,
    WindowAhead,
    advance,
    run_window,
    step_last,
    window_ahead,
)
from hope_models.components.numpy_layers import LN_EPS, Linear, fold_ln, layer_norm
from hope_models.components.vqvae.numpy_form import Normaliser, VQVAENumpy
from hope_models.data.features import FeatureSpec


class MidLoopNumpy:
    """One mid_loop checkpoint, runnable on windows of grid points. Immutable after load."""

    name = "mid_loop"

    def status_fields(self) -> dict:
        """What BrainService.status() adds for this component: the shape of its answer."""
        return {"horizons": self.horizon_names, "grid_step_s": self.grid_step_s, "window_k": self.window_k,
                "groups": self.groups, "n_codes": self.n_codes}

    def __init__(self, *, checkpoint: Path, config: dict[str, Any], spec: FeatureSpec,
                 tensors: dict[str, np.ndarray], sha256: str, version: str):
        self.checkpoint, self.config, self.spec, self.sha256, self.version = checkpoint, config, spec, sha256, version
        mc, window, vq_ref = config["model_config"], config["window"], config["vqvae"]
        self.obs_dim, self.act_dim = spec.obs_dim, spec.act_dim
        self.n_codes, self.n_layers = int(mc["n_codes"]), int(mc["n_layers"])
        self.horizon_steps = [int(s) for s in mc["horizon_steps"]]
        self.window_k = int(window["k"])
        self.grid_step_s = float(window["duration_s"]) / self.window_k
        self.horizons_s = [s * self.grid_step_s for s in self.horizon_steps]
        self.horizon_names = [f"{round(h, 6):g}s" for h in self.horizons_s]  # "0.5s", "1s"
        self.observation_fields = [(f.path, f.size) for f in spec.observation.fields]
        self.action_fields = [(f.path, f.size) for f in spec.action.fields]
        self.fit_fields = (self.observation_fields, self.action_fields)
        self.vqvae_sha256 = vq_ref.get("weights_sha256")
        self.vq = VQVAENumpy(tensors, groups=int(vq_ref["model_config"].get("groups", 1)), n_codes=self.n_codes,
                             prefix="vqvae.")
        self.groups = self.vq.groups
        self.norm = Normaliser(spec)
        t = tensors
        self._code_in = t["code_in.weight"]  # [G * n, d]
        self._act_in = Linear(np.ascontiguousarray(t["act_in.weight"].T), t["act_in.bias"])
        self._blocks = [SSMBlockNumpy(t, f"ssm.blocks.{i}", self.window_k) for i in range(self.n_layers)]
        self._lnf_w, self._lnf_b = t["ssm.ln_f.weight"], t["ssm.ln_f.bias"]
        self._head = Linear(np.ascontiguousarray(t["head.weight"].T), t["head.bias"])
        self._head_ln_w, self._head_ln_b = fold_ln(self._lnf_w, self._lnf_b, t["head.weight"], t["head.bias"])
        d = self._code_in.shape[1]
        self.d_model = d
        self._mean = np.full(d, 1.0 / d, np.float32)
        self._offsets = np.arange(self.groups) * self.n_codes
        self._same_codes: tuple[Any, bool] | None = None  # (the tokenizer last asked about, same_codes' answer)

    @classmethod
    def from_checkpoint(cls, path: str | Path, *, expected_sha256: str | None = None,
                        verify_manifest: bool = False) -> "MidLoopNumpy":
        ck = read_mid_loop(path, expected_sha256=expected_sha256, verify_manifest=verify_manifest)
        if grid_frame(ck.config) is not None:
            raise MidLoopNumpyError(f"{ck.path}: a grid Mid Loop (it reads camera frames): its form is "
                                    "numpy_grid.GridMidLoopNumpy (MidLoopRuntime.from_checkpoint picks it)")
        return cls(checkpoint=ck.path, config=ck.config, spec=ck.spec, tensors=ck.tensors, sha256=ck.sha256,
                   version=ck.version)

    # -- inputs ---------------------------------------------------------------------------------
    def codes_of(self, values: np.ndarray) -> np.ndarray:
        """Raw observation [obs_dim] -> group-local codes [G] of its own VQ-VAE (its own normalisation)."""
        return self.vq.codes(self.norm.obs(values))

    def rows(self, codes: np.ndarray) -> np.ndarray:
        """Group-local codes [..., G] -> rows of code_in (VQVAE.rows)."""
        return codes + self._offsets

    def _inputs(self, rows: np.ndarray, prev_act_n: np.ndarray) -> np.ndarray:
        x = self._act_in(prev_act_n)
        x += self._code_in[rows].sum(-2)
        return x

    def _mlp(self, blk: SSMBlockNumpy, x: np.ndarray) -> np.ndarray:
        x = x + blk.mlp(layer_norm(x, self._mean))
        return x

    def _logits(self, x: np.ndarray) -> np.ndarray:
        if x.ndim == 1:  # one point (predict's): LayerNorm's statistics as Python floats, ln_f folded into the head
            n = x - float(x.dot(self._mean))
            n *= 1.0 / math.sqrt(float(n.dot(n)) / self.d_model + LN_EPS)
            y = n.dot(self._head_ln_w)
            y += self._head_ln_b
            return y.reshape(len(self.horizon_steps), self.groups, self.n_codes)
        y = layer_norm(x, self._mean)
        y *= self._lnf_w
        y += self._lnf_b
        return self._head(y).reshape(*x.shape[:-1], len(self.horizon_steps), self.groups, self.n_codes)

    # -- the two forms --------------------------------------------------------------------------
    def forward(self, rows: np.ndarray, prev_act_n: np.ndarray, last_only: bool = False) -> np.ndarray:
        """A window from a zero state: rows [L, G] (code_in rows), normalised previous actions [L, A],
        L <= K -> logits [L, H, G, n] (last_only: [1, H, G, n], the last point's; the last block's
        MLP, ln_f and the head then run on that point only)."""
        length = rows.shape[0]
        if not 0 < length <= self.window_k:
            raise ValueError(f"a window holds 1 to {self.window_k} grid points, got {length}")
        x = self._inputs(rows, np.asarray(prev_act_n, dtype=np.float32))
        x = run_window(self._blocks, x, self._mean, last_only)
        return self._logits(x)

    def init_state(self) -> np.ndarray:
        return np.zeros((self.n_layers, self._blocks[0].a.shape[0]), np.float32)

    def step(self, rows: np.ndarray, prev_act_n: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One grid point (rows [G], previous action [A]) -> (logits [H, G, n], new state [n_layers, N]).
        Remembers everything since init_state (not window-exact: see the module doc)."""
        x = self._inputs(rows, np.asarray(prev_act_n, dtype=np.float32))
        new = np.empty_like(state)
        for i, blk in enumerate(self._blocks):
            u = blk.ln1(x, self._mean)
            h = blk.a * state[i] + u.dot(blk.bg_t)
            new[i] = h
            x = x + h.dot(blk.c_t) + u * blk.d
            x = self._mlp(blk, x)
        return self._logits(x), new

    # -- outputs --------------------------------------------------------------------------------
    def log_probs(self, logits: np.ndarray) -> np.ndarray:
        """log softmax over the codes, float64 (surprise sums these; no underflow to -inf)."""
        z = logits.astype(np.float64)
        z -= z.max(-1, keepdims=True)
        z -= np.log(np.exp(z).sum(-1, keepdims=True))
        return z

    def prediction_n(self, logp: np.ndarray) -> np.ndarray:
        """Log-probabilities [..., G, n] -> the expected observation, normalised [..., obs_dim]
        (MidLoop.predicted_observation: the decoder at the expected z_q)."""
        return self.vq.decode_expected(np.exp(logp).astype(np.float32))

    def prediction(self, logp: np.ndarray) -> np.ndarray:
        """As prediction_n, in raw units (the mid_loop's feature spec, spec order), float64."""
        return self.norm.raw_obs(self.prediction_n(logp))

    # -- what serving.py calls (GridMidLoopNumpy answers the same) ----------------------------------
    def point(self, values: np.ndarray, codes: np.ndarray | None = None) -> np.ndarray:
        """A grid point from the raw observation: its own VQ-VAE's group-local codes [G] (no frame is
        read); codes: those codes computed already (by a tokenizer for which same_codes() holds)."""
        return self.codes_of(values) if codes is None else np.asarray(codes)

    def same_codes(self, tokenizer: Any) -> bool:
        """Whether the served vqvae `tokenizer` (VQVAERuntime) computes this Mid Loop's codes of an
        observation: the same encoder, codebook and normalisation (array by array, once per
        tokenizer object), so BrainService encodes the observation once for both."""
        last = self._same_codes
        if last is not None and last[0] is tokenizer:
            return last[1]
        same = (tokenizer.frame_shape is None and self.vq.same_encoder(tokenizer.vq)
                and np.array_equal(tokenizer.norm.obs_inv_std, self.norm.obs_inv_std)
                and np.array_equal(tokenizer.norm.obs_shift, self.norm.obs_shift))
        self._same_codes = (tokenizer, bool(same))
        return bool(same)

    def predict(self, points: list[np.ndarray], acts_n: np.ndarray,
                ahead: WindowAhead | None = None) -> tuple[np.ndarray, np.ndarray, bool]:
        """The window's last point -> (expected observation per horizon [H, obs_dim] raw units, its
        log-probabilities [H, G, n] for a later surprise, finite). ahead: window_ahead() of
        points[:-1], acts_n[:-1] (completed here if it is not yet; then only the last point is run)."""
        if ahead is None:
            logits = self.forward(self.rows(np.stack(points)), acts_n, last_only=True)[-1]
        else:
            while not self.ahead_step(ahead):
                pass
            x = self._inputs(self.rows(points[-1]), np.asarray(acts_n[-1], dtype=np.float32))
            logits = self._logits(step_last(self._blocks, x, ahead.states, self._mean))
        logp = self.log_probs(logits)
        pred = self.prediction(logp)
        return pred, logp, bool(np.isfinite(pred).all() and np.isfinite(logp).all())

    def window_ahead(self, points: list[np.ndarray], acts_n: np.ndarray) -> WindowAhead:
        """The next window but its last point (points, their normalised previous actions, zeros at
        the first) -> the blocks' SSM states after them, the first stage done (ahead_step() does
        the others, one a call: a block's SSM, its MLP): computed on the ticks between grid points (serving.py), so the
        grid point runs its own point alone (predict(ahead=))."""
        x = (self._inputs(self.rows(np.stack(points)), np.asarray(acts_n, dtype=np.float32)) if points
             else np.zeros((0, self.d_model), np.float32))
        ahead = window_ahead(self._blocks, x)
        advance(self._blocks, ahead, self._mean)
        return ahead

    def ahead_step(self, ahead: WindowAhead) -> bool:
        """One more stage of a window_ahead() -> whether all are done."""
        return advance(self._blocks, ahead, self._mean)

    def prepare(self, newest: np.ndarray, due_next: dict[int, np.ndarray]) -> bool:
        """Nothing of a surprise to compute ahead (it is G look-ups in a kept prediction): False, so
        serving.py goes straight to window_ahead() (the grid form's prepare() has work here)."""
        return False

    def surprises(self, due: dict[int, np.ndarray], codes: np.ndarray) -> dict[int, float]:
        """{horizon index: logp predicted s_h points ago} -> {h: -sum over the groups of log P(the
        point's code) under that horizon} (nats)."""
        groups = np.arange(self.groups)
        return {h: float(-logp[h, groups, codes].sum()) for h, logp in due.items()}

    def warm(self) -> None:
        """A full window and a one-point one, so the first request after a swap pays no first-call costs."""
        zeros = np.zeros((self.window_k, self.groups), np.int64)
        acts = np.zeros((self.window_k, self.act_dim), np.float32)
        self.prediction(self.log_probs(self.forward(zeros + self._offsets, acts, last_only=True)[-1]))
        self.forward(zeros[:1] + self._offsets, acts[:1], last_only=True)
        points = list(zeros)
        self.predict(points, acts, self.window_ahead(points[:-1], acts[:-1]))
        self.codes_of(np.zeros(self.obs_dim))

    def describe_observation(self, limit: int = 12) -> str:
        names = self.spec.observation.dim_names()
        return ", ".join(names[:limit]) + (f", ... ({len(names) - limit} more)" if len(names) > limit else "")

    def __repr__(self) -> str:
        return (f"MidLoopNumpy({self.version}, {self.groups} x {self.n_codes} codes + act {self.act_dim}, "
                f"K={self.window_k}, horizons {self.horizon_names})")


class MidLoopRuntime:
    """What BrainService loads a mid_loop checkpoint with: the form its VQ-VAE asks for (a grid frame
    VQ-VAE's cells: numpy_grid.GridMidLoopNumpy; a vector VQ-VAE's codes: MidLoopNumpy)."""

    name = "mid_loop"  # the component it serves, as every RUNTIME names it

    @staticmethod
    def from_checkpoint(path: str | Path, *, expected_sha256: str | None = None,
                        verify_manifest: bool = False) -> "MidLoopNumpy | GridMidLoopNumpy":
        ck = read_mid_loop(path, expected_sha256=expected_sha256, verify_manifest=verify_manifest)
        form = GridMidLoopNumpy if grid_frame(ck.config) is not None else MidLoopNumpy
        return form(checkpoint=ck.path, config=ck.config, spec=ck.spec, tensors=ck.tensors, sha256=ck.sha256,
                    version=ck.version)


__all__ = ["MidLoopNumpy", "MidLoopRuntime"]


RUNTIME = MidLoopRuntime  # what BrainService serves for this component
