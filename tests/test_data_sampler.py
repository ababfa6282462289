"""The resumable anchor sampler: exact resume, imagined ratio, validation split by episode."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hope_models.data.cache import load_or_build
from hope_models.data.sampler import (
    MIN_VAL_EPISODES,
    AnchorSampler,
    is_validation_episode,
    split_episodes,
    validation_mask,
)

REPO = Path(__file__).resolve().parents[1]


from hope_models.data import synthetic as gen  # noqa: E402


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """40 episodes, a quarter of them imagined (origin imagined:*, tag continuon.imagined)."""
    ds = tmp_path_factory.mktemp("mixed")
    gen.generate_dataset(ds, 6000, obs_dim=4, act_dim=2, seed=2, episode_seconds=(2, 6), imagined_fraction=0.25)
    cache, _ = load_or_build(ds, tmp_path_factory.mktemp("cache"))
    return cache


def test_restored_sampler_draws_exactly_the_batches_it_would_have_drawn(mixed):
    full = AnchorSampler(mixed, 64, seed=11, imagined_ratio=0.25)
    ten = [full.next_batch() for _ in range(10)]
    first = AnchorSampler(mixed, 64, seed=11, imagined_ratio=0.25)
    for _ in range(4):
        first.next_batch()
    state = json.loads(json.dumps(first.state_dict()))  # as it travels in a checkpoint
    resumed = AnchorSampler(mixed, 64, seed=11, imagined_ratio=0.25)
    resumed.load_state_dict(state)
    for b in range(4, 10):
        np.testing.assert_array_equal(resumed.next_batch(), ten[b])
    other_seed = AnchorSampler(mixed, 64, seed=12, imagined_ratio=0.25)
    assert not np.array_equal(other_seed.batch(0), ten[0])


def test_a_state_from_another_configuration_is_refused(mixed):
    state = AnchorSampler(mixed, 64, seed=1).state_dict()
    with pytest.raises(ValueError, match="seed was 1, now 2"):
        AnchorSampler(mixed, 64, seed=2).load_state_dict(state)
    with pytest.raises(ValueError, match="batch_size was 64, now 32"):
        AnchorSampler(mixed, 32, seed=1).load_state_dict(state)


def test_one_epoch_visits_every_eligible_anchor_once(mixed):
    s = AnchorSampler(mixed, 64, seed=0, split="all")  # imagined_ratio 0: real episodes only
    real = np.flatnonzero(~mixed.imagined[mixed.episode_of(np.arange(mixed.n_steps))])
    n = len(real)
    assert s.anchors_per_epoch == n
    drawn = [s.next_batch() for _ in range(-(-n // 64))]
    assert all(np.all(np.diff(b) >= 0) for b in drawn)  # each batch ascending
    within_epoch = np.concatenate(drawn[:-1])  # the last batch reaches into the next epoch
    assert len(np.unique(within_epoch)) == len(within_epoch)
    assert np.array_equal(np.unique(np.concatenate(drawn)), real)


def test_imagined_share_of_every_batch_follows_the_ratio(mixed):
    imagined_steps = mixed.imagined[mixed.episode_of(np.arange(mixed.n_steps))]
    assert 0 < imagined_steps.sum() < mixed.n_steps
    quarter = AnchorSampler(mixed, 64, seed=4, imagined_ratio=0.25)
    assert all(imagined_steps[quarter.next_batch()].sum() == 16 for _ in range(30))
    tenth = AnchorSampler(mixed, 64, seed=4, imagined_ratio=0.1)
    counts = [int(imagined_steps[tenth.next_batch()].sum()) for _ in range(100)]
    assert sum(counts) == 640 and set(counts) <= {6, 7}  # 6.4 per batch on average, exactly
    real_only = AnchorSampler(mixed, 64, seed=4)
    assert all(imagined_steps[real_only.next_batch()].sum() == 0 for _ in range(30))
    only_imagined = AnchorSampler(mixed, 64, seed=4, imagined_ratio=1.0)
    assert imagined_steps[only_imagined.next_batch()].all()


def test_asking_for_imagined_data_that_does_not_exist_is_an_error(tmp_path):
    ds = tmp_path / "ds"
    gen.generate_dataset(ds, 500, obs_dim=2, act_dim=1, episode_seconds=(2, 4))
    cache, _ = load_or_build(ds, tmp_path / "c")
    with pytest.raises(ValueError, match=r"imagined_ratio=0.2 asks for imagined episodes, but the train split .* "
                                         r"0 imagined"):
        AnchorSampler(cache, 8, imagined_ratio=0.2)
    with pytest.raises(ValueError, match="imagined_ratio"):
        AnchorSampler(cache, 8, imagined_ratio=1.5)


def test_validation_split_is_by_episode_and_deterministic(mixed):
    train = set(split_episodes(mixed, "train", 0.2).tolist())
    val = set(split_episodes(mixed, "val", 0.2).tolist())
    assert train and val and not train & val and train | val == set(range(mixed.n_episodes))
    assert val == set(np.flatnonzero(validation_mask(mixed.episode_ids, 0.2)).tolist())
    s = AnchorSampler(mixed, 32, seed=0, split="val", val_fraction=0.2)
    eps = set(mixed.episode_of(np.concatenate([s.next_batch() for _ in range(20)])).tolist())
    assert eps <= val
    # membership depends on the id alone, so adding episodes never moves existing ones
    assert is_validation_episode("ep_00003_10hz", 0.2) == is_validation_episode("ep_00003_10hz", 0.2)
    assert sum(is_validation_episode(f"episode-{i}", 0.2) for i in range(2000)) == pytest.approx(400, abs=60)


def test_a_small_dataset_holds_out_at_least_three_episodes_and_growth_only_moves_them_to_training():
    ids = [f"demo-{i}" for i in range(10)]
    hashed = [is_validation_episode(e, 0.1) for e in ids]
    val = validation_mask(ids, 0.1)
    assert int(val.sum()) == max(MIN_VAL_EPISODES, sum(hashed)) and all(val[i] for i, h in enumerate(hashed) if h)
    assert int(validation_mask(ids[:5], 0.1).sum()) >= 1  # a third of 5
    assert not validation_mask(ids, 0.0).any()  # no validation asked for: none
    grown = [f"demo-{i}" for i in range(200)]
    big = validation_mask(grown, 0.1)
    for i in range(10):  # an episode held out of the big set was held out of the small one too
        assert not big[i] or val[i]


def test_min_history_and_horizon_restrict_anchors(mixed):
    s = AnchorSampler(mixed, 64, seed=0, split="all", min_history_s=1.0, horizon_s=0.5)
    a = np.concatenate([s.next_batch() for _ in range(40)])
    ep = mixed.episode_of(a)
    assert (mixed.t[a] >= 1.0 - 1e-9).all()
    assert (mixed.t[a] <= mixed.durations[ep] - 0.5 + 1e-9).all()


def _block_of(sampler, anchors):
    """Block index (of the pool's consecutive steps) of each anchor."""
    rows = sampler.anchor_group[1]
    return np.searchsorted(sampler.real.steps, anchors) // rows


def test_anchors_by_block_are_an_exact_permutation_whose_batches_share_blocks(mixed):
    s = AnchorSampler(mixed, 64, seed=5, split="all", anchors_per_block=4)
    k, rows = s.anchor_group
    assert k == 4 and rows % 4 == 0 and rows > 4
    assert AnchorSampler(mixed, 64, seed=5, split="all").anchor_group == (1, 1)  # the default: anchors alone
    n = s.anchors_per_epoch
    drawn = [s.next_batch() for _ in range(-(-n // 64))]
    within_epoch = np.concatenate(drawn[:-1])  # the last batch reaches into the next epoch
    assert len(np.unique(within_epoch)) == len(within_epoch)  # no anchor twice an epoch
    assert np.array_equal(np.unique(np.concatenate(drawn)), s.real.steps)  # every anchor, every block
    for b in drawn[:-1]:  # the last batch holds the one short tuple and reaches into the next epoch
        _, counts = np.unique(_block_of(s, b), return_counts=True)
        assert (counts % 4 == 0).all()  # 4 anchors a block (8 when two of its tuples land in one batch)
    again = AnchorSampler(mixed, 64, seed=5, split="all", anchors_per_block=4)
    assert all(np.array_equal(again.batch(i), drawn[i]) for i in (0, 7, len(drawn) - 1))
    other = AnchorSampler(mixed, 64, seed=6, split="all", anchors_per_block=4)
    assert not np.array_equal(other.batch(0), drawn[0])


def test_a_grouped_sampler_resumes_exactly_and_a_state_of_another_grouping_is_refused(mixed):
    grouped = AnchorSampler(mixed, 32, seed=3, anchors_per_block=4)
    for _ in range(5):
        grouped.next_batch()
    state = json.loads(json.dumps(grouped.state_dict()))
    assert state["anchor_group"] == list(grouped.anchor_group)
    resumed = AnchorSampler(mixed, 32, seed=3, anchors_per_block=4)
    resumed.load_state_dict(state)
    assert all(np.array_equal(resumed.next_batch(), grouped.next_batch()) for _ in range(3))
    with pytest.raises(ValueError, match=r"anchor_group was \[4, \d+\], now \[1, 1\]"):
        AnchorSampler(mixed, 32, seed=3).load_state_dict(state)
    alone = AnchorSampler(mixed, 32, seed=3).state_dict()
    assert "anchor_group" not in alone  # a state from before grouping existed still matches
    with pytest.raises(ValueError, match="anchor_group was \\[1, 1\\]"):
        AnchorSampler(mixed, 32, seed=3, anchors_per_block=4).load_state_dict(alone)
