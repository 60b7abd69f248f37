"""Carried attributes: the wedge values no quadric ranks, filled into a collapse log.

Tangents, skin influences (``JOINTS_n``/``WEIGHTS_n``), morph target deltas
(``TARGET{t}_*``) and custom ``_NAME`` attributes are CARRIED
(``mesh.ATTRIBUTE_RULES``): the kernel ranks and performs collapses on the
SOLVED columns alone (normals, UVs, colours: Hoppe 1999's attribute quadrics),
and the error skinning and morphing add is counted by pose quadrics
(``simplify.poses``). Afterwards, :func:`complete_log` replays the log once and
gives every merged wedge its carried value:

- ``t`` is where the new position projects onto the collapsed edge (0 at the
  survivor, 1 at the removed vertex, clamped), so a vertex placed at the edge's
  middle takes half of each end, one left at the survivor keeps its own value;
- each rule of ``MERGES`` then makes the interpolated value valid again.

Skin influences and morph deltas belong to the vertex, not the corner: if two
wedges of one vertex (the sides of a UV seam) disagree on them, the seam tears
open when the asset moves. A merge changes only the merged wedges, so which
values these take depends on which wedges the collapse leaves unmerged:

===========================  ==========================  ===================
survivor's wedges            removed vertex's wedges      per-vertex values
===========================  ==========================  ===================
all merged                   all merged                   interpolated at t
some unmerged (a seam)       all merged                   the survivor's
all merged                   some unmerged (moved over)   the removed's
some unmerged                some unmerged                the survivor's
===========================  ==========================  ===================

Only the last row (seams meeting, which the kernel's seam penalty makes rare)
leaves a vertex whose wedges disagree.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit

from ..mesh import Attributes, Mesh, attribute_rule, split_layout

# merge rule -> its code in the compiled replay (ATTRIBUTE_RULES' "merge" column)
VALUE, TANGENT, SKIN, VERTEX = 0, 1, 2, 3
MERGES = {"value": VALUE, "tangent": TANGENT, "skin": SKIN, "vertex": VERTEX}


def solved_part(mesh: Mesh) -> Mesh:
    """``mesh`` with only its SOLVED attribute columns (what the decimation kernel
    ranks); the same corners, so wedge ids are those of ``mesh``. ``mesh`` itself
    when nothing is carried."""
    attributes = mesh.attributes
    if attributes is None:
        return mesh
    solved, carried = split_layout(attributes.layout)
    if not len(carried):
        return mesh
    layout = tuple((name, width) for name, width in attributes.layout
                   if attribute_rule(name, width)[1] != "carried")
    part = Attributes(layout, attributes.values[:, solved], attributes.corners)
    return replace(mesh, attributes=part)


def carried_groups(layout) -> tuple[np.ndarray, np.ndarray]:
    """The carried column groups of ``layout``: ``groups (k, 3)`` int64 rows of
    (first column, width, merge code) in the full attribute vector, and ``skin (s, 2)``
    the (JOINTS_n first column, WEIGHTS_n first column) of every skin set, in n order.
    Every skin set is merged together, once, in the first ``JOINTS_n`` group's turn."""
    groups, joints, weights, start = [], {}, {}, 0
    for name, width in layout:
        _, kind, merge = attribute_rule(name, width)
        if kind == "carried":
            if merge == "skin":
                (joints if name.startswith("JOINTS_") else weights)[int(name.rsplit("_", 1)[1])] = start
            else:
                groups.append((start, width, MERGES[merge]))
        start += width
    if set(joints) != set(weights):
        raise ValueError("every JOINTS_n needs its WEIGHTS_n and the other way round")
    skin = np.array([(joints[n], weights[n]) for n in sorted(joints)], dtype=np.int64).reshape(-1, 2)
    if len(skin):
        groups.append((int(skin[0, 0]), 4, SKIN))
    return np.array(groups, dtype=np.int64).reshape(-1, 3), skin


def complete_log(mesh: Mesh, log):
    """``log`` (decimation of :func:`solved_part` of ``mesh``) with ``merge_value``
    widened to every column of ``mesh.attributes``: the solved columns as the kernel
    left them, the carried ones interpolated (module docstring). ``log`` itself when
    nothing is carried."""
    attributes = mesh.attributes
    if attributes is None or log.merge_value is None:
        return log
    solved, carried = split_layout(attributes.layout)
    if not len(carried):
        return log
    groups, skin = carried_groups(attributes.layout)
    normal = attributes.columns("NORMAL")
    value = np.zeros((len(log.merge_survivor), attributes.width), dtype=np.float64)
    value[:, solved] = log.merge_value
    owner = mesh.wedge_vertices()
    live = np.bincount(owner[owner >= 0], minlength=mesh.vertex_count).astype(np.int64)
    _replay(np.asarray(mesh.positions, dtype=np.float64).copy(), log.survivor, log.removed,
            log.position, log.merge_offsets, log.merge_survivor, log.merge_removed,
            attributes.values.copy(), value, groups, skin, -1 if normal is None else normal.start,
            live)
    return replace(log, merge_value=value)


@njit(cache=True, nogil=True)
def _replay(positions, survivor, removed, position, offsets, merge_survivor, merge_removed,
            current, value, groups, skin, normal_col, live):
    """Fill the carried columns of ``value`` (g, d), collapse by collapse.

    positions (n, 3), current (w, d) and live (n,) are scratch: every vertex's
    position, every wedge's full value and every vertex's wedge count as the log
    has them so far. ``value``'s solved columns (the normal among them) are already
    the merged ones.
    """
    k = survivor.shape[0]
    d = current.shape[1]
    sets = skin.shape[0]
    joint = np.empty(8 * max(sets, 1), np.float64)
    weight = np.empty(8 * max(sets, 1), np.float64)
    for i in range(k):
        s, r = survivor[i], removed[i]
        # where the new position projects onto the edge, survivor = 0, removed = 1
        ex = positions[r, 0] - positions[s, 0]
        ey = positions[r, 1] - positions[s, 1]
        ez = positions[r, 2] - positions[s, 2]
        length2 = ex * ex + ey * ey + ez * ez
        t = 0.5
        if length2 > 0.0:
            t = ((position[i, 0] - positions[s, 0]) * ex + (position[i, 1] - positions[s, 1]) * ey
                 + (position[i, 2] - positions[s, 2]) * ez) / length2
            t = min(max(t, 0.0), 1.0)
        pairs = offsets[i + 1] - offsets[i]
        # per-vertex values: the table in the module docstring
        whole_s, whole_r = live[s] == pairs, live[r] == pairs
        tv = t if whole_s and whole_r else (1.0 if whole_s else 0.0)
        live[s] += live[r] - pairs
        for g in range(offsets[i], offsets[i + 1]):
            a, b = merge_survivor[g], merge_removed[g]
            for row in range(groups.shape[0]):
                first, width, rule = groups[row, 0], groups[row, 1], groups[row, 2]
                if rule == SKIN and 0.0 < tv < 1.0:
                    _merge_skin(current, a, b, tv, skin, value, g, joint, weight)
                    continue
                if rule == SKIN:
                    # one end's influences, bit for bit (as the vertex's other wedges have them)
                    end = a if tv == 0.0 else b
                    for row2 in range(skin.shape[0]):
                        for k in range(4):
                            value[g, skin[row2, 0] + k] = current[end, skin[row2, 0] + k]
                            value[g, skin[row2, 1] + k] = current[end, skin[row2, 1] + k]
                    continue
                f = tv if rule == VERTEX else t
                for j in range(first, first + width):
                    value[g, j] = (1.0 - f) * current[a, j] + f * current[b, j]
                if rule == TANGENT:
                    _fix_tangent(value, g, first, normal_col, current, a, b, t)
            # the merged wedge now holds every column of value[g]
            for j in range(d):
                current[a, j] = value[g, j]
        positions[s, 0] = position[i, 0]
        positions[s, 1] = position[i, 1]
        positions[s, 2] = position[i, 2]


@njit(cache=True, nogil=True, inline="always")
def _fix_tangent(value, g, first, normal_col, current, a, b, t):
    """Make the interpolated tangent unit and orthogonal to the merged normal
    (Gram-Schmidt), with the handedness of the nearer end. Where interpolation
    cancels it out (opposite tangents), the survivor's direction is used."""
    for attempt in range(2):
        x, y, z = value[g, first], value[g, first + 1], value[g, first + 2]
        if normal_col >= 0:
            nx, ny, nz = value[g, normal_col], value[g, normal_col + 1], value[g, normal_col + 2]
            nn = nx * nx + ny * ny + nz * nz
            if nn > 0.0:
                dot = (x * nx + y * ny + z * nz) / nn
                x, y, z = x - dot * nx, y - dot * ny, z - dot * nz
        length = np.sqrt(x * x + y * y + z * z)
        if length > 1e-12:
            value[g, first], value[g, first + 1], value[g, first + 2] = (x / length, y / length,
                                                                         z / length)
            break
        for j in range(3):
            value[g, first + j] = current[a, first + j]
    end = a if t <= 0.5 else b
    value[g, first + 3] = -1.0 if current[end, first + 3] < 0.0 else 1.0


@njit(cache=True, nogil=True, inline="always")
def _merge_skin(current, a, b, t, skin, value, g, joint, weight):
    """The influences of wedges ``a`` (weight 1 - t) and ``b`` (t), every set together:
    summed per joint, the 4 x sets largest kept (ties: the lower joint), weights
    renormalised to sum 1, written heaviest first into JOINTS_0/WEIGHTS_0, JOINTS_1/...
    Unused slots get joint 0 with weight 0."""
    sets = skin.shape[0]
    count = 0
    for end in range(2):
        w = a if end == 0 else b
        factor = 1.0 - t if end == 0 else t
        for s in range(sets):
            for k in range(4):
                jw = current[w, skin[s, 1] + k] * factor
                if jw <= 0.0:
                    continue
                jj = current[w, skin[s, 0] + k]
                found = False
                for c in range(count):
                    if joint[c] == jj:
                        weight[c] += jw
                        found = True
                        break
                if not found:
                    joint[count] = jj
                    weight[count] = jw
                    count += 1
    # selection sort of the few influences: heaviest first, lower joint on ties
    keep = min(count, 4 * sets)
    for c in range(keep):
        best = c
        for e in range(c + 1, count):
            if weight[e] > weight[best] or (weight[e] == weight[best] and joint[e] < joint[best]):
                best = e
        joint[c], joint[best] = joint[best], joint[c]
        weight[c], weight[best] = weight[best], weight[c]
    total = 0.0
    for c in range(keep):
        total += weight[c]
    for s in range(sets):
        for k in range(4):
            c = 4 * s + k
            if c < keep and total > 0.0:
                value[g, skin[s, 0] + k] = joint[c]
                value[g, skin[s, 1] + k] = weight[c] / total
            else:
                value[g, skin[s, 0] + k] = 0.0
                value[g, skin[s, 1] + k] = 0.0
    if keep == 0:
        # neither end had a positive weight (an unskinned vertex): keep the survivor's
        for s in range(sets):
            for k in range(4):
                value[g, skin[s, 0] + k] = current[a, skin[s, 0] + k]
                value[g, skin[s, 1] + k] = current[a, skin[s, 1] + k]
