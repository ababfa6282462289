"""The serving path's shortcuts give the answers of the arithmetic they replace.

Each test computes the same answer the plain way (the formula the NumPy form used before, written
out here, or the window form that tests/test_brain_whole.py checks against torch) and compares:
- the VQ-VAE's SiLU layers halved at load (numpy_layers.silu_of_half): encode bit-equal;
- its nearest code with the cross term as one batched product: the same codes; decode_expected's
  probability-weighted rows as one batched product: the same decoding within float32 rounding;
- the Mid Loop's window but its last point computed ahead, a stage a tick (numpy_ssm.window_ahead,
  serving.py), then the last point alone: the window form's prediction, in a served session too;
- the Mid Loop reading the served tokenizer's codes when its own VQ-VAE and normalisation are the
  same (same_codes): the same answers as a Mid Loop encoding for itself, and never for another one;
- the fast_loop's finite check reading h, not the ring: a NaN or Inf entering the ring makes h
  non-finite on that very tick;
- the action bounds by np.maximum/np.minimum: np.clip's values, NaN kept.
"""
from __future__ import annotations

import numpy as np
import pytest
from brain_fixtures import brain_runs, brain_whole_runs, promote_pointer

from hope_models.components.fast_loop.numpy_form import FastLoopNumpy
from hope_models.components.mid_loop import numpy_form as mid_numpy
from hope_models.components.mid_loop.numpy_form import MidLoopNumpy
from hope_models.components.numpy_layers import silu
from hope_models.components.vqvae.numpy_form import VQVAENumpy
from hope_models.runtime.brain_service import BrainService
from hope_models.runtime.fast_sessions import finite


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return {**brain_runs(tmp_path_factory), **brain_whole_runs(tmp_path_factory)}


def random_vq(groups=4, n=64, obs=6, hidden=32, code_dim=24, seed=0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = {}
    for name, shape in (("encoder.0.0", (hidden, obs)), ("encoder.0.2", (hidden, hidden)), ("encoder.0.4", (code_dim, hidden)),
                        ("decoder.0", (hidden, code_dim)), ("decoder.2", (hidden, hidden)), ("decoder.4", (obs, hidden))):
        t[f"{name}.weight"] = rng.normal(0, 1 / np.sqrt(shape[1]), shape).astype(np.float32)
        t[f"{name}.bias"] = rng.normal(0, 0.1, shape[0]).astype(np.float32)
    t["codebook"] = rng.normal(0, 0.3, (groups * n, code_dim // groups)).astype(np.float32)
    return t


def plain_mlp(t: dict[str, np.ndarray], names: list[str], x: np.ndarray) -> np.ndarray:
    """Linear-SiLU-Linear-SiLU-Linear as the form computed it before the halving."""
    for i, name in enumerate(names):
        y = x.dot(np.ascontiguousarray(t[f"{name}.weight"].T))
        y += t[f"{name}.bias"]
        x = silu(y) if i < 2 else y
    return x


def plain_nearest(z: np.ndarray, book: np.ndarray) -> np.ndarray:
    zg = z.reshape(*z.shape[:-1], book.shape[0], 1, -1)
    d = (zg * zg).sum(-1) - np.float32(2.0) * (zg * book).sum(-1) + (book * book).sum(-1)
    return d.argmin(-1)


def test_vqvae_encode_codes_and_decode_equal_the_plain_arithmetic():
    t = random_vq()
    vq = VQVAENumpy(t, groups=4, n_codes=64)
    x = np.random.default_rng(1).normal(0, 1.5, (4000, 6)).astype(np.float32)
    enc = ["encoder.0.0", "encoder.0.2", "encoder.0.4"]
    z = plain_mlp(t, enc, x)
    z = z - z.mean(-1, keepdims=True)
    z /= np.sqrt((z * z).mean(-1, keepdims=True) + np.float32(1e-5))
    got = vq.encode(x)
    # the halving is exact: the SiLU's inputs are the same numbers (LayerNorm's reductions may differ in the last bit)
    assert np.allclose(got, z, atol=2e-6)
    first = x.dot(np.ascontiguousarray(t["encoder.0.0.weight"].T)) + t["encoder.0.0.bias"]
    halved = vq._enc[0](x)
    assert np.array_equal(silu(first), halved * (np.tanh(halved) + np.float32(1.0)))
    book = t["codebook"].reshape(4, 64, -1)
    want = plain_nearest(got, book)
    assert np.array_equal(vq.codes(x), want)  # a batch
    assert all(np.array_equal(vq.codes(x[i]), want[i]) for i in range(300))  # one observation, as served
    probs = np.random.default_rng(2).dirichlet(np.ones(64), (50, 2, 4)).astype(np.float32)
    zq = (probs[..., None] * book).sum(-2).reshape(50, 2, -1)
    want_dec = plain_mlp(t, ["decoder.0", "decoder.2", "decoder.4"], zq)
    assert np.allclose(vq.decode_expected(probs), want_dec, atol=1e-5, rtol=1e-5)
    assert np.allclose(vq.decode(want[:20]), plain_mlp(t, ["decoder.0", "decoder.2", "decoder.4"],
                                                       book[np.arange(4), want[:20]].reshape(20, -1)), atol=1e-6)


def test_mid_loop_window_ahead_a_stage_a_call_equals_the_window_form(runs):
    mid = MidLoopNumpy.from_checkpoint(runs["mid_a"])
    rng = np.random.default_rng(3)
    k = mid.window_k
    points = list(rng.integers(0, mid.n_codes, (k, mid.groups)))
    acts = rng.normal(0, 1, (k, mid.act_dim)).astype(np.float32)
    acts[0] = 0.0
    for length in (1, 2, 7, k):
        pts, a = points[:length], acts[:length]
        want, want_logp, _ = mid.predict(pts, a)  # the window form (forward over the points)
        ahead = mid.window_ahead(pts[:-1], a[:-1])
        assert ahead.done == (1 if length > 1 else 0)  # the first stage only: the other ticks do the rest
        if length > 1:
            stages = 2 * mid.n_layers - 1  # each block's SSM and MLP, the last block's SSM alone
            assert [mid.ahead_step(ahead) for _ in range(stages - 1)] == [False] * (stages - 2) + [True]
            assert ahead.done == stages and mid.ahead_step(ahead) and ahead.done == stages
        got, got_logp, finite_ = mid.predict(pts, a, ahead)
        assert finite_ and np.allclose(got, want, atol=1e-5) and np.allclose(got_logp, want_logp, atol=1e-4)
        # an ahead the ticks did not finish is finished by predict itself
        assert np.allclose(mid.predict(pts, a, mid.window_ahead(pts[:-1], a[:-1]))[0], want, atol=1e-5)


def test_a_served_session_predicts_what_the_window_form_does_over_its_last_k_points(runs, tmp_path, monkeypatch):
    home = tmp_path / "home"
    for component, name in (("vqvae", "vq_a"), ("fast_loop", "alpha30"), ("mid_loop", "mid_a")):
        promote_pointer(home, runs[name], component)
    mid = MidLoopNumpy.from_checkpoint(runs["mid_a"])
    calls = {"ahead": 0, "step": 0}
    real_ahead, real_step = mid_numpy.MidLoopNumpy.window_ahead, mid_numpy.MidLoopNumpy.ahead_step

    def counted(name, fn):
        def wrapper(self, *a):
            calls[name] += 1
            return fn(self, *a)
        return wrapper

    monkeypatch.setattr(mid_numpy.MidLoopNumpy, "window_ahead", counted("ahead", real_ahead))
    monkeypatch.setattr(mid_numpy.MidLoopNumpy, "ahead_step", counted("step", real_step))
    obs = np.random.default_rng(4).normal(0, 0.5, (5 * 30 + 1, 6)).tolist()
    with BrainService(home) as brain:
        calls.update(ahead=0, step=0)  # the load's warm-up
        outs = [brain.infer("fast_loop", o, session="s") for o in obs]
    k, points = mid.window_k, 31
    assert calls["ahead"] == points - 1 and calls["step"] >= points - 1  # every grid point but the first ran ahead
    codes = [mid.codes_of(np.asarray(obs[5 * j])) for j in range(points)]
    acts = [np.zeros(2, np.float32)] + [mid.norm.act(np.asarray(outs[5 * j - 1]["action"])) for j in range(1, points)]
    for j in (1, 5, k - 1, k, k + 3, points - 1):  # windows growing, full, and sliding
        lo = max(0, j + 1 - k)
        a = np.stack(acts[lo:j + 1])
        a[0] = 0.0  # a window's first point (previous_actions)
        logits = mid.forward(np.stack([mid.rows(c) for c in codes[lo:j + 1]]), a)[-1]
        want = mid.prediction(mid.log_probs(logits))
        got = outs[5 * j]["prediction"]
        assert outs[5 * j]["mid_grid_point"] == j
        assert np.allclose(got["0.5s"], want[0], atol=1e-5) and np.allclose(got["1s"], want[1], atol=1e-5)


def test_a_nan_or_inf_entering_the_ring_makes_h_non_finite_on_that_tick(runs):
    model = FastLoopNumpy.from_checkpoint(runs["alpha30"])
    x = model.normalise(np.asarray([0.1, -0.2, 0.3, 0.05, -0.4, 0.2]))
    n, plain = model.d_state, model._flat
    for bad in (np.nan, np.inf, -np.inf):
        flat = list(plain)
        vd_b = flat[11].copy()
        vd_b[n // 2] = bad  # one entry of v, the value the tick writes into the ring
        flat[11] = vd_b
        for ticks_before in range(model.window_k):  # every ring position, the wrap's recompute too
            state = model.init_state()
            for _ in range(ticks_before):
                _, state = model.tick(x, state)
            model._flat = tuple(flat)
            try:
                with np.errstate(invalid="ignore", over="ignore"):
                    a, new = model.tick(x, state)
            finally:
                model._flat = plain
            assert not np.isfinite(new.ring).all()  # what the ring check caught
            assert not finite(a, new) and not np.isfinite(new.h).all()


def test_the_action_bounds_clip_as_np_clip():
    class Bounded(FastLoopNumpy):
        def __init__(self):  # only what denormalise reads
            self._act_std, self._act_mean = np.asarray([2.0, 0.5]), np.asarray([0.1, -0.3])
            self.action_bounds = (-1.0, 1.0)

    m = Bounded()
    a = np.asarray([[0.2, -0.4], [5.0, -9.0], [np.nan, 0.3], [-0.6, np.inf], [0.45, -1.4]])
    want = np.clip(a * m._act_std + m._act_mean, -1.0, 1.0)
    assert np.array_equal(m.denormalise(a), want, equal_nan=True)


def test_the_mid_loop_reads_the_tokenizers_codes_only_when_they_are_its_own(runs, tmp_path, monkeypatch):
    import copy

    from hope_models.components.vqvae.numpy_form import VQVAERuntime

    mid = MidLoopNumpy.from_checkpoint(runs["mid_a"])
    own, other = VQVAERuntime.from_checkpoint(runs["vq_a"]), VQVAERuntime.from_checkpoint(runs["vq_b"])
    shifted = copy.copy(own)
    shifted.norm = copy.copy(own.norm)
    shifted.norm.obs_shift = own.norm.obs_shift + np.float32(0.5)  # the same weights, another normalisation
    assert mid.same_codes(own) and not mid.same_codes(other) and not mid.same_codes(shifted) and mid.same_codes(own)
    obs = np.random.default_rng(5).normal(0, 0.5, (61, 6)).tolist()
    answers, encodes = {}, []
    real = MidLoopNumpy.codes_of
    monkeypatch.setattr(MidLoopNumpy, "codes_of", lambda self, v: encodes.append(1) or real(self, v))
    for name, promoted in (("tokenizer", ("vq_a", "alpha30", "mid_a")), ("alone", (None, "alpha30", "mid_a"))):
        home = tmp_path / name
        for component, run in zip(("vqvae", "fast_loop", "mid_loop"), promoted, strict=True):
            if run is not None:
                promote_pointer(home, runs[run], component)
        with BrainService(home) as brain:
            encodes.clear()  # the load's warm-up
            answers[name] = [brain.infer("fast_loop", o, session="s") for o in obs]
        assert len(encodes) == (0 if name == "tokenizer" else 13)  # 13 grid points in 61 ticks
    keys = ("prediction", "surprise", "surprise_by_horizon", "mid_tick", "mid_grid_point")
    assert [{k: a[k] for k in keys} for a in answers["tokenizer"]] == [{k: a[k] for k in keys} for a in answers["alone"]]
