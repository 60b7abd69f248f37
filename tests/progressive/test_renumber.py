"""The compiled renumbering steps against their definitions, written slowly."""

from __future__ import annotations

import numpy as np
import pytest

from lodserver.progressive.renumber import (
    hierarchy,
    renumbered_faces,
    reverse_blocks,
    reversed_corners,
    split_face_order,
)


def _blocks(rng, k, width=None):
    """Random block sizes (some empty) as offsets, and values to cut into them."""
    sizes = rng.integers(0, 4, k)
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    shape = (offsets[-1],) if width is None else (offsets[-1], width)
    return offsets, rng.integers(0, 1000, shape).astype(np.int64)


@pytest.mark.parametrize("seed", range(5))
def test_reverse_blocks_is_last_block_first(seed):
    rng = np.random.default_rng(seed)
    offsets, values = _blocks(rng, 30)
    blocks = [values[offsets[i]:offsets[i + 1]] for i in range(30)]
    expected = np.concatenate(blocks[::-1])
    assert np.array_equal(reverse_blocks(values, offsets), expected)
    # rows of a 2-D array move whole (wedge attribute vectors)
    offsets, rows = _blocks(rng, 30, width=4)
    rows = rows.astype(np.float64)
    blocks = [rows[offsets[i]:offsets[i + 1]] for i in range(30)]
    assert np.array_equal(reverse_blocks(rows, offsets), np.concatenate(blocks[::-1]))
    # corners renumbered by face on the way
    new_face = rng.permutation(400)
    corners = 3 * rng.integers(0, 400, offsets[-1]) + rng.integers(0, 3, offsets[-1])
    out = reversed_corners(corners.astype(np.int64), offsets, new_face.astype(np.int64))
    flipped = reverse_blocks(corners.astype(np.int64), offsets)
    assert np.array_equal(out, 3 * new_face[flipped // 3] + flipped % 3)


def test_split_face_order_puts_survivors_first_then_splits():
    killed = np.array([4, 1, 6, 0], dtype=np.int64)
    offsets = np.array([0, 2, 2, 4], dtype=np.int64)   # collapse 1 kills no face
    order, new_face = split_face_order(killed, offsets, 8)
    assert order.tolist() == [2, 3, 5, 7, 6, 0, 4, 1]
    assert np.array_equal(new_face[order], np.arange(8))
    faces = np.arange(24, dtype=np.int64).reshape(8, 3) % 5
    new_id = np.array([4, 3, 2, 1, 0], dtype=np.int64)
    assert np.array_equal(renumbered_faces(faces, order, new_id), new_id[faces[order]])


@pytest.mark.parametrize("seed", range(5))
def test_hierarchy_follows_its_definition(seed):
    rng = np.random.default_rng(seed)
    n0, n, d = 3, 60, 2
    parent = np.full(n, -1, dtype=np.int64)
    for t in range(n0, n):
        parent[t] = rng.integers(0, t)
    full = rng.random((n, d))
    coarse = rng.random((n - n0, d))
    fine, new = hierarchy(parent, n0, full, coarse)
    for t in range(n0, n):
        s = parent[t]
        later = [u for u in range(t + 1, n) if parent[u] == s]    # s's next collapse above t
        assert np.array_equal(fine[t - n0], coarse[later[0] - n0] if later else full[s])
        children = [u for u in range(t + 1, n) if parent[u] == t]
        assert np.array_equal(new[t - n0], coarse[children[0] - n0] if children else full[t])
