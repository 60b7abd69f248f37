"""Which uploads are scenes, and reading them as one.

An upload whose glTF document is more than one mesh laid out (several meshes,
a mesh instanced by several nodes or by ``EXT_mesh_gpu_instancing``, a skin,
morph targets, animations, cameras: :func:`scene_reason`) is read with
``io.scene.load_scene`` instead of being flattened, and built as a scene of
parts (``scene.build``). A single mesh (OBJ, PLY, STL, OFF, or a glTF holding
one mesh placed once, without skin, morph targets, animations or cameras: its
static transform is baked in) is read by ``io.load_mesh``; it is stored as a
scene of one part without a document (``scene.asset``).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path

from ..io.gltf_document import parse_container, parse_json
from ..io.limits import LimitError, LoadLimits
from ..io.scene import load_scene
from ..mesh import MeshError

__all__ = ["SceneReport", "read_scene_upload", "scene_reason"]


def scene_reason(document: dict) -> str | None:
    """Why ``document`` (glTF JSON) must be kept as a scene, or None for a single mesh.

    A scene: more than one glTF mesh placed by nodes, a mesh placed by several
    nodes or instanced by ``EXT_mesh_gpu_instancing``, a skin, morph targets,
    animations or cameras. One mesh placed once keeps today's path (flattened,
    its static transform baked in: the same geometry either way).
    """
    nodes = [n for n in document.get("nodes") or () if isinstance(n, dict)]
    placed = [n["mesh"] for n in nodes if isinstance(n.get("mesh"), int)]
    meshes = [m for m in document.get("meshes") or () if isinstance(m, dict)]
    if len(set(placed)) > 1:
        return "it places more than one mesh"
    if len(placed) > len(set(placed)):
        return "it instances a mesh from several nodes"
    if any("EXT_mesh_gpu_instancing" in (n.get("extensions") or {}) for n in nodes):
        return "it instances a mesh (EXT_mesh_gpu_instancing)"
    if document.get("skins") or any("skin" in n for n in nodes):
        return "it has a skin"
    if any(m.get("weights") or any(isinstance(p, dict) and p.get("targets")
                                   for p in m.get("primitives") or ()) for m in meshes):
        return "it has morph targets"
    if document.get("animations"):
        return "it has animations"
    if document.get("cameras") or any("camera" in n for n in nodes):
        return "it has cameras"
    return None


def _document_of(path: Path, limits: LoadLimits) -> dict | None:
    """The glTF JSON of a .gltf or .glb file, reading no more than its JSON (a GLB's
    first chunk); None when it cannot be read, for ``load_mesh`` to say why."""
    try:
        limits.check("max_file_bytes", path.stat().st_size, "bytes (the file's size)")
        with open(path, "rb") as file:
            head = file.read(20)
            if head[:4] != b"glTF":
                file.seek(0)
                return parse_json(file.read(), limits)
            length, kind = struct.unpack_from("<I4s", head, 12)
            if kind != b"JSON":
                return None
            limits.check("max_json_bytes", length, "bytes of glTF JSON")
            document, _ = parse_container(head + file.read(length), limits)
            return document
    except (OSError, ValueError, struct.error, MeshError):
        return None


@dataclass
class SceneReport:
    """What loading a scene changed or left out: each part's ``LoadReport`` and the
    scene's notes. ``as_dict()`` has ``missing_files`` and ``dropped_attributes``
    (over all parts) as a LoadReport's has, for ``io.fileset.load_warnings``."""

    reason: str
    reports: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def as_dict(self) -> dict:
        dropped = sorted({name for r in self.reports.values() for name in r.dropped_attributes})
        missing = sorted({name for r in self.reports.values() for name in r.missing_files})
        return {"scene": True, "reason": self.reason, "notes": list(self.notes),
                "dropped_attributes": dropped, "missing_files": missing,
                "parts": {str(k): r.as_dict() for k, r in sorted(self.reports.items())}}


def read_scene_upload(path, *, root, limits: LoadLimits | None, max_triangles: int):
    """``(Scene, SceneReport)`` for a .gltf/.glb that is a scene (:func:`scene_reason`),
    else None (the caller loads it as one mesh). Same limits and ``root`` rule as
    ``io.load_mesh``; LimitError past ``max_triangles`` triangles over all meshes."""
    path = Path(path)
    if path.suffix.lower() not in (".gltf", ".glb"):
        return None
    if limits is None:      # io.load_mesh's default
        limits = LoadLimits() if root is not None else LoadLimits.unbounded()
    document = _document_of(path, limits)
    reason = None if document is None else scene_reason(document)
    if reason is None:
        return None
    scene = load_scene(path, root=root, limits=limits)
    faces = sum(m.face_count for m in scene.meshes.values()) + sum(scene.as_is_faces.values())
    if faces > max_triangles:
        raise LimitError(f"the scene has {faces} triangles; this server builds at most "
                         f"{max_triangles}")
    if not scene.meshes:
        raise MeshError(f"cannot load {path.name}: none of its meshes can be simplified "
                        f"({'; '.join(scene.notes) or 'it has none'})")
    return scene, SceneReport(reason, dict(scene.reports), list(scene.notes))
