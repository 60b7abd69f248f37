"""An atlas for a far level: charts from ``xatlas``, rasterized to texels.

:func:`make_atlas` cuts the level into charts and packs them into one square
texture (xatlas, its options fixed here so the same mesh gives the same atlas
everywhere); :func:`rasterize` finds, for every texel centre, the face of the
atlas that covers it and its barycentrics there; :func:`dilate` spreads each
chart's texels outwards into the padding so that mip levels and bilinear
filtering do not pull in the empty background.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..mesh import MeshError
from .raster import barycentric, pixel_box

# Texels left empty between charts (and grown into by dilate), at most; a
# small atlas has less room to spare.
PADDING = 4


def padding(size: int) -> int:
    """Texels between charts in an atlas of ``size`` texels a side."""
    return int(min(PADDING, max(1, size // 64)))


def make_atlas(positions: np.ndarray, faces: np.ndarray, size: int, largest: int | None = None):
    """Charts of the mesh (positions (n, 3), faces (f, 3)) packed into one square
    texture of ``size`` texels a side, or more where that cannot hold them.

    A clustered level may have hundreds of small charts, each of which takes
    its padding whatever its size: when they do not fit, the padding drops
    to one texel, then the side doubles (up to ``largest``, default 4 x size).

    Returns
    -------
    (vertex, uv, corners, size)
        ``vertex`` (w,) int64: the mesh vertex of each atlas vertex (a vertex
        on a chart seam appears once per chart); ``uv`` (w, 2) float64 in
        [0, 1], glTF's convention (v down); ``corners`` (f, 3) int64 atlas
        vertices of each face, in the input's face order; ``size`` the side used.
    """
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(positions, dtype=np.float32),
                   np.ascontiguousarray(faces, dtype=np.uint32))
    charts = xatlas.ChartOptions()
    charts.max_iterations = 1        # the default, named so it stays fixed
    charts.fix_winding = True        # clustering may leave charts mirrored
    largest = largest or 4 * size
    tries = []
    side = size
    while side <= largest:
        tries += [(side, padding(side)), (side, 1)]
        side *= 2
    for side, pad in tries:
        packed = _pack(atlas, charts, side, pad)
        if packed is not None:
            vertex, corners, uv = packed
            return (np.asarray(vertex, dtype=np.int64), uv,
                    np.asarray(corners, dtype=np.int64).reshape(-1, 3), side)
    raise MeshError(f"the far level's charts do not fit one {largest}x{largest} atlas")


def _pack(atlas, charts, size: int, pad: int):
    """xatlas's charts in one ``size`` square with ``pad`` texels between them:
    ``(vertex, corners, uv)``, or None when they do not fit."""
    import xatlas

    pack = xatlas.PackOptions()
    pack.resolution = int(size)
    pack.padding = pad
    pack.bilinear = True
    pack.blockAlign = False
    pack.bruteForce = False
    pack.rotate_charts = True
    # xatlas only estimates the scale (texels per mesh unit) that fills the
    # resolution: its packed rectangle, scaled to the square, then smaller
    # until the charts fit one square
    atlas.generate(chart_options=charts, pack_options=pack, verbose=False)
    scale = first = atlas.texels_per_unit * _FIT_SHRINK * size / max(atlas.width, atlas.height, 1)
    for _ in range(_FIT_STEPS):
        pack.texels_per_unit = float(scale)
        atlas.generate(chart_options=charts, pack_options=pack, verbose=False)
        if atlas.atlas_count == 1 and atlas.width <= size and atlas.height <= size:
            vertex, corners, uv = atlas[0]
            return vertex, corners, np.asarray(uv, dtype=np.float64) * [
                atlas.width / size, atlas.height / size]
        if atlas.atlas_count > 1 and scale < _SMALLEST * first:
            break       # the padding, not the charts, fills the square
        scale *= _FIT_SHRINK / np.sqrt(max(atlas.atlas_count, 1))
    return None


# make_atlas's fitting: tries, how much smaller each asks for than the last, and
# the scale below which it is the padding that does not fit
_FIT_STEPS = 6
_FIT_SHRINK = 0.97
_SMALLEST = 0.25


def rasterize(uv: np.ndarray, corners: np.ndarray, size: int):
    """Which face covers each texel centre of a ``size`` x ``size`` atlas.

    Returns ``(face, bary)``: (size, size) int64, the face (-1: none) of texel
    row y (v * size), column x (u * size); (size, size, 3) float64 its
    barycentrics at the texel centre. A texel two faces share goes to the
    later one, which is deterministic.
    """
    face = np.full((size, size), -1, dtype=np.int64)
    bary = np.zeros((size, size, 3))
    _rasterize(np.ascontiguousarray(uv * size), np.ascontiguousarray(corners), face, bary)
    return face, bary


@njit(cache=True, nogil=True)
def _rasterize(pixel, corners, face, bary):
    size = face.shape[0]
    for f in range(corners.shape[0]):
        ax, ay = pixel[corners[f, 0], 0], pixel[corners[f, 0], 1]
        bx, by = pixel[corners[f, 1], 0], pixel[corners[f, 1], 1]
        cx, cy = pixel[corners[f, 2], 0], pixel[corners[f, 2], 1]
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area == 0.0:
            continue
        x0, x1, y0, y1 = pixel_box(ax, ay, bx, by, cx, cy, size)
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                w0, w1, w2 = barycentric(ax, ay, bx, by, cx, cy, area, x + 0.5, y + 0.5)
                # a small tolerance closes the cracks between a chart's faces
                if w0 >= -1e-6 and w1 >= -1e-6 and w2 >= -1e-6:
                    face[y, x] = f
                    bary[y, x, 0] = w0
                    bary[y, x, 1] = w1
                    bary[y, x, 2] = w2


def conservative(face: np.ndarray, bary: np.ndarray, uv: np.ndarray, corners: np.ndarray):
    """Texels a chart's edge crosses but whose centre lies outside every face:
    given the nearest face of their 3x3 neighbourhood, with barycentrics
    clamped onto it, so the chart's border texels are sampled, not dilated."""
    size = face.shape[0]
    _conservative(face, bary, np.ascontiguousarray(uv * size), np.ascontiguousarray(corners))
    return face, bary


@njit(cache=True, nogil=True)
def _conservative(face, bary, pixel, corners):
    size = face.shape[0]
    source = face.copy()
    for y in range(size):
        for x in range(size):
            if source[y, x] >= 0:
                continue
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    yy, xx = y + dy, x + dx
                    if yy < 0 or xx < 0 or yy >= size or xx >= size or source[yy, xx] < 0:
                        continue
                    f = source[yy, xx]
                    ax, ay = pixel[corners[f, 0], 0], pixel[corners[f, 0], 1]
                    bx, by = pixel[corners[f, 1], 0], pixel[corners[f, 1], 1]
                    cx, cy = pixel[corners[f, 2], 0], pixel[corners[f, 2], 1]
                    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
                    w0, w1, w2 = barycentric(ax, ay, bx, by, cx, cy, area, x + 0.5, y + 0.5)
                    w0, w1, w2 = max(w0, 0.0), max(w1, 0.0), max(w2, 0.0)
                    total = w0 + w1 + w2
                    if total > 0.0 and face[y, x] < 0:
                        face[y, x] = f
                        bary[y, x, 0] = w0 / total
                        bary[y, x, 1] = w1 / total
                        bary[y, x, 2] = w2 / total


def dilate(image: np.ndarray, filled: np.ndarray, steps: int = 2 * PADDING) -> np.ndarray:
    """``image`` (h, w, c) with its empty texels (``filled`` False) given the
    mean of their filled 8-neighbours, ``steps`` rings outwards; what is still
    empty after takes the mean of all filled texels."""
    image = np.array(image, dtype=np.float64)
    filled = filled.copy()
    _dilate(image, filled, steps)
    if filled.any() and not filled.all():
        image[~filled] = image[filled].mean(axis=0)
    return image


@njit(cache=True, nogil=True)
def _dilate(image, filled, steps):
    h, w, c = image.shape
    # one sum for every texel, element by element: no array made per texel
    total = np.zeros(c)
    for _ in range(steps):
        grown = filled.copy()
        out = image.copy()
        for y in range(h):
            for x in range(w):
                if filled[y, x]:
                    continue
                count = 0
                for k in range(c):
                    total[k] = 0.0
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        yy, xx = y + dy, x + dx
                        if 0 <= yy < h and 0 <= xx < w and filled[yy, xx]:
                            for k in range(c):
                                total[k] += image[yy, xx, k]
                            count += 1
                if count:
                    for k in range(c):
                        out[y, x, k] = total[k] / count
                    grown[y, x] = True
        image[:] = out
        filled[:] = grown
