"""Vertex clustering: the fast, one-shot simplifier (Rossignac & Borrel 1993,
with Lindstrom 2000's quadric-optimal representatives).

The bounding box is cut into a uniform grid of cubic cells; all vertices of a
cell merge into one representative, placed where the sum of the cell's vertex
quadrics is smallest (pulled towards the cell's mean where that sum is flat,
and kept inside the cell); faces whose corners fall into fewer than three
distinct cells vanish, and faces that land on the same three cells are kept once.

Everything is vectorised numpy over (n, 3) and (m, 3) arrays: no per-vertex
Python loop. Unlike edge collapse it can merge separate parts and close
holes, and it does not keep the mesh manifold: use it for huge inputs, far
levels, or as a fast first stage.
"""

from __future__ import annotations

import numpy as np

from numba import njit, prange

from ..mesh import Mesh, MeshError
from ..mesh import to_unit_box, unit_box
from .quadrics import cell_representatives, vertex_quadrics

# Resolution search bounds: cells along the longest axis.
_MIN_CELLS = 1
_MAX_CELLS = 1 << 16
# Refinement when duplicates make the counted search undershoot.
_REFINE_STEPS = 8
_REFINE_GROWTH = 1.06
_CLOSE_ENOUGH = 0.9


def cluster(mesh: Mesh, *, cells: int | None = None, cell_size: float | None = None,
            target_faces: int | None = None) -> Mesh:
    """Simplify ``mesh`` by merging the vertices of each grid cell.

    Give exactly one of:

    cells : int
        Cells along the longest side of the bounding box.
    cell_size : float
        Cell edge length in mesh units.
    target_faces : int
        The finest grid whose result has at most this many faces (found by a
        short search over the resolution, starting from the area estimate).

    Returns
    -------
    Mesh
        Positions (k, 3) of the representatives, faces (f, 3) into them.
    """
    if sum(x is not None for x in (cells, cell_size, target_faces)) != 1:
        raise ValueError("give exactly one of cells, cell_size or target_faces")
    positions = np.asarray(mesh.positions, dtype=np.float64)
    lo, extent = unit_box(positions)
    # Face planes only (Lindstrom 2000): representatives are kept inside their
    # cells anyway, and skipping the border census saves a pass over the mesh.
    quadrics = vertex_quadrics(positions, mesh.faces, boundary_weight=0)
    if cell_size is not None:
        if not cell_size > 0:
            raise ValueError(f"cell_size must be positive, got {cell_size}")
        cells = int(np.ceil(extent / cell_size))
    if cells is not None:
        if cells < 1:
            raise ValueError(f"cells must be at least 1, got {cells}")
        result = _cluster_grid(positions, mesh.faces, quadrics, lo, extent, int(cells))
        if result is None:
            raise MeshError(f"no face survives clustering into {cells} cells per side")
        return result
    if target_faces < 1:
        raise ValueError(f"target_faces must be at least 1, got {target_faces}")
    return _search_resolution(positions, mesh.faces, quadrics, lo, extent, int(target_faces))


def _search_resolution(positions, faces, quadrics, lo, extent, target):
    """Cluster on the finest grid whose result has at most ``target`` faces.

    The search counts faces whose corners fall in three distinct cells (a
    compiled pass, no clustering); that count bounds the result from above
    (duplicates are dropped later), and it grows with the resolution, so a
    binary search over the resolution needs only the final clustering.
    """
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    unit = to_unit_box(positions, lo, extent)

    def fits(r):
        return _surviving_faces(unit, faces, r) <= target

    # faces ~ r^2 for a surface: guess from one count, then gallop to a
    # bracket [good, bad) and bisect it
    guess = int(64 * np.sqrt(target / max(_surviving_faces(unit, faces, 64), 1)))
    r = min(max(guess, _MIN_CELLS), _MAX_CELLS)
    if fits(r):
        good, bad = r, None
        while bad is None and good < _MAX_CELLS:
            step = min(_MAX_CELLS, max(good + 1, int(good * 1.25)))
            if fits(step):
                good = step
            else:
                bad = step
        bad = bad or _MAX_CELLS + 1
    else:
        good, bad = None, r
        while good is None and bad > _MIN_CELLS:
            step = max(_MIN_CELLS, min(bad - 1, int(bad / 1.25)))
            if fits(step):
                good = step
            else:
                bad = step
        if good is None:
            raise MeshError(f"vertex clustering cannot reach {target} faces")
    while bad - good > 1:
        middle = (good + bad) // 2
        if fits(middle):
            good = middle
        else:
            bad = middle
    result = _cluster_grid(positions, faces, quadrics, lo, extent, good)
    if result is None:
        raise MeshError(f"vertex clustering cannot reach {target} faces")
    # The count includes faces that clustering then finds duplicated (parts
    # lying on each other): if the result undershoots, refine a few times.
    # The count is not monotone in r either, so try a few finer grids and
    # keep the fullest result that still fits.
    r = good
    for _ in range(_REFINE_STEPS):
        if result.face_count >= _CLOSE_ENOUGH * target or r >= _MAX_CELLS:
            break
        r = min(_MAX_CELLS, max(r + 1, int(r * _REFINE_GROWTH)))
        finer = _cluster_grid(positions, faces, quadrics, lo, extent, r)
        if finer is not None and result.face_count < finer.face_count <= target:
            result = finer
    return result


@njit(cache=True, nogil=True)
def _cell_sums(used, cell_of_used, quadrics, positions, k):
    """Summed quadric (k, 11) and mean position (k, 3) of each cell's vertices."""
    q = np.zeros((k, quadrics.shape[1]))
    mean = np.zeros((k, 3))
    count = np.zeros(k)
    for i in range(used.shape[0]):
        v = used[i]
        c = cell_of_used[i]
        for j in range(quadrics.shape[1]):
            q[c, j] += quadrics[v, j]
        for j in range(3):
            mean[c, j] += positions[v, j]
        count[c] += 1.0
    for c in range(k):
        for j in range(3):
            mean[c, j] /= count[c]
    return q, mean


@njit(cache=True, nogil=True, parallel=True)
def _surviving_faces(unit, faces, cells):
    """Faces whose three corners lie in three different cells of a grid of
    ``cells`` per side over the unit box (``unit`` = positions scaled into it)."""
    n = unit.shape[0]
    key = np.empty(n, np.int64)
    for v in prange(n):
        x = min(int(unit[v, 0] * cells), cells - 1)
        y = min(int(unit[v, 1] * cells), cells - 1)
        z = min(int(unit[v, 2] * cells), cells - 1)
        key[v] = (x * (cells + 1) + y) * (cells + 1) + z
    count = 0
    for f in prange(faces.shape[0]):
        a = key[faces[f, 0]]
        b = key[faces[f, 1]]
        c = key[faces[f, 2]]
        if a != b and b != c and a != c:
            count += 1
    return count


def _cluster_grid(positions, faces, quadrics, lo, extent, cells):
    """One clustering at ``cells`` cells along the longest side; None if no face survives."""
    return _cluster_cells(positions, faces, quadrics, lo, extent / cells, 0.0, radix=cells)


def cluster_within(mesh: Mesh, target_faces: int, slack: float = 0.1) -> Mesh:
    """Vertex clustering that lands within ``slack`` of ``target_faces``.

    :func:`cluster`'s search steps the resolution by whole cells, and at a few
    hundred faces one cell more or less changes the count by far more than 10%.
    Here the cell size is continuous and the grid may be shifted by half a cell:
    a bisection over the size (the count grows as cells shrink, not strictly)
    keeps the result nearest to the target, stopping as soon as one lies in
    ``[(1 - slack) * target, (1 + slack) * target]``.

    Returns
    -------
    Mesh
        Positions (k, 3), faces (f, 3): the result nearest ``target_faces``
        among those tried (within the window whenever one was found).

    Raises
    ------
    MeshError
        When no grid keeps a face (a mesh of a few faces asked for fewer).
    """
    if target_faces < 1:
        raise ValueError(f"target_faces must be at least 1, got {target_faces}")
    positions = np.asarray(mesh.positions, dtype=np.float64)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
    lo, extent = unit_box(positions)
    quadrics = vertex_quadrics(positions, faces, boundary_weight=0)
    low, high = (1 - slack) * target_faces, (1 + slack) * target_faces
    best, best_miss = None, np.inf

    def attempt(size, shift):
        nonlocal best, best_miss
        result = _cluster_cells(positions, faces, quadrics, lo, size, shift)
        count = 0 if result is None else result.face_count
        miss = abs(np.log(max(count, 1) / target_faces))
        if result is not None and miss < best_miss:
            best, best_miss = result, miss
        return count

    # cells along the longest side, bisected in log space between a coarse grid
    # (few faces) and a fine one (many)
    coarse, fine = 1.0, float(_MAX_CELLS)
    guess = max(1.0, 2.0 * np.sqrt(target_faces))
    for _ in range(_BISECT_STEPS):
        for shift in _SHIFTS:
            count = attempt(extent / guess, shift)
            if low <= count <= high:
                return best
        if count > target_faces:
            fine = guess
        else:
            coarse = guess
        if fine <= _MAX_CELLS - 1 and fine / coarse < 1.0 + 1e-4:
            break
        guess = np.sqrt(coarse * fine) if fine < _MAX_CELLS else guess * 2.0
    if best is None:
        raise MeshError(f"vertex clustering cannot reach {target_faces} faces")
    return best


# cluster_within's search: bisection steps over the cell size, and the grid
# shifts (fractions of a cell) tried at each size, since a shifted grid cuts
# a mesh's parts differently and so gives another count.
_BISECT_STEPS = 40
_SHIFTS = (0.0, 0.5)


def _cluster_cells(positions, faces, quadrics, lo, size, shift, radix=None):
    """One clustering on a grid of cubic cells of edge ``size`` whose origin is
    ``shift`` cells below ``lo`` (``radix`` cells along each side: by default as
    many as the box needs); None if no face survives."""
    origin = lo - shift * size
    if radix is None:
        radix = max(1, int(np.ceil(float(np.max(positions.max(axis=0) - origin)) / size)))
    coords = np.minimum(np.floor((positions - origin) / size).astype(np.int64), radix - 1)
    keys = (coords[:, 0] * radix + coords[:, 1]) * radix + coords[:, 2]
    used = np.nonzero(np.bincount(faces.ravel(), minlength=len(positions)))[0]
    cell_keys, cell_of_used = np.unique(keys[used], return_inverse=True)
    cell_of = np.full(len(positions), -1, dtype=np.int64)
    cell_of[used] = cell_of_used
    k = len(cell_keys)

    q, mean = _cell_sums(used, cell_of_used, quadrics, positions, k)

    # The regularised solve (A + eps I) p = eps * mean - b of edge collapse's
    # placement (quadrics.solve_regularized); a cell with no planes stays at its mean.
    representative = np.empty((k, 3))
    cell_representatives(q, mean, representative)
    # Keep each representative inside its cell: a far-off optimum would fold faces.
    cell_lo = origin + np.stack([cell_keys // (radix * radix), (cell_keys // radix) % radix,
                                 cell_keys % radix], axis=1) * size
    representative = np.clip(representative, cell_lo, cell_lo + size)

    remapped = cell_of[faces]
    keep = ((remapped[:, 0] != remapped[:, 1]) & (remapped[:, 1] != remapped[:, 2])
            & (remapped[:, 0] != remapped[:, 2]))
    remapped = remapped[keep]
    if len(remapped) == 0:
        return None
    ordered = np.sort(remapped, axis=1)
    if k < (1 << 20):       # one int64 key per face: 1-D unique is far faster than rows
        ordered = (ordered[:, 0] << 40) | (ordered[:, 1] << 20) | ordered[:, 2]
    _, first = np.unique(ordered, axis=0 if ordered.ndim == 2 else None, return_index=True)
    remapped = remapped[np.sort(first)]
    # drop cells no surviving face uses, keeping the order
    alive, compact = np.unique(remapped, return_inverse=True)
    return Mesh(representative[alive], compact.reshape(-1, 3))
