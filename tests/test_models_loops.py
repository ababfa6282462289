"""Fast and Mid Loop models: window forward vs one-tick stepping, masks, action shifting, targets."""
from __future__ import annotations

import math

import pytest
import torch

from hope_models.components.fast_loop.model import FastLoop, FastLoopConfig
from hope_models.components.mid_loop.model import MidLoop, MidLoopConfig, previous_actions
from hope_models.components.mid_loop.metrics import mid_loop_loss
from hope_models.components.ssm import count_params
from hope_models.components.vqvae.model import VQVAE, VQVAEConfig

TOL = 1e-5


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _trained_looking_vq(**kw) -> VQVAE:
    vq = VQVAE(VQVAEConfig(**{"obs_dim": 20, "n_codes": 16, "code_dim": 8, "hidden": 32, "groups": 1, **kw}))
    x = (torch.randint(0, 256, (64, *vq.cfg.frame_shape), dtype=torch.uint8) if vq.cfg.input == "frame"
         else torch.randn(64, 20))
    vq(x, init_codebook=True)  # a seeded codebook, so codes vary
    return vq


def _step_fast(model: FastLoop, obs, frames=None):
    state = model.init_state(obs.shape[0])
    for t in range(obs.shape[1]):
        act, state = model.step(obs[:, t], state, None if frames is None else frames[:, t])
    return act


def test_default_fast_loop_is_small_enough_for_the_pi():
    torch.manual_seed(0)
    model = FastLoop(FastLoopConfig(obs_dim=20, act_dim=6))
    assert count_params(model) < 500_000
    assert "M trainable parameters" in model.describe()
    vq = _trained_looking_vq(n_codes=128)
    assert count_params(FastLoop(FastLoopConfig(obs_dim=20, act_dim=6, n_codes=128), vq), trainable_only=True) < 500_000


@pytest.mark.parametrize("with_vq", [False, True])
def test_fast_loop_stepping_through_a_window_gives_forwards_action(with_vq):
    torch.manual_seed(1)
    vq = _trained_looking_vq() if with_vq else None
    model = FastLoop(FastLoopConfig(obs_dim=20, act_dim=6, n_codes=16 if with_vq else 0), vq)
    obs = torch.randn(8, 5, 20)
    action = model(obs, torch.ones(8, 5, dtype=torch.bool))
    assert action.shape == (8, 6)
    assert (action - _step_fast(model, obs)).abs().max().item() < TOL
    if with_vq:
        assert len(torch.unique(model.codes(obs))) > 1


def test_fast_loop_with_a_masked_prefix_equals_stepping_from_the_episode_start():
    torch.manual_seed(2)
    model = FastLoop(FastLoopConfig(obs_dim=20, act_dim=6))
    obs = torch.randn(2, 5, 20)
    obs[0, :3] = 0.0  # window at an episode's third step: the first points are zero-filled and masked
    mask = torch.ones(2, 5, dtype=torch.bool)
    mask[0, :3] = False
    action = model(obs, mask)
    assert (action[0] - _step_fast(model, obs[:1, 3:])[0]).abs().max().item() < TOL
    assert (action[1] - _step_fast(model, obs[1:])[0]).abs().max().item() < TOL


def _trailing_windows(stream: torch.Tensor, ticks: list[int], episode_start: int, k: int):
    """forward()'s inputs at each tick, as make_windows builds them: the K points ending at the
    tick, those before the episode's start masked and zero-filled."""
    obs = torch.zeros(len(ticks), stream.shape[0], k, stream.shape[-1])
    mask = torch.zeros(len(ticks), stream.shape[0], k, dtype=torch.bool)
    for i, t in enumerate(ticks):
        for j in range(k):
            s = t - (k - 1) + j
            if s >= episode_start:
                obs[i, :, j] = stream[:, s]
                mask[i, :, j] = True
    return obs.flatten(0, 1), mask.flatten(0, 1)


@pytest.mark.parametrize("decays", ["init", "extreme"])
def test_fast_loop_stepped_for_2000_ticks_equals_forward_on_each_trailing_window(decays):
    """The inference contract: init_state() at an episode's start, then one step() per control tick,
    for as long as the robot runs; every action must be forward() over the last K observations."""
    torch.manual_seed(5)
    k, n, restart = 5, 2000, 1234  # a second episode starts at tick 1234: init_state() again
    model = FastLoop(FastLoopConfig(obs_dim=20, act_dim=6, window_k=k))
    if decays == "extreme":  # decays at both clamps (a ~ 0.9999 and a ~ 0) and beyond: the worst
        with torch.no_grad():  # cases for the subtracted a^K term and for rounding drift
            model.ssm.log_rate[0::3] = -40.0
            model.ssm.log_rate[1::3] = 40.0
    stream = 3.0 * torch.randn(2, n, 20)
    checked = sorted({*range(50), *range(0, n, 10), *range(restart, restart + 12), n - 1})
    stepped = {}
    with torch.no_grad():
        state = model.init_state(2)
        for t in range(n):
            if t == restart:
                state = model.init_state(2)
            action, state = model.step(stream[:, t], state)
            if t in checked:
                stepped[t] = action
        assert state.ring.shape == (2, k, model.cfg.d_state) and state.h.shape == (2, model.cfg.d_state)
        for start, ticks in ((0, [t for t in checked if t < restart]), (restart, [t for t in checked if t >= restart])):
            obs, mask = _trailing_windows(stream, ticks, start, k)
            want = model(obs, mask).unflatten(0, (len(ticks), 2))
            got = torch.stack([stepped[t] for t in ticks])
            err = (got - want).abs().amax(dim=(1, 2))
            assert err.max().item() < TOL, f"worst tick {ticks[int(err.argmax())]}: {err.max().item():.2e}"
        # not vacuous: the window's oldest point matters (a K-1 point window gives another action),
        # and nothing older does (forward() over 3 more points gives the same action)
        late = _trailing_windows(stream, [n - 1], 0, k)
        assert (model(late[0][:, 1:], late[1][:, 1:]) - stepped[n - 1]).abs().max().item() > 1e-3
        longer = _trailing_windows(stream, [n - 1], 0, k + 3)
        assert (model(*longer) - stepped[n - 1]).abs().max().item() < TOL
        # the masked history at an episode start matters too: the window without its mask differs
        obs, _ = _trailing_windows(stream, [restart + 2], 0, k)
        assert (model(obs) - stepped[restart + 2]).abs().max().item() > 1e-3


def test_fast_loop_actions_at_every_point_are_the_trailing_windows_actions():
    torch.manual_seed(6)
    model = FastLoop(FastLoopConfig(obs_dim=20, act_dim=6, window_k=4))
    stream = torch.randn(1, 30, 20)
    with torch.no_grad():
        every = model.actions(stream)
        obs, mask = _trailing_windows(stream, list(range(30)), 0, 4)
        torch.testing.assert_close(every[0], model(obs, mask), atol=TOL, rtol=0)
        state = model.init_state(1)
        for t in range(30):
            action, state = model.step(stream[:, t], state)
            assert (action[0] - every[0, t]).abs().max().item() < TOL


def test_fast_loop_stepping_never_mutates_the_state_it_was_given():
    torch.manual_seed(7)
    model = FastLoop(FastLoopConfig(obs_dim=20, act_dim=6))
    obs = torch.randn(8, 1, 20)
    with torch.no_grad():
        state = model.init_state(1)
        for t in range(7):
            _, state = model.step(obs[t], state)
        before = (state.h.clone(), state.ring.clone(), state.pos)
        a1, _ = model.step(obs[7], state)
        a2, _ = model.step(obs[7], state)  # the same tick again from the same state: e.g. a retry
    assert torch.equal(a1, a2)
    assert torch.equal(state.h, before[0]) and torch.equal(state.ring, before[1]) and state.pos == before[2]


def test_fast_loop_with_a_frame_vqvae_reads_frames_in_both_forms():
    torch.manual_seed(3)
    vq = _trained_looking_vq(input="frame", channels=4)
    model = FastLoop(FastLoopConfig(obs_dim=20, act_dim=6, n_codes=16), vq)
    assert model.wants_frames
    obs = torch.randn(2, 5, 20)
    frames = torch.randint(0, 256, (2, 5, 64, 64, 3), dtype=torch.uint8)
    action = model(obs, None, frames)
    assert (action - _step_fast(model, obs, frames)).abs().max().item() < TOL
    with pytest.raises(ValueError, match="pass frames"):
        model(obs)
    assert all(not p.requires_grad for p in model.vqvae.parameters())
    assert count_params(model, trainable_only=True) < count_params(model)


def test_fast_loop_refuses_a_codebook_size_that_does_not_match_its_vqvae():
    vq = _trained_looking_vq()
    with pytest.raises(ValueError, match="n_codes"):
        FastLoop(FastLoopConfig(obs_dim=20, act_dim=6, n_codes=32), vq)
    with pytest.raises(ValueError, match="n_codes"):
        FastLoop(FastLoopConfig(obs_dim=20, act_dim=6, n_codes=16), None)


def test_previous_actions_drop_the_anchors_own_action():
    act = torch.arange(1, 7, dtype=torch.float32).reshape(1, 3, 2)
    prev = previous_actions(act)
    assert prev.tolist() == [[[0, 0], [1, 2], [3, 4]]]


def test_mid_loop_stepping_gives_forwards_logits_at_every_point():
    torch.manual_seed(4)
    vq = _trained_looking_vq(groups=2)
    model = MidLoop(MidLoopConfig(act_dim=6, n_codes=16, horizon_steps=(2, 4)), vq).eval()  # eval: no dropout
    codes = torch.randint(0, 16, (3, 20, 2))
    prev = previous_actions(torch.randn(3, 20, 6))
    logits = model(codes, prev, torch.ones(3, 20, dtype=torch.bool))
    assert logits.shape == (3, 20, 2, 2, 16)
    state = model.init_state(3)
    for t in range(20):
        step_logits, state = model.step(codes[:, t], prev[:, t], state)
        assert (step_logits - logits[:, t]).abs().max().item() < TOL


def _mid(horizons=(2,), n_codes=8, groups=1):
    vq = _trained_looking_vq(n_codes=n_codes, groups=groups, code_dim=8)
    return MidLoop(MidLoopConfig(act_dim=6, n_codes=n_codes, horizon_steps=horizons), vq).eval()


def test_mid_loop_targets_and_copy_last_baseline_by_hand():
    model = _mid()
    codes = torch.tensor([[0, 1, 2, 3, 4, 5]])[..., None]  # [B, K, G=1]
    mask = torch.ones(1, 6, dtype=torch.bool)
    # perfect logits for horizon 2: the code two points later
    logits = torch.full((1, 6, 1, 1, 8), -20.0)
    for k in range(4):
        logits[0, k, 0, 0, codes[0, k + 2, 0]] = 20.0
    loss, m = mid_loop_loss(model, logits, codes, mask, training=False)
    assert m["targets"] == 4
    assert m["accuracy"] == 1.0 and m["copy_last_accuracy"] == 0.0 and loss.item() < 1e-6

    still = torch.full((1, 6, 1), 7)  # nothing changes: copying the last code is always right
    _, m = mid_loop_loss(model, logits, still, mask, training=False)
    assert m["copy_last_accuracy"] == 1.0 and m["accuracy"] == 0.0

    masked = torch.tensor([[False, False, True, True, True, True]])  # window starts before the episode
    _, m = mid_loop_loss(model, logits, codes, masked, training=False)
    assert m["targets"] == 2  # only points 2 and 3 (targets 4 and 5) are real pairs

    # beyond the window: the anchor's future code, where the episode still runs
    model2 = _mid(horizons=(10, 20), n_codes=10)
    future = torch.tensor([[7, 9]])[..., None]
    logits2 = torch.zeros(1, 6, 2, 1, 10)
    logits2[0, -1, 0, 0, 7] = 5.0
    _, m = mid_loop_loss(model2, logits2, codes, mask, future_codes=future,
                         future_mask=torch.tensor([[True, False]]), training=False)
    assert m["targets"] == 1
    assert m["anchor_accuracy"] == 1.0 and m["anchor_copy_last_accuracy"] == 0.0
    # no target at all (window shorter than the horizons, no futures): a zero loss, not a crash
    empty = logits2.clone().requires_grad_(True)
    loss, m = mid_loop_loss(model2, empty, codes, mask, training=False)
    assert loss.item() == 0.0 and m["targets"] == 0
    loss.backward()
    assert empty.grad is not None and (empty.grad == 0).all()


def test_mid_loop_baselines_are_counted_on_training_targets_only():
    """copy-last: P(stay) from the training targets' stays, the rest spread over the other codes;
    code frequency: Laplace-smoothed training frequencies. Evaluation never changes the counts."""
    model = _mid(n_codes=4)
    codes = torch.tensor([[0, 0, 0, 1, 1, 2]])[..., None]  # horizon 2 pairs: (0,0) (0,1) (0,1) (1,2)
    mask = torch.ones(1, 6, dtype=torch.bool)
    logits = torch.zeros(1, 6, 1, 1, 4)  # uniform: nll = ln 4 per target
    loss, m = mid_loop_loss(model, logits, codes, mask, training=True)
    assert model.stay_counts[0, 0].tolist() == [3.0, 1.0]  # [changed, stayed]
    assert model.code_counts[0].tolist() == [1.0, 2.0, 1.0, 0.0]  # targets 0, 1, 1, 2
    assert abs(loss.item() - math.log(4)) < 1e-6
    before = (model.stay_counts.clone(), model.code_counts.clone())
    _, m = mid_loop_loss(model, logits, codes, mask, training=False)
    assert torch.equal(model.stay_counts, before[0]) and torch.equal(model.code_counts, before[1])
    p_stay = (1 + 1) / (4 + 2)  # Laplace over [changed, stayed]
    copy = [p_stay, (1 - p_stay) / 3, (1 - p_stay) / 3, (1 - p_stay) / 3]
    freq = [(c + 1) / (4 + 4) for c in (1, 2, 2, 1)]  # P(target) of targets 0, 1, 1, 2
    assert abs(m["copy_last_nll"] - sum(-math.log(p) for p in copy) / 4) < 1e-5
    assert abs(m["code_freq_nll"] - sum(-math.log(p) for p in freq) / 4) < 1e-5
    assert abs(m["nll"] - math.log(4)) < 1e-6 and "nll_2steps" in m


def test_mid_loop_decoded_prediction_against_copy_last_observation():
    """obs_mse is the error of the expected decoded observation; copy_last_obs_mse the error of the
    real current observation; with one-hot logits the prediction is that code's reconstruction."""
    model = _mid(n_codes=8)
    obs = torch.randn(1, 6, 20)
    codes = model.codes(obs)
    mask = torch.ones(1, 6, dtype=torch.bool)
    logits = torch.full((1, 6, 1, 1, 8), -30.0)
    for k in range(4):
        logits[0, k, 0, 0, codes[0, k + 2, 0]] = 30.0
    _, m = mid_loop_loss(model, logits, codes, mask, obs=obs, training=False)
    recon = model.vqvae.decode(codes[0, 2:])
    assert abs(m["obs_mse"] - float(((recon - obs[0, 2:]) ** 2).mean())) < 1e-5
    assert abs(m["copy_last_obs_mse"] - float(((obs[0, :4] - obs[0, 2:]) ** 2).mean())) < 1e-5
    _, m = mid_loop_loss(model, logits, codes, mask, obs=obs, training=True)
    assert "obs_mse" not in m  # training batches skip the decoding


# -- the Mid Loop's action-conditioned world model (wm_*) ------------------------------------------

def _mid_wm(horizon=3):
    vq = _trained_looking_vq()
    return MidLoop(MidLoopConfig(act_dim=6, n_codes=16, horizon_steps=(2,), wm_horizon=horizon, wm_hidden=16), vq).eval()


def test_world_model_parameters_are_all_wm_and_leave_the_rest_as_it_was():
    with_wm, without = _mid_wm(), MidLoop(MidLoopConfig(act_dim=6, n_codes=16, horizon_steps=(2,), wm_horizon=0),
                                          _trained_looking_vq())
    extra = set(with_wm.state_dict()) - set(without.state_dict())
    assert extra and all(k.startswith("wm_") for k in extra)  # the torch-free runtime skips exactly these
    assert set(without.state_dict()) <= set(with_wm.state_dict()) and not without.has_world_model
    # a frame VQ-VAE gets no world model (it predicts observation vectors)
    frame = MidLoop(MidLoopConfig(act_dim=6, n_codes=16, horizon_steps=(2,)), _trained_looking_vq(input="frame"))
    assert not frame.has_world_model and not any(k.startswith("wm_") for k in frame.state_dict())


def test_world_model_is_causal_in_the_actions_and_forward_is_heads_of_context():
    torch.manual_seed(0)
    model = _mid_wm()
    obs, act = torch.randn(2, 8, 20), torch.randn(2, 8, 6)
    codes = model.codes(obs)
    y = model.context(codes, previous_actions(act))
    assert torch.allclose(model(codes, previous_actions(act)), model.heads(y))
    acts = torch.randn(2, 3, 6)
    pred = model.wm_predict(y[:, -1], obs[:, -1], acts)
    assert pred.shape == (2, 3, 20)
    later = acts.clone()
    later[:, 1:] = torch.randn(2, 2, 6)  # other actions after the first: the first prediction must not move
    pred2 = model.wm_predict(y[:, -1], obs[:, -1], later)
    assert torch.equal(pred[:, 0], pred2[:, 0]) and not torch.allclose(pred[:, 1], pred2[:, 1])
    # the planner's path (encode once, unroll many candidates) is wm_predict
    h = model.wm_encode(y[:, -1], obs[:, -1])[:, None]
    many = model.wm_unroll(h, obs[:, -1, None], torch.stack([acts, later], 1))
    assert torch.allclose(many[:, 0], pred, atol=TOL) and torch.allclose(many[:, 1], pred2, atol=TOL)


def test_world_model_loss_targets_by_hand_and_it_never_trains_the_ssm():
    from hope_models.components.mid_loop.metrics import world_model_loss

    torch.manual_seed(0)
    model = _mid_wm(horizon=3).train()
    obs, act = torch.randn(2, 6, 20), torch.randn(2, 6, 6)
    mask = torch.ones(2, 6, dtype=torch.bool)
    mask[1, :2] = False  # the pre-episode prefix: points 2..5 are real
    y = model.context(model.codes(obs), previous_actions(act), mask)
    loss, m = world_model_loss(model, y, obs, act, mask, grid_step_s=0.1)
    assert m["wm_targets"] == 3 + 1  # points k with k+3 in the window: 0,1,2 and, in the second row, 2
    assert set(m) >= {"wm_obs_mse", "wm_copy_obs_mse", "wm_obs_mse_0.1s", "wm_obs_mse_0.3s", "wm_copy_obs_mse_0.2s"}
    # the first target by hand: obs at 1..3 from obs 0, actions 0..2
    pred = model.wm_predict(y[0, 0], obs[0, 0], act[0, :3])
    assert m["wm_copy_obs_mse_0.1s"] == pytest.approx(float(((torch.cat([obs[0, :3], obs[1, 2:3]])
                                                              - torch.cat([obs[0, 1:4], obs[1, 3:4]])) ** 2).mean()),
                                                      rel=1e-5)
    assert torch.isfinite(pred).all()
    loss.backward()
    assert all(p.grad is None for p in model.ssm.parameters())  # the context is detached
    assert all(p.grad is not None for n, p in model.named_parameters() if n.startswith("wm_"))
    short, m = world_model_loss(model, y[:, :3], obs[:, :3], act[:, :3], mask[:, :3])
    assert m["wm_targets"] == 0 and float(short.detach()) == 0.0
