"""The stored form of an asset: one artefact file, one reader and one writer.

Every asset is stored as ONE artefact (:func:`encode_asset`,
:func:`decode_asset`), so that everything the store guarantees of an artefact
(one atomic write under a key naming its SHA-256, the row flipped to ready only
after it, fencing by attempt, nothing written when a part fails) holds for a
scene as for a single mesh. A single mesh (a scene of one part without a
document, ``SceneAsset.of_mesh``) is its ``.pm`` file (``progressive.artefact``),
byte for byte; a scene is a zip, told apart by its first bytes, so every
artefact ever stored reads back. A scene's zip (stored, not deflated; every
member CRC-32 checked on read) holds

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
import zipfile
from pathlib import Path

import numpy as np

from ..io.files import write_atomic
from ..io.scene import Scene
from ..mesh import Materials
from ..progressive import ArtefactError, decode_progressive, encode_progressive
from ..progressive.mesh import ProgressiveMesh
from .asset import SceneAsset, ScenePart, instances_and_diagonal

__all__ = ["ASSET_FORMAT", "decode_asset", "encode_asset", "load_artefact", "save_asset"]

ASSET_FORMAT = 1
_ZIP_MAGIC = b"PK\x03\x04"
# a fixed member timestamp: the same asset is the same bytes (zip's earliest date)
_STAMP = (1980, 1, 1, 0, 0, 0)


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
    if scene is None:
        return encode_progressive(asset.parts[0].pm)
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
    instances, diagonal = instances_and_diagonal(asset)
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
    """Parse bytes written by :func:`encode_asset`; ArtefactError (one sentence,
    naming ``source``) if they are not one."""
    if data[:4] != _ZIP_MAGIC:
        return SceneAsset.of_mesh(decode_progressive(data, source=source))
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


def load_artefact(path) -> SceneAsset:
    """The asset stored at ``path``; ArtefactError if it cannot be read (its cause
    the OSError) or is corrupt."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ArtefactError(f"cannot read {path}: {exc.strerror or exc}") from exc
    return decode_asset(data, source=str(path))
