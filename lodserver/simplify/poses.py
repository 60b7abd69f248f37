"""Pose quadrics: the error of a skinned or morphed mesh measured in the poses it is seen in.

A skinned or morphed mesh is simplified in its bind pose, but drawn bent: two
vertices that are close and coplanar at rest may fold apart at a joint. Here
every pose is a per-vertex affine map ``x -> A_v x + t_v`` (a ``(3, 4)`` matrix
``[A | t]``) from the bind position to the posed one:

- linear blend skinning: ``[A | t] = sum_i w_i M_{j_i}[:3]`` over the vertex's
  influences (joint matrices ``M`` from :func:`lodserver.io.animation.joint_matrices`);
- morph targets: ``A = I``, ``t = sum_t w_t delta_t`` (a translation);
- both: morph first, then skin: ``x -> S (x + d) = A_S x + (A_S d + t_S)``.

:func:`pose_quadrics` takes, for every pose, each face's area-weighted plane
quadric of the POSED triangle and pulls it back to bind space through each
corner vertex's own map: with ``M`` the 4x4 of the map and ``Q`` the posed
plane's 4x4 quadric, ``Q' = M^T Q M``, i.e. the plane ``(n, d)`` becomes
``(A^T n, n . t + d)`` (not unit any more). ``Q'(x)`` is then the squared
distance of the vertex, moved to bind position ``x`` and posed by its own map,
from the posed plane; at the vertex's own bind position it is zero, whatever the
pose, so a rigid or identity pose adds no error where there was none. A collapse
that folds across a bending joint, flat at rest, is charged what it costs in the
poses. ``collapse._prepare`` averages ``(bind + sum of poses) / (1 + P)``.

Memory: the maps are ``(P, n, 3, 4)`` float64, 96 bytes per vertex and pose
(1M vertices x 9 poses = 0.86 GB), and ``poses_to_unit_box`` makes one copy.
:func:`scene_poses` therefore caps ``P * n`` at :data:`MAX_POSE_VERTICES`
(2^21 vertex-poses, ~200 MB per copy): a mesh of n vertices gets at most
``max(1, 2^21 // n)`` poses, chosen evenly among those it would have had
(all 8 sampled poses up to 262k vertices, 2 at 1M, 1 beyond 2M). A mesh both
skinned and morphed holds three such arrays for a moment (skin, morph, composed).
"""

from __future__ import annotations

import re

import numpy as np
from numba import njit

from ..io.animation import joint_matrices, node_weights, node_worlds, sample_times
from ..mesh import MeshError
from .quadrics import QUADRIC_SIZE, add_plane, face_plane

# P * n bound of scene_poses (see the module docstring): 2^21 * 96 bytes = 201 MB.
MAX_POSE_VERTICES = 2**21
DEFAULT_POSES = 8


# --------------------------------------------------------------------------
# 1. Pose maps
# --------------------------------------------------------------------------

def skin_pose_maps(joints, weights, matrices) -> np.ndarray:
    """Linear-blend-skinning affine maps of every vertex in every pose.

    Parameters
    ----------
    joints : (n, 4k) int or float
        Joint indices (into the skin's ``joints``, i.e. the rows of ``matrices``)
        of each vertex's influences, every JOINTS_n set side by side.
    weights : (n, 4k) float
        Their weights (WEIGHTS_n side by side). Renormalised to sum 1 per vertex
        (the spec asks for 1; exporters round); a vertex with no weight keeps
        the identity map.
    matrices : (P, J, 4, 4) float
        Joint matrices per pose (:func:`lodserver.io.animation.joint_matrices`).

    Returns
    -------
    (P, n, 3, 4) float64
        ``[A | t]`` with the posed position ``A x + t``, mesh units.
    """
    joints = np.asarray(joints)
    weights = np.asarray(weights, dtype=np.float64)
    matrices = np.asarray(matrices, dtype=np.float64)
    if joints.shape != weights.shape or joints.ndim != 2:
        raise MeshError(f"joints {joints.shape} and weights {weights.shape} must both be "
                        "(n, 4k)")
    if matrices.ndim != 4 or matrices.shape[2:] != (4, 4):
        raise MeshError(f"joint matrices must have shape (P, J, 4, 4), got {matrices.shape}")
    if not np.isfinite(weights).all() or (weights < 0).any():
        raise MeshError("skin weights must be finite and not negative")
    index = np.rint(joints).astype(np.int64)
    used = weights != 0
    if used.any() and (index[used].min() < 0 or index[used].max() >= matrices.shape[1]):
        raise MeshError(f"a vertex is bound to a joint outside the skin's {matrices.shape[1]}")
    index = np.ascontiguousarray(np.where(used, index, 0))
    total = weights.sum(axis=1)
    # weights / total; a vertex with no weight at all keeps the identity (below)
    weights = np.ascontiguousarray(weights / np.where(total > 0, total, 1.0)[:, None])
    out = np.empty((len(matrices), len(index), 3, 4))
    _skin_maps(index, weights, np.ascontiguousarray(matrices), out)
    return out


@njit(cache=True, nogil=True)
def _skin_maps(index, weights, matrices, out):
    """``out[p, v] = sum_i weights[v, i] matrices[p, index[v, i], :3]`` (the identity
    for a vertex whose weights are all zero), without (n, 3, 4) temporaries."""
    for p in range(matrices.shape[0]):
        for v in range(index.shape[0]):
            total = 0.0
            for r in range(3):
                for c in range(4):
                    out[p, v, r, c] = 0.0
            for i in range(index.shape[1]):
                w = weights[v, i]
                if w == 0.0:
                    continue
                total += w
                j = index[v, i]
                for r in range(3):
                    for c in range(4):
                        out[p, v, r, c] += w * matrices[p, j, r, c]
            if total == 0.0:
                for r in range(3):
                    out[p, v, r, r] = 1.0


def morph_pose_maps(deltas, weights) -> np.ndarray:
    """Morph-target poses as translations.

    Parameters
    ----------
    deltas : (T, n, 3) float
        Each target's position deltas (TARGET{t}_POSITION), mesh units.
    weights : (P, T) float
        Target weights per pose.

    Returns
    -------
    (P, n, 3, 4) float64 : ``[I | sum_t w_t delta_t]``.
    """
    deltas = np.asarray(deltas, dtype=np.float64)
    weights = np.atleast_2d(np.asarray(weights, dtype=np.float64))
    if deltas.ndim != 3 or deltas.shape[2] != 3 or weights.shape[1] != deltas.shape[0]:
        raise MeshError(f"morph deltas {deltas.shape} and weights {weights.shape} do not match")
    out = np.zeros((len(weights), deltas.shape[1], 3, 4))
    out[:, :, :, :3] = np.eye(3)
    out[:, :, :, 3] = np.einsum("pt,tnc->pnc", weights, deltas)
    return out


def compose_maps(outer, inner) -> np.ndarray:
    """(P, n, 3, 4) maps ``outer o inner`` (``inner`` applied first), pose by pose."""
    out = np.empty(np.broadcast_shapes(outer.shape, inner.shape))
    out[..., :3] = outer[..., :3] @ inner[..., :3]
    out[..., 3] = (outer[..., :3] @ inner[..., 3, None])[..., 0] + outer[..., 3]
    return out


def poses_to_unit_box(maps, lo, scale) -> np.ndarray:
    """The maps rewritten for the kernel's unit box ``u = (x - lo) / scale`` on both
    sides: ``u -> A u + (A lo + t - lo) / scale`` (``A`` unchanged).

    maps : (P, n, 3, 4) float; lo : (3,) float; scale : float. Returns a new
    (P, n, 3, 4) float64 array."""
    maps = np.asarray(maps, dtype=np.float64)
    if maps.ndim != 4 or maps.shape[2:] != (3, 4):
        raise MeshError(f"poses must have shape (P, n, 3, 4), got {maps.shape}")
    lo = np.asarray(lo, dtype=np.float64).reshape(3)
    out = np.empty_like(maps)
    _unit_box_maps(np.ascontiguousarray(maps), lo, float(scale), out)
    return out


@njit(cache=True, nogil=True)
def _unit_box_maps(maps, lo, scale, out):
    """``out = [A | (A lo + t - lo) / scale]`` for every map of ``maps`` (P, n, 3, 4)."""
    for p in range(maps.shape[0]):
        for v in range(maps.shape[1]):
            for r in range(3):
                moved = maps[p, v, r, 3] - lo[r]
                for c in range(3):
                    out[p, v, r, c] = maps[p, v, r, c]
                    moved += maps[p, v, r, c] * lo[c]
                out[p, v, r, 3] = moved / scale


# --------------------------------------------------------------------------
# 2. Pose quadrics
# --------------------------------------------------------------------------

def pose_quadrics(unit, faces, maps) -> np.ndarray:
    """Posed face quadrics pulled back to bind space, summed per vertex.

    Parameters
    ----------
    unit : (n, 3) float
        Bind positions (the kernel's unit box).
    faces : (m, 3) int
    maps : (P, n, 3, 4) float
        Each vertex's map per pose, in the same frame as ``unit``
        (:func:`poses_to_unit_box`).

    Returns
    -------
    (n, 11) float64
        Rows as ``quadrics.vertex_quadrics``: per pose and face, the area-weighted
        plane of the posed triangle, as ``M_v^T Q M_v`` at each corner v; the area
        column sums the posed areas. Zero-area posed faces add nothing.
    """
    unit = np.ascontiguousarray(unit, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    maps = np.ascontiguousarray(maps, dtype=np.float64)
    if maps.ndim != 4 or maps.shape[1:] != (len(unit), 3, 4):
        raise MeshError(f"poses must have shape (P, {len(unit)}, 3, 4), got {maps.shape}")
    out = np.zeros((len(unit), QUADRIC_SIZE))
    posed = np.empty_like(unit)
    for p in range(len(maps)):
        _pose_positions(unit, maps[p], posed)
        _accumulate_pose_quadrics(posed, faces, maps[p], out)
    return out


@njit(cache=True, nogil=True)
def _pose_positions(unit, maps, out):
    """``out[v] = A_v unit[v] + t_v`` for one pose's maps (n, 3, 4)."""
    for v in range(unit.shape[0]):
        for r in range(3):
            out[v, r] = (maps[v, r, 0] * unit[v, 0] + maps[v, r, 1] * unit[v, 1]
                         + maps[v, r, 2] * unit[v, 2] + maps[v, r, 3])


@njit(cache=True, nogil=True)
def _accumulate_pose_quadrics(posed, faces, maps, out):
    """Add each posed face's quadric, pulled back through each corner's map, to
    that corner's row of ``out`` (n, 11)."""
    for f in range(faces.shape[0]):
        i, j, k = faces[f, 0], faces[f, 1], faces[f, 2]
        nx, ny, nz, d, area = face_plane(posed, i, j, k)
        if area == 0.0:
            continue
        for v in (i, j, k):
            # plane (n, d) at A x + t is the plane (A^T n, n . t + d) at x
            px = maps[v, 0, 0] * nx + maps[v, 1, 0] * ny + maps[v, 2, 0] * nz
            py = maps[v, 0, 1] * nx + maps[v, 1, 1] * ny + maps[v, 2, 1] * nz
            pz = maps[v, 0, 2] * nx + maps[v, 1, 2] * ny + maps[v, 2, 2] * nz
            pd = maps[v, 0, 3] * nx + maps[v, 1, 3] * ny + maps[v, 2, 3] * nz + d
            add_plane(out, v, area, px, py, pz, pd)


# --------------------------------------------------------------------------
# 3. The poses of a scene's mesh
# --------------------------------------------------------------------------

def vertex_columns(mesh, names) -> np.ndarray | None:
    """(n, sum of widths) float64: the attribute columns ``names`` of each vertex, taken
    from its first wedge (lowest wedge index); None if any name is missing.
    Vertices no face uses get zeros."""
    attributes = mesh.attributes
    if attributes is None or not names:
        return None
    slices = [attributes.columns(name) for name in names]
    if any(s is None for s in slices):
        return None
    owner = mesh.wedge_vertices()
    wedges = np.flatnonzero(owner >= 0)[::-1]
    first = np.full(mesh.vertex_count, -1, dtype=np.int64)
    first[owner[wedges]] = wedges              # assigned last = lowest wedge index
    values = np.concatenate([attributes.values[:, s] for s in slices], axis=1)
    out = np.zeros((mesh.vertex_count, values.shape[1]))
    out[first >= 0] = values[first[first >= 0]]
    return out


def _numbered(mesh, pattern) -> list:
    """The numbers in layout names matching ``pattern`` (one group), ascending."""
    if mesh.attributes is None:
        return []
    return sorted(int(m.group(1)) for name, _ in mesh.attributes.layout
                  if (m := re.fullmatch(pattern, name)))


def _evenly(items: list, cap: int) -> list:
    if len(items) <= cap:
        return items
    return [items[i] for i in np.linspace(0, len(items) - 1, cap).round().astype(int)]


def scene_poses(scene, mesh_index: int, mesh, count: int = DEFAULT_POSES):
    """The poses glTF mesh ``mesh_index`` of ``scene`` is seen in, as maps for
    ``decimate(poses=)``.

    Parameters
    ----------
    scene : lodserver.io.scene.Scene
    mesh_index : int
        The glTF mesh.
    mesh : Mesh
        Its lodserver mesh, whose ``attributes`` hold JOINTS_n / WEIGHTS_n and
        TARGET{t}_POSITION (a vertex takes its first wedge's values).
    count : int
        Poses sampled from the animations (:func:`~lodserver.io.animation.sample_times`).

    Returns
    -------
    (P, n, 3, 4) float64 or None
        - skinned (a node using the mesh has a skin, and the mesh has JOINTS_0 and
          WEIGHTS_0): ``count`` animation poses, skinned through the skin of the
          first such node (the rest pose when there are no animations);
        - morphed: each target alone at weight 1, plus the node's weights at the
          sampled times when a ``weights`` channel animates it;
        - both: morph then skin, at each sampled time with the weights of that
          time, plus each target alone skinned in the rest pose;
        - neither: None.
        ``P * n`` is capped at :data:`MAX_POSE_VERTICES` (poses kept evenly).
    """
    try:
        return _scene_poses(scene, mesh_index, mesh, count)
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        # load_scene checks the tree, skins and channels (io.animation.check_scene);
        # whatever else of the JSON is malformed is the file's fault, not a crash
        raise MeshError(f"its skin or animation data is malformed ({type(exc).__name__}: "
                        f"{str(exc)[:120]})") from exc


def _scene_poses(scene, mesh_index: int, mesh, count: int):
    document, carried = scene.document, scene.carried
    users = scene.mesh_nodes.get(mesh_index, [])
    nodes = document.get("nodes", [])
    skinned_by = [u for u in users if "skin" in nodes[u]]
    sets = _numbered(mesh, r"JOINTS_(\d+)")
    sets = [s for s in sets if s in _numbered(mesh, r"WEIGHTS_(\d+)")]
    targets = _numbered(mesh, r"TARGET(\d+)_POSITION")
    skinned = bool(skinned_by) and bool(sets)
    if not skinned and not targets:
        return None
    n = mesh.vertex_count
    cap = max(1, MAX_POSE_VERTICES // max(n, 1))
    node = skinned_by[0] if skinned else (users[0] if users else None)
    times = sample_times(document, carried, count)
    deltas = None
    if targets:
        if targets != list(range(len(targets))):
            raise MeshError(f"mesh {mesh_index}'s morph targets are not numbered 0..T-1")
        deltas = vertex_columns(mesh, [f"TARGET{t}_POSITION" for t in targets])
        deltas = deltas.reshape(n, len(targets), 3).transpose(1, 0, 2)

    # (clip, time, weights or None) per pose, before any map is made (the cap applies first)
    one_hot = [(None, 0.0, w) for w in np.eye(len(targets))] if targets else []
    animated_weights = node is not None and any(
        (channel.get("target", {}).get("node"), channel.get("target", {}).get("path"))
        == (node, "weights")
        for animation in document.get("animations", ())
        for channel in animation.get("channels", ()))
    if skinned:
        timed = [(clip, time, None) for clip, time in times] or [(None, 0.0, None)]
        if targets:
            timed = [(clip, time, node_weights(document, carried, node, time, clip))
                     for clip, time, _ in timed]
        plan = timed + one_hot
    else:
        plan = one_hot
        if animated_weights:
            plan += [(None, 0.0, node_weights(document, carried, node, time, clip))
                     for clip, time in times]
    plan = _evenly(plan, cap)

    morph = None
    if targets:
        weights = np.array([w for _, _, w in plan])
        morph = morph_pose_maps(deltas, weights)
    if not skinned:
        return morph
    joints_weights = vertex_columns(mesh, [f"JOINTS_{s}" for s in sets]
                                    + [f"WEIGHTS_{s}" for s in sets])
    half = joints_weights.shape[1] // 2
    skin = nodes[node]["skin"]
    matrices = np.array([joint_matrices(document, carried, skin, node,
                                        node_worlds(document, carried, time, clip))
                         for clip, time, _ in plan])
    maps = skin_pose_maps(joints_weights[:, :half], joints_weights[:, half:], matrices)
    return maps if morph is None else compose_maps(maps, morph)
