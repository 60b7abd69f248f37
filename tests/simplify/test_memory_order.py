"""Memory order (``parts.memory_order``): a large mesh is decimated with its
vertices renumbered along a Morton curve and the log mapped back to the
input's ids. The renumbering must be a deterministic permutation that puts
neighbours close, and the log it gives must be the renumbered run's own, in
the input's ids, with every level as exact as without it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lodserver.progressive import encode_progressive
from lodserver.progressive.mesh import from_collapse_log
from lodserver.simplify import collapse
from lodserver.simplify.collapse import decimate
from lodserver.simplify.options import DecimateOptions
from lodserver.simplify.parts import REORDER_MIN_VERTICES, memory_order

from ..meshes import canonical_faces, mesh
from ..progressive.test_appearance import corner_rows, same_level


def _shuffled(name, seed=0):
    """Mesh ``name`` with its vertex ids shuffled, so that any order is lost."""
    m = mesh(name)
    n = m.vertex_count
    order = np.random.default_rng(seed).permutation(n)
    inverse = np.empty(n, np.int64)
    inverse[order] = np.arange(n)
    return dataclasses.replace(m, positions=m.positions[order], faces=inverse[m.faces])


def test_the_order_is_a_deterministic_permutation_that_keeps_neighbours_close():
    m = _shuffled("icosphere")
    order = memory_order(m.positions)
    assert np.array_equal(np.sort(order), np.arange(m.vertex_count))
    np.testing.assert_array_equal(memory_order(m.positions.copy()), order)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))

    def id_gap(faces):
        # median distance between the ids of an edge's ends
        return np.median(np.abs(faces - np.roll(faces, 1, axis=1)))

    assert id_gap(inverse[m.faces]) < 0.1 * id_gap(m.faces)
    # points on a line come in their order along it
    line = np.c_[np.linspace(0, 1, 50)[::-1], np.zeros(50), np.zeros(50)]
    np.testing.assert_array_equal(memory_order(line), np.arange(50)[::-1])
    assert memory_order(np.array([[0.0, 0, 0], [np.nan, 0, 0]])) is None
    np.testing.assert_array_equal(memory_order(np.zeros((4, 3))), np.arange(4))


def _interleaved(cells):
    """Morton codes of (k, 3) cells of 21 bits, bit by bit (the definition)."""
    code = np.zeros(len(cells), np.uint64)
    for bit in range(21):
        for axis in range(3):
            code |= ((cells[:, axis].astype(np.uint64) >> np.uint64(bit)) & np.uint64(1)) \
                << np.uint64(3 * bit + axis)
    return code


def test_the_order_sorts_by_the_interleaved_bits_of_the_cells():
    rng = np.random.default_rng(3)
    for positions in (rng.normal(size=(2000, 3)) * 1e3, rng.random((500, 3)) * 1e-200,
                      np.array([[0.0, -0.0, 1.0], [1.0, 2.0, -3.0], [0.0, 0.0, 0.0]])):
        lo = positions.min(axis=0)
        scale = (2**21 - 1) / (positions.max(axis=0) - lo).max()
        cells = ((positions - lo) * scale).astype(np.int64)
        expected = np.argsort(_interleaved(cells), kind="stable")
        np.testing.assert_array_equal(memory_order(positions), expected)


def test_only_large_meshes_are_renumbered(monkeypatch):
    m = mesh("spot")
    assert m.vertex_count < REORDER_MIN_VERTICES
    default = encode_progressive(from_collapse_log(m, decimate(m)))
    monkeypatch.setattr(collapse, "REORDER_MIN_VERTICES", 0)
    renumbered = encode_progressive(from_collapse_log(m, decimate(m)))
    assert renumbered != default


@pytest.mark.parametrize("parts", [1, 2])
def test_the_log_is_the_renumbered_runs_in_the_inputs_ids(monkeypatch, parts):
    m = _shuffled("torus")
    monkeypatch.setattr(collapse, "REORDER_MIN_VERTICES", 0)
    log = decimate(m, DecimateOptions(parts=parts))
    # the same run by hand: renumber, decimate as it is, map the ids back
    order = memory_order(m.positions)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    renumbered = dataclasses.replace(m, positions=m.positions[order], faces=inverse[m.faces])
    monkeypatch.setattr(collapse, "REORDER_MIN_VERTICES", 10**9)
    direct = decimate(renumbered, DecimateOptions(parts=parts))
    np.testing.assert_array_equal(log.survivor, order[direct.survivor])
    np.testing.assert_array_equal(log.removed, order[direct.removed])
    np.testing.assert_array_equal(log.position, direct.position)
    np.testing.assert_array_equal(log.killed_faces, direct.killed_faces)
    np.testing.assert_array_equal(log.moved_corners, direct.moved_corners)
    # a logged position is where the survivor's input vertex moves: the
    # survivor and removed vertex of every row share an edge of the input
    edges = {tuple(sorted(e)) for f in m.faces for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    first = (int(log.survivor[0]), int(log.removed[0]))
    assert tuple(sorted(first)) in edges


@pytest.mark.parametrize("parts", [1, 2])
@pytest.mark.parametrize("name", ["torus", "grid", "spot"])
def test_every_level_is_exact_when_renumbered(monkeypatch, name, parts):
    m = _shuffled(name)
    monkeypatch.setattr(collapse, "REORDER_MIN_VERTICES", 0)
    pm = from_collapse_log(m, decimate(m, DecimateOptions(parts=parts)))
    assert pm.split_count > 0.9 * m.vertex_count
    replayed = pm.cursor(pm.base_vertices).seek(pm.vertex_count).arrays()
    assert np.array_equal(canonical_faces(*replayed), canonical_faces(m.positions, m.faces))
    for level in np.linspace(pm.base_vertices, pm.vertex_count, 9).astype(int):
        direct = pm.arrays_at(int(level))
        reached = pm.cursor(pm.base_vertices).seek(int(level)).arrays()
        assert np.array_equal(reached[0], direct[0]) and np.array_equal(reached[1], direct[1])
        faces = direct[1]
        assert np.all((faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
                      & (faces[:, 0] != faces[:, 2]))
    # the same input twice: the same bytes
    again = from_collapse_log(m, decimate(m, DecimateOptions(parts=parts)))
    assert encode_progressive(again) == encode_progressive(pm)


def test_attributes_locked_vertices_and_poses_follow_the_renumbering(monkeypatch):
    m = mesh("textured_sphere")
    monkeypatch.setattr(collapse, "REORDER_MIN_VERTICES", 0)
    pm = from_collapse_log(m, decimate(m, DecimateOptions(parts=2)))
    np.testing.assert_array_equal(corner_rows(pm.at(pm.vertex_count)), corner_rows(m))
    cursor = pm.cursor(pm.base_vertices)
    for level in np.linspace(pm.base_vertices, pm.vertex_count, 7).astype(int):
        assert same_level(cursor.seek(int(level)).mesh(), pm.at(int(level)))
    # locked vertices (in the input's ids) neither vanish nor move
    g = _shuffled("grid")
    locked = g.positions[:, 0] < np.median(g.positions[:, 0])
    log = decimate(g, locked=locked)
    assert not locked[log.removed].any()
    moved = locked[log.survivor]
    np.testing.assert_array_equal(log.position[moved], g.positions[log.survivor[moved]])
    # a wrong-shaped mask is still refused with the kernel's own message
    with pytest.raises(ValueError, match="boolean mask"):
        decimate(g, locked=locked[:-1])
    # poses are permuted with the vertices: the run equals one on the
    # renumbered mesh with its poses renumbered by hand
    poses = np.zeros((1, g.vertex_count, 3, 4))
    poses[0, :, :, :3] = np.eye(3)
    poses[0, :, 2, 2] = 1.0 + 3.0 * (g.positions[:, 0] - g.positions[:, 0].min())  # a stretch
    posed = decimate(g, poses=poses)
    order = memory_order(g.positions)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))
    renumbered = dataclasses.replace(g, positions=g.positions[order], faces=inverse[g.faces])
    monkeypatch.setattr(collapse, "REORDER_MIN_VERTICES", 10**9)
    direct = decimate(renumbered, poses=poses[:, order])
    np.testing.assert_array_equal(posed.removed, order[direct.removed])
    assert not np.array_equal(direct.removed, decimate(renumbered).removed)    # they counted
