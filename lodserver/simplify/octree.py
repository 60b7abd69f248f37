"""Octree vertex clustering recorded as collapses: a progressive mesh in one fast pass.

``cluster`` merges the vertices of one uniform grid at once. Here the grids
are the levels of an octree, finest first: at depth ``d`` (``2^d`` cells along
the longest side of the bounding box) the clusters of depth ``d + 1`` that share
a cell merge into one. The cells nest, so the clusters form a vertex hierarchy,
and every merge is written down as a collapse of one vertex into another:

- the cluster's survivor is the member vertex with the most faces; the others
  merge into it one at a time;
- a face holding both vertices of a merge vanishes (it has collapsed), and so
  does a face that lands on the same three vertices as a face already there
  (clustering folds parts onto each other; keeping both would be a duplicate).
  Both can only involve the survivor's own faces, so the check is local: a
  merge costs the two vertices' degrees, and no global face table is kept;
- the survivor moves to the cell's quadric-optimal representative (Lindstrom
  2000), kept inside the cell; the logged error is that placement's RMS
  quadric distance.

Within a depth, cells merge cheapest first. The log feeds
``progressive.from_collapse_log`` unchanged, so the result has every property
of an edge-collapse progressive mesh: replaying all splits gives the input
back exactly, any level is a prefix, levels are the same from any direction.
What it does not keep is topology: clustering may join parts, close holes and
leave non-manifold edges (which is the point of it for far levels and huge
inputs). Every level is exact; the octree depths are the levels where all
merges of a depth are done, the levels between them are partly merged depths.

Attributes are not simplified here: the result is geometry only.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..mesh import Mesh
from ..mesh import to_unit_box, unit_box
from .quadrics import optimal_position_xyz, quadric_error, vertex_quadrics
from .log import CollapseLog, log_arrays
from .queue import grow
from .topology import link_corners

# Finest depth: about this many cells per vertex spacing of a surface of n
# vertices (cells ~ sqrt(n) along a side), so the first depth merges only
# near-coincident vertices; capped by the 21 bits a cell coordinate gets.
_FINE_CELLS_PER_SPACING = 8
_MAX_DEPTH = 20


def octree_log(mesh: Mesh) -> CollapseLog:
    """Cluster ``mesh`` over every octree depth, logging each merge as a collapse.

    Returns
    -------
    CollapseLog
        Survivors, removed vertices, positions (mesh units), errors (RMS
        quadric distance, mesh units), killed faces and moved corners, as
        ``collapse.decimate`` returns them.
    """
    positions = np.asarray(mesh.positions, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    lo, extent = unit_box(positions)
    unit = to_unit_box(positions, lo, extent)
    quadrics = vertex_quadrics(unit, faces, boundary_weight=0)
    cells = _FINE_CELLS_PER_SPACING * np.sqrt(max(len(positions), 1))
    depth = int(min(_MAX_DEPTH, max(1, np.ceil(np.log2(cells)))))
    (s, r, p, error, killed_off, killed, moved_off, moved) = _octree_kernel(
        unit, faces, quadrics, depth)
    return CollapseLog(
        survivor=s, removed=r, position=lo + extent * p, error=error * extent,
        killed_offsets=killed_off, killed_faces=killed, moved_offsets=moved_off,
        moved_corners=moved, rejected={}, passes=depth + 1)


@njit(cache=True, nogil=True)
def _octree_kernel(unit, faces, quadrics, fine_depth):
    n = unit.shape[0]
    m = faces.shape[0]
    faces = faces.copy()
    vhead = np.full(n, -1, np.int64)
    cnext = np.full(3 * m, -1, np.int64)
    face_count = np.zeros(n, np.int64)
    link_corners(faces, vhead, cnext, face_count)
    face_alive = np.ones(m, np.bool_)
    alive_faces = m
    mark = np.zeros(n, np.int64)
    stamp = 0
    q = quadrics.copy()
    pos = unit.copy()

    log_s, log_r, log_p, log_e, killed_off, killed, moved_off, moved = log_arrays(n, m)
    nk = 0
    nkilled = 0
    nmoved = 0

    active = np.nonzero(face_count > 0)[0]
    qsum = np.empty(11)
    p = np.empty(3)
    for depth in range(fine_depth, -1, -1):
        cells = 1 << depth
        keys = np.empty(active.shape[0], np.int64)
        for i in range(active.shape[0]):
            v = active[i]
            # the cell of a cluster is that of its survivor's input position:
            # cells nest, so every member falls in the same one
            x = min(int(unit[v, 0] * cells), cells - 1)
            y = min(int(unit[v, 1] * cells), cells - 1)
            z = min(int(unit[v, 2] * cells), cells - 1)
            keys[i] = (x * cells + y) * cells + z
        order = np.argsort(keys, kind="mergesort")
        # runs of equal keys are this depth's cells; price the ones with 2+ clusters
        starts = np.empty(active.shape[0] + 1, np.int64)
        nruns = 0
        i = 0
        while i < order.shape[0]:
            j = i + 1
            while j < order.shape[0] and keys[order[j]] == keys[order[i]]:
                j += 1
            if j - i > 1:
                starts[nruns] = i
                nruns += 1
            i = j
        if nruns == 0:
            continue
        run_error = np.empty(nruns)
        run_pos = np.empty((nruns, 3))
        run_end = np.empty(nruns, np.int64)
        for g in range(nruns):
            i = starts[g]
            j = i + 1
            while j < order.shape[0] and keys[order[j]] == keys[order[i]]:
                j += 1
            run_end[g] = j
            qsum[:] = 0.0
            mx = 0.0; my = 0.0; mz = 0.0
            for k in range(i, j):
                v = active[order[k]]
                for c in range(11):
                    qsum[c] += q[v, c]
                mx += pos[v, 0]; my += pos[v, 1]; mz += pos[v, 2]
            count = j - i
            mx /= count; my /= count; mz /= count
            optimal_position_xyz(qsum, mx, my, mz, mx, my, mz, p)
            # inside the cell: a far-off optimum of a flat cell would fold faces
            v = active[order[i]]
            size = 1.0 / cells
            for c in range(3):
                low = min(int(unit[v, c] * cells), cells - 1) * size
                p[c] = min(max(p[c], low), low + size)
            run_pos[g, 0] = p[0]; run_pos[g, 1] = p[1]; run_pos[g, 2] = p[2]
            area = qsum[10]
            e = max(quadric_error(qsum, p[0], p[1], p[2]), 0.0)
            run_error[g] = np.sqrt(e / area) if area > 0.0 else 0.0
        merged = np.zeros(n, np.bool_)
        for g in np.argsort(run_error, kind="mergesort"):
            i = starts[g]
            j = run_end[g]
            s = active[order[i]]
            for k in range(i + 1, j):
                if face_count[active[order[k]]] > face_count[s]:
                    s = active[order[k]]
            for k in range(i, j):
                r = active[order[k]]
                if r == s:
                    continue
                # never remove the last faces: the base mesh must keep one
                shared = 0
                c = vhead[r]
                while c >= 0:
                    f = c // 3
                    if face_alive[f] and (faces[f, 0] == s or faces[f, 1] == s or faces[f, 2] == s):
                        shared += 1
                    c = cnext[c]
                if alive_faces - shared <= 0:
                    continue
                # s's faces as pairs of their other two vertices: a face of r
                # that lands on one of them is a duplicate, and goes
                stamp += 1
                deg = 0
                c = vhead[s]
                while c >= 0:
                    deg += 1
                    c = cnext[c]
                px = np.empty(deg, np.int64)
                py = np.empty(deg, np.int64)
                npairs = 0
                c = vhead[s]
                while c >= 0:
                    f = c // 3
                    if face_alive[f]:
                        slot = c - 3 * f
                        px[npairs] = faces[f, (slot + 1) % 3]
                        py[npairs] = faces[f, (slot + 2) % 3]
                        mark[px[npairs]] = stamp
                        mark[py[npairs]] = stamp
                        npairs += 1
                    c = cnext[c]
                c = vhead[r]
                while c >= 0:
                    nxt = cnext[c]
                    f = c // 3
                    if face_alive[f]:
                        if faces[f, 0] == s or faces[f, 1] == s or faces[f, 2] == s:
                            gone = True
                        else:
                            slot = c - 3 * f
                            faces[f, slot] = s
                            x = faces[f, (slot + 1) % 3]
                            y = faces[f, (slot + 2) % 3]
                            gone = False
                            if mark[x] == stamp and mark[y] == stamp:
                                for i in range(npairs):
                                    if (px[i] == x and py[i] == y) or (px[i] == y and py[i] == x):
                                        gone = True
                                        break
                            if not gone:
                                # a corner moves each time its vertex merges: more
                                # moves than corners are possible, so grow
                                if nmoved >= moved.shape[0]:
                                    moved = grow(moved, nmoved + 1)
                                moved[nmoved] = c
                                nmoved += 1
                                cnext[c] = vhead[s]
                                vhead[s] = c
                        if gone:
                            face_alive[f] = False
                            alive_faces -= 1
                            killed[nkilled] = f
                            nkilled += 1
                            for t in range(3):
                                face_count[faces[f, t]] -= 1
                            if faces[f, c - 3 * f] == s and faces[f, 0] != r \
                                    and faces[f, 1] != r and faces[f, 2] != r:
                                # a duplicate: its corner was counted at r, not s
                                face_count[s] += 1
                                face_count[r] -= 1
                        else:
                            face_count[s] += 1
                            face_count[r] -= 1
                    c = nxt
                vhead[r] = -1
                merged[r] = True
                for t in range(11):
                    q[s, t] += q[r, t]
                pos[s, 0] = run_pos[g, 0]; pos[s, 1] = run_pos[g, 1]; pos[s, 2] = run_pos[g, 2]
                log_s[nk] = s
                log_r[nk] = r
                log_p[nk, 0] = pos[s, 0]; log_p[nk, 1] = pos[s, 1]; log_p[nk, 2] = pos[s, 2]
                log_e[nk] = run_error[g]
                nk += 1
                killed_off[nk] = nkilled
                moved_off[nk] = nmoved
        kept = 0
        for i in range(active.shape[0]):
            if not merged[active[i]]:
                active[kept] = active[i]
                kept += 1
        active = active[:kept]
    return (log_s[:nk], log_r[:nk], log_p[:nk], log_e[:nk], killed_off[:nk + 1],
            killed[:nkilled], moved_off[:nk + 1], moved[:nmoved])


# The compiled kernel whose on-disk cache build.kernels_cold reads to tell a first run.
MAIN_KERNEL = _octree_kernel
