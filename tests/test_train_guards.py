"""The memory guard: RSS against the job's budget, soft limit, peak, message, budget validation."""
import math

import psutil
import pytest

from hope_models.train.guards import MemoryGuard, validate_budget_mb

MB = 1024 * 1024


def test_soft_limit_message_and_peak_with_an_injected_rss():
    readings = iter([50 * MB, 89 * MB, 95 * MB, 40 * MB])
    guard = MemoryGuard(100, soft_fraction=0.9, rss_fn=lambda: next(readings))
    first = guard.check()
    assert (first.rss_mb, first.peak_mb, first.over_soft) == (50, 50, False)
    assert not guard.check().over_soft  # 89 MB: just under the 90 MB soft limit
    hit = guard.check()
    assert hit.over_soft and hit.rss_mb == 95 and hit.peak_mb == 95
    for part in ("RSS 95 MB", "soft limit of 90 MB", "100 MB memory budget",
                 "checkpointing and pausing for memory"):
        assert part in hit.message, (part, hit.message)
    after = guard.check()  # memory went back down: not over, but the peak is remembered
    assert not after.over_soft and after.rss_mb == 40 and after.peak_mb == 95
    assert "under the soft limit" in after.message


def test_real_process_rss_against_a_tiny_budget_and_a_large_one():
    own = psutil.Process().memory_info().rss / MB
    tiny = MemoryGuard(budget_mb=1).check()  # any Python process is above 0.9 MB
    assert tiny.over_soft and tiny.rss_mb > 1
    roomy = MemoryGuard(budget_mb=1_000_000).check()
    assert not roomy.over_soft
    assert roomy.rss_mb == pytest.approx(own, rel=0.2)
    assert roomy.peak_mb >= roomy.rss_mb  # the kernel's high-water mark is included


def test_allocating_past_the_soft_limit_trips_the_guard():
    base = psutil.Process().memory_info().rss / MB
    guard = MemoryGuard(budget_mb=base + 200, soft_fraction=0.9)  # soft limit: base*0.9 + 180
    assert not MemoryGuard(budget_mb=base + 400, soft_fraction=0.9).check().over_soft
    block = bytearray(260 * MB)  # zero-filled by the allocator: resident once touched
    block[:: 4096] = b"\1" * len(block[:: 4096])
    try:
        verdict = guard.check()
        assert verdict.over_soft, verdict.message
        assert verdict.rss_mb >= base + 200
    finally:
        del block


@pytest.mark.parametrize("bad", [0, -5, math.nan, math.inf, "3072", None, True])
def test_budget_must_be_a_positive_number(bad):
    with pytest.raises(ValueError, match="memory_budget_mb"):
        MemoryGuard(bad)
    with pytest.raises(ValueError, match="must be a positive number"):
        validate_budget_mb(bad)


@pytest.mark.parametrize("bad", [0, 1.5, -0.1])
def test_soft_fraction_is_checked(bad):
    with pytest.raises(ValueError, match="soft_fraction"):
        MemoryGuard(100, soft_fraction=bad)
