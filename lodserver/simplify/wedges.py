"""Appearance attributes in edge collapse: wedges, their quadrics, their merges.

Hoppe, "New quadric metric for simplifying meshes with appearance
attributes" (IEEE Visualization 1999): the corners of a vertex that share an
attribute vector form a wedge; every wedge carries an attribute quadric
(``quadrics.wedge_quadrics``). Collapsing an edge merges the wedges paired by
the faces on the edge and solves their attributes with the position; every
other wedge keeps its value wherever the vertex goes.

``Wedges`` holds the kernel's wedge state (all empty for a geometry-only
mesh); the compiled steps here rank (``add_wedge_terms``) and perform
(``merge_wedges``) the attribute side of a collapse.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import njit

from ..mesh import is_solved
from .quadrics import add_fixed, add_reduced, best_attributes, seam_edges, wedge_quadrics
from .state import NO_REFCOUNT

# Default weight of each attribute's squared error against squared distance in
# the unit box (positions are scaled so the longest box side is 1): with 0.3, a
# UV error of 0.01 costs as much as a geometric error of 0.55% of the model's
# size. Chosen on the textured shared meshes (bench/appearance.py): heavier
# weights bought little texture accuracy for much geometric error. Normals
# weigh least: their field varies with curvature (1/radius per unit length),
# so even a small weight pins vertices against sliding along the surface, and
# normals come out right wherever the geometry does.
DEFAULT_ATTRIBUTE_WEIGHTS = {"NORMAL": 0.003, "TEXCOORD_0": 0.3, "TEXCOORD_1": 0.3, "COLOR_0": 0.3}

# corner (3m,) int32: the wedge of every face corner; quadric (w, 11 + 4d) and
# value (w, d): attribute quadrics and values scaled by sqrt(weight), updated
# in place; fixed (n, 11): per vertex, the summed fixed-value quadrics of its
# wedges (columns :10) and their number (column 10); mark (w,) and stamp (1,):
# visit marks; merged (d,): scratch for a merged value. Columns
# ``normal_col .. +3`` are renormalised to ``normal_len`` and ``color_col .. +4``
# clamped to [0, color_max] after a merge (-1: absent).
Wedges = namedtuple("Wedges", "corner quadric value fixed mark stamp merged "
                              "normal_col normal_len color_col color_max")

# The steps below run per candidate or per collapse and allocate nothing:
# they are compiled without reference counting (``state.NO_REFCOUNT``), as a
# namedtuple argument otherwise costs a count per array on every call.


def attribute_weight(name: str, weights: dict) -> float:
    """The weight of solved attribute ``name``: ``weights[name]``, else that of the first
    of its family (``TEXCOORD_0`` for every ``TEXCOORD_n``, ``COLOR_0`` for ``COLOR_n``),
    else the family's default."""
    family = name.rsplit("_", 1)[0] + "_0" if name.startswith(("TEXCOORD_", "COLOR_")) else name
    return float(weights.get(name, weights.get(family, DEFAULT_ATTRIBUTE_WEIGHTS[family])))


def attribute_scales(layout, weights: dict | None) -> np.ndarray:
    """(d,) float64: sqrt(weight) for every attribute column of ``layout`` (solved
    attributes only: carried ones have no quadric, ``simplify.carried``)."""
    weights = dict(weights or {})
    unknown = set(weights) - {name for name, _ in layout} - set(DEFAULT_ATTRIBUTE_WEIGHTS)
    if unknown:
        raise ValueError(f"no attribute named {', '.join(sorted(unknown))}; "
                         f"known are {', '.join(DEFAULT_ATTRIBUTE_WEIGHTS)}")
    carried = [name for name, _ in layout if not is_solved(name)]
    if carried:
        raise ValueError(f"the decimation kernel ranks solved attributes only, not "
                         f"{', '.join(carried)}: decimate simplify.carried.solved_part(mesh) "
                         f"and complete the log with simplify.carried.complete_log")
    scales = []
    for name, width in layout:
        weight = attribute_weight(name, weights)
        if not 0 < weight < float("inf"):
            raise ValueError(f"the weight of {name} must be a positive number, got {weight}")
        scales += [np.sqrt(weight)] * width
    return np.array(scales, dtype=np.float64)


def texture_seams(mesh):
    """``seam_edges`` over the wedges as UVs and colours alone see them.

    Seams where only the normal changes are creases: the geometric quadrics
    already keep a real crease, and pinning the many shallow ones that
    exporters leave (Duck.glb's median 13 degrees) with planes costs far more
    geometric error than it saves.
    """
    attributes = mesh.attributes
    keep = np.ones(attributes.width, dtype=bool)
    normal = attributes.columns("NORMAL")
    if normal is not None:
        keep[normal] = False
    if not keep.any():
        return None
    rows = np.concatenate([mesh.wedge_vertices()[:, None].astype(np.float64),
                           attributes.values[:, keep]], axis=1)
    _, texture_wedge = np.unique(rows, axis=0, return_inverse=True)
    return seam_edges(mesh.faces, texture_wedge.ravel()[attributes.corners])


def wedge_inputs(attributes, unit, faces, weights, n):
    """The kernel's ``Wedges`` for a mesh of ``n`` vertices (``unit``: positions
    in the unit box), and the (d,) sqrt(weight) scales of the attribute
    columns. Empty arrays for a geometry-only mesh (``attributes`` None)."""
    if attributes is None:
        corner, wq, wval, scales = (np.zeros(0, np.int64), np.zeros((0, 11)), np.zeros((0, 0)),
                                    np.ones(0))
        columns = (-1, 1.0, -1, 1.0)
    else:
        scales = attribute_scales(attributes.layout, weights)
        wval = attributes.values * scales
        wq = wedge_quadrics(unit, faces, attributes.corners, wval)
        corner = attributes.corners.ravel()
        normal = attributes.columns("NORMAL")
        color = attributes.columns("COLOR_0")
        columns = (-1 if normal is None else normal.start,
                   1.0 if normal is None else float(scales[normal.start]),
                   -1 if color is None else color.start,
                   1.0 if color is None else float(scales[color.start]))
    d = wval.shape[1]
    has = wq.shape[0] > 0
    wedges = Wedges(corner.astype(np.int32), wq, wval, np.zeros((n if has else 0, 11)),
                    np.zeros(wq.shape[0], np.int64), np.zeros(1, np.int64),
                    np.empty(d, np.float64), *columns)
    return wedges, scales


@njit(**NO_REFCOUNT)
def vertex_fixed(v, topo, wedges):
    """fixed[v, :10] = the sum of the fixed-value quadrics of v's wedges,
    fixed[v, 10] their number."""
    # fields read once, outside the loop (each read is a reference count)
    fv, corner, mark, wq, wval = wedges.fixed, wedges.corner, wedges.mark, wedges.quadric, wedges.value
    face_alive, cnext = topo.face_alive, topo.cnext
    wedges.stamp[0] += 1
    stamp = wedges.stamp[0]
    for j in range(11):
        fv[v, j] = 0.0
    c = topo.vhead[v]
    while c >= 0:
        if face_alive[c // 3]:
            w = corner[c]
            if mark[w] != stamp:
                mark[w] = stamp
                add_fixed(fv[v], wq, w, wval[w], 1.0)
                fv[v, 10] += 1.0
        c = cnext[c]


@njit(cache=True, nogil=True, inline="always")
def fill_fixed(topo, wedges):
    """``vertex_fixed`` of every vertex (no-op without wedges)."""
    if wedges.quadric.shape[0] > 0:
        for v in range(topo.vhead.shape[0]):
            vertex_fixed(v, topo, wedges)


@njit(**NO_REFCOUNT)
def add_wedge_terms(a, b, q, topo, wedges, pairs):
    """Add the attribute terms of collapsing (a, b) to ``q``.

    The faces on the edge pair each wedge of ``a`` with one of ``b``; such a
    pair merges into one wedge whose attributes are solved for (Hoppe's
    reduced quadric). Every other wedge of ``a`` and ``b`` keeps its value
    wherever the vertex goes (its fixed-value quadric, summed per vertex in
    ``fixed``). A seam along the edge keeps both sides (two pairs).

    Returns (legal, pair count, seams meet): ``pairs[g] = (a's wedge, b's
    wedge)`` for each pair. Not legal when the collapse would merge two wedges
    of one vertex, i.e. drag a seam across the surface (or the edge has three
    faces). Seams meet when both endpoints keep a wedge the other has no
    partner for: one of them is dragged off its seam whatever the placement,
    and the caller multiplies the cost by SEAM_PENALTY.
    """
    fv, cw, wq, wval = wedges.fixed, wedges.corner, wedges.quadric, wedges.value
    faces, cnext, face_alive = topo.faces, topo.cnext, topo.face_alive
    for j in range(10):
        q[j] += fv[a, j] + fv[b, j]
    n = 0
    c = topo.vhead[a]
    while c >= 0:
        f = c // 3
        if face_alive[f]:
            slot = c - 3 * f
            for t in range(1, 3):
                k = (slot + t) % 3
                if faces[f, k] == b:
                    if n == 2:
                        return False, 0, False      # non-manifold edge
                    pairs[n, 0] = cw[c]
                    pairs[n, 1] = cw[3 * f + k]
                    n += 1
        c = cnext[c]
    if n == 2:
        same_a = pairs[0, 0] == pairs[1, 0]
        if same_a != (pairs[0, 1] == pairs[1, 1]):
            return False, 0, False
        if same_a:
            n = 1
    seams_meet = False
    if n > 0:
        # fixed[v, 10] counts v's wedges; the pairs hold n of each endpoint's
        seams_meet = fv[a, 10] > n and fv[b, 10] > n
    d = wval.shape[1]
    for g in range(n):
        wa = pairs[g, 0]
        wb = pairs[g, 1]
        add_fixed(q, wq, wa, wval[wa], -1.0)
        add_fixed(q, wq, wb, wval[wb], -1.0)
        add_reduced(q, wq, wa, wb, d)
    return True, n, seams_meet


@njit(**NO_REFCOUNT)
def merge_wedges(p, n_pairs, pairs, wedges, log_value, log_survivor, log_removed, at):
    """Merge each pair ``(survivor's wedge, removed's wedge)`` of ``pairs``:
    sum their quadrics and solve the attributes at ``p`` (the average where
    the quadric has no area), renormalise normals, clamp colours. Writes the
    merges into the log rows from ``at`` on; returns the next free row."""
    wq = wedges.quadric
    wval = wedges.value
    value = wedges.merged
    d = wval.shape[1]
    normal_col, normal_len = wedges.normal_col, wedges.normal_len
    color_col, color_max = wedges.color_col, wedges.color_max
    for g in range(n_pairs):
        ws = pairs[g, 0]
        wr = pairs[g, 1]
        for j in range(wq.shape[1]):
            wq[ws, j] += wq[wr, j]
        if wq[ws, 10] > 0.0:
            best_attributes(wq, ws, p[0], p[1], p[2], value)
        else:
            for j in range(d):
                value[j] = 0.5 * (wval[ws, j] + wval[wr, j])
        if normal_col >= 0:
            length = np.sqrt(value[normal_col] ** 2 + value[normal_col + 1] ** 2
                             + value[normal_col + 2] ** 2)
            if length > 0.0:
                for j in range(normal_col, normal_col + 3):
                    value[j] *= normal_len / length
        if color_col >= 0:
            for j in range(color_col, color_col + 4):
                value[j] = min(max(value[j], 0.0), color_max)
        for j in range(d):
            wval[ws, j] = value[j]
            log_value[at, j] = value[j]
        log_survivor[at] = ws
        log_removed[at] = wr
        at += 1
    return at
