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

from .mesh import Mesh, MeshError
from .quadrics import REGULARIZATION, vertex_quadrics

# Resolution search: cells along the longest axis, and how many refinement
# steps the search for a face target may take (each costs one clustering).
_MIN_CELLS = 1
_MAX_CELLS = 1 << 16
_SEARCH_STEPS = 8


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
    lo = positions.min(axis=0)
    extent = float((positions.max(axis=0) - lo).max()) or 1.0
    quadrics = vertex_quadrics(positions, mesh.faces)
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
    """Largest tried grid with at most ``target`` faces.

    A surface crosses about r^2 cells at r cells per side, and keeps about two
    faces per cell, so faces ~ r^2: each step rescales r by sqrt(target / faces).
    """
    best = None
    below, above = _MIN_CELLS, _MAX_CELLS
    r = 64
    for _ in range(_SEARCH_STEPS):
        r = int(min(max(r, below), above))
        result = _cluster_grid(positions, faces, quadrics, lo, extent, r)
        if result is None or result.face_count <= target:
            if result is not None and (best is None or result.face_count > best.face_count):
                best = result
            below = r + 1
        else:
            above = r - 1
        if below > above or (best is not None and best.face_count >= 0.97 * target):
            break
        count = result.face_count if result is not None else 0
        guess = r * np.sqrt(target / max(count, 1)) * (0.98 if count > target else 1.0)
        # never re-try a resolution already known too coarse or too fine
        r = int(np.clip(np.floor(guess), below, above))
    if best is None:
        # even one cell per side gives too many faces (cannot happen: it gives none)
        raise MeshError(f"vertex clustering cannot reach {target} faces")
    return best


def _cluster_grid(positions, faces, quadrics, lo, extent, cells):
    """One clustering at ``cells`` cells along the longest side; None if no face survives."""
    size = extent / cells
    coords = np.minimum(((positions - lo) / size).astype(np.int64), cells - 1)
    keys = (coords[:, 0] * (cells + 1) + coords[:, 1]) * (cells + 1) + coords[:, 2]
    used = np.unique(faces)
    cell_keys, cell_of_used = np.unique(keys[used], return_inverse=True)
    cell_of = np.full(len(positions), -1, dtype=np.int64)
    cell_of[used] = cell_of_used
    k = len(cell_keys)

    # Summed quadric and mean position of each cell (bincount per column is
    # much faster than np.add.at).
    q = np.stack([np.bincount(cell_of_used, weights=quadrics[used, j], minlength=k)
                  for j in range(quadrics.shape[1])], axis=1)
    count = np.bincount(cell_of_used, minlength=k).astype(np.float64)
    mean = np.stack([np.bincount(cell_of_used, weights=positions[used, j], minlength=k)
                     for j in range(3)], axis=1) / count[:, None]

    # Regularised solve (A + eps I) p = eps * mean - b, as in quadrics.optimal_position.
    a = np.empty((k, 3, 3))
    a[:, 0, 0], a[:, 0, 1], a[:, 0, 2] = q[:, 0], q[:, 1], q[:, 2]
    a[:, 1, 0], a[:, 1, 1], a[:, 1, 2] = q[:, 1], q[:, 3], q[:, 4]
    a[:, 2, 0], a[:, 2, 1], a[:, 2, 2] = q[:, 2], q[:, 4], q[:, 5]
    eps = REGULARIZATION * (q[:, 0] + q[:, 3] + q[:, 5])
    eps = np.where(eps > 0, eps, 1.0)      # a cell with no planes stays at its mean
    a += eps[:, None, None] * np.eye(3)
    rhs = eps[:, None] * mean - q[:, 6:9]
    representative = np.linalg.solve(a, rhs[:, :, None])[:, :, 0]
    # Keep each representative inside its cell: a far-off optimum would fold faces.
    cell_lo = lo + np.stack([cell_keys // ((cells + 1) ** 2), (cell_keys // (cells + 1)) % (cells + 1),
                             cell_keys % (cells + 1)], axis=1) * size
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
