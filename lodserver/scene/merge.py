"""A static scene's far level as one mesh: every part placed in the world, merged.

Where a whole scene's level stays over its budget, the parts of a scene whose
nodes never move relative to each other (no animation, no skin, no morph
target) can be drawn as one: :func:`world_mesh` places every instance of every
part in world space (normals by the inverse transpose, mirrored instances
turned) with one layout of the columns a bake reads (``NORMAL``, ``TEXCOORD_0``
/``_1``, ``COLOR_0``, ``TANGENT`` where every part has it), and
``bake.level.merged_level`` remeshes and bakes it: one primitive, one material.
"""

from __future__ import annotations

import numpy as np

from ..bake.normalmap import vertex_normals_of
from ..io.animation import node_worlds
from ..mesh import Attributes, Mesh
from .budget import instance_matrices

# The columns a bake reads (a part without one gets a default: _columns).
_COLUMNS = (("NORMAL", 3), ("TEXCOORD_0", 2), ("TEXCOORD_1", 2), ("COLOR_0", 4),
            ("TANGENT", 4))


# The most triangles a merge places in world space at once (every instance of
# every part): a heavily instanced scene would otherwise hold them all in memory.
MAX_WORLD_FACES = 5_000_000


def static_reason(scene, parts: dict | None = None) -> str | None:
    """Why ``scene``'s parts cannot be merged into one mesh, or None when they can.
    ``parts``: glTF mesh index -> (its attribute layout, its faces) when
    ``scene.meshes`` does not hold the meshes (a stored asset's scene)."""
    if parts is None:
        parts = {index: (mesh.attributes.layout if mesh.attributes is not None else (),
                         mesh.face_count) for index, mesh in scene.meshes.items()}
    document = scene.document
    if document.get("animations"):
        return "it is animated"
    if document.get("skins"):
        return "it has skins"
    if scene.as_is:
        return "some of its meshes have no triangles"
    for layout, _ in parts.values():
        if any(name.startswith(("TARGET", "JOINTS")) for name, _ in layout):
            return "it has morph targets or skinned meshes"
    world = node_worlds(scene.document, scene.carried)
    drawn = sum(len(instance_matrices(scene, index, world)) * faces
                for index, (_, faces) in parts.items())
    if drawn > MAX_WORLD_FACES:
        return f"it draws {drawn} triangles, more than the {MAX_WORLD_FACES} merged at once"
    return None


def world_mesh(scene) -> Mesh:
    """Every instance of every part of ``scene`` in world space, as one mesh whose
    ``face_material`` indexes ``scene.materials``."""
    world = node_worlds(scene.document, scene.carried)
    return placed_mesh([(scene.meshes[index], instance_matrices(scene, index, world))
                        for index in sorted(scene.meshes)], scene.materials)


def placed_mesh(pieces: list, materials) -> Mesh:
    """One mesh of ``pieces``: (a mesh, its (k, 4, 4) placements) each, every
    placement a copy of the mesh moved by it (normals by the inverse transpose,
    mirrored copies turned), in one layout of the columns a bake reads; its
    ``face_material`` indexes ``materials``, as the pieces' do."""
    meshes = [mesh for mesh, _ in pieces]
    layout = [(name, width) for name, width in _COLUMNS if name != "TANGENT" or all(
        m.attributes is not None and m.attributes.columns("TANGENT") is not None
        for m in meshes)]
    layout = [(name, width) for name, width in layout if name in ("NORMAL", "TANGENT") or any(
        m.attributes is not None and m.attributes.columns(name) is not None
        for m in meshes)]
    positions, faces, values, corners, face_material = [], [], [], [], []
    vertex_base = wedge_base = 0
    for mesh, matrices in pieces:
        own = _columns(mesh, layout)
        for matrix in matrices:
            linear = matrix[:3, :3]
            placed = mesh.positions @ linear.T + matrix[:3, 3]
            turned = own.copy()
            start = 0
            for name, width in layout:
                if name == "NORMAL":
                    normal = own[:, start:start + 3] @ np.linalg.inv(linear)
                    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
                    turned[:, start:start + 3] = normal
                elif name == "TANGENT":
                    tangent = own[:, start:start + 3] @ linear.T
                    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-300)
                    turned[:, start:start + 3] = tangent
                start += width
            mirrored = np.linalg.det(linear) < 0
            order = [0, 2, 1] if mirrored else [0, 1, 2]
            positions.append(placed)
            faces.append(mesh.faces[:, order] + vertex_base)
            values.append(turned)
            # a mesh without attributes: one wedge per vertex
            wedges = (mesh.attributes.corners if mesh.attributes is not None
                      else np.asarray(mesh.faces))
            corners.append(wedges[:, order] + wedge_base)
            face_material.append(mesh.face_material if mesh.face_material is not None
                                 else np.full(mesh.face_count, -1, np.int32))
            vertex_base += len(placed)
            wedge_base += len(turned)
    return Mesh(np.concatenate(positions), np.concatenate(faces),
                Attributes(tuple(layout), np.concatenate(values), np.concatenate(corners)),
                np.concatenate(face_material), materials)


def _columns(mesh: Mesh, layout) -> np.ndarray:
    """(w, d) the mesh's wedge values in ``layout``: its own where it has them,
    else area-weighted vertex normals, zero UVs, white colour."""
    attributes = mesh.attributes
    count = attributes.wedge_count if attributes is not None else mesh.vertex_count
    out = []
    for name, width in layout:
        columns = attributes.columns(name) if attributes is not None else None
        if columns is not None:
            own = attributes.values[:, columns]
            if name == "COLOR_0" and own.shape[1] == 3:
                own = np.concatenate([own, np.ones((count, 1))], axis=1)
            out.append(own)
        elif name == "NORMAL":
            out.append(vertex_normals_of(mesh.positions, mesh.faces)[mesh.wedge_vertices() if attributes is not None
                                             else np.arange(count)])
        elif name == "COLOR_0":
            out.append(np.ones((count, 4)))
        else:
            out.append(np.zeros((count, width)))
    return np.concatenate(out, axis=1) if out else np.zeros((count, 0))


def baked_together(fulls: list, levels: list, materials) -> list:
    """Far levels of several parts (``levels[i]``: positions and faces in the space
    of the full-detail ``fulls[i]``, whose ``face_material`` indexes ``materials``)
    baked into one atlas and one material (``bake.level.bake_level``): each part
    set apart from the others by more than their sizes while the atlas is made
    and sampled, so that a texel's nearest full-detail point is on its own part,
    then moved back. Returns each part's level with ``NORMAL``, ``TANGENT``,
    ``TEXCOORD_0`` and the one shared material, on an atlas of the side a merged
    level has by default (``bake.level.DEFAULT_ATLAS``), larger only where its
    charts do not fit (``bake.atlas.make_atlas``): a bake's memory grows with its
    texels, and a far level is drawn small."""
    from ..bake.level import DEFAULT_ATLAS, bake_level

    extent = max(float(np.ptp(np.concatenate([full.positions, level.positions]), axis=0).max())
                 for full, level in zip(fulls, levels))
    lows = [np.minimum(full.positions.min(axis=0), level.positions.min(axis=0))
            for full, level in zip(fulls, levels)]
    # part i's lowest corner moved to (3 i extent, 0, 0): two extents of gap between parts
    offsets = [np.array([3.0 * i * max(extent, 1e-9), 0.0, 0.0]) - low
               for i, low in enumerate(lows)]
    full = placed_mesh([(mesh, _translation(offset)[None]) for mesh, offset
                        in zip(fulls, offsets)], materials)
    level = Mesh(np.concatenate([m.positions + offset for m, offset in zip(levels, offsets)]),
                 np.concatenate([m.faces + base for m, base
                                 in zip(levels, np.cumsum([0] + [m.vertex_count
                                                                 for m in levels[:-1]]))]))
    baked = bake_level(full, level, DEFAULT_ATLAS)
    out, start = [], 0
    for part, offset in zip(levels, offsets):
        stop = start + part.face_count
        faces, corners = baked.faces[start:stop], baked.attributes.corners[start:stop]
        vertices, faces = np.unique(faces, return_inverse=True)
        wedges, corners = np.unique(corners, return_inverse=True)
        out.append(Mesh(baked.positions[vertices] - offset, faces.reshape(-1, 3),
                        Attributes(baked.attributes.layout, baked.attributes.values[wedges],
                                   corners.reshape(-1, 3)),
                        baked.face_material[start:stop], baked.materials))
        start = stop
    return out


def _translation(offset) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, 3] = offset
    return matrix
