"""Scenes kept as assets with parts: one progressive mesh per glTF mesh, and the document.

An upload whose glTF document is more than one mesh laid out (several meshes,
a mesh instanced by several nodes or by ``EXT_mesh_gpu_instancing``, a skin,
morph targets, animations, cameras: :func:`scene_reason`) is read with
``io.scene.load_scene`` instead of being flattened, and built as a
:class:`SceneAsset`: each glTF mesh of ``Scene.meshes`` is a *part* with its own
:class:`~lodserver.progressive.mesh.ProgressiveMesh`, in glTF mesh order
(part ``p`` is the ``p``-th such mesh). A single mesh (OBJ, PLY, STL, OFF, or a
glTF holding one mesh placed once, without skin, morph targets, animations or
cameras: its static transform is baked in) stays a plain
progressive mesh; the API calls it a scene of one part.

The asset is stored as ONE artefact (:func:`encode_asset`), so that everything
the store guarantees of an artefact holds for a scene unchanged: one atomic
write under a key naming its SHA-256, the row flipped to ready only after it,
fencing by attempt, nothing written when a part fails. The file is a zip
(stored, not deflated; every member CRC-32 checked on read) of

- ``scene.json``: format, the glTF document as read, the parts (index, glTF
  mesh, name, nodes), the meshes kept as they are, notes, the carried accessors'
  records (``Scene.carried``: record, role, dtype, shape), the materials' glTF
  records, metadata, and each part's instance scales and the scene's world
  diagonal (``budget.scene_instances``, slow to derive for many nodes);
- ``carried/<accessor>``: each carried accessor's values, little-endian, C order,
  once for accessors aliasing one byte range (the others' entries in
  ``scene.json`` name it as their ``alias``);
- ``images/<i>``: each image file, byte for byte;
- ``parts/<p>.pm``: each part's ``.pm`` file (``progressive.artefact``), without
  the materials (stored once above, shared by every part and given back on load).

Members have a fixed timestamp, so a deterministic build writes the same bytes
(and digest) on every server.
"""

from __future__ import annotations

import copy
import io
import json
import struct
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .budget import chain_levels, scene_instances, scene_levels
from ..io.animation import node_worlds
from ..io.gltf_document import parse_container, parse_json
from ..io.limits import LimitError, LoadLimits
from ..io.scene import Scene, load_scene
from ..io.scene_glb import encode_scene
from ..io.files import write_atomic
from ..mesh import Materials, MeshError
from ..progressive import (ArtefactError, decode_progressive, encode_progressive,
                           load_progressive)
from ..progressive.mesh import ProgressiveMesh
from ..simplify.poses import scene_poses

__all__ = ["ASSET_FORMAT", "PartError", "ScenePart", "SceneAsset", "SceneReport",
           "artefact_summary", "build_scene", "encode_asset", "decode_asset", "instances_of",
           "load_artefact",
           "part_of", "read_scene_upload", "save_asset", "scene_chain_glb", "scene_glb",
           "scene_levels_for", "scene_reason"]

ASSET_FORMAT = 1
_ZIP_MAGIC = b"PK\x03\x04"
# a fixed member timestamp: the same asset is the same bytes (zip's earliest date)
_STAMP = (1980, 1, 1, 0, 0, 0)


class PartError(LookupError):
    """A part index the mesh does not have (HTTP 404)."""


# ---- which uploads are scenes -----------------------------------------------------
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


# ---- the asset ---------------------------------------------------------------------
@dataclass(eq=False)
class ScenePart:
    """One part of a scene: glTF mesh ``mesh`` (named ``name``), placed by ``nodes``."""

    index: int
    mesh: int
    name: str
    nodes: list
    pm: ProgressiveMesh


@dataclass(eq=False)
class SceneAsset:
    """A built scene: ``scene`` (document, carried accessors, materials, meshes kept
    as they are; ``scene.meshes`` maps each part's glTF mesh to None, the
    geometry being the parts'), its ``parts`` in order, and ``metadata``."""

    scene: Scene
    parts: list
    metadata: dict = field(default_factory=dict)
    _instances: tuple | None = field(default=None, repr=False)   # (instances, diagonal)

    @property
    def materials(self) -> Materials | None:
        return self.scene.materials

    @property
    def pms(self) -> dict:
        return {part.index: part.pm for part in self.parts}

    def summary(self) -> dict:
        """As ``ProgressiveMesh.summary``, for the whole scene (counts summed over the
        parts, world bounds, a scene error curve by :func:`scene_levels_for`), with
        ``scene: True`` and ``parts``: each part's index, name, glTF mesh, nodes
        and its own summary (without metadata)."""
        pms = self.pms
        curve = []
        for ratio in np.geomspace(1.0, 1e-3, 25):
            levels = scene_levels_for(self, ratio=float(ratio))
            vertices = sum(levels.values())
            if curve and curve[-1]["vertices"] == vertices:
                continue
            curve.append({"ratio": round(float(ratio), 6), "vertices": vertices,
                          "faces": sum(pms[p].faces_at_level(v) for p, v in levels.items()),
                          "error": max(pms[p].error_at_level(v) for p, v in levels.items())})
        parts = []
        for part in self.parts:
            own = {k: v for k, v in part.pm.summary().items() if k != "metadata"}
            parts.append({"index": part.index, "name": part.name, "mesh": part.mesh,
                          "nodes": list(part.nodes), **own})
        total = {key: sum(p[key] for p in parts)
                 for key in ("vertices", "faces", "base_vertices", "base_faces", "splits")}
        return {**total, "max_error": max(p["max_error"] for p in parts),
                "bounds": _world_bounds(self), "error_curve": curve, "scene": True,
                "parts": parts, "metadata": self.metadata}


def artefact_summary(artefact) -> dict:
    """The catalogue summary of a ProgressiveMesh or SceneAsset: its ``summary()`` with
    only the load report and options of its metadata."""
    summary = {key: value for key, value in artefact.summary().items() if key != "metadata"}
    summary["metadata"] = {name: artefact.metadata[name] for name in ("load_report", "options")
                           if name in artefact.metadata}
    return summary


def part_of(artefact, index: int) -> ProgressiveMesh:
    """Part ``index``'s progressive mesh: a ProgressiveMesh is a scene of one part."""
    count = len(artefact.parts) if isinstance(artefact, SceneAsset) else 1
    if not 0 <= index < count:
        raise PartError(f"this mesh has {count} part{'s' if count > 1 else ''} "
                        f"(0 to {count - 1}); there is no part {index}")
    return artefact.parts[index].pm if isinstance(artefact, SceneAsset) else artefact


# ---- building ----------------------------------------------------------------------
def build_scene(scene: Scene, *, build, options: dict, lock_border: bool = False,
                progress=None, cancel=None) -> SceneAsset | None:
    """Build every part of ``scene`` with ``build`` (``lodserver.build.build``).

    A skinned or morphed part is built with its poses
    (``simplify.poses.scene_poses``: its error is measured in its animated
    poses too). ``progress(done, expected)`` is over the whole scene: faces of the parts
    built, plus the running part's fraction of its faces. None when ``cancel``
    was set (a cut-short part is not the mesh's progressive mesh). A part that
    fails raises its MeshError, naming the part; nothing is kept.
    """
    order = sorted(scene.meshes)
    total = sum(scene.meshes[m].face_count for m in order) or 1
    users = scene.mesh_nodes
    records = scene.document.get("meshes", [])
    parts, before = [], 0
    for index, mesh_index in enumerate(order):
        mesh = scene.meshes[mesh_index]

        def part_progress(done, expected, before=before, faces=mesh.face_count):
            if progress is not None:
                progress(before + faces * min(done / max(expected, 1), 1.0), total)

        locked = None
        if lock_border:
            from ..simplify.topology import census
            locked = np.zeros(mesh.vertex_count, dtype=bool)
            locked[census(mesh.faces, mesh.vertex_count).on_boundary] = True
        name = records[mesh_index].get("name") if isinstance(records[mesh_index], dict) else None
        name = name if isinstance(name, str) else f"mesh {mesh_index}"
        try:
            # a skinned or morphed part is simplified for its animated poses too
            poses = scene_poses(scene, mesh_index, mesh)
            extra = {} if poses is None else {"poses": poses}
            pm = build(mesh, locked=locked, progress=part_progress, cancel=cancel, **options,
                       **extra)
        except MeshError as exc:
            raise MeshError(f"part {index} ({name}): {exc}") from exc
        if cancel is not None and cancel.is_set():
            return None
        parts.append(ScenePart(index, mesh_index, name, list(users.get(mesh_index, [])), pm))
        before += mesh.face_count
    kept = Scene(scene.document, meshes=dict.fromkeys(order), materials=scene.materials,
                 carried=scene.carried, notes=list(scene.notes), as_is=dict(scene.as_is),
                 as_is_faces=dict(scene.as_is_faces))
    return SceneAsset(kept, parts)


# ---- the stored form -------------------------------------------------------------
def _member(archive: zipfile.ZipFile, name: str, data: bytes) -> None:
    info = zipfile.ZipInfo(name, date_time=_STAMP)
    info.compress_type = zipfile.ZIP_STORED
    archive.writestr(info, data)


def _without_materials(pm: ProgressiveMesh) -> ProgressiveMesh:
    """``pm`` sharing its arrays, with no materials (they are stored once per scene).
    A shallow copy of the frozen dataclass, changed before anyone sees it: a
    ``dataclasses.replace`` would derive the whole hierarchy again."""
    bare = copy.copy(pm)
    object.__setattr__(bare, "materials", None)
    return bare


def encode_asset(asset: SceneAsset) -> bytes:
    """The stored bytes of ``asset`` (module docstring)."""
    scene = asset.scene
    carried, first = [], {}
    for index in sorted(scene.carried):
        values, record, role = scene.carried[index]
        entry = {"index": int(index), "record": record, "role": role,
                 "dtype": np.asarray(values).dtype.newbyteorder("<").str,
                 "shape": list(np.shape(values))}
        # accessors aliasing one byte range share one array (io.gltf reads them
        # once): stored once, the others naming it
        if id(values) in first:
            entry["alias"] = first[id(values)]
        else:
            first[id(values)] = int(index)
        carried.append(entry)
    materials = scene.materials
    head = {"format": ASSET_FORMAT, "document": scene.document,
            "parts": [{"index": p.index, "mesh": p.mesh, "name": p.name, "nodes": p.nodes}
                      for p in asset.parts],
            "as_is": {str(k): v for k, v in scene.as_is.items()},
            "as_is_faces": {str(k): int(v) for k, v in scene.as_is_faces.items()},
            "notes": list(scene.notes), "carried": carried,
            "materials": None if materials is None else materials.gltf,
            "images": 0 if materials is None else len(materials.images),
            "metadata": asset.metadata}
    # the instances are stored, not derived on load: deriving them walks every
    # node of the scene, which for tens of thousands of nodes is slow
    instances, diagonal = _instances(asset)
    head["instances"] = {str(p): np.asarray(scales, np.float64).tolist()
                         for p, scales in instances.items()}
    head["diagonal"] = diagonal
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as archive:
        _member(archive, "scene.json", json.dumps(head).encode())
        for entry in carried:
            if "alias" in entry:
                continue
            values = scene.carried[entry["index"]][0]
            _member(archive, f"carried/{entry['index']}",
                    np.ascontiguousarray(values, dtype=entry["dtype"]).tobytes())
        for i, image in enumerate(() if materials is None else materials.images):
            _member(archive, f"images/{i}", bytes(image))
        for part in asset.parts:
            _member(archive, f"parts/{part.index}.pm",
                    encode_progressive(_without_materials(part.pm)))
    return out.getvalue()


def decode_asset(data: bytes, *, source: str = "the artefact") -> SceneAsset:
    """Parse bytes written by :func:`encode_asset`; ArtefactError (one sentence) if
    they are not one."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            head = json.loads(archive.read("scene.json"))
            if head.get("format") != ASSET_FORMAT:
                raise ArtefactError(f"{source} is a scene of format {head.get('format')!r}; "
                                    f"this lodserver reads format {ASSET_FORMAT}")
            materials = None
            if head["materials"] is not None:
                images = tuple(archive.read(f"images/{i}") for i in range(head["images"]))
                materials = Materials(head["materials"], images)
            carried = {}
            for entry in head["carried"]:
                if "alias" in entry:        # the same values as an earlier accessor's
                    values = carried[entry["alias"]][0]
                else:
                    values = np.frombuffer(archive.read(f"carried/{entry['index']}"),
                                           dtype=np.dtype(entry["dtype"])
                                           ).reshape(entry["shape"])
                carried[entry["index"]] = (values, entry["record"], entry["role"])
            parts = []
            for entry in head["parts"]:
                pm = decode_progressive(archive.read(f"parts/{entry['index']}.pm"),
                                        source=f"{source} (part {entry['index']})")
                # the materials are the scene's, stored once: given back to the
                # part just decoded, which no one else holds yet
                object.__setattr__(pm, "materials", materials)
                parts.append(ScenePart(int(entry["index"]), int(entry["mesh"]),
                                       str(entry["name"]), list(entry["nodes"]), pm))
    except ArtefactError:
        raise
    except (zipfile.BadZipFile, KeyError, ValueError, TypeError, EOFError) as exc:
        raise ArtefactError(f"{source} is not a readable lodserver scene ({exc})") from None
    if [p.index for p in parts] != list(range(len(parts))) or not parts:
        raise ArtefactError(f"{source} is a scene whose parts are not numbered 0 to n-1")
    scene = Scene(head["document"], meshes=dict.fromkeys(p.mesh for p in parts),
                  materials=materials, carried=carried, notes=list(head["notes"]),
                  as_is={int(k): v for k, v in head["as_is"].items()},
                  as_is_faces={int(k): v for k, v in head["as_is_faces"].items()})
    try:
        instances = ({int(p): np.asarray(scales, np.float64)
                      for p, scales in head["instances"].items()}, float(head["diagonal"]))
        if any(scales.ndim != 1 for scales in instances[0].values()):
            raise ValueError("instance scales are not lists of numbers")
    except (KeyError, ValueError, TypeError, AttributeError) as exc:
        raise ArtefactError(f"{source} is a scene without its instances ({exc})") from None
    if set(instances[0]) != {p.index for p in parts}:
        raise ArtefactError(f"{source} is a scene whose instances do not match its parts")
    return SceneAsset(scene, parts, dict(head.get("metadata") or {}), instances)


def save_asset(asset: SceneAsset, path) -> None:
    """Write ``asset`` to ``path`` atomically (``io.files.write_atomic``)."""
    write_atomic(path, encode_asset(asset))


def load_artefact(path, *, single=load_progressive):
    """The SceneAsset stored at ``path`` when its magic bytes say it is one, else
    ``single(path)`` (a ``.pm`` file); ArtefactError if it is corrupt."""
    path = Path(path)
    try:
        with open(path, "rb") as file:
            scene = file.read(4) == _ZIP_MAGIC
    except OSError:
        scene = False       # `single` says why it cannot be read
    if not scene:
        return single(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ArtefactError(f"cannot read {path}: {exc.strerror or exc}") from exc
    return decode_asset(data, source=str(path))


# ---- levels of the whole scene ---------------------------------------------------
def _instances(asset: SceneAsset) -> tuple[dict, float]:
    """``budget.scene_instances`` of the asset, by part index: per part one world
    scale per instance (node transforms, instancing, a skinned node's bind-pose
    joints), and the scene's world bounding-box diagonal. Kept on the asset."""
    if asset._instances is None:
        by_mesh, diagonal = scene_instances(asset.scene, {p.mesh: p.pm for p in asset.parts})
        asset._instances = ({p.index: by_mesh[p.mesh] for p in asset.parts}, diagonal)
    return asset._instances


def instances_of(asset: SceneAsset) -> dict:
    """Part index -> one world scale factor per instance, as ``budget.scene_levels``
    takes them."""
    return _instances(asset)[0]


def _world_bounds(asset: SceneAsset) -> dict:
    """Full-detail bounding box of the parts placed by their nodes' rest-pose world
    transforms, world units: {min: [x, y, z], max: [x, y, z]} (what a viewer frames;
    ``EXT_mesh_gpu_instancing`` offsets and skinning are not applied)."""
    world = node_worlds(asset.scene.document, asset.scene.carried)
    corners = []
    for part in asset.parts:
        positions = part.pm.positions
        if not len(positions) or not part.nodes:
            continue
        lo, hi = positions.min(axis=0), positions.max(axis=0)
        box = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
        corners += [(box @ world[node].T)[:, :3] for node in part.nodes]
    if not corners:
        return {"min": [0.0] * 3, "max": [0.0] * 3}
    stacked = np.concatenate(corners)
    return {"min": stacked.min(axis=0).tolist(), "max": stacked.max(axis=0).tolist()}


def scene_levels_for(asset: SceneAsset, *, ratio=None, error=None) -> dict:
    """Part index -> level (vertex count) of the whole scene at ``ratio`` of its
    triangles (each instance counted) or ``error`` (a fraction of its world
    bounding-box diagonal): one budget for the scene (``budget.scene_levels``).
    MeshError on a bad criterion."""
    instances, diagonal = _instances(asset)
    return {int(p): int(v) for p, v in scene_levels(asset.pms, instances, ratio=ratio,
                                                    error=error, diagonal=diagonal).items()}


def _labelled(asset: SceneAsset) -> Scene:
    """``asset.scene`` with ``extras.lodserver_part = p`` on each part's glTF mesh
    record, which ``encode_scene`` copies onto every mesh it writes for it."""
    scene = asset.scene
    document = dict(scene.document)
    meshes = list(document.get("meshes", []))
    for part in asset.parts:
        record = dict(meshes[part.mesh])
        extras = record.get("extras")
        record["extras"] = {**(extras if isinstance(extras, dict) else {}),
                            "lodserver_part": part.index}
        meshes[part.mesh] = record
    document["meshes"] = meshes
    return Scene(document, meshes=scene.meshes, materials=scene.materials,
                 carried=scene.carried, notes=scene.notes, as_is=scene.as_is,
                 as_is_faces=scene.as_is_faces)


def scene_glb(asset: SceneAsset, levels: dict) -> bytes:
    """The GLB of the whole scene with part ``p`` at level ``levels[p]`` (node tree,
    skins, animations, cameras kept); each part's glTF mesh has
    ``extras.lodserver_part``."""
    meshes = {part.mesh: [part.pm.at(levels[part.index])] for part in asset.parts}
    return encode_scene(_labelled(asset), meshes, [1.0], level=0)


def scene_chain_glb(asset: SceneAsset, ratios, coverage) -> bytes:
    """The ``MSFT_lod`` scene: level k of every part at scene ratio ``ratios[k]``."""
    # each part only coarsens along the chain (budget.chain_levels)
    instances, diagonal = _instances(asset)
    chain = chain_levels(asset.pms, instances, lods=list(ratios), diagonal=diagonal)
    meshes = {part.mesh: [part.pm.at(levels[part.index]) for levels in chain]
              for part in asset.parts}
    return encode_scene(_labelled(asset), meshes, list(coverage))
