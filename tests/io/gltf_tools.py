"""The npm glTF tools the compression tests run, and how their outputs are compared.

``tests/tools/package.json`` (with its lock file) pins gltfpack and glTF-Transform's
CLI; ``.ci/run`` installs them with ``npm ci --prefix tests/tools``. A test asking for
a tool that is not installed skips with how to install it (fails under CI=true).

Comparisons are of what a renderer draws: a flattened mesh's wedges matched face by
face (:func:`matched_corners`), a scene's vertices posed in world space through
node transforms, skins and morph weights (:func:`posed_vertices`).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lodserver.io.animation import joint_matrices, node_weights, node_worlds

from ..conftest import need

TOOLS = Path(__file__).resolve().parents[1] / "tools"
BIN = TOOLS / "node_modules" / ".bin"

# how each conversion is run: the tool, then its arguments around input and output
CONVERSIONS = {
    "gltfpack -cc": ("gltfpack", lambda i, o: ["-i", i, "-o", o, "-cc"]),
    "gltfpack -c": ("gltfpack", lambda i, o: ["-i", i, "-o", o, "-c"]),
    "gltfpack -noq": ("gltfpack", lambda i, o: ["-i", i, "-o", o, "-noq"]),
    "draco": ("gltf-transform", lambda i, o: ["draco", i, o]),
    "meshopt": ("gltf-transform", lambda i, o: ["meshopt", i, o]),
    "quantize": ("gltf-transform", lambda i, o: ["quantize", i, o]),
}


def tool(name: str) -> Path:
    """The installed command ``name`` of tests/tools, or ``need`` (skip, fail in CI)."""
    path = BIN / name
    if not path.exists():
        need(f"{name} is not installed: run npm ci --prefix tests/tools (as .ci/run does)")
    return path


def convert(source: Path, how: str, output: Path) -> Path:
    """``source`` written by the conversion ``how`` (:data:`CONVERSIONS`) to ``output``."""
    name, arguments = CONVERSIONS[how]
    command = [str(tool(name)), *arguments(str(source), str(output))]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600, check=False)
    assert result.returncode == 0 and output.is_file(), \
        f"{how} of {source.name} failed: {result.stdout[-500:]} {result.stderr[-500:]}"
    return output


def texture_transform(mesh, face_material: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(scale (m, 2), offset (m, 2)) of each face's base colour KHR_texture_transform
    (gltfpack stores quantized UVs and puts their range there); identity without one."""
    scale, offset = np.ones((len(face_material), 2)), np.zeros((len(face_material), 2))
    if mesh.materials is None:
        return scale, offset
    for m, material in enumerate(mesh.materials.gltf.get("materials", ())):
        info = (material.get("pbrMetallicRoughness") or {}).get("baseColorTexture") or {}
        transform = (info.get("extensions") or {}).get("KHR_texture_transform")
        if transform:
            assert not transform.get("rotation"), "a rotated texture transform"
            scale[face_material == m] = transform.get("scale", (1, 1))
            offset[face_material == m] = transform.get("offset", (0, 0))
    return scale, offset


def corner_values(mesh, name: str) -> np.ndarray | None:
    """(m, 3, k) values of attribute ``name`` at every face corner (UVs through their
    texture transform), None when the mesh lacks it."""
    attributes = mesh.attributes
    columns = attributes.columns(name) if attributes is not None else None
    if columns is None:
        return None
    values = attributes.values[attributes.corners][:, :, columns]
    if name.startswith("TEXCOORD") and mesh.face_material is not None:
        scale, offset = texture_transform(mesh, mesh.face_material)
        values = values * scale[:, None] + offset[:, None]
    return values


def matched_corners(original, other, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(original face of each of ``other``'s faces, rotation aligning its corners):
    every vertex of ``other`` is matched to the original vertex nearest it (within
    ``tolerance``), and each face to the original face on the same three vertices."""
    distance, nearest = cKDTree(original.positions).query(other.positions)
    assert distance.max() <= tolerance, \
        f"a vertex lies {distance.max():.3g} from every original one (tolerance {tolerance:.3g})"
    keys = {}
    for face, corners in enumerate(original.faces.tolist()):
        keys.setdefault(tuple(sorted(corners)), []).append(face)
    faces, rotation = np.empty(other.face_count, np.int64), np.empty(other.face_count, np.int64)
    mapped = nearest[other.faces]
    for face, corners in enumerate(mapped.tolist()):
        found = keys.get(tuple(sorted(corners)))
        assert found, f"face {face} of the decoded mesh has no original face on its vertices"
        faces[face] = found.pop() if len(found) > 1 else found[0]
        first = original.faces[faces[face]].tolist().index(corners[0])
        rotation[face] = first
    return faces, rotation


def attribute_errors(original, other, tolerance: float) -> dict:
    """The largest difference per attribute between two loads of one mesh, matched
    face by face (:func:`matched_corners`): degrees for NORMAL and TANGENT xyz,
    absolute for TEXCOORD_n and COLOR_n."""
    faces, rotation = matched_corners(original, other, tolerance)
    order = (rotation[:, None] + np.arange(3)) % 3
    errors = {}
    for name, _ in original.attributes.layout if original.attributes is not None else ():
        theirs = corner_values(other, name)
        assert theirs is not None, f"the decoded mesh lacks {name}"
        mine = corner_values(original, name)[faces[:, None], order]
        if name in ("NORMAL", "TANGENT"):
            a, b = mine[..., :3], theirs[..., :3]
            cosine = (a * b).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1)
                                                 * np.linalg.norm(b, axis=-1), 1e-30)
            errors[name] = float(np.degrees(np.arccos(np.clip(cosine, -1, 1))).max())
        else:
            errors[name] = float(np.abs(mine - theirs).max())
    return errors


def posed_vertices(scene, clip=None, time: float = 0.0) -> np.ndarray:
    """(v, 3) world positions of every vertex of every mesh instance of a Scene at
    ``time`` of animation ``clip``: morph targets weighted, skins applied (in the mesh
    node's space, as ``io.animation`` has it), node world transform last."""
    document = scene.document
    worlds = node_worlds(document, scene.carried, time, clip)
    placed = []
    for index, node in enumerate(document.get("nodes", ())):
        if "mesh" not in node or node["mesh"] not in scene.meshes:
            continue
        mesh = scene.meshes[node["mesh"]]
        local = mesh.positions.copy()
        attributes = mesh.attributes
        weights = node_weights(document, scene.carried, index, time, clip)
        owner = mesh.wedge_vertices() if attributes is not None else None
        for t, weight in enumerate(weights):
            columns = attributes.columns(f"TARGET{t}_POSITION")
            if columns is not None and weight:
                delta = np.zeros_like(local)
                delta[owner[owner >= 0]] = attributes.values[owner >= 0][:, columns]
                local += weight * delta
        if "skin" in node:
            joints = attributes.values[:, attributes.columns("JOINTS_0")]
            weight = attributes.values[:, attributes.columns("WEIGHTS_0")]
            matrices = joint_matrices(document, scene.carried, node["skin"], index, worlds)
            blend = np.einsum("wk,wkij->wij", weight, matrices[joints.astype(int)])
            per_vertex = np.zeros((len(local), 4, 4))
            per_vertex[owner[owner >= 0]] = blend[owner >= 0]
            homogeneous = np.column_stack([local, np.ones(len(local))])
            local = np.einsum("vij,vj->vi", per_vertex, homogeneous)[:, :3]
        placed.append(local @ worlds[index][:3, :3].T + worlds[index][:3, 3])
    return np.concatenate(placed)


def hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    """The symmetric Hausdorff distance between two point sets (v, 3)."""
    return float(max(cKDTree(b).query(a)[0].max(), cKDTree(a).query(b)[0].max()))


def extent(positions: np.ndarray) -> float:
    """The largest side of the bounding box of (v, 3) positions."""
    return float(np.ptp(positions, axis=0).max())
