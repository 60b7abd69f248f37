"""Attribute deviation: normals, UVs, colours and texture colour between two meshes,
compared at the same surface samples."""

from __future__ import annotations

import numba
import numpy as np

from .nearest import FLAT_SIN2, closest_on_segment, cross, edge_side, nearest_on_mesh
from .surface import distance_figures, judged, sample_barycentric

# Attributes attribute_deviation always reports (None where it cannot compare).
_COMPARED = ("NORMAL", "TEXCOORD_0", "TEXCOORD_1", "COLOR_0")


@numba.njit(cache=True, parallel=True)
def closest_barycentrics(positions, faces, face, closest):
    """(k, 3) barycentric weights, on the corners of ``faces[face[q]]`` in their
    stored order, of the point ``closest[q]``, which lies on that triangle.

    Weights come from cross products against the face normal (first-order
    accurate, unlike the Gram-matrix form); rounding just outside the triangle
    is clamped and the weights renormalised. A flat triangle (the distance
    kernel's test) has the point on one of its edges: the nearest edge gives
    the weights.
    """
    k = face.shape[0]
    out = np.empty((k, 3))
    for q in numba.prange(k):
        f = face[q]
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        ax, ay, az = positions[i0, 0], positions[i0, 1], positions[i0, 2]
        e0x, e0y, e0z = positions[i1, 0] - ax, positions[i1, 1] - ay, positions[i1, 2] - az
        e1x, e1y, e1z = positions[i2, 0] - ax, positions[i2, 1] - ay, positions[i2, 2] - az
        px, py, pz = closest[q, 0] - ax, closest[q, 1] - ay, closest[q, 2] - az
        nx, ny, nz = cross(e0x, e0y, e0z, e1x, e1y, e1z)
        nn = nx * nx + ny * ny + nz * nz
        l0 = e0x * e0x + e0y * e0y + e0z * e0z
        l1 = e1x * e1x + e1y * e1y + e1z * e1z
        w0 = w1 = w2 = 0.0
        if nn > FLAT_SIN2 * l0 * l1 and nn > 0.0:
            # p = w1 e0 + w2 e1: n . (p x e1) = w1 nn, n . (e0 x p) = w2 nn
            w1 = edge_side(nx, ny, nz, px, py, pz, e1x, e1y, e1z) / nn
            w2 = edge_side(nx, ny, nz, e0x, e0y, e0z, px, py, pz) / nn
            w1 = min(max(w1, 0.0), 1.0)
            w2 = min(max(w2, 0.0), 1.0)
            w0 = max(1.0 - w1 - w2, 0.0)
            total = w0 + w1 + w2
            w0, w1, w2 = w0 / total, w1 / total, w2 / total
        else:
            best = np.inf
            for edge in range(3):
                # edge from corner u to corner v, as offsets from corner 0
                if edge == 0:
                    ux, uy, uz, vx, vy, vz = 0.0, 0.0, 0.0, e0x, e0y, e0z
                elif edge == 1:
                    ux, uy, uz, vx, vy, vz = e0x, e0y, e0z, e1x, e1y, e1z
                else:
                    ux, uy, uz, vx, vy, vz = e1x, e1y, e1z, 0.0, 0.0, 0.0
                d2, sx, sy, sz = closest_on_segment(px, py, pz, ux, uy, uz, vx, vy, vz)
                if d2 < best:
                    best = d2
                    dx, dy, dz = vx - ux, vy - uy, vz - uz
                    den = dx * dx + dy * dy + dz * dz
                    t = 0.0
                    if den > 0.0:
                        t = ((sx - ux) * dx + (sy - uy) * dy + (sz - uz) * dz) / den
                        t = min(max(t, 0.0), 1.0)
                    if edge == 0:
                        w0, w1, w2 = 1.0 - t, t, 0.0
                    elif edge == 1:
                        w0, w1, w2 = 0.0, 1.0 - t, t
                    else:
                        w0, w1, w2 = t, 0.0, 1.0 - t
        out[q, 0] = w0
        out[q, 1] = w1
        out[q, 2] = w2
    return out


@numba.njit(cache=True, parallel=True)
def _interpolate(values, corners, face, bary, lo, hi):
    """(k, hi - lo): columns lo..hi-1 of the wedge values, blended over each
    point's face corners with its barycentric weights."""
    k = face.shape[0]
    out = np.zeros((k, hi - lo))
    for q in numba.prange(k):
        f = face[q]
        for c in range(3):
            w = bary[q, c]
            row = corners[f, c]
            for j in range(lo, hi):
                out[q, j - lo] += w * values[row, j]
    return out


@numba.njit(cache=True, parallel=True)
def _sample_texture(image, uv):
    """(k, c) bilinear texture lookups at glTF UVs (u right, v down from the
    top-left corner), texel centres at half-integers, REPEAT wrapping."""
    h, w, channels = image.shape
    k = uv.shape[0]
    out = np.empty((k, channels))
    for q in numba.prange(k):
        x = uv[q, 0] * w - 0.5
        y = uv[q, 1] * h - 0.5
        fx, fy = np.floor(x), np.floor(y)
        tx, ty = x - fx, y - fy
        x0 = int(fx) % w
        y0 = int(fy) % h
        x1 = (x0 + 1) % w
        y1 = (y0 + 1) % h
        for c in range(channels):
            top = (1.0 - tx) * image[y0, x0, c] + tx * image[y0, x1, c]
            bottom = (1.0 - tx) * image[y1, x0, c] + tx * image[y1, x1, c]
            out[q, c] = (1.0 - ty) * top + ty * bottom
    return out


def _error_stats(errors_ab: np.ndarray, errors_ba: np.ndarray) -> dict:
    """RMS, median, 99th percentile and maximum of per-sample errors, pooled
    over both directions, plus each direction's RMS."""
    pooled = np.concatenate([errors_ab, errors_ba])
    if len(pooled) == 0:
        return None

    def rms(e):
        return float(np.sqrt(np.mean(e * e))) if len(e) else None

    return {
        "rms": rms(pooled),
        "p50": float(np.percentile(pooled, 50)),
        "p99": float(np.percentile(pooled, 99)),
        "max": float(pooled.max()),
        "rms_ab": rms(errors_ab),
        "rms_ba": rms(errors_ba),
    }


def _angle_degrees(n1: np.ndarray, n2: np.ndarray):
    """Angles between the renormalised rows, and the mask of rows where both
    are long enough to have a direction."""
    l1 = np.linalg.norm(n1, axis=1)
    l2 = np.linalg.norm(n2, axis=1)
    ok = (l1 > 1e-12) & (l2 > 1e-12)
    a = n1[ok] / l1[ok, None]
    b = n2[ok] / l2[ok, None]
    # atan2(|a x b|, a . b) keeps small angles accurate, unlike acos
    angle = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), (a * b).sum(axis=1)))
    return angle, ok


def _texture_array(texture) -> np.ndarray:
    image = np.asarray(texture)
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[0] < 1 or image.shape[1] < 1 or image.shape[2] < 1:
        raise ValueError(f"texture must have shape (h, w) or (h, w, c), got {np.shape(texture)}")
    # RGB(A): compare the colour channels only; alpha is coverage, not colour
    return np.ascontiguousarray(image[:, :, : min(3, image.shape[2])], dtype=np.float64)


def attribute_deviation(reference, candidate, *, samples=100_000, seed=0, texture=None) -> dict:
    """How far a candidate mesh's surface and appearance attributes are from a
    reference's, at corresponding surface points.

    Both arguments are :class:`~lodserver.mesh.Mesh` objects (or ``(positions,
    faces)`` tuples, which have no attributes). What is computed, in each
    direction (reference -> candidate, then candidate -> reference):

    1. ``samples`` area-weighted uniform points on the source surface, from the
       same two seed streams as :func:`surface_distance` (so the geometric
       figures equal ``surface_distance(reference, candidate, samples=samples,
       seed=seed)`` exactly), each with the source's attributes interpolated
       barycentrically over its face's corners (``values[corners]``).
    2. The closest point on the other surface (the same exact BVH search), its
       barycentric weights on the triangle it lies on, and the other mesh's
       attributes interpolated there.
    3. Per sample, the difference, pooled over both directions.

    Returns a dict:

    - ``samples`` (per direction), ``diagonal`` (the reference's, as in
      :func:`surface_distance`).
    - ``geometry``: ``rms``, ``hausdorff`` and the one-sided ``rms_ab``,
      ``rms_ba``, ``hausdorff_ab``, ``hausdorff_ba``, as fractions of the
      diagonal: :func:`surface_distance`'s figures.
    - ``NORMAL``, ``TEXCOORD_0``, ``TEXCOORD_1``, ``COLOR_0``: None unless both
      meshes carry that attribute; otherwise ``rms``, ``p50``, ``p99``,
      ``max`` of the per-sample error pooled over both directions, and the
      one-sided ``rms_ab``, ``rms_ba``. The error is the UV distance (UV
      units) for texture coordinates; the angle in degrees between the
      renormalised normals for ``NORMAL`` (samples where either normal has
      zero length are left out and counted in ``excluded``); the RMS over the
      four channels of the RGBA difference for ``COLOR_0``.
    - ``texture``: None unless ``texture`` is given and both meshes have
      ``TEXCOORD_0``; otherwise the same statistics of the colour difference
      (RMS over its first three channels, in the image's units: 8-bit levels
      for a uint8 image) between ``texture`` looked up bilinearly at the two
      points' UVs (glTF convention: origin top-left, v down; REPEAT wrap). This
      is what a viewer sees of a base-colour texture, and it forgives UV
      differences that land on the same texels.

    Near a UV seam the closest point may legitimately lie in the other chart,
    where the UVs differ a lot and the texture colour not at all, and near a
    hard edge on the other side of the crease: ``max`` reports those, ``p99``
    is the figure robust to them. Raises ValueError like
    :func:`surface_distance`.
    """
    reference, candidate, samples, diagonal = judged(reference, candidate, samples)
    image = None if texture is None else _texture_array(texture)
    seed_ref, seed_cand = np.random.SeedSequence(seed).spawn(2)

    ra, ca = reference.attributes, candidate.attributes
    shared = []
    if ra is not None and ca is not None:
        shared = [name for name in _COMPARED
                  if ra.columns(name) is not None and ca.columns(name) is not None]

    def one_way(source, source_seed, target):
        """Squared distances and, per shared attribute, (source, target) values."""
        points, face, bary = sample_barycentric(source, samples, source_seed)
        d2, target_face, closest = nearest_on_mesh(points, target)
        values = {}
        if shared:
            target_bary = closest_barycentrics(target.positions, target.faces,
                                                target_face, closest)
            for name in shared:
                pair = []
                for mesh, f, b in ((source, face, bary), (target, target_face, target_bary)):
                    cols = mesh.attributes.columns(name)
                    pair.append(_interpolate(mesh.attributes.values, mesh.attributes.corners,
                                             f, b, cols.start, cols.stop))
                values[name] = pair
        return d2, values

    d2_ab, values_ab = one_way(reference, seed_ref, candidate)
    d2_ba, values_ba = one_way(candidate, seed_cand, reference)
    report = {
        "samples": samples,
        "diagonal": diagonal,
        "geometry": distance_figures(d2_ab, d2_ba, diagonal),
    }
    for name in _COMPARED:
        report[name] = None
    report["texture"] = None
    for name in shared:
        (a_src, a_dst), (b_src, b_dst) = values_ab[name], values_ba[name]
        if name == "NORMAL":
            e_ab, ok_ab = _angle_degrees(a_src, a_dst)
            e_ba, ok_ba = _angle_degrees(b_src, b_dst)
            stats = _error_stats(e_ab, e_ba)
            if stats is not None:
                stats["excluded"] = int((~ok_ab).sum() + (~ok_ba).sum())
        elif name.startswith("TEXCOORD"):
            stats = _error_stats(np.linalg.norm(a_src - a_dst, axis=1),
                                 np.linalg.norm(b_src - b_dst, axis=1))
        else:
            stats = _error_stats(np.sqrt(((a_src - a_dst) ** 2).mean(axis=1)),
                                 np.sqrt(((b_src - b_dst) ** 2).mean(axis=1)))
        report[name] = stats
    if image is not None and "TEXCOORD_0" in shared:
        errors = []
        for src, dst in (values_ab["TEXCOORD_0"], values_ba["TEXCOORD_0"]):
            diff = _sample_texture(image, src) - _sample_texture(image, dst)
            errors.append(np.sqrt((diff * diff).mean(axis=1)))
        report["texture"] = _error_stats(*errors)
    return report
