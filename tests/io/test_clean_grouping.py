"""Welding's grouping of equal rows: the hash table and its sorting fallback agree."""

from __future__ import annotations

import numpy as np
import pytest

from lodserver.io import clean


def _rows():
    rng = np.random.default_rng(7)
    floats = rng.integers(0, 6, (3000, 3)).astype(np.float64)
    floats[rng.random(3000) < 0.2] *= -1.0          # -0.0 beside 0.0
    floats[rng.random(3000) < 0.01, 2] = np.nan      # a NaN row equals no row
    return [floats, rng.integers(0, 40, (4000, 3)), np.zeros((1, 3)), np.zeros((0, 3)),
            np.array([[0.0, -0.0], [-0.0, 0.0], [np.nan, 1.0], [np.nan, 1.0]])]


@pytest.mark.parametrize("index", range(5))
def test_the_hash_table_groups_as_the_sort_does(index):
    rows = _rows()[index]
    first, inverse = clean._first_occurrences(rows)
    sorted_first, sorted_inverse = clean._sorted_first_occurrences(rows)
    assert np.array_equal(first, sorted_first) and np.array_equal(inverse, sorted_inverse)
    if len(rows):
        assert np.array_equal(rows[first][inverse], rows, equal_nan=True)
        assert (np.diff(first) > 0).all() and (inverse[first] == np.arange(len(first))).all()


def test_rows_past_the_probe_budget_are_sorted_instead(monkeypatch):
    rows = _rows()[0]
    _, _, hashed = clean._group_rows(clean.read_only(rows), clean.read_only(rows).view(np.int64),
                                     0)
    assert not hashed           # the budget is spent on this many rows: the caller sorts
    monkeypatch.setattr(clean, "PROBES_PER_ROW", 0)
    first, inverse = clean._first_occurrences(rows)
    expected = clean._sorted_first_occurrences(rows)
    assert np.array_equal(first, expected[0]) and np.array_equal(inverse, expected[1])
