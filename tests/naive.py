"""Slow, obviously right reference versions that the compiled kernels are checked against."""

from __future__ import annotations

from collections import Counter, defaultdict

import numpy as np

from lodserver.mesh import to_unit_box, unit_box
from lodserver.simplify.quadrics import DET_RELATIVE_EPS, REGULARIZATION
from lodserver.simplify.rules import DEGENERATE_AREA


def plane_error(positions, faces, vertex, point):
    """Sum over the faces at ``vertex`` of area x squared distance from ``point`` to the face plane."""
    total = 0.0
    for face in faces:
        if vertex not in face:
            continue
        a, b, c = (np.asarray(positions[i], float) for i in face)
        normal = np.cross(b - a, c - a)
        double_area = np.linalg.norm(normal)
        if double_area == 0:
            continue
        distance = np.dot(normal / double_area, np.asarray(point) - a)
        total += 0.5 * double_area * distance * distance
    return total


def edge_face_counts(faces):
    """{(min, max): number of faces using that edge}."""
    counts = Counter()
    for face in faces:
        for k in range(3):
            a, b = int(face[k]), int(face[(k + 1) % 3])
            counts[(min(a, b), max(a, b))] += 1
    return counts


def fans(faces, n):
    """Edge-connected fans around each vertex, by flood fill over its faces."""
    around = defaultdict(list)
    for f, face in enumerate(faces):
        for v in face:
            around[int(v)].append(f)
    out = np.zeros(n, dtype=np.int64)
    for v, fs in around.items():
        unseen = set(fs)
        while unseen:
            out[v] += 1
            stack = [unseen.pop()]
            while stack:
                f = stack.pop()
                link = set(int(x) for x in faces[f]) - {v}
                for g in list(unseen):
                    if link & (set(int(x) for x in faces[g]) - {v}):
                        unseen.remove(g)
                        stack.append(g)
    return out


# --------------------------------------------------------------------------
# A pure-Python edge collapse: kinds, quadrics, placement, legality
# --------------------------------------------------------------------------
# Written from the papers, not from the kernel: quadrics as 4x4 matrices
# (Garland & Heckbert 1997, section 5), the placement by numpy's solver, the
# rules as set operations on the faces around the two vertices. Kinds:
# 0 interior, 1 border, 2 locked (simplify.rules).
# The tolerances (DET_RELATIVE_EPS, REGULARIZATION, DEGENERATE_AREA) are the
# kernel's own, imported above.


def vertex_kinds(faces, n, locked=None):
    """0 interior, 1 border (on an edge of one face), 2 locked (non-manifold
    edge, two or more fans, or in ``locked``)."""
    counts = edge_face_counts(faces)
    kind = np.zeros(n, dtype=np.int64)
    for (a, b), c in counts.items():
        if c == 1:
            kind[[a, b]] = np.maximum(kind[[a, b]], 1)
    for (a, b), c in counts.items():
        if c > 2:
            kind[[a, b]] = 2
    kind[fans(faces, n) > 1] = 2
    if locked is not None:
        kind[np.asarray(locked, bool)] = 2
    return kind


def plane_matrix(normal, d, weight):
    """The 4x4 quadric of the plane ``normal . p + d = 0``, times ``weight``."""
    v = np.append(normal, d)
    return weight * np.outer(v, v)


def quadric_matrices(positions, faces, boundary_weight=1.0):
    """Per vertex the 4x4 sum of its area-weighted face planes and of the planes
    through its border edges perpendicular to their face (weight
    ``boundary_weight * |edge|^2``), and its total face area."""
    positions = np.asarray(positions, float)
    n = len(positions)
    K = np.zeros((n, 4, 4))
    area = np.zeros(n)
    counts = edge_face_counts(faces)
    for face in faces:
        a, b, c = (positions[i] for i in face)
        normal = np.cross(b - a, c - a)
        double_area = np.linalg.norm(normal)
        if double_area == 0:
            continue
        unit = normal / double_area
        plane = plane_matrix(unit, -unit @ a, 0.5 * double_area)
        for v in face:
            K[v] += plane
            area[v] += 0.5 * double_area
        if boundary_weight > 0:
            for k in range(3):
                u, w = int(face[k]), int(face[(k + 1) % 3])
                if counts[(min(u, w), max(u, w))] != 1:
                    continue
                along = positions[w] - positions[u]
                perp = np.cross(along, normal)
                length = np.linalg.norm(perp)
                if length == 0:
                    continue
                perp /= length
                plane = plane_matrix(perp, -perp @ positions[u], boundary_weight * along @ along)
                K[u] += plane
                K[w] += plane
    return K, area


def quadric_cost(K, p):
    v = np.append(p, 1.0)
    return float(v @ K @ v)


def place(K, pa, pb):
    """G&H's placement: minimise ``K`` by a regularised solve (pulled towards
    the midpoint), and where ``K``'s 3x3 part is (nearly) singular keep the
    best of that, the midpoint and the endpoints. Returns (point, cost)."""
    A, b = K[:3, :3], K[:3, 3]
    mid = 0.5 * (pa + pb)
    trace = np.trace(A)
    eps = REGULARIZATION * trace
    M = A + eps * np.eye(3)
    candidates = []
    if trace > 0 and np.linalg.det(M) > 0:
        candidates.append(np.linalg.solve(M, eps * mid - b))
        if np.linalg.det(A) > DET_RELATIVE_EPS * trace ** 3:
            return candidates[0], quadric_cost(K, candidates[0])
    candidates += [mid, pa, pb]
    costs = [quadric_cost(K, c) for c in candidates]
    best = int(np.argmin(costs))
    return candidates[best], costs[best]


def plan(positions, K, kind, a, b):
    """Survivor, placement and cost of collapsing (a, b), or None if neither
    vertex may vanish into the other. A locked vertex never vanishes and never
    moves; a border vertex vanishes only into a border or locked one; a
    survives when both ways are open."""
    def may_vanish(r, s):
        return kind[r] == 0 or (kind[r] == 1 and kind[s] >= 1)
    if may_vanish(b, a):
        s = a
    elif may_vanish(a, b):
        s = b
    else:
        return None
    Q = K[a] + K[b]
    if kind[s] == 2:
        return s, positions[s].copy(), max(quadric_cost(Q, positions[s]), 0.0)
    p, cost = place(Q, positions[a], positions[b])
    return s, p, max(cost, 0.0)


def refusals(positions, faces, kind, s, r, p, flip_cos=0.2):
    """Every rule that refuses collapsing edge (s, r) of the initial mesh
    into s at ``p``, in the kernel's order of testing: a list of reason names
    (``simplify.rules.REASON_NAMES``), empty if the collapse is legal."""
    positions = np.asarray(positions, float)
    faces = [tuple(int(x) for x in f) for f in faces]
    at_s = [f for f in faces if s in f]
    at_r = [f for f in faces if r in f]
    shared = [f for f in at_s if r in f]
    out = []
    if not shared:
        return ["not_an_edge"]
    if len(shared) > 2:
        return ["non_manifold_edge"]
    both_border = kind[s] != 0 and kind[r] != 0
    if (len(shared) == 2) == both_border:
        out.append("pinch")
    opposite = {v for f in shared for v in f if v not in (s, r)}
    neighbours_s = {v for f in at_s for v in f} - {s, r}
    neighbours_r = {v for f in at_r for v in f} - {s, r}
    if neighbours_s & neighbours_r != opposite:
        out.append("link")
    if len(opposite) == 2:
        on = set(opposite)
        if any(set(f) - {s} == on for f in at_s) and any(set(f) - {r} == on for f in at_r):
            out.append("tetrahedron")
    remaining = len(set(at_s) | set(at_r)) - len(shared)
    alone = [o for o in opposite if sum(o in f for f in faces) <= 1]
    if remaining <= 0 or alone:
        out.append("last_face")
    # the faces that move, s's first, each in face order (as the kernel walks them)
    order = sorted(set(at_s) - set(shared), key=faces.index) + \
        sorted(set(at_r) - set(shared), key=faces.index)
    for f in order:
        before = positions[list(f)]
        after = before.copy()
        after[[k for k in range(3) if f[k] in (s, r)]] = p
        n0 = np.cross(before[1] - before[0], before[2] - before[0])
        n1 = np.cross(after[1] - after[0], after[2] - after[0])
        if n1 @ n1 <= DEGENERATE_AREA:
            out.append("degenerate")
            break
        if n0 @ n0 > DEGENERATE_AREA and n0 @ n1 <= flip_cos * np.sqrt((n0 @ n0) * (n1 @ n1)):
            out.append("flip")
            break
    return out


def unit_frame(positions):
    """Positions scaled into the unit box, as the kernel sees them: (unit, lo, extent)."""
    lo, extent = unit_box(positions)
    return to_unit_box(positions, lo, extent), lo, extent
