"""A CPU rasterizer: which face of a mesh each pixel of an orthographic view sees.

:func:`rasterize_view` projects a mesh's vertices onto a view's pixel grid
(the caller gives each vertex its pixel coordinates and its depth) and keeps,
for every pixel centre, the nearest face covering it and the barycentrics of
the centre on that face: a z-buffer over plain arrays, in one thread and in
face order, so the same input gives the same answer on any machine. The
impostor bake (``impostor.py``) shades these pixels from the surface's
materials (``textures.SurfaceLook``).
"""

from __future__ import annotations

import numpy as np
from numba import njit


def rasterize_view(pixels: np.ndarray, depth: np.ndarray, faces: np.ndarray,
                   size: int) -> tuple[np.ndarray, np.ndarray]:
    """The nearest face at each pixel centre of a ``size`` x ``size`` view.

    Parameters
    ----------
    pixels : (n, 2) float
        Each vertex's position on the view in pixels: x to the right, y down,
        pixel (col, row) covering [col, col + 1) x [row, row + 1).
    depth : (n,) float
        Each vertex's depth towards the viewer: the larger, the nearer.
    faces : (f, 3) int
        Vertex indices of the triangles, either winding (seen from both sides).

    Returns
    -------
    (face, bary)
        ``face`` (size, size) int64: the nearest face at each pixel (-1: none),
        row-major from the top; ``bary`` (size, size, 3) float64 its
        barycentrics at the pixel centre. Of two faces at the same depth the
        earlier keeps the pixel.
    """
    face = np.full((size, size), -1, dtype=np.int64)
    bary = np.zeros((size, size, 3))
    zbuffer = np.full((size, size), -np.inf)
    _rasterize(np.ascontiguousarray(pixels, dtype=np.float64),
               np.ascontiguousarray(depth, dtype=np.float64),
               np.ascontiguousarray(faces, dtype=np.int64), face, bary, zbuffer)
    return face, bary


@njit(cache=True, nogil=True)
def pixel_box(ax, ay, bx, by, cx, cy, size):
    """The pixels (x0, x1, y0, y1, inclusive) of a ``size`` square a triangle's
    bounding box touches."""
    x0 = max(0, int(np.floor(min(ax, bx, cx))))
    x1 = min(size - 1, int(np.ceil(max(ax, bx, cx))))
    y0 = max(0, int(np.floor(min(ay, by, cy))))
    y1 = min(size - 1, int(np.ceil(max(ay, by, cy))))
    return x0, x1, y0, y1


@njit(cache=True, nogil=True)
def barycentric(ax, ay, bx, by, cx, cy, area, px, py):
    """Barycentrics (w0, w1, w2) of point (px, py) on the triangle whose doubled
    signed area is ``area``."""
    w0 = ((bx - px) * (cy - py) - (by - py) * (cx - px)) / area
    w1 = ((cx - px) * (ay - py) - (cy - py) * (ax - px)) / area
    return w0, w1, 1.0 - w0 - w1


@njit(cache=True, nogil=True)
def _rasterize(pixels, depth, faces, face, bary, zbuffer):
    size = face.shape[0]
    for f in range(faces.shape[0]):
        i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay = pixels[i, 0], pixels[i, 1]
        bx, by = pixels[j, 0], pixels[j, 1]
        cx, cy = pixels[k, 0], pixels[k, 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0.0:
            continue
        x0, x1, y0, y1 = pixel_box(ax, ay, bx, by, cx, cy, size)
        width = x1 - x0 + 1
        for at in range(width * max(0, y1 - y0 + 1)):     # the box's pixels, row by row
            y, x = y0 + at // width, x0 + at % width
            w0, w1, w2 = barycentric(ax, ay, bx, by, cx, cy, area, x + 0.5, y + 0.5)
            if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                continue
            z = w0 * depth[i] + w1 * depth[j] + w2 * depth[k]
            if z > zbuffer[y, x]:
                zbuffer[y, x] = z
                face[y, x] = f
                bary[y, x, 0] = w0
                bary[y, x, 1] = w1
                bary[y, x, 2] = w2
