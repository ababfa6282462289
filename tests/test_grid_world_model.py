"""The grid Mid Loop's world model (grid_model.py, wm_*): the joints after each held action, trained in
the mid_loop's loss beside the cell codes, skipped by the torch-free runtime, absent from grid
checkpoints made before it (stored_defaults)."""
from __future__ import annotations

import torch

from hope_models.components import spec_of
from hope_models.components.mid_loop.grid_model import GridMidLoop
from hope_models.components.mid_loop.metrics import world_model_loss
from hope_models.components.mid_loop.model import MidLoopConfig, previous_actions
from hope_models.components.vqvae.model import VQVAE, VQVAEConfig

SIDE = 8


def _model(**kw) -> GridMidLoop:
    vq = VQVAE(VQVAEConfig(input="frame", layout="grid", patch=8, n_codes=8, channels=4, groups=SIDE * SIDE,
                           code_dim=SIDE * SIDE * 2))
    cfg = dict(act_dim=2, n_codes=8, obs_dim=2, horizon_steps=(2, 4), d_model=32, d_state=16, dropout=0.0,
               wm_hidden=32)
    return GridMidLoop(MidLoopConfig(**{**cfg, **kw}), vq)


def _arm(b: int, k: int, gen: torch.Generator):
    """Two joints that turn by the held action (held for a few points); the codes say nothing of it."""
    act = torch.randn(b, k, 2, generator=gen).repeat_interleave(3, 1)[:, :k]
    q = torch.cumsum(0.5 * act, 1) - 0.5 * act + torch.randn(b, 1, 2, generator=gen)  # q_{k+1} = q_k + 0.5 act_k
    codes = torch.randint(0, 8, (b, 1, SIDE * SIDE), generator=gen).expand(b, k, -1)
    return codes, act, q, torch.ones(b, k, dtype=torch.bool)


def test_the_grid_world_model_learns_the_joints_after_each_held_action():
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    model = _model()
    assert model.has_world_model and {n.split(".")[0] for n, _ in model.named_parameters() if n.startswith("wm_")} \
        == {"wm_enc", "wm_cell", "wm_out"}
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], 3e-3)
    first = None
    for _ in range(150):
        codes, act, q, mask = _arm(32, 10, gen)
        y = model.context(codes, previous_actions(act), q, mask)
        loss, m = world_model_loss(model, y, q, act, mask, 0.1)
        first = first if first is not None else m["wm_obs_mse"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        codes, act, q, mask = _arm(64, 10, gen)
        _, m = world_model_loss(model, model.context(codes, previous_actions(act), q, mask), q, act, mask, 0.1)
    assert m["wm_obs_mse"] < 0.2 * first and m["wm_obs_mse"] < 0.2 * m["wm_copy_obs_mse"], (first, m)
    assert {"wm_obs_mse_0.1s", "wm_copy_obs_mse_0.4s"} <= set(m)


def test_a_grid_mid_loop_without_the_world_model_is_what_older_checkpoints_hold():
    assert not _model(grid_world_model=0).has_world_model and not _model(wm_horizon=0).has_world_model
    assert spec_of("mid_loop").stored_config({"d_model": 8})["grid_world_model"] == 0
    assert spec_of("mid_loop").stored_config({"grid_world_model": 1})["grid_world_model"] == 1


def test_the_mid_loop_component_adds_the_world_models_loss_for_a_grid(tmp_path):
    from frame_fixtures import camera_checkpoints
    from grid_mid_fixtures import grid_mid_component

    comp = grid_mid_component(camera_checkpoints(tmp_path, "grid")["vq"])
    model = comp.model
    assert isinstance(model, GridMidLoop) and model.has_world_model
    gen = torch.Generator().manual_seed(1)
    codes = torch.randint(0, model.cfg.n_codes, (3, 20, model.groups), generator=gen)
    act, q = torch.randn(3, 20, 2, generator=gen), torch.randn(3, 20, 4, generator=gen)
    mask = torch.ones(3, 20, dtype=torch.bool)
    y = model.context(codes, previous_actions(act), q, mask)
    base = torch.tensor(1.0)
    loss, metrics = comp._with_world_model(model, base, {}, y, q, act, mask)
    wm, _ = world_model_loss(model, y, q, act, mask, 0.1)
    assert abs(float(loss.detach()) - float((base + model.cfg.wm_weight * wm).detach())) < 1e-6 and metrics["wm_obs_mse"] > 0
    assert "wm_obs_mse_0.1s" in metrics  # labelled with the window's grid step
