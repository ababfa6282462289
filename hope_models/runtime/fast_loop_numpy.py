"""The fast_loop's per-tick (window-exact recurrent) form in NumPy, straight from a checkpoint dir.

    model = FastLoopNumpy.from_checkpoint("runs/reach/checkpoints/00002500")
    state = model.init_state()                     # an episode's start
    action, state = model.act(observation, state)  # raw observation vector -> denormalised action

Why NumPy and not torch: BrainService lives in the webapp, which `serve` runs in one process with
the daemon and the worker parent under a 400 MB RSS budget; importing torch alone costs ~250 MB.
The fast_loop's tick is small (a few matrix-vector products, three LayerNorms and one diagonal
recurrence), so it is re-implemented here from the safetensors weights (`safetensors.numpy`) and
config.json, and tests/test_fast_loop_numpy.py checks it equal to torch's FastLoop.step and
FastLoop.forward within 1e-5 over thousands of ticks. This module never imports torch.

The arithmetic is hope_models/models/fast_loop.py and WindowSSM in models/ssm.py (float32
throughout, like the torch model):

    e = obs_in(x) [+ code_in[code(x)]] ;  x = e + GatedMLP_enc(LN_enc(e))
    u = LN_ssm(x) ;  v = (B u) * gain ;  h_t = a h_{t-1} + v_t - a^K v_{t-K}  (ring of the last K v)
    y = C h + D * u ;  z = x + y ;  z = z + GatedMLP_head(LN_head(z)) ;  action = out(LN_out(z))

including WindowSSM's exact recompute of h from the ring each time the ring wraps (every K ticks),
which bounds float32 drift for any run length. At batch 1 a tick costs what its array operations
cost (each ~0.5 us of NumPy dispatch), not its flops, so constants are folded at load time: each
LayerNorm's affine into the product after it, the gate and up projections into one product, the
SSM gain into B. One observation takes a flat path (tick, act -> _core) whose weights are folded
further (_prepare_flat: the residual stream kept centred so no LayerNorm computes a mean, D * u
riding in the B product, act's normalisation and denormalisation in obs_in and out); batches and
the window re-run (forward) take the batched path. Both agree with torch within float32 rounding.

A fast_loop that reads codes of a frozen vector VQ-VAE is supported (its MLP encoder, the
parameter-free LayerNorm and the nearest codebook row are a few more products); one whose VQ-VAE
reads camera frames is refused (a conv stack is not worth re-implementing for a runtime that
receives observation vectors).

Observations are normalised exactly as the dataset cache and ReflexPolicy do (float32
x * 1/std - mean/std) and actions denormalised (a * std + mean, float64); for the dm_control
reacher's spec the action is also clipped to the motor bounds [-1, 1], as ReflexPolicy does.
Anything this runtime cannot run (another component, a frame VQ-VAE, weights that do not match the
config, non-finite weights, a spec without statistics) raises FastLoopNumpyError naming the file
and the reason.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.windows import MAX_K
from hope_models.promote.pointers import PointerError, checkpoint_version
from hope_models.train.checkpoint import CheckpointError, read_json_object

CONFIG_FORMAT = "hope.component_config/1"  # components.CONFIG_FORMAT (that module imports torch)
MODEL_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
LN_EPS = 1e-5  # torch.nn.LayerNorm's default, used by every LayerNorm of the fast_loop and the VQ-VAE
RATE_MIN = 1e-4  # WindowSSM.RATE_MIN / RATE_MAX: the clamp on the decay rate
RATE_MAX = 20.0
MODEL_CONFIG_KEYS = ("obs_dim", "act_dim", "window_k", "d_model", "d_state", "mlp_ratio", "min_timescale",
                     "max_timescale", "n_codes")


class FastLoopNumpyError(ValueError):
    """This checkpoint cannot be run by the NumPy fast_loop; the message names the file and why."""


class NumpyWindowState(NamedTuple):
    """Recurrent state, as WindowState in ssm.py: h [B, N], ring [B, K, N] (slot `pos` = the oldest), pos."""
    h: np.ndarray
    ring: np.ndarray
    pos: int


def _mm(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """x [..., in] times w [in, out]. ndarray.dot for a vector or a matrix (for a vector it dispatches
    in about two thirds of the time of @, and a tick is a dozen of these); @ for 3-D batches, where
    dot has no BLAS path."""
    return x.dot(w) if x.ndim <= 2 else x @ w


@dataclass(frozen=True)
class _Linear:
    w_t: np.ndarray  # [in, out]: transposed once at load so a tick is x.dot(w_t) + b
    b: np.ndarray

    def __call__(self, x: np.ndarray) -> np.ndarray:
        y = _mm(x, self.w_t)
        y += self.b  # in place on the fresh product: a tick is bound by array-op count and temporaries
        return y


@dataclass(frozen=True)
class _NormMLP:
    """GatedMLP(LayerNorm(x)) with the LayerNorm's affine folded into one [d, 2h] product for the
    gate and up projections: w_out(silu(gate) * up). The gate columns are pre-scaled by 1/2 (exact
    in binary), so silu(g) = g' (1 + tanh g') with g' = g / 2: four element-wise ops, no overflow."""
    gu_w: np.ndarray  # [d, 2h]: (w_gate * ln_w / 2 | w_up * ln_w)^T
    gu_b: np.ndarray  # [2h]
    out_w: np.ndarray  # [h, d]
    out_b: np.ndarray
    hidden: int

    @classmethod
    def fold(cls, t: dict[str, np.ndarray], ln: str, mlp: str) -> "_NormMLP":
        w = np.concatenate([t[f"{mlp}.w_gate.weight"] * 0.5, t[f"{mlp}.w_up.weight"]])  # [2h, d]
        b = np.concatenate([t[f"{mlp}.w_gate.bias"] * 0.5, t[f"{mlp}.w_up.bias"]])
        gu_w, gu_b = _fold_ln(t[f"{ln}.weight"], t[f"{ln}.bias"], w, b)
        return cls(gu_w, gu_b, np.ascontiguousarray(t[f"{mlp}.w_out.weight"].T), t[f"{mlp}.w_out.bias"],
                   t[f"{mlp}.w_gate.weight"].shape[0])

    def __call__(self, n: np.ndarray) -> np.ndarray:
        """n = the LayerNorm's normalised input (before its affine), [..., d]."""
        gu = _mm(n, self.gu_w)
        gu += self.gu_b
        g = gu[..., :self.hidden]
        m = np.tanh(g)
        m += np.float32(1.0)
        m *= g
        m *= gu[..., self.hidden:]
        out = _mm(m, self.out_w)
        out += self.out_b
        return out


def _fold_ln(ln_w: np.ndarray, ln_b: np.ndarray, w: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear(w, b) after a LayerNorm's affine (ln_w, ln_b) as one linear map of the normalised input:
    W (n * ln_w + ln_b) + b = (W diag(ln_w)) n + (W ln_b + b). Returns ([in, out] transposed, bias)."""
    w64 = w.astype(np.float64)
    return (np.ascontiguousarray((w64 * ln_w.astype(np.float64)[None, :]).T.astype(np.float32)),
            (w64 @ ln_b.astype(np.float64) + b.astype(np.float64)).astype(np.float32))


def _silu(x: np.ndarray) -> np.ndarray:
    # x * sigmoid(x) through tanh: no overflow warning for large |x| (exp(-x) would overflow)
    return x * (np.float32(0.5) + np.float32(0.5) * np.tanh(np.float32(0.5) * x))


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _reacher_bounds(spec: FeatureSpec) -> tuple[float, float] | None:
    """The reacher's motor bounds when the spec is the dm_control reacher's (observation and action)."""
    from hope_models.sim.reacher import ACTION_FIELD, ACTION_HIGH, ACTION_LOW, OBS_FIELDS

    obs = [(f.path, f.size) for f in spec.observation.fields]
    act = [(f.path, f.size) for f in spec.action.fields]
    if obs == [tuple(x) for x in OBS_FIELDS] and act == [tuple(ACTION_FIELD)]:
        return (ACTION_LOW, ACTION_HIGH)
    return None


class FastLoopNumpy:
    """One fast_loop checkpoint, runnable tick by tick (see the module doc). Immutable after load:
    several threads may step it at once with their own states."""

    name = "fast_loop"

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
        t = tensors

        def lin(prefix: str) -> _Linear:
            return _Linear(np.ascontiguousarray(t[f"{prefix}.weight"].T), t[f"{prefix}.bias"])

        self._obs_in = lin("obs_in")
        self._enc = _NormMLP.fold(t, "enc_ln", "enc_mlp")
        self._ssm_ln_w, self._ssm_ln_b = t["ssm_ln.weight"], t["ssm_ln.bias"]
        self._head = _NormMLP.fold(t, "head_ln", "head_mlp")
        self._out = _Linear(*_fold_ln(t["out_ln.weight"], t["out_ln.bias"], t["out.weight"], t["out.bias"]))
        self._mean_d = np.full(self.d_model, 1.0 / self.d_model, np.float32)  # x @ this = the mean over d
        self._code_in = t.get("code_in.weight")
        if self.n_codes:
            self._vq_layers = [lin(f"vqvae.encoder.0.{i}") for i in (0, 2, 4)]
            self._codebook = t["vqvae.codebook"]
            self._codebook_sq = (self._codebook * self._codebook).sum(1)
            self._mean_code = np.full(self._codebook.shape[1], 1.0 / self._codebook.shape[1], np.float32)
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
        """Weights of the one-vector serving path (tick, act), folded further than the batched path's.

        The residual stream is kept centred: every LayerNorm of it subtracts the mean first, and
        everything that reads the stream reads it through one (u = LN_ssm(x), LN_head(z), LN_out(y)),
        so adding c * ones anywhere changes no output. Each product that writes into the stream
        (obs_in, code_in, the MLPs' w_out, C) has its output centred at load (W - row mean, b - mean),
        and the SSM's D * u term rides in the B product as extra columns diag(ln_w * D) centred, so
        no LayerNorm of the flat path computes a mean. The SSM LayerNorm's affine is folded into
        those columns and into B (v = n (diag(ln_w) B^T gain) + ln_b B^T gain, the same v as the
        batched path's up to float32 rounding). act() also folds the observation normalisation into
        obs_in and the action denormalisation into out (float64, as denormalise computes it)."""
        f64 = np.float64

        def centred(w: np.ndarray, b: np.ndarray | None = None):  # w [in, out]: centre each row's outputs
            w = w.astype(f64)
            wc = np.ascontiguousarray((w - w.mean(1, keepdims=True)).astype(np.float32))
            return wc if b is None else (wc, (b.astype(f64) - b.astype(f64).mean()).astype(np.float32))

        d, n = self.d_model, self.d_state
        w_in, b_in = self._obs_in.w_t.astype(f64), self._obs_in.b.astype(f64)
        self._e_w, self._e_b = centred(w_in, b_in)  # normalised observation -> centred embedding
        inv_std, shift = self._inv_std.astype(f64), self._shift.astype(f64)  # the float32 constants normalise uses
        self._e_w_raw, self._e_b_raw = centred(inv_std[:, None] * w_in, b_in - shift @ w_in)  # raw observation
        self._code_in_c = None if self._code_in is None else centred(self._code_in)
        ln_w, ln_b = t["ssm_ln.weight"].astype(f64), t["ssm_ln.bias"].astype(f64)
        bg = t["ssm.B"].T.astype(f64) * gain.astype(f64)[None, :]  # [d, N]
        wd, bd = ln_w * t["ssm.D"].astype(f64), ln_b * t["ssm.D"].astype(f64)
        self._vd_w = np.ascontiguousarray(np.concatenate(
            [ln_w[:, None] * bg, np.diag(wd) - wd[:, None] / d], axis=1).astype(np.float32))  # [d, N + d]
        self._vd_b = np.concatenate([ln_b @ bg, bd - bd.mean()]).astype(np.float32)
        self._c_t_c = centred(self._c_t)
        enc_out_w, enc_out_b = centred(self._enc.out_w, self._enc.out_b)
        head_out_w, head_out_b = centred(self._head.out_w, self._head.out_b)
        out_w, out_b = self._out.w_t.astype(f64), self._out.b.astype(f64)
        self._a_w_raw = np.ascontiguousarray(out_w * self._act_std[None, :])  # float64 [d, act]
        self._a_b_raw = out_b * self._act_std + self._act_mean
        self._flat = (1.0 / d, LN_EPS, np.float32(1.0), n, self.window_k,
                      self._enc.gu_w, self._enc.gu_b, self._enc.hidden, enc_out_w, enc_out_b,
                      self._vd_w, self._vd_b, self._a, self._a_k, self._kernel, self._c_t_c,
                      self._head.gu_w, self._head.gu_b, self._head.hidden, head_out_w, head_out_b)

    # -- loading --------------------------------------------------------------------------------
    @classmethod
    def from_checkpoint(cls, path: str | Path, *, expected_sha256: str | None = None) -> "FastLoopNumpy":
        """Load <path>/config.json + model.safetensors (a checkpoint dir). expected_sha256: refuse
        weights whose sha256 differs (the promotion pointer's record of what was promoted). The
        weights' bytes are read once: the hash and the tensors come from the same bytes."""
        ckpt = Path(path)
        cfg_path, weights_path = ckpt / CONFIG_FILE, ckpt / MODEL_FILE
        if not ckpt.is_dir():
            raise FastLoopNumpyError(f"{ckpt}: checkpoint dir not found")
        try:
            config = read_json_object(cfg_path)  # untrusted: size, depth and type bounded there
        except FileNotFoundError:
            raise FastLoopNumpyError(f"{cfg_path}: not found (a checkpoint dir holds {MODEL_FILE} + "
                                     f"{CONFIG_FILE})") from None
        except CheckpointError as exc:
            raise FastLoopNumpyError(str(exc)) from None
        spec = _check_config(config, cfg_path)
        try:
            data = weights_path.read_bytes()
        except FileNotFoundError:
            raise FastLoopNumpyError(f"{weights_path}: weights file not found") from None
        except OSError as exc:
            raise FastLoopNumpyError(f"{weights_path}: cannot read: {exc.strerror or exc}") from None
        sha = _sha256(data)
        if expected_sha256 is not None and sha != expected_sha256:
            raise FastLoopNumpyError(f"{weights_path}: sha256 {sha[:12]}... does not match the promoted "
                                     f"{expected_sha256[:12]}... (the file changed after promotion)")
        tensors = _load_tensors(data, weights_path)
        _check_tensors(tensors, config["model_config"], weights_path)
        # the one naming rule (pointers.checkpoint_version); it hashes the file again, which also
        # catches weights replaced while we were loading them
        try:
            version, file_sha = checkpoint_version(ckpt)
        except PointerError as exc:
            raise FastLoopNumpyError(str(exc)) from None
        if file_sha != sha:
            raise FastLoopNumpyError(f"{weights_path}: changed while it was being loaded; try again")
        return cls(checkpoint=ckpt, config=config, spec=spec, tensors=tensors, sha256=sha, version=version)

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
            action = np.clip(action, self.action_bounds[0], self.action_bounds[1])
        return action

    # -- LayerNorm cores (the affine is folded into the next product) ---------------------------
    @staticmethod
    def _norm(x: np.ndarray, mean_vec: np.ndarray) -> np.ndarray:
        """(x - mean) / sqrt(var + eps) over the last axis of [..., d] (biased variance, as torch)."""
        xc = x - (x @ mean_vec)[..., None]
        xc /= np.sqrt((xc * xc) @ mean_vec + np.float32(LN_EPS))[..., None]
        return xc

    # -- pointwise parts of the batched path (one grid point each) --------------------------------
    def codes(self, obs_n: np.ndarray) -> np.ndarray:
        """Nearest codebook row of the frozen vector VQ-VAE for normalised obs [..., obs_dim]."""
        z = obs_n
        for i, layer in enumerate(self._vq_layers):
            z = layer(z)
            if i < len(self._vq_layers) - 1:
                z = _silu(z)
        z = self._norm(z, self._mean_code)  # the encoder's closing LayerNorm has no parameters
        d = (z * z).sum(-1, keepdims=True) - np.float32(2.0) * (z @ self._codebook.T) + self._codebook_sq
        return d.argmin(-1)

    def _encode(self, obs_n: np.ndarray, norm) -> np.ndarray:
        e = self._obs_in(obs_n)
        if self.n_codes:
            e += self._code_in[self.codes(obs_n)]
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
        return self._norm(x, self._mean_d)

    # -- the two forms --------------------------------------------------------------------------
    def init_state(self, batch: int = 1) -> NumpyWindowState:
        """A fresh state: an episode's start (every earlier point masked)."""
        return NumpyWindowState(np.zeros((batch, self.d_state), np.float32),
                                np.zeros((batch, self.window_k, self.d_state), np.float32), 0)

    def step(self, obs_n: np.ndarray, state: NumpyWindowState) -> tuple[np.ndarray, NumpyWindowState]:
        """One tick: normalised obs [B, obs_dim] float32, state -> (normalised action [B, act_dim], new
        state). Never mutates `state` (a request that fails half-way leaves its session untouched).

        WindowSSM's recurrence: h_t = a h_{t-1} + v_t - a^K v_{t-K}, v_{t-K} from the ring; each time
        the ring wraps (every K ticks) h is recomputed exactly from it, which bounds float32 drift."""
        if obs_n.shape[0] == 1:  # one vector: the flat serving path
            a, state = self.tick(obs_n[0], state)
            return a[None, :], state
        norm = self._batch_norm
        x = self._encode(obs_n, norm)
        u = self._ssm_in(x, norm)
        v = u.dot(self._bg_t)
        h = self._a * state.h + v - self._a_k * state.ring[:, state.pos]
        ring = state.ring.copy()
        ring[:, state.pos] = v
        pos = (state.pos + 1) % self.window_k
        if pos == 0:
            h = (ring * self._kernel).sum(1)
        return self._finish(x + h.dot(self._c_t) + u * self._d, norm), NumpyWindowState(h, ring, pos)

    def _core(self, e: np.ndarray, ee: float, state: NumpyWindowState) -> tuple[np.ndarray, float, NumpyWindowState]:
        """step() for one vector, from the centred embedding e [d] (ee = e.e) to the centred last
        residual y [d] and its LayerNorm scale (LN_out(y) = y * scale), and the new state. At batch 1
        a tick costs what its array operations and Python calls cost, not its flops, so this is
        written flat: locals, in-place ops on fresh temporaries, LayerNorm statistics as Python
        floats, and the weights folded at load (_prepare_flat) so that no LayerNorm computes a mean.
        WindowSSM's recurrence and its exact recompute from the ring as in step()."""
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

    def forward(self, obs_n: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """The whole window again: normalised obs [B, L, obs_dim] (mask [B, L], True = a real point)
        -> the last point's normalised action [B, act_dim], from the last K points (FastLoop.forward:
        every point encoded, the state of the last point summed from its K inputs)."""
        norm = self._batch_norm
        x = self._encode(obs_n, norm)
        u = self._ssm_in(x, norm)
        if mask is not None:
            u = u * np.asarray(mask, dtype=np.float32)[..., None]
        k = self.window_k
        v = u[:, -k:] @ self._bg_t  # [B, <=K, N]: only the last K points reach the last state
        h = (v * self._kernel[k - v.shape[1]:]).sum(1)
        return self._finish(x[:, -1] + h.dot(self._c_t) + u[:, -1] * self._d, norm)

    # -- one control tick from raw values ---------------------------------------------------------
    def act(self, values: Any, state: NumpyWindowState) -> tuple[np.ndarray, NumpyWindowState]:
        """Raw observation (obs_dim numbers) + state -> (denormalised action float64 [act_dim], state).
        The normalisation is folded into obs_in and the denormalisation into out (see _prepare_flat);
        the values are checked as observation_vector checks them."""
        x = np.asarray(values, dtype=np.float64)
        if x.shape != (self.obs_dim,):
            x = self.observation_vector(values)  # the exact message, or a [1, obs_dim] flattened
        if self.n_codes:  # the codes read the normalised observation itself
            a, state = self.tick(self.normalise(self.observation_vector(x)), state)
            return self.denormalise(a), state
        if state.h.shape[0] != 1:
            raise ValueError(f"act() steps one observation; this state holds a batch of {state.h.shape[0]}")
        e = x.astype(np.float32).dot(self._e_w_raw)
        e += self._e_b_raw
        ee = float(e.dot(e))
        if not math.isfinite(ee):  # a NaN/Inf observation (or one beyond float32): observation_vector decides
            self.observation_vector(x)
        y, r, state = self._core(e, ee, state)
        a = y.dot(self._a_w_raw)  # float64, as denormalise
        a *= r
        a += self._a_b_raw
        if self.action_bounds is not None:
            np.clip(a, self.action_bounds[0], self.action_bounds[1], out=a)
        return a, state

    def tick(self, obs_n: np.ndarray, state: NumpyWindowState) -> tuple[np.ndarray, NumpyWindowState]:
        """step() for one normalised observation [obs_dim] and a batch-1 state -> (normalised action
        [act_dim], new state): the serving path, without the batch dimension's wrapping."""
        if state.h.shape[0] != 1:
            raise ValueError(f"tick() steps one observation; this state holds a batch of {state.h.shape[0]}")
        e = obs_n.dot(self._e_w)
        e += self._e_b
        if self.n_codes:
            e += self._code_in_c[self.codes(obs_n)]
        y, r, state = self._core(e, float(e.dot(e)), state)
        a = y.dot(self._out.w_t)
        a *= r
        a += self._out.b
        return a, state

    def __repr__(self) -> str:
        codes = f" + codes of {self.n_codes}" if self.n_codes else ""
        return f"FastLoopNumpy({self.version}, obs {self.obs_dim}{codes} -> act {self.act_dim}, K={self.window_k})"


# -- checks ----------------------------------------------------------------------------------------

def _check_config(config: Any, where: Path) -> FeatureSpec:
    if not isinstance(config, dict):
        raise FastLoopNumpyError(f"{where}: must be a JSON object")
    fmt = config.get("format")
    if fmt != CONFIG_FORMAT:
        raise FastLoopNumpyError(f"{where}: format {fmt!r} is not {CONFIG_FORMAT!r}")
    comp = config.get("component")
    if comp != "fast_loop":
        raise FastLoopNumpyError(f"{where}: component is {comp!r}; this runtime runs fast_loop checkpoints only")
    mc = config.get("model_config")
    if not isinstance(mc, dict):
        raise FastLoopNumpyError(f"{where}: 'model_config' is missing or not an object")
    for key in MODEL_CONFIG_KEYS:
        value = mc.get(key)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise FastLoopNumpyError(f"{where}: model_config.{key}={value!r} is missing or not a number")
    for key in ("obs_dim", "act_dim", "window_k", "d_model", "d_state", "mlp_ratio"):
        if not isinstance(mc[key], int) or mc[key] < 1:
            raise FastLoopNumpyError(f"{where}: model_config.{key}={mc[key]!r} must be an integer >= 1")
    if not isinstance(mc["n_codes"], int) or mc["n_codes"] < 0:
        raise FastLoopNumpyError(f"{where}: model_config.n_codes={mc['n_codes']!r} must be an integer >= 0")
    # Every other dim is the shape of a weight (checked against the file); window_k only sizes the
    # recurrent state's ring, which init_state allocates per session, so it is bounded here.
    if mc["window_k"] > MAX_K:
        raise FastLoopNumpyError(f"{where}: model_config.window_k={mc['window_k']} is more than a window's "
                                 f"{MAX_K} points")
    window = config.get("window")
    if isinstance(window, dict) and window.get("k") != mc["window_k"]:
        raise FastLoopNumpyError(f"{where}: window.k={window.get('k')!r} differs from model_config.window_k="
                                 f"{mc['window_k']} (the stepped form must see the training window's K points)")
    try:
        spec = FeatureSpec.from_json_obj(config.get("feature_spec"), f"{where}: feature_spec")
    except FeatureSpecError as exc:
        raise FastLoopNumpyError(str(exc)) from None
    if spec.obs_dim != mc["obs_dim"] or spec.act_dim != mc["act_dim"]:
        raise FastLoopNumpyError(f"{where}: the feature spec has {spec.obs_dim} observation / {spec.act_dim} action "
                                 f"values, model_config says obs_dim={mc['obs_dim']}, act_dim={mc['act_dim']}")
    if mc["n_codes"]:
        vq = config.get("vqvae")
        vq_cfg = vq.get("model_config") if isinstance(vq, dict) else None
        if not isinstance(vq_cfg, dict):
            raise FastLoopNumpyError(f"{where}: n_codes={mc['n_codes']} but 'vqvae' does not describe the VQ-VAE")
        if vq_cfg.get("input") != "vector":
            raise FastLoopNumpyError(f"{where}: this fast_loop reads codes of a VQ-VAE with input "
                                     f"{vq_cfg.get('input')!r} (camera frames); the inference runtime runs "
                                     "state-only fast_loops (observation vectors)")
        if vq_cfg.get("obs_dim") != mc["obs_dim"] or vq_cfg.get("n_codes") != mc["n_codes"]:
            raise FastLoopNumpyError(f"{where}: the VQ-VAE's obs_dim/n_codes ({vq_cfg.get('obs_dim')}/"
                                     f"{vq_cfg.get('n_codes')}) do not fit the fast_loop's "
                                     f"({mc['obs_dim']}/{mc['n_codes']})")
    return spec


def _load_tensors(data: bytes, where: Path) -> dict[str, np.ndarray]:
    from safetensors import SafetensorError
    from safetensors.numpy import load

    n = int.from_bytes(data[:8], "little") if len(data) >= 8 else -1
    if not (2 <= n <= 100_000_000 and data[8:9] == b"{"):
        kind = " (it looks like a pickle / torch.save file, which is never loaded)" if data[:1] == b"\x80" or \
            data[:2] == b"PK" else ""
        raise FastLoopNumpyError(f"{where}: not a safetensors file{kind}")
    try:
        return load(data)
    except (SafetensorError, ValueError, TypeError) as exc:
        raise FastLoopNumpyError(f"{where}: not a readable safetensors file: {exc}") from None


def expected_shapes(mc: dict[str, Any], vq_cfg: dict[str, Any] | None = None) -> dict[str, tuple[int, ...]]:
    """Tensor name -> shape of every weight the NumPy form reads."""
    d, n, hidden = mc["d_model"], mc["d_state"], mc["mlp_ratio"] * mc["d_model"]
    shapes: dict[str, tuple[int, ...]] = {
        "obs_in.weight": (d, mc["obs_dim"]), "obs_in.bias": (d,),
        "ssm.B": (n, d), "ssm.C": (d, n), "ssm.D": (d,), "ssm.log_rate": (n,),
        "out.weight": (mc["act_dim"], d), "out.bias": (mc["act_dim"],),
    }
    for name in ("enc_ln", "ssm_ln", "head_ln", "out_ln"):
        shapes[f"{name}.weight"] = shapes[f"{name}.bias"] = (d,)
    for name in ("enc_mlp", "head_mlp"):
        shapes.update({f"{name}.w_gate.weight": (hidden, d), f"{name}.w_gate.bias": (hidden,),
                       f"{name}.w_up.weight": (hidden, d), f"{name}.w_up.bias": (hidden,),
                       f"{name}.w_out.weight": (d, hidden), f"{name}.w_out.bias": (d,)})
    if mc["n_codes"]:
        shapes["code_in.weight"] = (mc["n_codes"], d)
    return shapes


def _check_tensors(t: dict[str, np.ndarray], mc: dict[str, Any], where: Path) -> None:
    want = expected_shapes(mc)
    n_codes = mc["n_codes"]
    if n_codes:
        w0 = t.get("vqvae.encoder.0.0.weight")
        w4 = t.get("vqvae.encoder.0.4.weight")
        hidden = w0.shape[0] if w0 is not None and w0.ndim == 2 else -1
        code_dim = w4.shape[0] if w4 is not None and w4.ndim == 2 else -1
        want.update({"vqvae.encoder.0.0.weight": (hidden, mc["obs_dim"]), "vqvae.encoder.0.0.bias": (hidden,),
                     "vqvae.encoder.0.2.weight": (hidden, hidden), "vqvae.encoder.0.2.bias": (hidden,),
                     "vqvae.encoder.0.4.weight": (code_dim, hidden), "vqvae.encoder.0.4.bias": (code_dim,),
                     "vqvae.codebook": (n_codes, code_dim)})
    missing = sorted(set(want) - set(t))
    # names the runtime does not read: the VQ-VAE's decoder and EMA buffers are fine, anything else
    # means the file describes another model than config.json does
    unexpected = sorted(k for k in set(t) - set(want) if not (n_codes and k.startswith("vqvae.")))
    wrong = [f"{k}: file {list(t[k].shape)} {t[k].dtype}, config {list(s)} float32"
             for k, s in want.items() if k in t and (tuple(t[k].shape) != s or t[k].dtype != np.float32)]
    if missing or unexpected or wrong:
        parts = []
        if wrong:
            parts.append(f"shape/dtype mismatch: {'; '.join(wrong[:5])}{' ...' if len(wrong) > 5 else ''}")
        if missing:
            parts.append(f"missing: {missing[:5]}{' ...' if len(missing) > 5 else ''}")
        if unexpected:
            parts.append(f"unexpected: {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}")
        raise FastLoopNumpyError(f"{where}: weights do not fit the fast_loop config.json describes "
                                 f"({', '.join(parts)})")
    bad = [k for k in want if not np.isfinite(t[k]).all()]
    if bad:
        raise FastLoopNumpyError(f"{where}: non-finite weights (NaN/Inf) in {', '.join(bad[:5])}"
                                 f"{' ...' if len(bad) > 5 else ''}")
    if n_codes:
        init = t.get("vqvae.initialized")
        if init is None or int(np.asarray(init).reshape(-1)[0]) != 1:
            raise FastLoopNumpyError(f"{where}: the fast_loop's VQ-VAE was never trained (codebook not initialised)")


__all__ = ["FastLoopNumpy", "FastLoopNumpyError", "NumpyWindowState", "expected_shapes"]
