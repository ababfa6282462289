"""The diagonal SSM: parallel (scan) and recurrent forms agree, masks, chunking, stability, determinism."""
from __future__ import annotations

import pytest
import torch

from hope_models.components.ssm import DiagonalSSM, SSMBlock, SSMConfig, SSMStack, WindowSSM

TOL = 1e-5


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _step_layer(layer: DiagonalSSM, u: torch.Tensor, h: torch.Tensor | None = None):
    h = u.new_zeros(u.shape[0], layer.d_state) if h is None else h
    ys = []
    for t in range(u.shape[1]):
        y, h = layer.step(u[:, t], h)
        ys.append(y)
    return torch.stack(ys, 1), h


@pytest.mark.parametrize("length", [1, 5, 20, 64])
def test_layer_scan_and_step_agree(length):
    torch.manual_seed(0)
    layer = DiagonalSSM(32, 16)
    u = torch.randn(3, length, 32)
    y_scan, h_scan = layer(u)
    y_step, h_step = _step_layer(layer, u)
    assert y_scan.shape == (3, length, 32) and h_scan.shape == (3, 16)
    assert (y_scan - y_step).abs().max().item() < TOL
    assert (h_scan - h_step).abs().max().item() < TOL
    assert y_scan.abs().max().item() > 0.1  # a real signal, not two zeros agreeing


def test_layer_matches_the_recurrence_written_out():
    torch.manual_seed(1)
    layer = DiagonalSSM(4, 3)
    u = torch.randn(2, 6, 4)
    a = torch.exp(-torch.exp(layer.log_rate))
    g = torch.sqrt(1 - a * a)
    h = torch.zeros(2, 3)
    expected = []
    for t in range(6):
        h = a * h + g * (u[:, t] @ layer.B.t())
        expected.append(h @ layer.C.t() + layer.D * u[:, t])
    y, _ = layer(u)
    torch.testing.assert_close(y, torch.stack(expected, 1), atol=TOL, rtol=0)
    assert ((a > 0) & (a < 1)).all()


def test_long_inputs_run_in_chunks_carrying_the_state_and_an_initial_state_is_honoured():
    torch.manual_seed(2)
    layer = DiagonalSSM(8, 8, chunk=7)  # 50 steps = 8 chunks
    u = torch.randn(2, 50, 8)
    h0 = torch.randn(2, 8)
    y_scan, h_scan = layer(u, h0)
    y_step, h_step = _step_layer(layer, u, h0)
    assert (y_scan - y_step).abs().max().item() < TOL and (h_scan - h_step).abs().max().item() < TOL
    y_zero, _ = layer(u)
    assert (y_scan - y_zero).abs().max().item() > 1e-3  # h0 changed the output


def test_decays_stay_in_the_unit_interval_for_extreme_parameters():
    layer = DiagonalSSM(4, 4)
    with torch.no_grad():
        layer.log_rate.copy_(torch.tensor([-30.0, -5.0, 3.0, 30.0]))
    y, h = layer(torch.randn(1, 64, 4))
    assert torch.isfinite(y).all() and torch.isfinite(h).all()
    a = torch.exp(layer.log_a())
    assert (a >= 0).all() and (a <= 1).all()


def test_block_and_stack_scan_and_step_agree():
    torch.manual_seed(3)
    cfg = SSMConfig(d_model=32, d_state=16, n_layers=3)
    block = SSMBlock(cfg)
    x = torch.randn(4, 20, 32)
    y_scan, h_scan = block(x)
    h = torch.zeros(4, 16)
    ys = []
    for t in range(20):
        y, h = block.step(x[:, t], h)
        ys.append(y)
    assert (y_scan - torch.stack(ys, 1)).abs().max().item() < TOL and (h_scan - h).abs().max().item() < TOL

    stack = SSMStack(cfg)
    y_scan, s_scan = stack(x)
    state = stack.init_state(4)
    ys = []
    for t in range(20):
        y, state = stack.step(x[:, t], state)
        ys.append(y)
    assert s_scan.shape == (3, 4, 16)
    assert (y_scan - torch.stack(ys, 1)).abs().max().item() < TOL
    assert (s_scan - state).abs().max().item() < TOL


def test_a_masked_prefix_is_a_fresh_state():
    """Window points before an episode's first step must not move the state in any layer."""
    torch.manual_seed(4)
    stack = SSMStack(SSMConfig(d_model=16, d_state=8, n_layers=2))
    x = torch.randn(1, 10, 16)
    mask = torch.tensor([[False] * 4 + [True] * 6])
    y_masked, s_masked = stack(x, mask)
    y_valid, s_valid = stack(x[:, 4:])
    assert (y_masked[:, 4:] - y_valid).abs().max().item() < TOL
    assert (s_masked - s_valid).abs().max().item() < TOL
    y_unmasked, _ = stack(x)
    assert (y_unmasked[:, 4:] - y_valid).abs().max().item() > 1e-3  # the prefix does matter unmasked


def test_same_seed_same_model_and_output_bitwise():
    def run():
        torch.manual_seed(7)
        stack = SSMStack(SSMConfig(d_model=16, d_state=8))
        x = torch.randn(2, 12, 16)
        y, _ = stack(x)
        y.square().mean().backward()
        return y.detach(), stack.blocks[0].ssm.log_rate.grad.clone()

    (y1, g1), (y2, g2) = run(), run()
    assert torch.equal(y1, y2) and torch.equal(g1, g2)
    assert torch.isfinite(g1).all() and g1.abs().sum() > 0  # decays are learned


# -- WindowSSM: the same recurrence over exactly the last K inputs ----------------------------

def test_window_layer_matches_the_recurrence_restarted_k_points_back():
    torch.manual_seed(8)
    k = 4
    layer = WindowSSM(6, 5, window=k)
    u = torch.randn(2, 11, 6)
    a = torch.exp(layer.log_a())
    g = torch.sqrt((1 - a * a) / (1 - a ** (2 * k)))
    expected = []
    for t in range(11):
        h = torch.zeros(2, 5)  # zero state at the window's start, then the plain recurrence
        for s in range(max(0, t - k + 1), t + 1):
            h = a * h + g * (u[:, s] @ layer.B.t())
        expected.append(h @ layer.C.t() + layer.D * u[:, t])
    y, hs = layer(u)
    torch.testing.assert_close(y, torch.stack(expected, 1), atol=TOL, rtol=0)
    assert hs.shape == (2, 11, 5)
    y_alone, _ = layer(u[:, 5:9])  # the window ending at point 8 alone gives the same output there
    assert (y_alone[:, -1] - y[:, 8]).abs().max().item() < TOL


@pytest.mark.parametrize("k", [1, 3, 7])
def test_window_layer_stepped_equals_the_parallel_form_at_every_point(k):
    torch.manual_seed(9)
    layer = WindowSSM(16, 12, window=k)
    u = 2.0 * torch.randn(3, 300, 16)
    with torch.no_grad():
        y_par, h_par = layer(u)
        state = layer.init_state(3)
        for t in range(300):
            y, state = layer.step(u[:, t], state)
            assert (y - y_par[:, t]).abs().max().item() < TOL, t
            assert (state.h - h_par[:, t]).abs().max().item() < TOL, t
    assert state.ring.shape == (3, k, 12) and state.pos == 300 % k  # O(K) state, whatever the run length
    assert y_par.abs().max().item() > 0.1


def test_window_layer_decays_stay_strictly_inside_the_unit_interval():
    layer = WindowSSM(4, 4, window=5)
    with torch.no_grad():
        layer.log_rate.copy_(torch.tensor([-60.0, -5.0, 3.0, 60.0]))
    a = torch.exp(layer.log_a())
    assert ((a > 0) & (a < 1)).all()  # never 1: the rounding of the subtraction always decays
    y, h = layer(torch.randn(1, 64, 4))
    assert torch.isfinite(y).all() and torch.isfinite(h).all()
    y.square().mean().backward()
    assert torch.isfinite(layer.log_rate.grad).all()
    layer.zero_grad()
    layer.log_rate.data.zero_()
    layer(torch.randn(1, 8, 4))[0].square().mean().backward()
    assert layer.log_rate.grad.abs().sum() > 0  # decays are learned
    with pytest.raises(ValueError, match="window=0"):
        WindowSSM(4, 4, window=0)
