"""hope_models/train/adamw.py: torch.optim.AdamW's steps and state_dict (what it is for: tests/test_compiler_unloaded.py)."""
from __future__ import annotations

import torch
from torch import nn

from hope_models.checkpoints import flatten_optimizer, unflatten_optimizer
from hope_models.train.adamw import AdamW


def _model(seed: int = 0) -> nn.Module:
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(5, 7), nn.LayerNorm(7), nn.Linear(7, 3), nn.Embedding(4, 3))


def _groups(model: nn.Module) -> list[dict]:
    ps = list(model.parameters())
    return [{"params": [p for p in ps if p.dim() >= 2], "weight_decay": 0.1},
            {"params": [p for p in ps if p.dim() < 2], "weight_decay": 0.0}]


def _step(model: nn.Module, opt, i: int) -> None:
    for g in opt.param_groups:
        g["lr"] = 1e-2 * (1 + i % 3)  # the trainer sets each step's rate in the groups
    g = torch.Generator().manual_seed(100 + i)
    x = torch.randn(8, 5, generator=g)
    loss = model[2](model[1](model[0](x))).pow(2).mean()
    if i % 4 == 0:  # some steps leave the embedding without a gradient
        loss = loss + model[3](torch.tensor([i % 4])).sum()
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()


def _same(a: nn.Module, b: nn.Module) -> None:
    for (name, x), (_, y) in zip(a.state_dict().items(), b.state_dict().items(), strict=True):
        assert torch.equal(x, y), name


def _same_state(a: dict, b: dict) -> None:
    assert a["param_groups"] == b["param_groups"]
    assert a["state"].keys() == b["state"].keys()
    for n in a["state"]:
        assert a["state"][n].keys() == b["state"][n].keys()
        for k in a["state"][n]:
            assert torch.equal(a["state"][n][k], b["state"][n][k]), (n, k)


def test_the_steps_and_the_state_are_torchs_bit_for_bit():
    ours_m, torch_m = _model(), _model()
    ours = AdamW(_groups(ours_m), lr=1e-2, betas=(0.9, 0.95), eps=1e-8)
    ref = torch.optim.AdamW(_groups(torch_m), lr=1e-2, betas=(0.9, 0.95), eps=1e-8)
    for i in range(25):
        _step(ours_m, ours, i)
        _step(torch_m, ref, i)
    _same(ours_m, torch_m)
    _same_state(ours.state_dict(), ref.state_dict())


def test_a_checkpoints_optimizer_state_goes_both_ways_with_torchs():
    """A checkpoint written with torch.optim.AdamW (before this module) resumes here, and the other way."""
    for writer, reader in ((torch.optim.AdamW, AdamW), (AdamW, torch.optim.AdamW)):
        first_m = _model()
        first = writer(_groups(first_m), lr=1e-2, betas=(0.9, 0.95), eps=1e-8)
        for i in range(6):
            _step(first_m, first, i)
        tensors, meta = flatten_optimizer(first.state_dict())  # as a checkpoint holds it
        resumed_m = _model(seed=1)
        resumed_m.load_state_dict(first_m.state_dict())
        resumed = reader(_groups(resumed_m), lr=5.0, betas=(0.5, 0.5), eps=1.0)  # the checkpoint's values win
        resumed.load_state_dict(unflatten_optimizer({k: v.clone() for k, v in tensors.items()}, meta))
        for i in range(6, 12):
            _step(first_m, first, i)
            _step(resumed_m, resumed, i)
        _same(first_m, resumed_m)
        _same_state(first.state_dict(), resumed.state_dict())


def test_a_state_of_another_model_is_refused_naming_what_differs():
    m = _model()
    opt = AdamW(_groups(m), lr=1e-2)
    state = opt.state_dict()
    state["param_groups"][0]["params"] = state["param_groups"][0]["params"][:-1]
    try:
        AdamW(_groups(_model()), lr=1e-2).load_state_dict(state)
    except ValueError as exc:
        assert "a group of 2 parameter(s), the model's has 3" in str(exc)
    else:
        raise AssertionError("a state of another model was loaded")
