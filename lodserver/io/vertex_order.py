"""The triangle and vertex order a GPU draws fastest, for exported files.

:func:`optimize_order` reorders one primitive's triangles for the post-transform
vertex cache (meshoptimizer's ``optimize_vertex_cache``, Forsyth's algorithm as
meshoptimizer tunes it, or its strip-like variant for the smallest compressed file) and then its vertices in the order the triangles first
use them (what ``meshopt_optimizeVertexFetchRemap`` computes; done here in numpy,
as the PyPI wrapper declares no ctypes signature for that function). Both orders
are also what EXT_meshopt_compression's codecs compress best.

Only exported files are reordered: the server's packets and its json levels keep
the progressive mesh's order, which their slots depend on.
"""

from __future__ import annotations

import numpy as np


def optimize_order(triangles: np.ndarray, vertex_count: int, *,
                   strip: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A primitive's triangles in vertex-cache order over its vertices in fetch order.

    Parameters
    ----------
    triangles : (f, 3) uint32
        Triangles over ``vertex_count`` vertices, every vertex used.
    vertex_count : int
        The primitive's vertices.
    strip : bool
        Order the triangles as strips do (``optimize_vertex_cache_strip``): a little
        more cache missing, but consecutive triangles share edges, which
        EXT_meshopt_compression's triangle codec stores in fewer bytes (what
        gltfpack -cc does).

    Returns
    -------
    triangles : (f, 3) uint32
        The same triangles (each with its winding) in the new order, over the
        vertices renumbered.
    order : (vertex_count,) int64
        ``order[new] = old``: the vertex arrays of the primitive are ``array[order]``.
    """
    import meshoptimizer

    flat = np.ascontiguousarray(triangles, dtype=np.uint32).ravel()
    if flat.size == 0:
        return triangles.astype(np.uint32), np.arange(vertex_count)
    cached = np.empty_like(flat)
    optimize = meshoptimizer.optimize_vertex_cache_strip if strip else \
        meshoptimizer.optimize_vertex_cache
    optimize(cached, flat, flat.size, vertex_count)
    used, first = np.unique(cached, return_index=True)
    order = used[np.argsort(first, kind="stable")].astype(np.int64)
    remap = np.empty(vertex_count, dtype=np.uint32)
    remap[order] = np.arange(len(order), dtype=np.uint32)
    return remap[cached].reshape(-1, 3), order
