"""StallAwareAge: ages restart after the reader's own stall, and only then."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.kernel.stall import StallAwareAge


def test_regular_ticks_give_plain_ages() -> None:
    ages = StallAwareAge(0.2)
    for k in range(100):
        ages.tick(k * 0.05)
    assert ages.stalls == 0
    assert ages.age_s(1.0, 4.95) == pytest.approx(3.95)


def test_a_stall_restarts_ages_at_the_resume() -> None:
    ages = StallAwareAge(0.2)
    ages.tick(10.0)
    ages.tick(10.05)
    ages.tick(10.95)  # 0.9 s without a tick
    assert ages.stalls == 1
    assert ages.longest_stall_s == pytest.approx(0.9)
    assert ages.age_s(10.05, 10.95) == 0.0
    assert ages.age_s(10.05, 11.5) == pytest.approx(0.55)
    assert ages.age_s(11.2, 11.5) == pytest.approx(0.3)  # newer than the resume: its own age


def test_the_first_tick_is_not_a_stall() -> None:
    ages = StallAwareAge(0.2)
    ages.tick(1000.0)
    assert ages.stalls == 0
    assert ages.resumed_s == -math.inf


def test_a_gap_must_be_positive() -> None:
    with pytest.raises(ValueError, match="stall_gap_s"):
        StallAwareAge(0.0)


@given(
    gaps=st.lists(st.floats(0.001, 2.0), min_size=1, max_size=50),
    stamp_back_s=st.floats(0.0, 5.0),
)
def test_never_older_than_the_plain_age_nor_negative_for_past_stamps(
    gaps: list[float], stamp_back_s: float
) -> None:
    ages = StallAwareAge(0.2)
    t = 0.0
    ages.tick(t)
    for g in gaps:
        t += g
        ages.tick(t)
    stamp = t - stamp_back_s
    a = ages.age_s(stamp, t)
    assert 0.0 <= a <= stamp_back_s + 1e-12
