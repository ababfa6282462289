"""The NumPy fast_loop (BrainService's runtime) computes what torch's FastLoop computes.

Equality within 1e-5 (normalised action) against FastLoop.step over thousands of ticks, against
FastLoop.forward on each trailing window (including an episode's first K-1 ticks, whose windows have
a masked prefix), for a fast_loop that reads VQ-VAE codes too, and the whole tick from raw values
(FastLoopNumpyAct: normalisation, denormalisation, the reacher's clipping) against ReflexPolicy. Then what it refuses.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from brain_fixtures import brain_runs, rewrite_manifest
from hope_models.promoted import checkpoint_version
from hope_models.components.fast_loop.numpy_act import FastLoopNumpyAct
from hope_models.components.fast_loop.numpy_form import FastLoopNumpy, FastLoopNumpyError
from hope_models.components.build import component_from_checkpoint

REPO = Path(__file__).resolve().parents[1]
TOL = 1e-5


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return brain_runs(tmp_path_factory)


def _pair(ckpt: Path):
    return FastLoopNumpy.from_checkpoint(ckpt), component_from_checkpoint(ckpt).model.eval()


def _observations(n: int, dim: int, seed: int) -> np.ndarray:
    # normalised observations: a smooth walk plus noise and a few large excursions, so LayerNorms,
    # gates and the codebook see more than the unit ball
    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.normal(0, 0.3, (n, dim)), axis=0) * 0.2 + rng.normal(0, 1.0, (n, dim))
    x[rng.random(n) < 0.02] *= 6.0
    return x.astype(np.float32)


@pytest.mark.parametrize("name", ["big", "alpha30", "alpha_vq"])
def test_step_equals_torch_step_and_forward_over_many_ticks(runs, name, torch_one_thread):
    model, tmodel = _pair(runs[name])
    k = model.window_k
    ticks = 2000 if name == "big" else 3000
    obs = _observations(ticks, model.obs_dim, seed=len(name))
    state, tstate = model.init_state(), tmodel.init_state(1)
    worst_step = worst_fwd = 0.0
    checked_fwd = 0
    with torch.inference_mode():
        for t in range(ticks):
            a, state = model.step(obs[t:t + 1], state)
            ta, tstate = tmodel.step(torch.from_numpy(obs[t:t + 1]), tstate)
            worst_step = max(worst_step, float(np.abs(a - ta.numpy()).max()))
            if t < k or t % 37 == 0 or t == ticks - 1:
                # the trailing window of K points, masked before the episode's start (as make_windows builds it)
                window = np.zeros((1, k, model.obs_dim), np.float32)
                mask = np.zeros((1, k), bool)
                lo = max(0, t - k + 1)
                window[0, k - (t + 1 - lo):] = obs[lo:t + 1]
                mask[0, k - (t + 1 - lo):] = True
                fwd = tmodel(torch.from_numpy(window), torch.from_numpy(mask)).numpy()
                worst_fwd = max(worst_fwd, float(np.abs(a - fwd).max()),
                                float(np.abs(model.forward(window, mask) - fwd).max()))
                checked_fwd += 1
    assert worst_step < TOL, f"{name}: NumPy step vs torch step differ by {worst_step:.2e}"
    assert worst_fwd < TOL, f"{name}: NumPy vs torch forward on the trailing window differ by {worst_fwd:.2e}"
    assert checked_fwd > 50


def test_forward_equals_torch_on_random_batched_windows(runs, torch_one_thread):
    model, tmodel = _pair(runs["big"])
    rng = np.random.default_rng(7)
    for length in (1, 3, model.window_k, 12):  # shorter, equal and longer than K
        obs = rng.normal(0, 1.5, (8, length, model.obs_dim)).astype(np.float32)
        mask = np.ones((8, length), bool)
        mask[:4, : length // 2] = False  # episodes that started inside the window
        with torch.inference_mode():
            want = tmodel(torch.from_numpy(obs), torch.from_numpy(mask)).numpy()
        got = model.forward(obs, mask)
        assert got.shape == want.shape == (8, model.act_dim)
        assert np.abs(got - want).max() < TOL, f"window of {length}"


@pytest.mark.parametrize("name", ["big", "alpha_vq"])
def test_batched_step_equals_torch(runs, name, torch_one_thread):
    """step() on a batch takes the batched path (one vector takes the flat serving path)."""
    model, tmodel = _pair(runs[name])
    obs = _observations(3 * 40, model.obs_dim, seed=9).reshape(40, 3, model.obs_dim)
    state, tstate = model.init_state(3), tmodel.init_state(3)
    with torch.inference_mode():
        for t in range(40):
            a, state = model.step(obs[t], state)
            ta, tstate = tmodel.step(torch.from_numpy(obs[t]), tstate)
            assert np.abs(a - ta.numpy()).max() < TOL, t


def test_codes_equal_the_vqvae_codes(runs, torch_one_thread):
    model, tmodel = _pair(runs["alpha_vq"])
    obs = _observations(4000, model.obs_dim, seed=3)
    with torch.inference_mode():
        want = tmodel.codes(torch.from_numpy(obs)).numpy()
    got = model.codes(obs)
    assert len(set(map(tuple, want.tolist()))) > 3  # the test means something only if codes vary
    assert (got == want).mean() > 0.999  # an exact tie in float32 could flip one code; none expected
    assert (got == want).all()


def _as_reacher(src: Path, dst: Path) -> Path:
    """A copy of a 6 -> 2 checkpoint whose spec names the dm_control reacher's fields (same sizes)."""
    shutil.copytree(src, dst)
    cfg = json.loads((dst / "config.json").read_text())
    obs = cfg["feature_spec"]["observation"]
    obs["fields"] = [{"path": "observation.robot_state.joint_positions", "size": 2},
                     {"path": "observation.robot_state.joint_velocities", "size": 2},
                     {"path": "observation.target_offset", "size": 2}]
    cfg["feature_spec"]["action"]["fields"] = [{"path": "action.command", "size": 2}]
    # wide action statistics, so that some denormalised actions fall outside the motor bounds
    cfg["feature_spec"]["action"].update(mean=[0.8, -0.8], std=[2.0, 2.0])
    (dst / "config.json").write_text(json.dumps(cfg))
    rewrite_manifest(dst)
    return dst


def test_act_from_raw_values_equals_reflex_policy(runs, tmp_path, torch_one_thread):
    from hope_models.promote.reflex_policy import ReflexPolicy

    ckpt = _as_reacher(runs["alpha30"], tmp_path / "run" / "checkpoints" / "00000030")
    model = FastLoopNumpyAct.from_checkpoint(ckpt)
    policy = ReflexPolicy.from_checkpoint(ckpt)
    assert model.version == policy.version == checkpoint_version(ckpt)[0]
    assert model.action_bounds == (-1.0, 1.0)
    rng = np.random.default_rng(11)
    raw = rng.normal(0, 1.0, (600, 6)) * np.array([1, 1, 5, 5, 0.2, 0.2])
    raw[::50] *= 40.0  # far outside the data: the action saturates and must be clipped alike
    state = model.init_state()
    clipped = inside = 0
    for t, x in enumerate(raw):
        if t == 300:  # an episode restart on both sides
            state = model.init_state()
            policy.reset()
        a, state = model.act(x.tolist(), state)
        want = policy.act(x)
        assert np.abs(a - want).max() < TOL * 10, f"tick {t}: {a} vs {want}"  # denormalised: std up to ~3
        clipped += int(np.any(np.abs(a) == 1.0))
        inside += int(np.all(np.abs(a) < 1.0))
    assert clipped > 10 and inside > 10  # both paths were exercised


def test_other_specs_are_not_clipped(runs):
    model = FastLoopNumpy.from_checkpoint(runs["alpha30"])
    assert model.action_bounds is None
    a = model.denormalise(np.array([50.0, -50.0]))
    assert abs(a[0]) > 1.0 and abs(a[1]) > 1.0


def test_observation_checks_name_the_problem(runs):
    model = FastLoopNumpyAct.from_checkpoint(runs["alpha30"])
    with pytest.raises(FastLoopNumpyError, match="has 5 values.*needs 6"):
        model.act([0.0] * 5, model.init_state())
    with pytest.raises(FastLoopNumpyError, match="non-finite"):
        model.act([0.0] * 5 + [float("nan")], model.init_state())


# -- what it refuses ------------------------------------------------------------------------------

def _copy(src: Path, tmp_path: Path, name: str = "00000030") -> Path:
    dst = tmp_path / "edited" / "checkpoints" / name
    shutil.copytree(src, dst)
    return dst


def _edit_config(ckpt: Path, fn) -> None:
    cfg = json.loads((ckpt / "config.json").read_text())
    fn(cfg)
    (ckpt / "config.json").write_text(json.dumps(cfg))


def test_refuses_another_component(runs):
    with pytest.raises(FastLoopNumpyError, match=r"config.json: component is 'vqvae'; .*fast_loop"):
        FastLoopNumpy.from_checkpoint(runs["vq"])


def test_refuses_a_frame_vqvae(runs, tmp_path):
    ckpt = _copy(runs["alpha_vq"], tmp_path, "00000020")
    _edit_config(ckpt, lambda c: c["vqvae"]["model_config"].update(input="frame"))
    with pytest.raises(FastLoopNumpyError, match="camera frames"):
        FastLoopNumpy.from_checkpoint(ckpt)


def test_refuses_a_config_that_does_not_fit_its_weights(runs, tmp_path):
    ckpt = _copy(runs["alpha30"], tmp_path)

    def bigger(c):
        c["model_config"]["d_model"] = 32

    _edit_config(ckpt, bigger)
    with pytest.raises(FastLoopNumpyError, match=r"model.safetensors: weights do not fit.*obs_in.weight"):
        FastLoopNumpy.from_checkpoint(ckpt)


def test_refuses_a_spec_whose_size_differs_from_the_model(runs, tmp_path):
    ckpt = _copy(runs["alpha30"], tmp_path)

    def smaller(c):  # a consistent spec of 5 values, for a model that reads 6
        obs = c["feature_spec"]["observation"]
        obs["fields"][0]["size"] -= 1
        obs["mean"], obs["std"] = obs["mean"][:5], obs["std"][:5]

    _edit_config(ckpt, smaller)
    with pytest.raises(FastLoopNumpyError, match="the feature spec has 5 observation .* obs_dim=6"):
        FastLoopNumpy.from_checkpoint(ckpt)


def test_refuses_non_finite_weights(runs, tmp_path):
    from safetensors.numpy import load_file, save_file

    ckpt = _copy(runs["alpha30"], tmp_path)
    tensors = load_file(str(ckpt / "model.safetensors"))
    tensors["head_mlp.w_up.weight"][0, 0] = np.nan
    save_file(tensors, str(ckpt / "model.safetensors"))
    with pytest.raises(FastLoopNumpyError, match=r"non-finite weights .*head_mlp.w_up.weight"):
        FastLoopNumpy.from_checkpoint(ckpt)


def test_refuses_pickle_and_a_sha_mismatch(runs, tmp_path):
    ckpt = _copy(runs["alpha30"], tmp_path)
    version, sha = checkpoint_version(ckpt)
    with pytest.raises(FastLoopNumpyError, match="does not match the promoted"):
        FastLoopNumpy.from_checkpoint(ckpt, expected_sha256="0" * 64)
    assert FastLoopNumpy.from_checkpoint(ckpt, expected_sha256=sha).version == version
    torch.save({"w": torch.zeros(2)}, ckpt / "model.safetensors")
    with pytest.raises(FastLoopNumpyError, match="pickle"):
        FastLoopNumpy.from_checkpoint(ckpt)
    with pytest.raises(FastLoopNumpyError, match="not found"):
        FastLoopNumpy.from_checkpoint(tmp_path / "nowhere")


def test_runtime_modules_do_not_import_torch():
    code = ("import sys; import hope_models.runtime.brain_service, hope_models.components.fast_loop.numpy_form; "
            "bad = [m for m in ('torch', 'dm_control', 'mujoco') if m in sys.modules]; print(bad); "
            "sys.exit(1 if bad else 0)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
