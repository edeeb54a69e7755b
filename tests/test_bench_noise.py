"""The noise measure behind the drive-maps tables (``benchmarks/drive_maps.paired_interval``).

The README's verdicts ("clear of the query's noise") rest on this interval, so it is checked
against what a bootstrap over source places must do: hold its own point estimate when a stop
weighs heavily, treat re-timings of one drive as one drive, and cover a known difference about
as often as it says.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np

from benchmarks.drive_maps import paired_interval


def _drive(places: Any) -> Any:
    """What the interval reads of a query drive: the source place of each frame."""
    return SimpleNamespace(variant=SimpleNamespace(places=np.asarray(places, dtype=np.int64)))


def test_a_stop_at_the_drive_s_ends_stays_inside_its_interval() -> None:
    # 60 standing frames at the first and at the last place, all right with map a and wrong with
    # map b: the point estimate must lie inside the interval (blocks that could not reach the
    # drive's ends put it outside: +0.176 against +0.024..+0.149 on a real drive)
    rng = np.random.default_rng(1)
    places = np.r_[np.zeros(60, int), np.arange(800), np.full(60, 799)]
    a = rng.random(len(places)) < 0.6
    b = rng.random(len(places)) < 0.5
    stop = (places == 0) | (places == 799)
    a[stop], b[stop] = True, False
    lo, hi = paired_interval([(_drive(places), a, b)])
    point = a.mean() - b.mean()
    assert lo < point < hi


def test_no_difference_gives_an_empty_interval() -> None:
    right = np.random.default_rng(2).random(300) < 0.5
    assert paired_interval([(_drive(np.arange(300)), right, right)]) == (0.0, 0.0)


def test_re_timings_of_one_drive_are_resampled_as_one() -> None:
    # the same drive twice (or re-timed: every place repeated) carries no more evidence than once;
    # drawing each copy's blocks on their own would narrow the interval by about sqrt(2)
    rng = np.random.default_rng(3)
    places = np.arange(400)
    a, b = rng.random(400) < 0.7, rng.random(400) < 0.5
    one = paired_interval([(_drive(places), a, b)])
    twice = paired_interval([(_drive(places), a, b), (_drive(places), a, b)])
    slow = paired_interval([(_drive(np.repeat(places, 3)), np.repeat(a, 3), np.repeat(b, 3))])
    assert np.allclose(one, twice) and np.allclose(one, slow)


def test_it_covers_a_known_difference_about_95_percent_of_the_time() -> None:
    # independent frames whose difference has mean 0.1: the 95 % interval should hold 0.1 in
    # about 95 of 100 drives (a bootstrap of 300 frames: between 88 and 99)
    rng = np.random.default_rng(4)
    covered = 0
    for seed in range(100):
        a = rng.random(300) < 0.6
        b = rng.random(300) < 0.5
        lo, hi = paired_interval([(_drive(np.arange(300)), a, b)], n=500, seed=seed)
        covered += lo <= 0.1 <= hi
    assert 88 <= covered <= 99
