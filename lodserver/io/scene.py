"""Reading a glTF scene kept whole: the document, and each glTF mesh as one Mesh.

:func:`load_scene` reads a .gltf or .glb as :func:`~lodserver.io.load_mesh`
does (the same size checks, :class:`~.limits.LoadLimits`, ``root=`` rule and
primitive decoding, :func:`.gltf.read_gltf_meshes`), but instead of flattening
the default scene it keeps the JSON document (scenes, the node tree with names
and transforms, cameras, ``KHR_lights_punctual``, materials with their
extensions, samplers, images, animations of node transforms, ``extras``,
unknown extensions) and turns each glTF mesh a node uses into one cleaned
:class:`~lodserver.mesh.Mesh` in that mesh's LOCAL space (all its triangle
primitives, one material per primitive), however many nodes instance it.

Each Mesh holds every vertex attribute of its primitives
(:mod:`.gltf_attributes`): NORMAL, TEXCOORD_n, COLOR_n, TANGENT, JOINTS_n and
WEIGHTS_n (joint indices into the skin of the nodes using it, checked to exist),
morph target deltas as ``TARGET{t}_POSITION``/``_NORMAL``/``_TANGENT`` and custom
``_NAME`` attributes; a primitive lacking one another primitive has gets a neutral
value. Skinned and morphed meshes are simplified like any other; the skins,
inverse bind matrices, mesh ``weights``, ``extras.targetNames`` and the animations
driving them are carried. Only meshes without triangles (points, lines) are kept
AS THEY ARE (:attr:`Scene.as_is`): one level, every accessor they use carried.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from ..mesh import Materials, MeshError
from .animation import check_scene
from .clean import clean_mesh
from .gltf import read_gltf_meshes
from .gltf_document import TRIANGLE_FAN, TRIANGLE_STRIP, TRIANGLES, check_carried
from .limits import LoadLimits
from .load import file_errors

# Extensions a document may require: carried as they are (materials, textures,
# lights, metadata) or decoded by the reader (quantized and compressed geometry).
HONOURED_REQUIRED = frozenset({
    "KHR_draco_mesh_compression", "EXT_meshopt_compression",
    "KHR_texture_transform", "KHR_texture_basisu", "EXT_texture_webp", "KHR_lights_punctual",
    "KHR_mesh_quantization", "KHR_xmp_json_ld", "KHR_materials_emissive_strength",
    "KHR_materials_unlit", "KHR_materials_clearcoat", "KHR_materials_transmission",
    "KHR_materials_volume", "KHR_materials_ior", "KHR_materials_specular",
    "KHR_materials_sheen", "KHR_materials_iridescence", "KHR_materials_anisotropy",
    "KHR_materials_dispersion", "KHR_materials_pbrSpecularGlossiness", "EXT_mesh_gpu_instancing",
})

# Extensions that describe geometry the output writes afresh (as its compress= says,
# io.glb.GlbWriter): dropped from extensionsUsed/Required of the output.
GEOMETRY_EXTENSIONS = frozenset({"KHR_mesh_quantization", "KHR_draco_mesh_compression",
                                 "EXT_meshopt_compression"})


@dataclass
class Scene:
    """A glTF document with each of its meshes as a lodserver Mesh.

    Attributes
    ----------
    document : dict
        The glTF JSON as read (not modified; the writer copies what it keeps).
    meshes : dict of int to Mesh
        glTF mesh index -> its triangles in the mesh's local space, welded and
        cleaned; ``face_material`` indexes ``materials``. Every mesh some node
        uses but those in ``as_is``.
    reports : dict of int to LoadReport
        What cleaning each mesh changed.
    materials : Materials or None
        Every material, texture, sampler and image of the document, shared.
    carried : dict of int to (ndarray, dict, str)
        Accessor index -> (its values (count, width) in its own dtype, its
        record, its role: VERTEX, INDEX or OTHER) for the accessors written as
        they are (:func:`carried_accessors`).
    notes : list of str
        What is not kept exactly, or kept without levels.
    as_is : dict of int to str
        Meshes written as they are, one level (those without triangles), with
        the reason (:func:`kept_as_is`); not in ``meshes``.
    as_is_faces : dict of int to int
        Their triangle counts (strips and fans unrolled).
    """

    document: dict
    meshes: dict = field(default_factory=dict)
    reports: dict = field(default_factory=dict)
    materials: Materials | None = None
    carried: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)
    as_is: dict = field(default_factory=dict)
    as_is_faces: dict = field(default_factory=dict)

    @property
    def mesh_nodes(self) -> dict:
        """glTF mesh index -> the indices of the nodes that instance it, in node order."""
        users = {}
        for index, node in enumerate(self.document.get("nodes", ())):
            if "mesh" in node:
                users.setdefault(node["mesh"], []).append(index)
        return users


def load_scene(path, *, root=None, limits: LoadLimits | None = None) -> Scene:
    """Read a .gltf or .glb file as a :class:`Scene`.

    Parameters
    ----------
    path : str or os.PathLike
        The file; a ``.gltf`` finds its buffers and images relative to it.
    root, limits
        As for :func:`lodserver.io.load_mesh` (``root`` confines every file
        the document names; ``limits`` default to ``LoadLimits()`` with a
        root, unbounded without).

    Raises
    ------
    MeshError
        For what :func:`load_mesh` refuses, and for an ``extensionsRequired``
        entry lodserver cannot honour (a vendor's geometry extension),
        one sentence naming the file by its name only; and for a node tree, skin,
        morph weights or animation that cannot be evaluated
        (:func:`.animation.check_scene`: cycles, joints or channel targets that are
        no nodes, non-finite or decreasing keyframe times, ...) or animation and
        skin data without bytes behind it.
    LimitError
        If the file declares more than ``limits`` allow, its carried data
        included (``LoadLimits.carried_ratio``, checked on the declarations
        before any of it is read).
    """
    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in ("gltf", "glb"):
        raise MeshError(f"cannot load {path.name} as a scene: only .gltf and .glb files hold one")
    if limits is None:
        limits = LoadLimits() if root is not None else LoadLimits.unbounded()
    root = Path(root) if root is not None else None
    with file_errors(path):
        if not path.is_file():
            raise MeshError("no such file" if not path.exists() else "it is not a regular file")
        size = path.stat().st_size
        if size == 0:
            raise MeshError("the file is empty")
        limits.check("max_file_bytes", size, "bytes (the file's size)")

        def check(document):
            # the bytes uploaded: the file and the buffer files it names
            external = sum(buffer.get("byteLength", 0) for buffer in document.get("buffers", ())
                           if isinstance(buffer.get("uri"), str)
                           and buffer["uri"][:5].lower() != "data:")
            carried = carried_accessors(document, _without_triangles(document))
            _check_carried_records(document, carried)
            check_carried(document, carried, size + external, limits)

        try:
            parts = read_gltf_meshes(path, kind, root=root, limits=limits,
                                     honoured=HONOURED_REQUIRED, check=check)
            return _scene(parts)
        except MeshError:       # a ValueError too, already one sentence
            raise
        except (KeyError, IndexError, TypeError, ValueError, AttributeError) as exc:
            # a malformed record of the parts this module reads (animations, nodes; a
            # string where an object belongs has no .get)
            raise MeshError(f"it could not be parsed as {kind.upper()} "
                            f"({type(exc).__name__}: {exc})") from exc


def kept_as_is(document: dict, meshes: dict) -> dict:
    """Meshes this version writes as they are (one level, every accessor carried
    byte-exact in value), each with the one-sentence reason.

    ``meshes`` maps mesh index -> arrays, or the message of a mesh without
    triangles (:func:`.gltf.read_gltf_meshes`): only those are kept as they are.
    Skinned and morphed meshes have their joints, weights and target deltas as
    attributes and are simplified like any other.
    """
    return {index: "it has no triangles (only points or lines)"
            for index, arrays in meshes.items() if isinstance(arrays, str)}


def _without_triangles(document: dict) -> list:
    """The meshes some node uses whose primitives are all points or lines: from the
    declarations, the meshes :func:`kept_as_is` will name (their accessors carried)."""
    used = {node["mesh"] for node in document.get("nodes", ())
            if isinstance(node, dict) and isinstance(node.get("mesh"), int)}
    meshes = document.get("meshes", [])
    return sorted(m for m in used if 0 <= m < len(meshes) and not any(
        isinstance(p, dict) and p.get("mode", TRIANGLES) in (TRIANGLES, TRIANGLE_STRIP,
                                                             TRIANGLE_FAN)
        for p in meshes[m].get("primitives", ())))


# how a carried accessor is used, for its bufferView's target and alignment
VERTEX, INDEX, OTHER = "vertex", "index", "other"


def carried_accessors(document: dict, as_is=()) -> dict:
    """Accessor index -> VERTEX, INDEX or OTHER for the accessors the output writes as
    they are: animation sampler inputs and outputs, ``EXT_mesh_gpu_instancing``
    attributes, skins' inverse bind matrices, and every accessor of the meshes in
    ``as_is`` (attributes, indices, morph target attributes)."""
    found = {}
    for animation in document.get("animations", ()):
        for sampler in animation.get("samplers", ()):
            found[sampler["input"]] = found[sampler["output"]] = OTHER
    for node in document.get("nodes", ()):
        instancing = (node.get("extensions") or {}).get("EXT_mesh_gpu_instancing")
        if isinstance(instancing, dict):
            found.update(dict.fromkeys(instancing.get("attributes", {}).values(), OTHER))
    for skin in document.get("skins", ()):
        if "inverseBindMatrices" in skin:
            found[skin["inverseBindMatrices"]] = OTHER
    for index in as_is:
        for primitive in document["meshes"][index]["primitives"]:
            for attributes in (primitive["attributes"], *primitive.get("targets", ())):
                found.update(dict.fromkeys(attributes.values(), VERTEX))
            if "indices" in primitive:
                found[primitive["indices"]] = INDEX
    return found


def _check_backed(accessor: dict, index: int) -> None:
    """MeshError for a carried accessor whose values no bytes of the file give: one
    without a bufferView reads as zeros (bar its sparse values), so a few bytes of JSON
    could declare ten million keyframes or inverse bind matrices (the rule
    ``gltf_document.check_geometry_has_data`` applies to geometry)."""
    count = accessor.get("count") if isinstance(accessor, dict) else None
    sparse = accessor.get("sparse") if isinstance(accessor, dict) else None
    sparse_count = sparse.get("count") if isinstance(sparse, dict) else 0
    if isinstance(accessor, dict) and "bufferView" not in accessor and count \
            and sparse_count != count:
        raise MeshError(f"its animation or skin accessor {index} has {count!r:.20} values "
                        f"without a bufferView (only {sparse_count!r:.20} given)")


def _check_carried_records(document: dict, carried: dict) -> None:
    """MeshError for a carried accessor that does not exist, or (animation, skin and
    instancing data) has no bytes behind it (:func:`_check_backed`)."""
    accessors = document.get("accessors", [])
    for index, role in carried.items():
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(accessors):
            raise MeshError(f"its animation, skin, mesh or instancing data refers to accessor "
                            f"{index!r}, which does not exist")
        if role == OTHER:
            _check_backed(accessors[index], index)


def _scene(parts: dict) -> Scene:
    document, arrays = parts["document"], parts["meshes"]
    scene = Scene(document, materials=parts["materials"])
    scene.as_is = kept_as_is(document, arrays)
    accessors = document.get("accessors", [])
    carried = carried_accessors(document, scene.as_is)
    _check_carried_records(document, carried)
    for index, role in carried.items():
        scene.carried[index] = (parts["accessor"](index), accessors[index], role)
    # the node tree, skins and animations the poses and the writer evaluate
    check_scene(document, scene.carried)
    for index, mesh_arrays in arrays.items():
        if index in scene.as_is:
            scene.notes.append(f"mesh {index} is written as it is, one level: "
                               f"{scene.as_is[index]}")
            scene.as_is_faces[index] = (0 if isinstance(mesh_arrays, str)
                                        else len(mesh_arrays["faces"]))
            continue
        arrays_in = dict(mesh_arrays)
        dropped = arrays_in.pop("dropped_attributes", [])
        arrays_in.pop("missing_files", None)
        mesh, report = clean_mesh(**arrays_in)
        report.dropped_attributes = list(dropped)
        if dropped:
            scene.notes.append(f"mesh {index}: its attributes {', '.join(dropped)} are not kept "
                               "(matrix-typed or unknown)")
        scene.meshes[index], scene.reports[index] = mesh, report
    for index, mesh in enumerate(document.get("meshes", ())):
        if index in scene.as_is:
            continue
        primitives = mesh.get("primitives", ())
        # compression is decoded, not lost: only other extensions count
        if any("extras" in p or set(p.get("extensions") or ()) - GEOMETRY_EXTENSIONS
               for p in primitives):
            scene.notes.append(f"mesh {index}: its primitives' extras and extensions are not "
                               "kept (the levels have one primitive per material)")
        if any(p.get("mode", 4) not in (4, 5, 6) for p in primitives):
            scene.notes.append(f"mesh {index}: its points and lines are not kept")
        if index not in arrays:
            scene.notes.append(f"mesh {index}: no node uses it, so it is not written")
    return scene
