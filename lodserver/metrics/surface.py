"""Area-weighted surface samples and the two-sided surface distance between meshes."""

from __future__ import annotations

import numpy as np

from ..mesh import Mesh
from .nearest import as_mesh, face_areas, nearest_on_mesh, used_diagonal


def sample_surface(positions, faces, count, *, seed=0) -> np.ndarray:
    """``count`` points drawn uniformly over the surface area, shape (count, 3).

    Each point picks a face with probability proportional to its area, then a
    uniform point on it: with r1, r2 ~ U[0, 1) and s = sqrt(r1), the point is
    (1 - s) a + s (1 - r2) b + s r2 c. Zero-area faces are never picked.
    ``seed`` is anything :func:`numpy.random.default_rng` accepts; the same seed
    gives the same points. Raises ValueError if the surface has zero area.
    """
    return sample_mesh(as_mesh((positions, faces)), count, seed)


def sample_mesh(mesh: Mesh, count, seed) -> np.ndarray:
    return sample_barycentric(mesh, count, seed)[0]


def sample_barycentric(mesh: Mesh, count, seed):
    """:func:`sample_surface`'s points (k, 3), the same for the same seed, with
    the face each lies on (k,) and its barycentric weights (k, 3) on that
    face's corners."""
    face, s, r2 = _sample_parameters(mesh, count, seed)
    corners = mesh.faces[face]
    a, b, c = (mesh.positions[corners[:, k]] for k in range(3))
    points = (1.0 - s) * a + s * (1.0 - r2) * b + s * r2 * c
    bary = np.concatenate([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    return points, face, bary


def _sample_parameters(mesh: Mesh, count, seed):
    """The face (k,) and the (k, 1) columns s, r2 of each sample (see
    :func:`sample_surface`)."""
    count = int(count)
    if count < 0:
        raise ValueError(f"count must be >= 0, got {count}")
    rng = np.random.default_rng(seed)
    area = face_areas(mesh.positions, mesh.faces)
    cdf = np.cumsum(area)
    total = cdf[-1]
    if not total > 0.0:
        raise ValueError("the surface has zero area: nothing to sample")
    # side="right" skips zero-area faces (their cdf step is empty); the clip
    # catches u * total rounding up to total, landing on the last positive face
    last = int(np.flatnonzero(area > 0.0)[-1])
    pick = np.searchsorted(cdf, rng.random(count) * total, side="right")
    face = np.minimum(pick, last)
    r1, r2 = rng.random(count), rng.random(count)
    return face, np.sqrt(r1)[:, None], r2[:, None]


def point_to_mesh_distance(points, positions, faces) -> np.ndarray:
    """Exact Euclidean distance, shape (k,), from each point to the nearest point
    on any triangle of (positions, faces): interiors, edges and corners alike,
    not merely the nearest vertex. Degenerate triangles count as the segment or
    point they collapse to.
    """
    mesh = as_mesh((positions, faces))
    d2, _, _ = nearest_on_mesh(points, mesh)
    return np.sqrt(d2)


def judged(reference, candidate, samples):
    """The two meshes as ``Mesh``, the sample count checked, and the reference's
    used bounding-box diagonal (errors are reported relative to it)."""
    reference = as_mesh(reference)
    candidate = as_mesh(candidate)
    samples = int(samples)
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    diagonal = used_diagonal(reference)
    if not diagonal > 0.0:
        raise ValueError("the reference mesh has a zero bounding-box diagonal")
    return reference, candidate, samples, diagonal


def surface_distance(reference, candidate, *, samples=200_000, seed=0) -> dict:
    """Two-sided surface distance between a reference mesh and a candidate.

    Both arguments are :class:`~lodserver.mesh.Mesh` objects or
    ``(positions, faces)`` tuples. What is computed:

    1. ``samples`` area-weighted uniform points on the reference surface
       (:func:`sample_surface`), and ``samples`` on the candidate surface, from
       two independent streams spawned from ``seed`` (the reference's points
       depend only on the reference and the seed, so candidates compared with
       one reference are all measured from the same points).
    2. For each reference point the exact Euclidean distance to the nearest
       point on any candidate triangle (:func:`point_to_mesh_distance`), giving
       d_ab; for each candidate point the distance to the reference, d_ba.
    3. Everything is divided by ``diagonal``, the length of the axis-aligned
       bounding-box diagonal of the reference vertices used by its faces.

    Returns a dict of floats:

    - ``rms_ab`` = sqrt(mean(d_ab**2)) / diagonal  (reference -> candidate)
    - ``rms_ba`` = sqrt(mean(d_ba**2)) / diagonal  (candidate -> reference)
    - ``rms`` = sqrt(mean of d**2 over both sets pooled) / diagonal, i.e.
      sqrt((rms_ab**2 + rms_ba**2) / 2) since both sets have ``samples`` points
    - ``hausdorff_ab`` = max(d_ab) / diagonal, ``hausdorff_ba`` = max(d_ba) / diagonal
    - ``hausdorff`` = max(hausdorff_ab, hausdorff_ba)
    - ``diagonal`` = the reference diagonal, in mesh units

    The Hausdorff values are the maximum over the samples, so they estimate
    (from below) the true Hausdorff distance. Degenerate faces of either mesh
    get no samples but are still surface that distances are measured to;
    unreferenced vertices play no part. Raises ValueError if either surface has
    zero area or the reference diagonal is zero.
    """
    reference, candidate, samples, diagonal = judged(reference, candidate, samples)
    seed_ref, seed_cand = np.random.SeedSequence(seed).spawn(2)
    on_ref = sample_mesh(reference, samples, seed_ref)
    on_cand = sample_mesh(candidate, samples, seed_cand)
    d2_ab, _, _ = nearest_on_mesh(on_ref, candidate)
    d2_ba, _, _ = nearest_on_mesh(on_cand, reference)
    return {**distance_figures(d2_ab, d2_ba, diagonal), "diagonal": diagonal}


def distance_figures(d2_ab, d2_ba, diagonal) -> dict:
    """The two-sided figures of :func:`surface_distance` from the squared
    distances of both sample sets, relative to ``diagonal``."""
    ms_ab, ms_ba = float(d2_ab.mean()), float(d2_ba.mean())
    h_ab, h_ba = float(np.sqrt(d2_ab.max())), float(np.sqrt(d2_ba.max()))
    return {
        "rms": float(np.sqrt(0.5 * (ms_ab + ms_ba))) / diagonal,
        "hausdorff": max(h_ab, h_ba) / diagonal,
        "rms_ab": float(np.sqrt(ms_ab)) / diagonal,
        "rms_ba": float(np.sqrt(ms_ba)) / diagonal,
        "hausdorff_ab": h_ab / diagonal,
        "hausdorff_ba": h_ba / diagonal,
    }

