"""The Mid Loop over a grid frame tokenizer (mid_loop/grid_model.py, grid_metrics.py): per-cell codes
of one shared codebook and the joints in, each cell's code and the joints at each horizon out,
decoded only where targets are scored."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from hope_models.components.build import build_component, component_from_checkpoint
from hope_models.components.layers import expand
from hope_models.components.mid_loop.checkpoint import MidLoopNumpyError
from hope_models.components.mid_loop.grid_metrics import grid_loss
from hope_models.components.mid_loop.grid_model import GridMidLoop
from hope_models.components.mid_loop.held_out import held_out_line, mid_loop_verdict
from hope_models.components.mid_loop.layers import decoded_cells
from hope_models.components.mid_loop.model import MidLoopConfig, previous_actions
from hope_models.components.mid_loop.numpy_form import MidLoopNumpy, MidLoopRuntime
from hope_models.components.mid_loop.numpy_grid import GridMidLoopNumpy
from hope_models.components.resolve import resolve
from hope_models.components.vqvae.model import VQVAE, VQVAEConfig
from hope_models.data.cache import load_or_build
from hope_models.data.features import FeatureField, FeatureGroup, FeatureSpec, FrameFeature
from hope_models.data.sampler import AnchorSampler
from hope_models.data.synthetic import generate_dataset
from hope_models.data.windows import make_windows
from hope_models.train.estimate import ACT_FACTOR, config_layers, estimate_from_config, estimate_memory, model_layers

pytestmark = pytest.mark.usefixtures("torch_one_thread")

MOVES = torch.tensor([[1, 0], [-1, 0], [0, 1], [0, -1]])
SIDE, OBJECT = 8, 5  # an 8x8 grid (64x64 frames, 8-pixel cells); the moving thing's code


def _grid_vq(n_codes: int = 8) -> VQVAE:
    return VQVAE(VQVAEConfig(input="frame", layout="grid", patch=8, n_codes=n_codes, channels=4, groups=SIDE * SIDE,
                             code_dim=SIDE * SIDE * 2))


def _model(**kw) -> GridMidLoop:
    cfg = dict(act_dim=2, n_codes=8, obs_dim=2, horizon_steps=(2, 4), d_model=48, d_state=16, dropout=0.0)
    return GridMidLoop(MidLoopConfig(**{**cfg, **kw}), _grid_vq())


def _toy(b: int, k: int, horizons: tuple[int, ...], gen: torch.Generator):
    """One code moves one cell per step in the direction of the action (held, changed with p 0.1),
    stopping at the walls, over a fixed background; the 'joint' turns with the action's x."""
    n = k + max(horizons)
    a = torch.randint(0, 4, (b,), generator=gen)
    pos, theta, acts = [torch.randint(2, SIDE - 2, (b, 2), generator=gen)], [torch.zeros(b)], []
    for _ in range(n):
        a = torch.where(torch.rand(b, generator=gen) < 0.1, torch.randint(0, 4, (b,), generator=gen), a)
        acts.append(MOVES[a].float())
        pos.append((pos[-1] + MOVES[a]).clamp(0, SIDE - 1))
        theta.append(theta[-1] + 0.3 * MOVES[a][:, 0].float())
    where = torch.stack(pos[:n], 1)
    codes = (torch.arange(SIDE * SIDE) % 3).repeat(b, n, 1)
    codes.scatter_(-1, (where[..., 1] * SIDE + where[..., 0])[..., None], OBJECT)
    obs = torch.stack([torch.stack(theta[:n], 1), torch.zeros(b, n)], -1)
    fut = torch.stack([codes[:, k - 1 + s] for s in horizons], 1)
    fobs = torch.stack([obs[:, k - 1 + s] for s in horizons], 1)
    return codes[:, :k], torch.stack(acts, 1)[:, :k], obs[:, :k], torch.ones(b, k, dtype=torch.bool), fut, fobs


def _loss(model, batch, training):
    codes, act, obs, mask, fut, fobs = batch
    y = model.context(codes, previous_actions(act), obs, mask)
    return grid_loss(model, y, codes, obs, mask, future_codes=fut, future_obs=fobs, training=training)


def test_only_scored_cells_are_decoded_and_the_head_is_small():
    """No [B, K, H, G, n_codes] tensor: training decodes the changed cells and a sample of the
    others at score_points targets per horizon, evaluation every cell of those targets only."""
    torch.manual_seed(0)
    model = _model(score_points=2, stay_sample=0.25)
    rows = []
    model.cell_out.register_forward_hook(lambda m, i, o: rows.append(o.shape[:-1].numel()))
    batch = _toy(16, 8, (2, 4), torch.Generator().manual_seed(0))
    _loss(model, batch, training=False)
    full = 16 * 2 * SIDE * SIDE  # per horizon: 16 windows x 2 targets x every cell
    assert rows == [full, full]
    rows.clear()
    loss, m = _loss(model, batch, training=True)
    loss.backward()
    assert all(r < 0.5 * full for r in rows), rows  # ~1/8 of the cells change: far fewer decoded
    assert m["targets"] == 2 * 16 * 2 and m["window_targets"] == 2 * 16
    vector_head = len(model.cfg.horizon_steps) * 256 * 256 * model.cfg.d_model  # at 256 cells x 256 codes
    big = GridMidLoop(MidLoopConfig(act_dim=2, n_codes=256, obs_dim=4), VQVAE(VQVAEConfig(
        input="frame", layout="grid", patch=4, n_codes=256, channels=4, groups=256, code_dim=256 * 2)))
    # the code heads' size (the world model over the joints, wm_*, is its own head)
    trainable = sum(p.numel() for n, p in big.named_parameters() if p.requires_grad and not n.startswith("wm_"))
    assert trainable < 0.05 * vector_head, trainable


def test_a_grid_mid_loop_learns_a_moving_code_better_than_copy_last_and_the_frequencies():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    model = _model()
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], 3e-3)
    for _ in range(250):
        loss, _ = _loss(model, _toy(32, 8, (2, 4), gen), training=True)
        opt.zero_grad()
        loss.backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        _, m = _loss(model, _toy(256, 8, (2, 4), gen), training=False)
    for label in ("2steps", "4steps"):
        assert m[f"nll_{label}"] < 0.8 * min(m[f"copy_last_nll_{label}"], m[f"code_freq_nll_{label}"]), m
        assert m[f"joint_mse_{label}"] < 0.7 * m[f"copy_last_joint_mse_{label}"], m
        assert m[f"changed_accuracy_{label}"] > 0.1  # it moves the code, copy-last never does


def test_stepping_gives_the_windows_context_at_every_point():
    torch.manual_seed(1)
    model = _model().eval()
    codes, act, obs, mask, _, _ = _toy(3, 6, (2, 4), torch.Generator().manual_seed(1))
    prev = previous_actions(act)
    with torch.no_grad():
        y = model.context(codes, prev, obs, mask)
        state = model.init_state(3)
        for t in range(6):
            y_t, state = model.step(codes[:, t], prev[:, t], obs[:, t], state)
            assert (y_t - y[:, t]).abs().max().item() < 1e-5, t


def test_the_baselines_are_per_cell_and_counted_on_training_targets_only():
    model = _model(score_points=1)
    batch = _toy(8, 8, (2, 4), torch.Generator().manual_seed(2))
    _loss(model, batch, training=False)
    assert float(model.code_counts.sum()) == 0 and float(model.stay_counts.sum()) == 0
    _loss(model, batch, training=True)
    assert float(model.code_counts.sum()) == 2 * 8 * SIDE * SIDE  # 8 anchors per horizon, every cell
    # a background cell far from the object never changes: its copy-last stay count is full
    assert float(model.stay_counts[0, :, 0].sum()) > 0 and float(model.stay_counts[0, 0, 1]) >= 1


def test_the_gate_reads_the_joints_of_a_grid_mid_loop():
    val = {f"{k}_{h}": v for h in ("0.5s", "1s") for k, v in
           (("nll", 10.0), ("copy_last_nll", 20.0), ("code_freq_nll", 30.0), ("joint_mse", 0.2),
            ("copy_last_joint_mse", 1.0))}
    assert mid_loop_verdict(val, ["0.5s", "1s"], False, 0.3, joints=True)[0] == "passed"
    status, text = mid_loop_verdict({**val, "joint_mse_1s": 0.8}, ["0.5s", "1s"], False, 0.3, joints=True)
    assert status == "failed" and "1s: its predicted joints' error is 20% lower than copy-last's" in text
    status, text = mid_loop_verdict({k: v for k, v in val.items() if "joint" not in k}, ["0.5s"], False, 0.3,
                                    joints=True)
    assert status == "failed" and "joints' error was not measured" in text
    line = held_out_line({"0.5s": {"nll": 10.0, "copy_last_nll": 20.0, "code_freq_nll": 30.0, "joint_mse": 0.2,
                                   "copy_last_joint_mse": 1.0}})
    assert "joint error 0.200 vs copy-last 1.000 (80 % lower)" in line


@pytest.fixture(scope="module")
def frame_cache(tmp_path_factory):
    root = tmp_path_factory.mktemp("gridframes")
    generate_dataset(root / "ds", 600, obs_dim=4, act_dim=2, seed=1, episode_seconds=(6, 8), rates_hz=(20,),
                     frame_blobs=True)
    cache, _ = load_or_build(root / "ds", root / "cache")
    return cache


def _save(comp, d: Path) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    save_file(comp.model.state_dict(), str(d / "model.safetensors"))
    (d / "config.json").write_text(json.dumps(comp.config()), encoding="utf-8")
    return d


def test_a_grid_mid_loop_component_trains_on_frames_round_trips_and_the_numpy_runtime_loads_it(
        frame_cache, tmp_path):
    torch.manual_seed(0)
    vq = build_component("vqvae", frame_cache.spec, model_config={"layout": "grid", "patch": 8, "n_codes": 16,
                                                                  "channels": 4})
    vq.model(torch.from_numpy(frame_cache.frame_rows(np.arange(32))), init_codebook=True)
    comp = build_component("mid_loop", frame_cache.spec, vqvae_dir=_save(vq, tmp_path / "vq"))
    assert isinstance(comp.model, GridMidLoop) and comp.model_config.obs_dim == 4
    sampler = AnchorSampler(frame_cache, 4, seed=0, horizon_s=1.0)
    opt = torch.optim.Adam([p for p in comp.model.parameters() if p.requires_grad], 1e-3)
    for b in range(2):
        loss, m = comp.loss(make_windows(frame_cache, sampler.batch(b), comp.window, frames=True))
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert np.isfinite(loss.item()) and m["targets"] > m["window_targets"] > 0 and m["joint_targets"] > 0
    ck = _save(comp, tmp_path / "mid")
    back = component_from_checkpoint(ck)
    for k, v in comp.model.state_dict().items():
        assert torch.equal(back.model.state_dict()[k], v), k
    batch = make_windows(frame_cache, sampler.batch(9), comp.window, frames=True)
    ev = back.evaluate(batch)
    assert ev == comp.evaluate(batch)
    assert {"nll_0.5s", "copy_last_nll_1s", "code_freq_nll_1s", "joint_mse_0.5s", "copy_last_joint_mse_1s"} <= set(ev)
    served = MidLoopRuntime.from_checkpoint(ck)  # numpy_grid.py (tests/test_mid_loop_numpy_grid.py: equal to torch)
    assert isinstance(served, GridMidLoopNumpy) and served.obs_dim == 4 and served.frame_shape == (64, 64, 3)
    with pytest.raises(MidLoopNumpyError, match="a grid Mid Loop"):
        MidLoopNumpy.from_checkpoint(ck)


def test_the_layer_table_is_the_grid_models_and_the_estimate_counts_its_decoded_cells():
    spec = FeatureSpec(FeatureGroup([FeatureField("observation.joints", 4)]),
                       FeatureGroup([FeatureField("action.command", 2)]), FrameFeature("observation.rgb", (64, 64, 3)))
    vq_cfg = resolve("vqvae", spec, {"layout": "grid", "patch": 8, "n_codes": 16, "channels": 4}).cfg
    r = resolve("mid_loop", spec, {"d_model": 24, "cell_rank": 8}, vq_cfg)
    model = GridMidLoop(r.cfg, VQVAE(vq_cfg))
    by_name = {layer.name: layer for layer in expand(config_layers(r))}
    assert by_name == {layer.name: layer for layer in expand(model_layers(model))}
    assert by_name["cell_out"].per_sample > 0 and by_name["keypoints.score"].per_point == 64
    built = estimate_memory("mid_loop", model, 32, r.window.k, 4, 2, True, horizons=len(r.window.horizons_s))
    assert estimate_from_config(r, 32, 4, 2) == built
    # each decoded cell keeps the cell decoder's outputs: code 8 + norm 8 + gated MLP 16 + 16 + 8 + logits 16
    more = resolve("mid_loop", spec, {"d_model": 24, "cell_rank": 8, "score_points": 8}, vq_cfg)
    cells = decoded_cells(more.cfg, 64) - decoded_cells(r.cfg, 64)
    grown = estimate_from_config(more, 32, 4, 2).breakdown["activations"] - built.breakdown["activations"]
    assert cells > 0 and grown == pytest.approx(ACT_FACTOR * 4 * 32 * 72 * cells / 2**20)


def test_copy_last_in_the_mixture_caps_what_a_wrong_change_costs():
    """A decoder sure of a change that does not come: alone it pays its whole log-probability on
    every cell; mixed with copy-last (copy_mix) at most -log(copy_mix x P(stay)) a cell."""
    batch = _toy(8, 8, (2, 4), torch.Generator().manual_seed(3))
    costs = {}
    for mix in (0.0, 0.2):
        model = _model(copy_mix=mix).eval()
        with torch.no_grad():
            model.cell_out.bias.fill_(-30.0)
            model.cell_out.bias[7] = 30.0  # every cell will turn into code 7, which no cell of the toy holds
        _, m = _loss(model, batch, training=False)
        costs[mix] = m["nll_2steps"] / (SIDE * SIDE)
        assert m["accuracy_2steps"] == 0.0  # the mixture's most probable code is still the decoder's
    # no counts yet: copy-last's P(stay) is 0.5; a cell that stayed costs at most -log(0.1), one
    # that changed -log(0.2 x 0.5 / 7) (the other codes share the rest), and most cells stayed
    assert costs[0.0] > 50 and costs[0.2] < -np.log(0.1) + 0.1 * -np.log(0.2 * 0.5 / 7), costs
