"""The kernels' warm-up: numba loads (or compiles) every kernel an upload's
build and its packets run, before the server says it is ready.

numba compiles a kernel once per signature, and a signature is every
argument's type: an array's dtype, dimensions, layout and whether it is
read-only. The warm-up therefore builds what an upload builds, the same way:

- a small mesh with every kind of attribute (SOLVED normals, UVs and
  colours; the CARRIED tangents and skin) and poses, the inputs of a skinned
  part (the whole-mesh kernel);
- one with ``simplify.parts.PARALLEL_MIN_VERTICES`` vertices and normals
  (the Morton order and the partitioned run of a large upload);
- each sent through multiprocessing's pickle, as the parse workers send a
  parsed mesh back;
- the loaders' welding (``io.clean``) once, for the parse workers' cache;
- then the packets of a small progressive mesh both ways.
"""

from __future__ import annotations

from multiprocessing.reduction import ForkingPickler

import numpy as np

from ..build import build
from ..io import clean_mesh
from ..mesh import Attributes, Mesh
from ..simplify.parts import PARALLEL_MIN_VERTICES

__all__ = ["warm_up", "warm_meshes"]

# Poses of the warm-up's skinned mesh: enough to run the pose quadrics.
POSES = 2


def warm_up() -> None:
    """Build the warm-up meshes (``warm_meshes``) and encode the packets of the
    small one and of an octahedron without attributes both ways, so numba
    loads (or compiles) every kernel before a real build or the first packet
    request."""
    from ..packets import encode_packet, packet_between

    meshes = warm_meshes()
    # the loaders' welding, which the parse workers load from the same on-disk cache
    clean_mesh(meshes[0][0].positions, meshes[0][0].faces)
    small, _ = [build(mesh, poses=poses) for mesh, poses in meshes]
    positions = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
    faces = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                      [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    # packets with and without wedges; the small mesh's, as the encoders run the same
    for pm in (build(Mesh(positions, faces)), small):
        pm.at(pm.base_vertices)
        encode_packet(pm, pm.base_vertices, pm.vertex_count)
        encode_packet(pm, pm.vertex_count, pm.base_vertices)
        packet_between(pm, pm.base_vertices, pm.vertex_count)
        packet_between(pm, pm.vertex_count, pm.base_vertices)


def warm_meshes() -> list[tuple[Mesh, np.ndarray | None]]:
    """``(mesh, poses)`` pairs the warm-up builds, each through multiprocessing's
    pickle: a small torus with every attribute kind and ``POSES`` poses (P, n,
    3, 4), and one of ``PARALLEL_MIN_VERTICES`` vertices with its normals only
    and no poses (the partitioned run's kernels take the same array types
    whatever the attributes, as long as there are some, and the large build
    is then a fraction of the warm-up)."""
    side = int(np.ceil(np.sqrt(PARALLEL_MIN_VERTICES)))
    mesh, _ = _torus(side, side)
    normals = mesh.attributes.values[:, :3]
    large = (Mesh(mesh.positions, mesh.faces,
                  Attributes((("NORMAL", 3),), normals, mesh.attributes.corners)), None)
    return [ForkingPickler.loads(ForkingPickler.dumps(pair)) for pair in (_torus(12, 16), large)]


def _torus(rows: int, cols: int) -> tuple[Mesh, np.ndarray]:
    """A (rows x cols)-vertex torus with normals, UVs (one seam), colours,
    tangents and one skin influence set, and ``POSES`` small rigid poses."""
    u = np.repeat(np.arange(rows) * (2 * np.pi / rows), cols)
    v = np.tile(np.arange(cols) * (2 * np.pi / cols), rows)
    ring = 2.0 + 0.6 * np.cos(v)
    positions = np.stack([ring * np.cos(u), ring * np.sin(u), 0.6 * np.sin(v)], axis=1)
    normals = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    a = (r * cols + c).ravel()
    b = (r * cols + (c + 1) % cols).ravel()
    d = (((r + 1) % rows) * cols + c).ravel()
    e = (((r + 1) % rows) * cols + (c + 1) % cols).ravel()
    faces = np.concatenate([np.stack([a, b, e], 1), np.stack([a, e, d], 1)])
    n = rows * cols
    # one wedge per vertex, and a second for each vertex of the first row
    # where the last row's faces meet it (a UV seam)
    last = np.tile(r.ravel() == rows - 1, 2)[:, None]
    corners = np.where(last & (faces < cols), faces + n, faces)
    owner = np.concatenate([np.arange(n), np.arange(cols)])
    uv = np.stack([u[owner] / (2 * np.pi), v[owner] / (2 * np.pi)], axis=1)
    uv[n:, 0] = 1.0
    colour = np.concatenate([0.5 + 0.5 * normals[owner], np.ones((len(owner), 1))], axis=1)
    tangent = np.stack([-np.sin(u[owner]), np.cos(u[owner]), np.zeros(len(owner)),
                        np.ones(len(owner))], axis=1)
    joints = np.zeros((len(owner), 4))
    weights = np.zeros((len(owner), 4))
    weights[:, 0] = 1.0
    values = np.concatenate([normals[owner], uv, colour, tangent, joints, weights], axis=1)
    layout = (("NORMAL", 3), ("TEXCOORD_0", 2), ("COLOR_0", 4), ("TANGENT", 4),
              ("JOINTS_0", 4), ("WEIGHTS_0", 4))
    mesh = Mesh(positions, faces, Attributes(layout, values, corners))
    poses = np.zeros((POSES, n, 3, 4))
    poses[:, :, :, :3] = np.eye(3)
    poses[1, :, 2, 3] = 0.1             # the second pose lifted a little
    return mesh, poses
