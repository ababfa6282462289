"""The fast_loop's per-tick (window-exact recurrent) form in NumPy, straight from a checkpoint dir.

    model = FastLoopNumpy.from_checkpoint("runs/reach/checkpoints/00002500")
    state = model.init_state()                          # an episode's start
    a, state = model.tick(model.normalise(x), state)    # one normalised observation -> normalised action
    action = model.denormalise(a)

Why NumPy and not torch: BrainService lives in the webapp, which `serve` runs in one process with
the daemon and the worker parent under a 400 MB RSS budget; importing torch alone costs ~250 MB.
The fast_loop's tick is small (a few matrix-vector products, three LayerNorms and one diagonal
recurrence), so it is re-implemented here from the safetensors weights (`safetensors.numpy`) and
config.json, and tests/test_fast_loop_numpy.py checks it equal to torch's FastLoop.step and
FastLoop.forward within 1e-5 over thousands of ticks. This module never imports torch.

The arithmetic is hope_models/components/fast_loop/model.py and WindowSSM in hope_models/components/ssm.py (float32
throughout, like the torch model):

    e = obs_in(x) [+ code_in[code(x)]] ;  x = e + GatedMLP_enc(LN_enc(e))
    u = LN_ssm(x) ;  v = (B u) * gain ;  h_t = a h_{t-1} + v_t - a^K v_{t-K}  (ring of the last K v)
    y = C h + D * u ;  z = x + y [+ keypoints(codes of a grid frame)] ;  z = z + GatedMLP_head(LN_head(z))
    action = out(LN_out(z))

including WindowSSM's exact recompute of h from the ring each time the ring wraps (every K ticks),
which bounds float32 drift for any run length. Constants are folded at load (hope_models/components/numpy_layers.py): each
LayerNorm's affine into the product after it, the gate and up projections into one product, the
SSM gain into B. Two forms serve: one observation takes the flat path (tick -> _core, BrainService's
path), whose weights are folded further (_prepare_flat: the residual stream kept centred so no
LayerNorm computes a mean, D * u riding in the B product); batches and the window re-run (step,
forward) take the batched path. Both agree with torch within float32 rounding. (hope_models/components/fast_loop/numpy_act.py
adds the bench's act(), which folds the normalisation in too.)

A fast_loop that reads codes of a frozen vector VQ-VAE is supported (its MLP encoder, the
parameter-free LayerNorm and the nearest codebook row are a few more products), and one over a
frame VQ-VAE (a camera reflex): the frame's codes come from vqvae/numpy_frame.py's conv encoder,
computed by the caller (frame_codes(frame), so BrainService encodes a frame once for every model
that reads the same encoder) and passed to tick/step/forward as `codes`. A flat frame VQ-VAE's
codes are summed from code_in as a vector one's; a grid's are read as keypoints
(components/numpy_keypoints.py, CodeKeypoints) added at the acting point, z = x + y + keypoints,
before the head, their out() centred at load like obs_in. What
this runtime accepts as a checkpoint, and the refusals, are hope_models/components/fast_loop/checkpoint.py's.

Observations are normalised exactly as the dataset cache and ReflexPolicy do (float32
x * 1/std - mean/std) and actions denormalised (a * std + mean, float64); for the dm_control
reacher's spec the action is also clipped to the motor bounds [-1, 1], as ReflexPolicy does.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from hope_models.components.fast_loop.checkpoint import FastLoopNumpyError, read_fast_loop, vqvae_frame, vqvae_groups
from hope_models.components.numpy_keypoints import KeypointsNumpy, keypoint_gain
from hope_models.components.numpy_layers import LN_EPS, Linear, NormMLP, NumpyWindowState, fold_ln, layer_norm
from hope_models.components.vqvae.numpy_form import VQVAENumpy
from hope_models.data.features import FeatureSpec
from hope_models.sim.reacher import ACTION_FIELD, ACTION_HIGH, ACTION_LOW, OBS_FIELDS

RATE_MIN = 1e-4  # WindowSSM.RATE_MIN / RATE_MAX: the clamp on the decay rate
RATE_MAX = 20.0


def _reacher_bounds(spec: FeatureSpec) -> tuple[float, float] | None:
    """The reacher's motor bounds when the spec is the dm_control reacher's (observation and action)."""
    obs = [(f.path, f.size) for f in spec.observation.fields]
    act = [(f.path, f.size) for f in spec.action.fields]
    if obs == [tuple(x) for x in OBS_FIELDS] and act == [tuple(ACTION_FIELD)]:
        return (ACTION_LOW, ACTION_HIGH)
    return None


def _grid_step(config: dict[str, Any]) -> float | None:
    """The window's grid step (s): the control period the fast_loop is ticked at (None if unknown)."""
    w = config.get("window")
    d, k = (w.get("duration_s"), w.get("k")) if isinstance(w, dict) else (None, None)
    ok = isinstance(d, (int, float)) and isinstance(k, int) and not isinstance(k, bool) and k > 0 and d > 0
    return float(d) / k if ok and math.isfinite(d) else None


def centred(w: np.ndarray, b: np.ndarray | None = None):
    """w [in, out] with each row's outputs centred (and b centred), computed in float64: a product
    that writes into the centred residual stream keeps it centred."""
    w = w.astype(np.float64)
    wc = np.ascontiguousarray((w - w.mean(1, keepdims=True)).astype(np.float32))
    return wc if b is None else (wc, (b.astype(np.float64) - b.astype(np.float64).mean()).astype(np.float32))


class FastLoopNumpy:
    """One fast_loop checkpoint, runnable tick by tick (see the module doc). Immutable after load:
    several threads may step it at once with their own states."""

    name = "fast_loop"

    def status_fields(self) -> dict:
        """What BrainService.status() adds for this component: the shape of its answer."""
        return {}

    def __init__(self, *, checkpoint: Path, config: dict[str, Any], spec: FeatureSpec,
                 tensors: dict[str, np.ndarray], sha256: str, version: str):
        self.checkpoint = checkpoint
        self.config = config
        self.spec = spec
        self.sha256 = sha256
        self.version = version
        mc = config["model_config"]
        self.obs_dim, self.act_dim = int(mc["obs_dim"]), int(mc["act_dim"])
        self.window_k, self.d_model, self.d_state = int(mc["window_k"]), int(mc["d_model"]), int(mc["d_state"])
        self.n_codes = int(mc["n_codes"])
        self.observation_fields = [(f.path, f.size) for f in spec.observation.fields]
        self.action_fields = [(f.path, f.size) for f in spec.action.fields]
        self.action_bounds = _reacher_bounds(spec)
        frame = vqvae_frame(config) if self.n_codes else None
        # a camera reflex reads the request's frame too: a replacement must read the same size of frame
        self.frame_shape: tuple[int, ...] | None = None if frame is None else tuple(frame.frame_shape)
        self.fit_fields = (self.observation_fields, self.action_fields, self.frame_shape)
        vq_ref = config.get("vqvae")  # the VQ-VAE it was trained with (BrainService's consistency check)
        self.vqvae_sha256 = vq_ref.get("weights_sha256") if isinstance(vq_ref, dict) else None
        self.control_period_s = _grid_step(config)
        t = tensors

        def lin(prefix: str) -> Linear:
            return Linear(np.ascontiguousarray(t[f"{prefix}.weight"].T), t[f"{prefix}.bias"])

        self._obs_in = lin("obs_in")
        self._enc = NormMLP.fold(t, "enc_ln", "enc_mlp")
        self._ssm_ln_w, self._ssm_ln_b = t["ssm_ln.weight"], t["ssm_ln.bias"]
        self._head = NormMLP.fold(t, "head_ln", "head_mlp")
        self._out = Linear(*fold_ln(t["out_ln.weight"], t["out_ln.bias"], t["out.weight"], t["out.bias"]))
        self._mean_d = np.full(self.d_model, 1.0 / self.d_model, np.float32)  # x @ this = the mean over d
        self._code_in = t.get("code_in.weight")
        self._kp: KeypointsNumpy | None = None
        self._view_joint = int(mc.get("view_joint", -1))
        self._view_mean = np.float32(mc.get("view_joint_mean", 0.0))
        self._view_std = np.float32(mc.get("view_joint_std", 1.0))
        self.frame_vq: VQVAENumpy | None = None  # the frame VQ-VAE whose codes tick() reads
        if self.n_codes:  # the frozen VQ-VAE's encoder and codebook (hope_models/components/vqvae/numpy_form.py)
            self.groups = vqvae_groups(config)
            self._vq = VQVAENumpy(t, groups=self.groups, n_codes=self.n_codes, prefix="vqvae.", decoder=False,
                                  frame=frame)
            self._offsets = np.arange(self.groups) * self.n_codes
            if frame is not None:
                self.frame_vq = self._vq
                if frame.layout == "grid":  # model.py: a grid's cells are read as keypoints
                    self._kp = KeypointsNumpy(t, "keypoints", frame.grid_shape, keypoint_gain(mc))
        # The SSM: the decay constants as WindowSSM._consts computes them (float32 log_a; the powers
        # and the gain from it), the gain folded into B^T, then C^T and D.
        log_rate = np.clip(t["ssm.log_rate"], np.float32(math.log(RATE_MIN)), np.float32(math.log(RATE_MAX)))
        log_a = -np.exp(log_rate.astype(np.float32))
        k = self.window_k
        powers = np.exp(np.arange(k + 1, dtype=np.float32)[:, None] * log_a).astype(np.float32)  # [K+1, N]
        self._kernel = np.ascontiguousarray(powers[:k][::-1])  # [K, N]: a^(K-1-i), oldest first
        gain = np.sqrt(np.expm1(np.float32(2.0) * log_a) / np.expm1(np.float32(2.0 * k) * log_a)).astype(np.float32)
        self._a, self._a_k = powers[1], powers[k]
        self._bg_t = np.ascontiguousarray(t["ssm.B"].T * gain[None, :])  # [d_model, N]: v = u @ this
        self._c_t = np.ascontiguousarray(t["ssm.C"].T)  # [N, d_model]
        self._d = t["ssm.D"]
        # normalisation, as ReflexPolicy: float32 x * inv_std - mean * inv_std; actions back in float64
        obs_mean, obs_std, act_mean, act_std = spec.normalizer()
        self._inv_std = (1.0 / obs_std).astype(np.float32)
        self._shift = (obs_mean * self._inv_std).astype(np.float32)
        self._act_mean = np.asarray(act_mean, dtype=np.float64)
        self._act_std = np.asarray(act_std, dtype=np.float64)
        self._prepare_flat(t, gain)

    def _prepare_flat(self, t: dict[str, np.ndarray], gain: np.ndarray) -> None:
        """Weights of the one-vector serving path (tick), folded further than the batched path's.

        The residual stream is kept centred: every LayerNorm of it subtracts the mean first, and
        everything that reads the stream reads it through one (u = LN_ssm(x), LN_head(z), LN_out(y)),
        so adding c * ones anywhere changes no output. Each product that writes into the stream
        (obs_in, code_in, the MLPs' w_out, C) has its output centred at load (W - row mean, b - mean),
        and the SSM's D * u term rides in the B product as extra columns diag(ln_w * D) centred, so
        no LayerNorm of the flat path computes a mean. The SSM LayerNorm's affine is folded into
        those columns and into B (v = n (diag(ln_w) B^T gain) + ln_b B^T gain, the same v as the
        batched path's up to float32 rounding)."""
        f64 = np.float64
        d, n = self.d_model, self.d_state
        w_in, b_in = self._obs_in.w_t.astype(f64), self._obs_in.b.astype(f64)
        self._e_w, self._e_b = centred(w_in, b_in)  # normalised observation -> centred embedding
        self._code_in_c = None if self._code_in is None else centred(self._code_in)
        self._kp_c = None if self._kp is None else centred(self._kp.w_t, self._kp.b)
        ln_w, ln_b = t["ssm_ln.weight"].astype(f64), t["ssm_ln.bias"].astype(f64)
        bg = t["ssm.B"].T.astype(f64) * gain.astype(f64)[None, :]  # [d, N]
        wd, bd = ln_w * t["ssm.D"].astype(f64), ln_b * t["ssm.D"].astype(f64)
        self._vd_w = np.ascontiguousarray(np.concatenate(
            [ln_w[:, None] * bg, np.diag(wd) - wd[:, None] / d], axis=1).astype(np.float32))  # [d, N + d]
        self._vd_b = np.concatenate([ln_b @ bg, bd - bd.mean()]).astype(np.float32)
        self._c_t_c = centred(self._c_t)
        enc_out_w, enc_out_b = centred(self._enc.out_w, self._enc.out_b)
        head_out_w, head_out_b = centred(self._head.out_w, self._head.out_b)
        self._flat = (1.0 / d, LN_EPS, np.float32(1.0), n, self.window_k,
                      self._enc.gu_w, self._enc.gu_b, self._enc.hidden, enc_out_w, enc_out_b,
                      self._vd_w, self._vd_b, self._a, self._a_k, self._kernel, self._c_t_c,
                      self._head.gu_w, self._head.gu_b, self._head.hidden, head_out_w, head_out_b)

    # -- loading --------------------------------------------------------------------------------
    @classmethod
    def from_checkpoint(cls, path: str | Path, *, expected_sha256: str | None = None,
                        verify_manifest: bool = False) -> "FastLoopNumpy":
        """Load <path>/config.json + model.safetensors (fast_loop_checkpoint.read_fast_loop: what is
        refused and why; expected_sha256 is the promotion pointer's record of the weights;
        verify_manifest checks every file against the manifest, each hashed once)."""
        ck = read_fast_loop(path, expected_sha256=expected_sha256, verify_manifest=verify_manifest)
        return cls(checkpoint=ck.path, config=ck.config, spec=ck.spec, tensors=ck.tensors, sha256=ck.sha256,
                   version=ck.version)

    # -- normalisation --------------------------------------------------------------------------
    def observation_vector(self, values: Any) -> np.ndarray:
        """A raw observation (sequence of obs_dim finite numbers, spec order) -> float64 [obs_dim];
        FastLoopNumpyError naming the problem otherwise."""
        x = np.asarray(values, dtype=np.float64).reshape(-1)
        if x.size != self.obs_dim:
            raise FastLoopNumpyError(f"observation has {x.size} values, {self.version} needs {self.obs_dim} "
                                     f"({self.describe_observation()})")
        if not np.isfinite(x).all():
            raise FastLoopNumpyError("observation has non-finite values (NaN or Inf)")
        return x

    def describe_observation(self, limit: int = 12) -> str:
        """The observation's values by name, in order (the first `limit`), for error messages."""
        names = self.spec.observation.dim_names()
        more = f", ... ({len(names) - limit} more)" if len(names) > limit else ""
        return ", ".join(names[:limit]) + more

    def normalise(self, x: np.ndarray) -> np.ndarray:
        x32 = np.asarray(x, dtype=np.float32) * self._inv_std
        x32 -= self._shift
        return x32

    def denormalise(self, a: np.ndarray) -> np.ndarray:
        action = a * self._act_std + self._act_mean  # float64: the statistics are float64
        if self.action_bounds is not None:
            np.maximum(action, self.action_bounds[0], out=action)  # np.clip's values in half its time
            np.minimum(action, self.action_bounds[1], out=action)
        return action

    # -- pointwise parts of the batched path (one grid point each) --------------------------------
    def codes(self, obs_n: np.ndarray) -> np.ndarray:
        """Nearest row of each group's codebook of the frozen vector VQ-VAE for normalised obs
        [..., obs_dim] -> group-local codes [..., G], as FastLoop.codes."""
        if self.frame_vq is not None:
            raise ValueError(f"{self.version} reads camera frames: its codes are frame_codes(frames)")
        return self._vq.codes(obs_n)

    def frame_codes(self, frames: np.ndarray) -> np.ndarray:
        """A camera reflex: uint8 frames [..., H, W, 3] -> its frame VQ-VAE's codes [..., G]."""
        if self.frame_vq is None:
            raise ValueError(f"{self.version} reads no camera")
        return self.frame_vq.codes(frames)

    def _codes(self, obs_n: np.ndarray, codes: np.ndarray | None) -> np.ndarray:
        """The codes a point reads: given (a frame's, frame_codes) or the vector VQ-VAE's of obs_n."""
        if self.frame_vq is None:
            return self._vq.codes(obs_n)
        if codes is None:
            raise ValueError(f"{self.version} reads camera frames: pass codes=frame_codes(frame)")
        return codes

    def _code_embedding(self, obs_n: np.ndarray, codes: np.ndarray | None, flat: bool = False) -> np.ndarray:
        """What the codes add to e (not a grid's: see _keypoints): the sum of their code_in rows
        (group g's code c is row g * n_codes + c); flat: the centred weights of the flat path."""
        c = self._codes(obs_n, codes)
        return (self._code_in_c if flat else self._code_in)[c + self._offsets].sum(-2)

    def _keypoints(self, obs_n: np.ndarray, codes: np.ndarray | None, flat: bool = False) -> np.ndarray | None:
        """What a grid's codes add to z at the acting point (model.py's _head), or None."""
        if self._kp is None:
            return None
        c = self._codes(obs_n, codes)
        angle = None
        if self._view_joint >= 0:  # model.py's view_angle: the joint angle, in radians
            angle = obs_n[..., self._view_joint] * self._view_std + self._view_mean
        if flat and self._kp_c is not None:
            return self._kp(c, *self._kp_c, angle=angle)
        return self._kp(c, angle=angle)

    def _encode(self, obs_n: np.ndarray, norm, codes: np.ndarray | None = None) -> np.ndarray:
        e = self._obs_in(obs_n)
        if self._code_in is not None:
            e += self._code_embedding(obs_n, codes)
        x = self._enc(norm(e))
        x += e
        return x

    def _ssm_in(self, x: np.ndarray, norm) -> np.ndarray:
        u = norm(x)
        u *= self._ssm_ln_w
        u += self._ssm_ln_b
        return u

    def _finish(self, z: np.ndarray, norm) -> np.ndarray:
        """z = x + y (the SSM block's output) -> the action: the head's residual MLP, then out."""
        y = self._head(norm(z))
        y += z
        return self._out(norm(y))

    def _batch_norm(self, x: np.ndarray) -> np.ndarray:
        return layer_norm(x, self._mean_d)

    # -- the two forms --------------------------------------------------------------------------
    def init_state(self, batch: int = 1) -> NumpyWindowState:
        """A fresh state: an episode's start (every earlier point masked)."""
        return NumpyWindowState(np.zeros((batch, self.d_state), np.float32),
                                np.zeros((batch, self.window_k, self.d_state), np.float32), 0)

    def step(self, obs_n: np.ndarray, state: NumpyWindowState,
             codes: np.ndarray | None = None) -> tuple[np.ndarray, NumpyWindowState]:
        """One tick: normalised obs [B, obs_dim] float32, state -> (normalised action [B, act_dim], new
        state). Never mutates `state` (a request that fails half-way leaves its session untouched).
        codes [B, G]: a camera reflex's frame codes (frame_codes).

        WindowSSM's recurrence: h_t = a h_{t-1} + v_t - a^K v_{t-K}, v_{t-K} from the ring; each time
        the ring wraps (every K ticks) h is recomputed exactly from it, which bounds float32 drift."""
        if obs_n.shape[0] == 1:  # one vector: the flat serving path
            a, state = self.tick(obs_n[0], state, None if codes is None else codes[0])
            return a[None, :], state
        norm = self._batch_norm
        x = self._encode(obs_n, norm, codes)
        kp = self._keypoints(obs_n, codes)
        u = self._ssm_in(x, norm)
        v = u.dot(self._bg_t)
        h = self._a * state.h + v - self._a_k * state.ring[:, state.pos]
        ring = state.ring.copy()
        ring[:, state.pos] = v
        pos = (state.pos + 1) % self.window_k
        if pos == 0:
            h = (ring * self._kernel).sum(1)
        z = x + h.dot(self._c_t) + u * self._d
        if kp is not None:
            z += kp
        return self._finish(z, norm), NumpyWindowState(h, ring, pos)

    def _core(self, e: np.ndarray, ee: float, state: NumpyWindowState,
              kp: np.ndarray | None = None) -> tuple[np.ndarray, float, NumpyWindowState]:
        """step() for one vector, from the centred embedding e [d] (ee = e.e) to the centred last
        residual y [d] and its LayerNorm scale (LN_out(y) = y * scale), and the new state. At batch 1
        a tick costs what its array operations and Python calls cost, not its flops, so this is
        written flat: locals, in-place ops on fresh temporaries, LayerNorm statistics as Python
        floats, and the weights folded at load (_prepare_flat) so that no LayerNorm computes a mean.
        WindowSSM's recurrence and its exact recompute from the ring as in step(). kp: a grid's
        keypoints (centred), added to z before the head."""
        (inv_d, eps, one, n, k, gu_w1, gu_b1, hid1, out_w1, out_b1, vd_w, vd_b, a_, a_k, kernel, c_t,
         gu_w2, gu_b2, hid2, out_w2, out_b2) = self._flat
        # encoder: x = e + GatedMLP(LN(e))  (silu(g) = g' (1 + tanh g'), g' = g / 2 folded into gu_w)
        gu = (e * (1.0 / math.sqrt(ee * inv_d + eps))).dot(gu_w1)
        gu += gu_b1
        g = gu[:hid1]
        m = np.tanh(g)
        m += one
        m *= g
        m *= gu[hid1:]
        x = m.dot(out_w1)
        x += out_b1
        x += e
        # SSM: [v | D u (centred)] = LN_ssm(x) in one product; h_t = a h_{t-1} + v_t - a^K v_{t-K}
        vd = (x * (1.0 / math.sqrt(float(x.dot(x)) * inv_d + eps))).dot(vd_w)
        vd += vd_b
        v = vd[:n]
        ring_prev, pos = state.ring, state.pos
        h = a_ * state.h[0]  # 1-D: a [N] * [1, N] would broadcast, which costs twice as much
        h += v
        h -= a_k * ring_prev[0, pos]
        ring = ring_prev.copy()
        ring[0, pos] = v
        pos += 1
        if pos == k:  # the ring is in time order: recompute h exactly (see step)
            pos = 0
            h = (ring[0] * kernel).sum(0)
        z = h.dot(c_t)
        z += x
        z += vd[n:]
        if kp is not None:
            z += kp
        # head: y = z + GatedMLP(LN(z)); the caller applies out(LN(y))
        gu = (z * (1.0 / math.sqrt(float(z.dot(z)) * inv_d + eps))).dot(gu_w2)
        gu += gu_b2
        g = gu[:hid2]
        m = np.tanh(g)
        m += one
        m *= g
        m *= gu[hid2:]
        y = m.dot(out_w2)
        y += out_b2
        y += z
        return y, 1.0 / math.sqrt(float(y.dot(y)) * inv_d + eps), NumpyWindowState(h[None], ring, pos)

    def forward(self, obs_n: np.ndarray, mask: np.ndarray | None = None,
                codes: np.ndarray | None = None) -> np.ndarray:
        """The whole window again: normalised obs [B, L, obs_dim] (mask [B, L], True = a real point)
        -> the last point's normalised action [B, act_dim], from the last K points (FastLoop.forward:
        every point encoded, the state of the last point summed from its K inputs). codes [B, L, G]:
        a camera reflex's frame codes."""
        norm = self._batch_norm
        x = self._encode(obs_n, norm, codes)
        kp = self._keypoints(obs_n[:, -1], None if codes is None else codes[:, -1])  # the acting point's
        u = self._ssm_in(x, norm)
        if mask is not None:
            u = u * np.asarray(mask, dtype=np.float32)[..., None]
        k = self.window_k
        v = u[:, -k:] @ self._bg_t  # [B, <=K, N]: only the last K points reach the last state
        h = (v * self._kernel[k - v.shape[1]:]).sum(1)
        z = x[:, -1] + h.dot(self._c_t) + u[:, -1] * self._d
        if kp is not None:
            z += kp
        return self._finish(z, norm)

    def tick(self, obs_n: np.ndarray, state: NumpyWindowState,
             codes: np.ndarray | None = None) -> tuple[np.ndarray, NumpyWindowState]:
        """step() for one normalised observation [obs_dim] and a batch-1 state -> (normalised action
        [act_dim], new state): the serving path, without the batch dimension's wrapping. codes [G]:
        a camera reflex's frame codes (frame_codes(frame))."""
        if state.h.shape[0] != 1:
            raise ValueError(f"tick() steps one observation; this state holds a batch of {state.h.shape[0]}")
        e = obs_n.dot(self._e_w)
        e += self._e_b
        if self._code_in is not None:
            e += self._code_embedding(obs_n, codes, flat=True)
        y, r, state = self._core(e, float(e.dot(e)), state, self._keypoints(obs_n, codes, flat=True))
        a = y.dot(self._out.w_t)
        a *= r
        a += self._out.b
        return a, state

    def warm(self) -> None:
        """One tick, so the first real request after a swap pays no first-call costs."""
        codes = None if self.frame_shape is None else self.frame_codes(np.zeros((1, *self.frame_shape), np.uint8))
        self.step(np.zeros((1, self.obs_dim), np.float32), self.init_state(), codes)

    def __repr__(self) -> str:
        codes = f" + codes of {self.n_codes}" if self.n_codes else ""
        if self.frame_shape is not None:
            codes += " of a " + "x".join(map(str, self.frame_shape)) + " frame"
        return f"FastLoopNumpy({self.version}, obs {self.obs_dim}{codes} -> act {self.act_dim}, K={self.window_k})"


__all__ = ["FastLoopNumpy", "FastLoopNumpyError", "NumpyWindowState", "centred"]


RUNTIME = FastLoopNumpy  # what BrainService serves for this component
