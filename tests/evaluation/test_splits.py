"""Database/query splits: no query sees its own time window; dropped queries are counted."""

import numpy as np
import pytest

from sgvloc.core.errors import InputError
from sgvloc.tools.evaluation.splits import make_split


def out_and_back(n: int = 40, dt: float = 1.0):
    """A drive along x and back: scan i at x = 2 i for the first half, then returning."""
    half = n // 2
    x = np.concatenate([np.arange(half) * 2.0, (half - 1 - np.arange(n - half)) * 2.0])
    pos = np.stack([x, np.zeros(n), np.zeros(n)], axis=1)
    return np.arange(n) * dt + 100.0, pos  # times with an offset: splits use relative times


def test_time_split_database_is_the_past_and_queries_the_rest():
    times, pos = out_and_back()
    s = make_split(times, pos, db_until=19.0, threshold=5.0)
    assert s.database.tolist() == list(range(20))
    assert set(s.queries) | set(s.dropped) == set(range(20, 40))
    assert not set(s.queries) & set(s.dropped)
    for q in s.queries:
        assert (s.times[s.database_for(q)] <= 19.0).all()
        assert s.times[q] > 19.0


def test_loop_split_never_shows_a_query_its_own_time_window():
    times, pos = out_and_back()
    s = make_split(times, pos, min_gap=10.0, threshold=5.0)
    assert len(s.queries) > 0
    for q in s.queries:
        db = s.database_for(q)
        assert len(db) and (s.times[q] - s.times[db] >= 10.0).all()
        assert np.linalg.norm(pos[db] - pos[q], axis=1).min() <= 5.0
    # while driving out, nothing older than 10 s is within 5 m: those are dropped
    assert s.dropped.tolist()[:3] == [10, 11, 12]
    assert len(s.queries) + len(s.dropped) == 30
    assert s.summary()["dropped_queries"] == len(s.dropped)


def test_queries_without_a_database_scan_within_the_threshold_are_dropped_and_counted():
    times, pos = out_and_back()
    pos[30:] += [0.0, 50.0, 0.0]  # the last ten come back on a parallel road 50 m away
    s = make_split(times, pos, db_until=19.0, threshold=5.0)
    assert set(s.dropped) == set(range(30, 40))
    assert s.summary()["dropped_queries"] == 10 and s.summary()["queries"] == 10
    wide = make_split(times, pos, db_until=19.0, threshold=60.0)
    assert len(wide.dropped) == 0


def test_thinning_and_bad_arguments():
    times, pos = out_and_back()
    s = make_split(times, pos, db_until=19.0, max_queries=4)
    assert len(s.queries) == 4 and s.queries[0] == 20
    assert len(make_split(times, pos, db_until=19.0, query_stride=5).queries) == 4
    with pytest.raises(InputError):
        make_split(times, pos)
    with pytest.raises(InputError):
        make_split(times, pos, db_until=5.0, min_gap=5.0)
    with pytest.raises(InputError):
        make_split(times, pos, db_until=-1.0)
    with pytest.raises(InputError):
        make_split(times, pos[:, :2], min_gap=5.0)


def test_leave_out_split_hides_the_querys_own_stretch_both_ways():
    times, pos = out_and_back()
    s = make_split(times, pos, leave_out=5.0, threshold=5.0)
    assert s.mode == "leave-out" and s.summary()["leave_out_s"] == 5.0
    assert set(s.queries) | set(s.dropped) == set(range(40))
    for q in s.queries:
        db = s.database_for(q)
        assert q not in db and (np.abs(s.times[db] - s.times[q]) >= 5.0).all()
        # scans before and after the query's window are both in its database
        assert (s.times[db] < s.times[q]).any() or (s.times[db] > s.times[q]).any()
    # the turning point is revisited only within its own window: out of coverage
    assert 19 in s.dropped and 20 in s.dropped
    with pytest.raises(InputError, match="leave_out"):
        make_split(times, pos, leave_out=-1.0)
    # a scan with no other scan the gap away has nothing to search: no query at all, not
    # a negative (as the map's leave-out self-test plans it)
    times = np.arange(10, dtype=np.float64)  # 0..9 s
    s = make_split(times, np.zeros((10, 3)), leave_out=6.0, threshold=5.0)
    assert set(s.queries) | set(s.dropped) == {0, 1, 2, 3, 6, 7, 8, 9}


def test_a_narrow_view_needs_a_database_scan_facing_the_same_way():
    """Out along x (heading 0) and back (heading 180): with max_heading_deg the way back
    has no database scan that sees what it sees, so it is out of coverage."""
    times, pos = out_and_back()
    heading = np.where(np.arange(40) < 20, 0.0, 180.0)
    heading[30:] = -10.0  # the last ten turn round to face like the way out (wrapped)
    s = make_split(times, pos, db_until=19.0, threshold=5.0)
    assert len(s.queries) == 20 and s.summary()["coverage_heading_deg"] is None
    v = make_split(
        times, pos, db_until=19.0, threshold=5.0, headings_deg=heading, max_heading_deg=35.0
    )
    assert set(v.queries) == set(range(30, 40)) and set(v.dropped) == set(range(20, 30))
    assert v.summary()["coverage_heading_deg"] == 35.0
    with pytest.raises(InputError, match="headings_deg"):
        make_split(times, pos, db_until=19.0, max_heading_deg=35.0)
    with pytest.raises(InputError, match="max_heading_deg"):
        make_split(times, pos, db_until=19.0, headings_deg=heading, max_heading_deg=0.0)
