"""Partitioned decimation (``simplify.parts``): the parts cannot touch each
other's data, the merged log is a valid order, and the progressive mesh it
makes is as exact as the whole-mesh one, with attributes, whatever the
number of threads."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from lodserver.progressive import encode_progressive
from lodserver.progressive.mesh import from_collapse_log
from lodserver.simplify import collapse, parts
from lodserver.simplify.collapse import decimate
from lodserver.simplify.log import LogColumns
from lodserver.simplify.options import DecimateOptions
from lodserver.simplify.parts import FROZEN, merge_logs, partition

from ..meshes import canonical_faces, mesh
from ..progressive.test_appearance import corner_rows, same_level

GEOMETRY = ["spot", "torus", "icosphere", "grid"]
TEXTURED = ["textured_sphere", "hard_sphere"]


def _pm(name, parts):
    m = mesh(name)
    return m, from_collapse_log(m, decimate(m, DecimateOptions(parts=parts)))


def _labels(m, parts):
    alive = np.zeros(m.vertex_count, bool)
    alive[m.faces.ravel()] = True
    return partition(m.positions, m.faces, alive, parts)


@pytest.mark.parametrize("parts", [2, 4])
@pytest.mark.parametrize("name", GEOMETRY + TEXTURED)
def test_a_part_shares_nothing_a_collapse_touches(name, parts):
    m = mesh(name)
    label = _labels(m, parts)
    sizes = np.bincount(label[label != FROZEN], minlength=parts)
    assert len(sizes) == parts and sizes.min() > 0
    # every vertex of a face at a vertex next to a part's vertex is in that
    # part or frozen: the faces, counters and wedges a collapse of the part
    # writes (its ends' and the opposite vertices') are no other part's
    faces = m.faces
    n = m.vertex_count
    for part in range(parts):
        own = label == part
        ring = np.zeros(n, bool)
        ring[faces[own[faces].any(axis=1)].ravel()] = True       # own vertices and neighbours
        touched = faces[ring[faces].any(axis=1)].ravel()          # every vertex of their faces
        assert set(np.unique(label[touched])) <= {part, FROZEN}


def test_the_halves_are_equal_and_a_bad_count_is_refused():
    m = mesh("icosphere")
    alive = np.ones(m.vertex_count, bool)
    label = partition(m.positions, m.faces, alive, 2)
    frozen = label == FROZEN
    assert 0 < frozen.sum() < m.vertex_count // 2
    # the cut is at the median of the longest side: every vertex of part 0
    # lies at or below every vertex of part 1 along it
    axis = np.argmax(np.ptp(m.positions, axis=0))
    assert m.positions[label == 0, axis].max() <= m.positions[label == 1, axis].min()
    np.testing.assert_array_equal(partition(m.positions, m.faces, alive, 2), label)
    with pytest.raises(ValueError, match="power of two"):
        partition(m.positions, m.faces, alive, 3)


def _log(keys, first_face, width=1):
    """A made-up log of len(keys) collapses, each killing one face and moving
    two corners, with one wedge merge; rows numbered from ``first_face``."""
    k = len(keys)
    rows = first_face + np.arange(k)
    offsets = np.arange(k + 1)
    return LogColumns(rows, rows + 1000, np.c_[rows, rows, rows].astype(float),
                      np.asarray(keys, float), np.ones(k), offsets, rows, 2 * offsets,
                      np.repeat(rows, 2), offsets, rows, rows + 1,
                      np.c_[rows.astype(float)] * np.ones(width))


def test_merged_logs_keep_each_order_and_follow_the_keys():
    a, b, tail = _log([1, 5, 2, 6], 0), _log([3, 4], 100), _log([0.5], 200)
    merged = merge_logs([a, b], [a.cost, b.cost], tail)
    survivor = merged.survivor
    # running maxima 1 5 5 6 and 3 4: a0, b0, b1, a1, a2, a3, then the tail
    np.testing.assert_array_equal(survivor, [0, 100, 101, 1, 2, 3, 200])
    # every block column follows its row
    np.testing.assert_array_equal(merged[6], survivor)
    np.testing.assert_array_equal(merged[8], np.repeat(survivor, 2))
    np.testing.assert_array_equal(merged[10], survivor)
    np.testing.assert_array_equal(merged[12][:, 0], survivor)
    np.testing.assert_array_equal(merged[5], np.arange(8))
    np.testing.assert_array_equal(merged[7], 2 * np.arange(8))


def test_merging_phases_lets_go_of_the_parts_logs():
    # the build's peak memory: the merge and the final join take the parts'
    # columns out of the lists they are handed, so each can be freed once joined
    a, b, c, tail = _log([1, 5], 0), _log([3], 100), _log([2, 4], 300), _log([0.5], 200)
    phases = [([a, b], [a.cost, b.cost]), ([c], [c.cost])]
    logs = [parts.merge_phases(phases), tail]
    assert phases == []
    joined = parts.concatenate_logs(logs)
    assert logs == []
    np.testing.assert_array_equal(joined.survivor, [0, 100, 1, 300, 301, 200])
    np.testing.assert_array_equal(joined.killed_faces, joined.survivor)
    np.testing.assert_array_equal(joined.moved_corners, np.repeat(joined.survivor, 2))
    np.testing.assert_array_equal(joined.killed_offsets, np.arange(7))
    np.testing.assert_array_equal(joined.merge_value[:, 0], joined.survivor)


@pytest.mark.parametrize("parts", [2, 4, 8])
@pytest.mark.parametrize("name", GEOMETRY)
def test_every_level_is_exact(name, parts):
    m, pm = _pm(name, parts)
    assert pm.split_count > 0.9 * m.vertex_count
    replayed = pm.cursor(pm.base_vertices).seek(pm.vertex_count).arrays()
    assert np.array_equal(replayed[0], pm.positions)
    assert np.array_equal(canonical_faces(*replayed), canonical_faces(m.positions, m.faces))
    rng = np.random.default_rng(0)
    cursor = pm.cursor(pm.vertex_count)
    for level in rng.integers(pm.base_vertices, pm.vertex_count + 1, 12):
        direct = pm.arrays_at(int(level))
        for start in (pm.base_vertices, pm.vertex_count):
            reached = pm.cursor(start).seek(int(level)).arrays()
            assert np.array_equal(reached[0], direct[0]) and np.array_equal(reached[1], direct[1])
        walked = cursor.seek(int(level)).arrays()
        assert np.array_equal(walked[1], direct[1])
        faces = direct[1]
        assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                      & (faces[:, 0] != faces[:, 2]))
        assert len(np.unique(np.sort(faces, axis=1), axis=0)) == len(faces)


@pytest.mark.parametrize("parts", [2, 8])
@pytest.mark.parametrize("name", TEXTURED)
def test_every_level_is_exact_with_attributes(name, parts):
    m, pm = _pm(name, parts)
    assert pm.has_attributes and pm.split_count > 0.9 * m.vertex_count
    full = pm.at(pm.vertex_count)
    np.testing.assert_array_equal(corner_rows(full), corner_rows(m))
    cursor = pm.cursor(pm.base_vertices)
    base = cursor.mesh()
    assert same_level(cursor.seek(pm.vertex_count).mesh(), full)
    for level in np.linspace(pm.base_vertices, pm.vertex_count, 9).astype(int):
        assert same_level(pm.cursor(pm.vertex_count).seek(int(level)).mesh(), pm.at(int(level)))
        assert same_level(cursor.seek(int(level)).mesh(), pm.at(int(level)))
    assert same_level(cursor.seek(pm.base_vertices).mesh(), base)


@pytest.mark.parametrize("name", ["spot", "textured_sphere"])
def test_the_artefact_does_not_depend_on_the_threads(name):
    m = mesh(name)
    artefacts = []
    threads = numba.get_num_threads()
    try:
        for count in (1, numba.config.NUMBA_NUM_THREADS, 1):
            numba.set_num_threads(count)
            log = decimate(m, DecimateOptions(parts=4))
            artefacts.append(encode_progressive(from_collapse_log(m, log)))
    finally:
        numba.set_num_threads(threads)
    assert artefacts[0] == artefacts[1] == artefacts[2]


def test_parts_are_the_default_only_for_large_meshes(monkeypatch):
    from lodserver import build
    m = mesh("spot")

    def artefact(pm, parts):
        # the build's metadata on the log of ``parts`` parts
        log = decimate(m, DecimateOptions(parts=parts))
        return encode_progressive(from_collapse_log(m, log, pm.metadata))

    built = build(m)
    assert encode_progressive(built) == artefact(built, 1)
    monkeypatch.setattr(parts, "PARALLEL_MIN_VERTICES", 10)
    split = build(m)
    assert encode_progressive(split) == artefact(split, parts.default_parts(m.vertex_count))
    assert encode_progressive(split) != artefact(split, 1)


def test_a_collapse_limit_or_close_pairs_run_whole():
    m = mesh("torus")
    for options in (dict(max_collapses=40), dict(pair_threshold=0.05)):
        limited = decimate(m, DecimateOptions(parts=2, **options))
        whole = decimate(m, DecimateOptions(parts=1, **options))
        np.testing.assert_array_equal(limited.removed, whole.removed)
        np.testing.assert_array_equal(limited.position, whole.position)


def test_the_part_count_follows_the_mesh_not_the_machine():
    assert parts.default_parts(parts.PARALLEL_MIN_VERTICES - 1) == 1
    assert parts.default_parts(parts.PARALLEL_MIN_VERTICES) == 2
    assert parts.default_parts(556_051) == 8              # the 1.1M-face bunny
    assert parts.default_parts(4_704_258) == 64           # the 9.4M-face brain
    assert parts.default_parts(10**9) == parts.MAX_PARTS
    counts = [parts.default_parts(n) for n in range(100_000, 20_000_000, 77_777)]
    assert all(a <= b for a, b in zip(counts, counts[1:]))
    assert all(c & (c - 1) == 0 for c in counts)


def test_min_vertices_holds_across_parts():
    m = mesh("icosphere")
    log = decimate(m, DecimateOptions(parts=2, min_vertices=60))
    assert m.vertex_count - len(log) == 60
