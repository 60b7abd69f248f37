"""Render vertices: the arrays a renderer draws for a mesh, made valid for glTF.

glTF has a single index per corner, so a mesh's wedges (a vertex seen with one
attribute vector) become render vertices, one per wedge a primitive uses
(:func:`render_primitives`, a primitive per material); :func:`render_attributes`
makes each column valid as glTF requires whatever interpolation left (unit
normals and tangents, colours in [0, 1], skin influences that sum to 1). The GLB
writers (:mod:`.glb`, :mod:`.scene_glb`) write what these give.
"""

from __future__ import annotations

import numpy as np

from ..mesh import Mesh
from .gltf_attributes import perpendicular


def render_primitives(mesh: Mesh):
    """Per material, the arrays a renderer draws: one vertex per wedge used.

    Yields
    ------
    material : int
        Index into ``mesh.materials``, -1 for faces without one.
    positions : (r, 3) float64
        The render vertices' positions, ``positions[wedge vertex]``.
    attributes : dict of str to (r, k) array
        Every layout column, as written (:func:`render_attributes`): float32 but
        JOINTS_n (uint8, or uint16 when a joint is 256 or more); ``TARGET{t}_*``
        are morph target t's deltas (the writer puts them in ``targets``).
    indices : (f, 3) uint32
        The primitive's triangles over its render vertices, in mesh face order.
    """
    faces = mesh.faces
    # without attributes a render vertex is a mesh vertex; with them, a wedge
    keys = mesh.attributes.corners if mesh.attributes is not None else faces
    owner = mesh.wedge_vertices() if mesh.attributes is not None else None
    if mesh.face_material is None:
        groups = [(-1, np.arange(len(faces)))]
    else:
        order = np.argsort(mesh.face_material, kind="stable")  # keeps face order within a group
        materials, starts = np.unique(mesh.face_material[order], return_index=True)
        groups = zip(materials.tolist(), np.split(order, starts[1:]))
    for material, rows in groups:
        used, local = np.unique(keys[rows], return_inverse=True)
        indices = local.reshape(-1, 3).astype(np.uint32)
        vertices = used if owner is None else owner[used]
        attributes = {}
        if mesh.attributes is not None:
            attributes = render_attributes(mesh.attributes.layout, mesh.attributes.values[used],
                                           mesh.positions[vertices], indices)
        yield material, mesh.positions[vertices], attributes, indices


def render_attributes(layout, values: np.ndarray, positions: np.ndarray,
                      triangles: np.ndarray) -> dict:
    """The glTF vertex attributes of render vertices: ``values`` (r, d) in ``layout``,
    ``positions`` (r, 3), ``triangles`` (f, 3) over them; name -> (r, k) array.

    Each column made valid as glTF requires, whatever interpolation left:
    NORMAL unit (:func:`_unit_normals`); COLOR_n clipped to [0, 1]; TANGENT xyz
    unit (a zero one perpendicular to the normal) and w exactly +-1 (0 -> +1);
    JOINTS_n rounded to uint8 (uint16 when a joint is 256 or more) and WEIGHTS_n
    float32 (:func:`skin_influences`); TEXCOORD_n, morph deltas and custom
    ``_NAME`` columns float32 as they are.
    """
    columns = {}
    start = 0
    for name, width in layout:
        columns[name] = values[:, start:start + width]
        start += width
    out = {}
    for name, _ in layout:
        column = columns[name]
        if name == "NORMAL":
            column = _unit_normals(column, positions, triangles)
        elif name.startswith("COLOR_"):
            column = np.clip(column, 0.0, 1.0)  # glTF colours are in [0, 1]
        elif name == "TANGENT":
            # a zero tangent is replaced in the plane of the normal (or of the faces)
            normal = columns.get("NORMAL", np.zeros((len(column), 3)))
            column = unit_tangents(column, _unit_normals(normal, positions, triangles))
        elif name.startswith(("JOINTS_", "WEIGHTS_")):
            continue        # all sets at once, below
        out[name] = column.astype(np.float32)
    sets = sorted(int(name[8:]) for name, _ in layout if name.startswith("WEIGHTS_")
                  and f"JOINTS_{name[8:]}" in columns)
    if sets:
        joints, weights = skin_influences(
            np.hstack([columns[f"JOINTS_{n}"] for n in sets]),
            np.hstack([columns[f"WEIGHTS_{n}"] for n in sets]))
        for k, n in enumerate(sets):
            out[f"JOINTS_{n}"] = joints[:, 4 * k:4 * k + 4]
            out[f"WEIGHTS_{n}"] = weights[:, 4 * k:4 * k + 4]
    for name, _ in layout:      # a JOINTS_n or WEIGHTS_n set without its partner
        if name.startswith(("JOINTS_", "WEIGHTS_")) and name not in out:
            out[name] = (columns[name].astype(np.float32) if name.startswith("W")
                         else _joint_array(columns[name]))
    return {name: out[name] for name, _ in layout}      # in layout order


def unit_tangents(tangents: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(r, 4) float64 tangents made valid: xyz unit length (a zero or non-finite one
    replaced by a unit vector perpendicular to ``normals`` (r, 3)), w exactly +-1
    by its sign (0 counts as +1)."""
    xyz = np.array(tangents[:, :3], dtype=np.float64)
    length = np.linalg.norm(xyz, axis=1)
    bad = ~(length > 1e-12)
    xyz[bad] = perpendicular(normals[bad])
    length[bad] = 1.0
    w = np.where(tangents[:, 3] < 0, -1.0, 1.0)
    return np.column_stack([xyz / length[:, None], w])


def skin_influences(joints: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joints (r, 4s) and weights (r, 4s) of s influence sets made valid for glTF.

    Weights below 0 become 0; a joint named twice in a vertex keeps one slot with
    the sum of its weights; a slot of weight 0 gets joint 0 (the validator warns of
    a joint used with weight 0); each vertex's weights are renormalised to sum to 1
    over all sets, in float32 (the largest absorbs the rounding), and a vertex whose
    weights sum to 0 gets joint 0 with weight 1.

    Returns
    -------
    joints : (r, 4s) uint8, or uint16 when a joint is 256 or more
    weights : (r, 4s) float32
    """
    joints = np.rint(np.asarray(joints, dtype=np.float64)).astype(np.int64)
    weights = np.maximum(np.asarray(weights, dtype=np.float64), 0.0)
    slots = joints.shape[1]
    # merge repeated joints: a slot whose joint an earlier slot of the vertex holds
    for b in range(1, slots):
        for a in range(b):
            same = (joints[:, a] == joints[:, b]) & (weights[:, b] > 0)
            weights[same, a] += weights[same, b]
            weights[same, b] = 0.0
    total = weights.sum(axis=1)
    empty = ~(total > 0)
    weights[empty] = 0.0
    weights[empty, 0] = 1.0
    joints[empty] = 0       # joint 0 exists in every skin
    total[empty] = 1.0
    weights /= total[:, None]
    joints[weights == 0] = 0
    single = weights.astype(np.float32)
    # the float32 sum off by a few ulps: the largest weight takes the difference
    largest = np.argmax(single, axis=1)
    rows = np.arange(len(single))
    rest = single.astype(np.float64).sum(axis=1) - single[rows, largest]
    single[rows, largest] = np.float32(1.0) - rest.astype(np.float32)
    return _joint_array(joints), single


def _joint_array(joints) -> np.ndarray:
    """Joint indices rounded, as uint8 (uint16 when one is 256 or more)."""
    joints = np.rint(np.asarray(joints, dtype=np.float64))
    return joints.astype(np.uint16 if joints.size and joints.max() >= 256 else np.uint8)


def _unit_normals(normals: np.ndarray, positions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Normals (r, 3) scaled to unit length, as glTF requires.

    A zero normal (from a zero-area face in the source, say) has no direction to
    keep: it takes the area-weighted normal of the triangles around its render
    vertex, or +Z if those have no area either.
    """
    normals = np.array(normals, dtype=np.float64)
    zero = np.linalg.norm(normals, axis=1) < 1e-12
    if zero.any():
        corners = positions[triangles]
        weighted = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        around = np.zeros_like(normals)
        np.add.at(around, triangles.ravel(), np.repeat(weighted, 3, axis=0))
        normals[zero] = around[zero]
        normals[np.linalg.norm(normals, axis=1) == 0] = (0.0, 0.0, 1.0)
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)
