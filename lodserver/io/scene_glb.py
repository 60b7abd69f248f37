"""Writing a :class:`~lodserver.io.scene.Scene` back as GLB, each mesh replaced by its levels.

:func:`encode_scene` writes the input document (scenes, nodes with their names,
transforms, cameras, children and extensions, cameras, lights, materials,
samplers, images, animations, extras) with every glTF mesh replaced by levels
of detail of it:

- the chain form (``level=None``): the node that held mesh M holds M's level 0
  and ``extensions.MSFT_lod.ids`` names extra nodes (appended after the input's
  nodes, in no scene's root list) holding levels 1..k, each with the node's
  name suffixed ``" LOD<k>"`` and its transform; ``extras.MSFT_screencoverage``
  gives the hints. Each level of M is ONE glTF mesh shared by every node that
  instances M, so the output has levels x source meshes glTF meshes.
- the single-level form (``level=i``): the same document with level i in
  place of every mesh, for ``export --separate``.

Each level keeps every attribute column (:func:`.glb.render_attributes`): joints
and weights (valid for the skin, summing to 1), tangents, morph targets as
``primitive.targets`` with the mesh's ``weights`` and ``extras`` (``targetNames``)
carried. A node's LOD nodes carry its transform, ``skin``, morph ``weights`` and
``EXT_mesh_gpu_instancing``, so every level is posed and instanced like level 0
(animations still target the node itself: a viewer that swaps levels by MSFT_lod
draws the LOD node's static weights). Skins keep their
inverse bind matrices. A mesh in ``scene.as_is`` (no triangles) is written once,
as it was: its primitives over its carried accessors, no ``MSFT_lod``, in every
form.

Node indices are kept, so animation channels, camera and light references
and unknown extensions naming nodes stay right; the accessors animations and
``EXT_mesh_gpu_instancing`` use are rewritten tightly packed and renumbered.
"""

from __future__ import annotations

import copy

import numpy as np

from ..mesh import MeshError
from .glb import GlbWriter
from .gltf import ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, FLOAT
from .scene import GEOMETRY_EXTENSIONS, INDEX, VERTEX, Scene

# what the writer makes afresh, never copied from the input
_REBUILT = ("meshes", "accessors", "bufferViews", "buffers", "images", "materials", "textures",
            "samplers", "extensionsUsed", "extensionsRequired")

_LOD_KEYS = ("matrix", "translation", "rotation", "scale", "skin", "weights")


def encode_scene(scene: Scene, levels: dict, coverage: list[float], *,
                 level: int | None = None, compress: str = "none") -> bytes:
    """The GLB of ``scene`` with every mesh replaced by its levels.

    Parameters
    ----------
    scene : Scene
        As read by :func:`lodserver.io.scene.load_scene`.
    levels : dict of int to list of Mesh
        glTF mesh index -> its levels, finest first, the same count for every
        mesh; each level's ``face_material`` indexes ``scene.materials``.
    coverage : list of float
        ``MSFT_screencoverage`` per level (``glb.coverage_from_ratios``).
    level : int, optional
        Write only this level in place of each mesh (no ``MSFT_lod``).
    compress : str
        :data:`.glb.COMPRESSIONS`: the levels' attributes quantized and compressed
        as :class:`.glb.GlbWriter` does, their positions float32 (the nodes keep
        their transforms; skins and instances depend on them).

    Returns
    -------
    bytes
        The GLB file.
    """
    count = len(coverage)
    if set(levels) != set(scene.meshes) or any(len(c) != count for c in levels.values()):
        raise MeshError(f"every mesh of the scene needs {count} levels, one per coverage value")
    if level is not None and not 0 <= level < count:
        raise MeshError(f"level {level} does not exist; there are {count}")
    source = scene.document
    document = {key: copy.deepcopy(value) for key, value in source.items()
                if key not in _REBUILT}
    document["asset"] = {**document.get("asset", {}), "version": "2.0",
                         "generator": "lodserver"}
    writer = GlbWriter(scene.materials, compress)
    accessors = _carry_accessors(writer, scene.carried)
    for animation in document.get("animations", ()):
        for sampler in animation.get("samplers", ()):
            sampler["input"], sampler["output"] = (accessors[sampler["input"]],
                                                   accessors[sampler["output"]])
    for skin in document.get("skins", ()):
        if "inverseBindMatrices" in skin:
            skin["inverseBindMatrices"] = accessors[skin["inverseBindMatrices"]]

    # one glTF mesh per source mesh and level, shared by every node instancing it
    wanted = range(count) if level is None else [level]
    made = {}
    for index in sorted(levels):
        record = source["meshes"][index]
        for k in wanted:
            made[index, k] = writer.add_mesh(levels[index][k])
            out = writer.meshes[made[index, k]]
            name = record.get("name")
            if name is not None:
                out["name"] = name if k == 0 or level is not None else f"{name} LOD{k}"
            for key in ("extras", "extensions"):
                if key in record:
                    out[key] = copy.deepcopy(record[key])
            targets = max((len(p.get("targets", ())) for p in out["primitives"]), default=0)
            if "weights" in record and len(record["weights"]) == targets:
                out["weights"] = list(record["weights"])      # the default morph weights

    for index in sorted(scene.as_is):
        # kept as it is: the same primitives over the carried accessors
        record = copy.deepcopy(source["meshes"][index])
        for primitive in record["primitives"]:
            for attributes in (primitive["attributes"], *primitive.get("targets", ())):
                for name in attributes:
                    attributes[name] = accessors[attributes[name]]
            if "indices" in primitive:
                primitive["indices"] = accessors[primitive["indices"]]
            extensions = primitive.get("extensions", {})
            for name in GEOMETRY_EXTENSIONS & set(extensions):
                del extensions[name]  # compressed data is not carried; the plain data is
            if "extensions" in primitive and not extensions:
                del primitive["extensions"]
        writer.meshes.append(record)
        for k in wanted:
            made[index, k] = len(writer.meshes) - 1

    nodes = document.get("nodes", [])
    chained = False
    for number in range(len(nodes)):
        node = nodes[number]
        instancing = (node.get("extensions") or {}).get("EXT_mesh_gpu_instancing")
        if isinstance(instancing, dict):
            attributes = instancing.get("attributes", {})
            for key in attributes:
                attributes[key] = accessors[attributes[key]]
        if "mesh" not in node:
            continue
        mesh = node["mesh"]
        if level is not None or count == 1 or mesh in scene.as_is:
            node["mesh"] = made[mesh, 0 if level is None else level]
            continue
        ids = []
        for k in range(1, count):
            # the same transform, skin and morph weights: each level is posed like level 0
            lod = {key: copy.deepcopy(node[key]) for key in _LOD_KEYS if key in node}
            if isinstance(instancing, dict):
                # an instanced node's levels are drawn at every one of its instances
                lod["extensions"] = {"EXT_mesh_gpu_instancing": copy.deepcopy(instancing)}
            if "name" in node:
                lod["name"] = f"{node['name']} LOD{k}"
            lod["mesh"] = made[mesh, k]
            ids.append(len(nodes))
            nodes.append(lod)
        node["mesh"] = made[mesh, 0]
        node.setdefault("extensions", {})["MSFT_lod"] = {"ids": ids}
        extras = node.setdefault("extras", {})
        if isinstance(extras, dict):  # extras may be any JSON value; a non-object is kept as is
            extras["MSFT_screencoverage"] = [float(c) for c in coverage]
        chained = True
    document["meshes"] = writer.meshes

    # a mesh kept as it is may still hold quantized attributes
    dropped = GEOMETRY_EXTENSIONS - ({"KHR_mesh_quantization"} if scene.as_is else set())
    used = [name for name in source.get("extensionsUsed", ()) if name not in dropped]
    if chained and "MSFT_lod" not in used:
        used.append("MSFT_lod")
    required = [name for name in source.get("extensionsRequired", ()) if name not in dropped]
    return writer.finish_document(document, extensions=used, required=required)


def _carry_accessors(writer: GlbWriter, carried: dict) -> dict:
    """Write each carried accessor's values tightly packed; old index -> new index
    (accessors sharing one array share one new index).

    The record keeps its componentType, type, normalized, name and extras, and
    gets min and max of the values as written (the validator checks them, and
    an animation input or a POSITION must have them); sparse storage is
    applied, not kept. Vertex data gets the ARRAY_BUFFER target and, when an
    element is not a multiple of 4 bytes (a u8 VEC2, say), a padded byteStride,
    as glTF requires of vertex attributes; indices get ELEMENT_ARRAY_BUFFER.
    """
    mapping, written = {}, {}
    for index in sorted(carried):
        values, record, role = carried[index]
        # accessors aliasing one byte range share one array (io.gltf reads them
        # once): one accessor written, named by all of them
        same = (id(values), role, record.get("componentType"), record.get("type"),
                bool(record.get("normalized", False)))
        if same in written:
            mapping[index] = written[same]
            continue
        values = np.ascontiguousarray(values, dtype=values.dtype.newbyteorder("<"))
        element = values.dtype.itemsize * values.shape[1]
        data, stride = values.tobytes(), None
        if role == VERTEX and element % 4:
            stride = element + (-element % 4)
            padded = np.zeros((len(values), stride), np.uint8)
            padded[:, :element] = values.view(np.uint8).reshape(len(values), element)
            data = padded.tobytes()
        target = {VERTEX: ARRAY_BUFFER, INDEX: ELEMENT_ARRAY_BUFFER}.get(role)
        view = writer.add_view(data, target)
        if stride is not None:
            writer.views[view]["byteStride"] = stride
        accessor = {"bufferView": view, "componentType": record["componentType"],
                    "count": len(values), "type": record["type"]}
        for key in ("normalized", "name", "extras"):
            if key in record:
                accessor[key] = copy.deepcopy(record[key])
        if len(values) and role != INDEX:
            low, high = values.min(axis=0), values.max(axis=0)
            cast = float if record["componentType"] == FLOAT else int
            accessor["min"] = [cast(v) for v in low]
            accessor["max"] = [cast(v) for v in high]
        writer.accessors.append(accessor)
        mapping[index] = written[same] = len(writer.accessors) - 1
    return mapping
