"""The collapse rules one by one on tiny hand-built meshes, each refusal by
its named reason, and the kernel against the pure-Python reference."""

from __future__ import annotations

import numpy as np
import pytest

from lodserver.simplify.collapse import check_collapse, classify_vertices, decimate
from lodserver.simplify.options import DecimateOptions
from lodserver.mesh import Mesh
from lodserver.simplify import rules
from lodserver.simplify.topology import census

from .. import naive
from ..meshes import mesh


def _mesh(positions, faces):
    return Mesh(np.asarray(positions, float), np.asarray(faces, np.int64))


def _mask(n, *vertices):
    mask = np.zeros(n, bool)
    mask[list(vertices)] = True
    return mask


def _naive_refusals(m, a, b, locked=None, flip_cos=rules.DEFAULT_FLIP_COS, verdict=None):
    """The reference's refusals of (a, b), at the kernel's placement."""
    unit, lo, extent = naive.unit_frame(m.positions)
    kind = naive.vertex_kinds(m.faces, m.vertex_count, locked)
    K, _ = naive.quadric_matrices(unit, m.faces)
    planned = naive.plan(unit, K, kind, a, b)
    if planned is None:
        return ["locked"]
    s, p, _ = planned
    if verdict is not None:
        p = (verdict.position - lo) / extent
    return naive.refusals(unit, m.faces, kind, s, b if s == a else a, p, flip_cos)


def lone_triangle():
    return _mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])


def strip():
    """Two rows of four vertices (every vertex on the border), six faces:
    top 0..3, bottom 4..7."""
    positions = [[x, 1, 0] for x in range(4)] + [[x, 0, 0] for x in range(4)]
    faces = [f for i in range(3) for f in ([i, 4 + i, 5 + i], [i, 5 + i, i + 1])]
    return _mesh(positions, faces)


def tetrahedron():
    positions = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    return _mesh(positions, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def small_torus():
    """The 3 x 3 torus: 9 vertices of degree 6, so the two ends of every edge
    share four neighbours, only two of them opposite the edge."""
    u = np.arange(3)[:, None] * 2 * np.pi / 3
    v = np.arange(3)[None, :] * 2 * np.pi / 3
    big, small = 3.0, 1.0
    x = ((big + small * np.cos(v)) * np.cos(u)).ravel()
    y = ((big + small * np.cos(v)) * np.sin(u)).ravel()
    z = np.broadcast_to(small * np.sin(v), (3, 3)).ravel()
    faces = []
    for i in range(3):
        for j in range(3):
            a, b = 3 * i + j, 3 * ((i + 1) % 3) + j
            c, d = 3 * ((i + 1) % 3) + (j + 1) % 3, 3 * i + (j + 1) % 3
            faces += [[a, b, c], [a, c, d]]
    return _mesh(np.stack([x, y, z], 1), faces)


def bow_tie():
    """Two fans of three faces around vertex 0, touching only there."""
    ring = [[np.cos(t), np.sin(t), 0.0] for t in np.linspace(0.2, 1.4, 4)]
    other = [[-x, -y, 0.0] for x, y, _ in ring]
    faces = [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 5, 6], [0, 6, 7], [0, 7, 8]]
    return _mesh([[0, 0, 0], *ring, *other], faces)


def fin():
    """Three faces on the edge (0, 1): a non-manifold edge."""
    positions = [[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]]
    return _mesh(positions, [[0, 1, 2], [1, 0, 3], [0, 1, 4]])


def tent(height=0.5):
    """An apex (vertex 0, interior) over a ring of six border vertices."""
    ring = [[np.cos(t), np.sin(t), 0.0] for t in np.arange(6) * np.pi / 3]
    faces = [[0, 1 + k, 1 + (k + 1) % 6] for k in range(6)]
    return _mesh([[0, 0, height], *ring], faces)


def fan_with_a_straight_side():
    """Interior vertex 0 in a flat fan whose ring vertices 1, 2, 3 lie on one
    line: collapsing 0 into 1 leaves the face (1, 2, 3) without area."""
    positions = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 2, 0], [-1, 0, 0], [0, -1, 0]]
    return _mesh(positions, [[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5], [0, 5, 1]])


def two_triangles(gap=0.1):
    """Two separate triangles in one plane, corners 0 and 3 ``gap * sqrt 2`` apart."""
    g = gap
    positions = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [-g, -g, 0], [-1 - g, -g, 0], [-g, -1 - g, 0]]
    return _mesh(positions, [[0, 1, 2], [3, 4, 5]])


# --------------------------------------------------------------------------
# One rule each
# --------------------------------------------------------------------------

def test_the_last_face_of_a_vertex_is_kept():
    m = lone_triangle()
    for a, b in ((0, 1), (1, 2), (2, 0)):
        assert check_collapse(m, a, b).reason == "last_face"
        assert _naive_refusals(m, a, b) == ["last_face"]


def test_an_interior_edge_between_border_vertices_pinches():
    m = strip()
    for a, b in ((1, 5), (2, 6)):
        assert check_collapse(m, a, b).reason == "pinch"
        assert _naive_refusals(m, a, b) == ["pinch"]
    # positive control: along the border the same vertices may merge
    verdict = check_collapse(m, 1, 2)
    assert verdict.reason is None and _naive_refusals(m, 1, 2, verdict=verdict) == []
    assert verdict.survivor == 1 and abs(verdict.position[1] - 1.0) < 1e-9   # stays on the border


def test_squashing_a_tetrahedron_is_refused():
    m = tetrahedron()
    for a, b in ((0, 1), (0, 2), (1, 3), (2, 3)):
        verdict = check_collapse(m, a, b)
        assert verdict.reason == "tetrahedron"
        assert _naive_refusals(m, a, b, verdict=verdict)[0] == "tetrahedron"


def test_the_link_condition_keeps_a_handle_open():
    m = small_torus()
    kinds = classify_vertices(census(m.faces, m.vertex_count), m.vertex_count)
    assert np.all(kinds == rules.INTERIOR)
    for a, b in ((0, 3), (0, 1), (0, 4)):
        verdict = check_collapse(m, a, b)
        assert verdict.reason == "link"
        assert _naive_refusals(m, a, b, verdict=verdict)[0] == "link"
    # and the whole build stops there: every edge of it violates the link condition
    log = decimate(m)
    assert len(log) == 0 and log.rejected["link"] > 0


def test_a_bow_tie_vertex_is_locked_and_never_vanishes():
    m = bow_tie()
    kinds = classify_vertices(census(m.faces, m.vertex_count), m.vertex_count)
    assert kinds[0] == rules.LOCKED and np.all(kinds[1:] == rules.BORDER)
    # a border neighbour may vanish into it, and it does not move
    verdict = check_collapse(m, 1, 0)
    assert verdict.reason is None and verdict.survivor == 0
    assert np.array_equal(verdict.position, m.positions[0])
    assert _naive_refusals(m, 1, 0, verdict=verdict) == []
    # an interior edge from it to its fan is two border-like vertices: a pinch
    assert check_collapse(m, 0, 2).reason == "pinch"
    log = decimate(m)
    assert 0 not in log.removed


def test_two_locked_vertices_never_merge():
    m = fin()
    kinds = classify_vertices(census(m.faces, m.vertex_count), m.vertex_count)
    assert kinds[0] == kinds[1] == rules.LOCKED
    assert check_collapse(m, 0, 1).reason == "locked"
    assert _naive_refusals(m, 0, 1) == ["locked"]
    # a caller's lock is the same rule
    t = tent()
    both = _mask(t.vertex_count, 0, 1)
    assert check_collapse(t, 0, 1, locked=both).reason == "locked"
    assert check_collapse(t, 0, 1, locked=_mask(t.vertex_count, 1)).survivor == 1


def test_a_face_turning_too_far_is_a_flip():
    m = tent(height=0.5)            # faces slope ~30 degrees; flattening them turns them so
    strict = check_collapse(m, 0, 1, DecimateOptions(flip_cos=0.95))
    assert strict.reason == "flip"
    assert _naive_refusals(m, 0, 1, flip_cos=0.95, verdict=strict) == ["flip"]
    verdict = check_collapse(m, 0, 1)
    assert verdict.reason is None and verdict.survivor == 1     # the border vertex survives
    assert _naive_refusals(m, 0, 1, verdict=verdict) == []


def test_a_face_left_without_area_is_degenerate():
    m = fan_with_a_straight_side()
    locked = _mask(m.vertex_count, 1)    # 0 must land exactly on 1
    verdict = check_collapse(m, 0, 1, locked=locked)
    assert verdict.reason == "degenerate"
    assert _naive_refusals(m, 0, 1, locked=locked, verdict=verdict) == ["degenerate"]
    # the artefact's counters file it with the flips
    assert rules.REJECT_REASONS[rules.COUNTED_AS[rules.REJECT_DEGENERATE]] == "flip"
    # positive control: into the vertex across the fan nothing degenerates
    other = check_collapse(m, 0, 4, locked=_mask(m.vertex_count, 4))
    assert other.reason is None and other.survivor == 4


def test_close_pairs_need_a_threshold_and_stay_close():
    m = two_triangles(gap=0.1)
    assert check_collapse(m, 0, 3).reason == "not_an_edge"
    verdict = check_collapse(m, 0, 3, DecimateOptions(pair_threshold=0.2))
    assert verdict.reason is None
    assert check_collapse(m, 0, 3, DecimateOptions(pair_threshold=0.1)).reason == "pair_too_far"


def test_reason_table_is_consistent():
    assert len(set(rules.REASON_NAMES)) == rules.REASON_COUNT
    assert rules.REJECT_REASONS[:3] == ("stale", "not_an_edge", "non_manifold_edge")
    assert len(rules.REJECT_REASONS) == 12          # the artefact's counters, unchanged
    for i, name in enumerate(rules.REASON_NAMES):
        assert getattr(rules, "REJECT_" + name.upper()) == i
    counts = np.arange(rules.REASON_COUNT)
    folded = rules.rejected_counts(counts)
    assert sum(folded.values()) == counts.sum()
    assert folded["flip"] == rules.REJECT_FLIP + rules.REJECT_DEGENERATE
    # a locked vertex may absorb anything and vanish into nothing
    assert rules.CAN_COLLAPSE[:rules.LOCKED, rules.LOCKED].all()
    assert not rules.CAN_COLLAPSE[rules.LOCKED].any()


# --------------------------------------------------------------------------
# The kernel against the reference on every edge
# --------------------------------------------------------------------------

def _edges(faces):
    return sorted({(min(int(f[k]), int(f[(k + 1) % 3])), max(int(f[k]), int(f[(k + 1) % 3])))
                   for f in faces for k in range(3)})


def _noisy(name, seed, scale=0.02):
    m = mesh(name)
    rng = np.random.default_rng(seed)
    return Mesh(m.positions + rng.normal(scale=scale, size=m.positions.shape), m.faces)


def _compact(positions, faces):
    used = np.unique(faces)
    remap = np.full(len(positions), -1)
    remap[used] = np.arange(len(used))
    return Mesh(positions[used], remap[faces])


def _soup(seed, n=12, m=20):
    """Random triangles over a few vertices, cleaned: open sheets, fans,
    non-manifold edges and bow ties."""
    from lodserver.io import clean_mesh
    rng = np.random.default_rng(seed)
    faces = np.array([rng.choice(n, 3, replace=False) for _ in range(m)])
    return clean_mesh(rng.normal(size=(n, 3)), faces)[0]


# (mesh, seed, flip_cos, fraction of vertices locked)
SMALL = [("icosphere", 0, 0.2, 0.0), ("icosphere", 1, 0.9, 0.1), ("grid", 2, 0.2, 0.0),
         ("grid", 3, 0.95, 0.05), ("two_boxes", 4, 0.2, 0.0), ("tent", 5, 0.2, 0.0),
         ("strip", 6, 0.2, 0.0), ("soup", 7, 0.2, 0.0), ("soup", 8, 0.5, 0.0),
         ("soup", 9, 0.2, 0.2)]


def _small(name, seed):
    if name == "tent":
        return tent()
    if name == "strip":
        return strip()
    if name == "soup":
        return _soup(seed)
    m = _noisy(name, seed)
    # cut a small piece: the pure-Python reference is slow
    keep = m.positions[:, 2] > 0.6 if name == "icosphere" else m.positions[:, 1] < 0.3
    if name != "two_boxes":
        m = _compact(m.positions, m.faces[keep[m.faces].all(axis=1)])
    return m


@pytest.mark.parametrize("name,seed,flip_cos,locked_share", SMALL)
def test_every_edge_gets_the_reference_verdict(name, seed, flip_cos, locked_share):
    m = _small(name, seed)
    locked = np.random.default_rng(seed).random(m.vertex_count) < locked_share
    unit, lo, extent = naive.unit_frame(m.positions)
    kind = naive.vertex_kinds(m.faces, m.vertex_count, locked)
    K, _ = naive.quadric_matrices(unit, m.faces)
    legal = []
    for a, b in _edges(m.faces):
        verdict = check_collapse(m, a, b, DecimateOptions(preserve_volume=False,
                                                                 flip_cos=flip_cos), locked=locked)
        planned = naive.plan(unit, K, kind, a, b)
        if planned is None:
            assert verdict.reason == "locked"
            continue
        s, p, cost = planned
        assert verdict.survivor == s
        # quadric cost and placement: the same, up to the solver's rounding
        assert verdict.cost == pytest.approx(cost, rel=1e-6, abs=1e-12)
        assert np.allclose((verdict.position - lo) / extent, p, atol=1e-7)
        expected = naive.refusals(unit, m.faces, kind, s, b if s == a else a,
                                  (verdict.position - lo) / extent, flip_cos)
        assert verdict.reason == (expected[0] if expected else None), (a, b, expected)
        if not expected:
            legal.append((verdict.cost, s, b if s == a else a))
    # the first collapse decimate takes is the cheapest legal one
    legal.sort()
    if len(legal) > 1 and legal[1][0] > legal[0][0] * (1 + 1e-9):
        first = decimate(m, DecimateOptions(max_collapses=1, preserve_volume=False,
                                             flip_cos=flip_cos), locked=locked)
        assert (first.survivor[0], first.removed[0]) == legal[0][1:]


def test_the_geometry_only_rank_is_the_full_rank_bit_for_bit():
    """``rank_geometry`` (meshes without attributes) computes what
    ``rank_collapse`` does: the same cost, survivor and placement bits, on
    every edge of a mesh with borders and locked vertices."""
    from lodserver.simplify.collapse import _prepare
    from lodserver.simplify.rank import rank_collapse, rank_geometry
    from lodserver.simplify.state import new_scratch, new_topology

    m = mesh("grid")
    locked = _mask(m.vertex_count, *range(40, 80))
    verts, faces, wedges, _, _, _ = _prepare(m, DecimateOptions(), locked)
    topo = new_topology(faces.astype(np.int32), m.vertex_count)
    full, lean = new_scratch(m.vertex_count), new_scratch(m.vertex_count)
    edges = np.unique(np.sort(np.r_[m.faces[:, :2], m.faces[:, 1:], m.faces[:, ::2]], axis=1),
                      axis=0)
    locked_pairs = 0
    for a, b in edges:
        cost, s, _, _, reason = rank_collapse(a, b, verts.pos, verts.quadrics, verts.kind,
                                              full.q, full.p, full.pairs, topo, wedges)
        lean_cost, lean_s = rank_geometry(a, b, verts.pos, verts.quadrics, verts.kind, lean.q,
                                          lean.p)
        assert lean_cost == cost or (np.isinf(lean_cost) and np.isinf(cost))
        if reason == rules.REJECT_LOCKED:
            assert lean_s == -1
            locked_pairs += 1
            continue
        assert lean_s == s
        np.testing.assert_array_equal(lean.p, full.p)
        np.testing.assert_array_equal(lean.q, full.q)
    assert locked_pairs > 0
