"""Which levels of detail a chain holds: ratios or error bounds, checked once.

The one place the chain's options live (:class:`ChainOptions`: ``lods``,
``errors``, ``per_mesh``, ``separate``, ``reach``), with their parsers for the
command line and the HTTP query (:func:`parse_lods`, :func:`parse_errors`) and
the levels of one progressive mesh they pick (:func:`lod_chain`,
:func:`error_chain`), and what an export wrote (:class:`Exported`). The pipeline (``pipeline.py``), the API's chain route
and the command line take them from here; a scene's levels are chosen by the
scene's budget (``scene.budget.chain_levels``).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .io.glb import LOD_NAMINGS, check_compress, coverage_from_ratios
from .mesh import Materials, Mesh, MeshError
from .progressive.mesh import ProgressiveMesh

DEFAULT_LODS = (1.0, 0.5, 0.2, 0.05)


def parse_lods(text: str) -> tuple[float, ...]:
    """Face ratios from ``"1,0.5,0.2"``: finest first, each in (0, 1], decreasing."""
    return check_lods(_numbers(text, "LOD ratios", "1,0.5,0.2"))


def _numbers(text: str, what: str, example: str) -> tuple[float, ...]:
    """The comma-separated numbers of ``text``; MeshError naming ``what`` otherwise."""
    try:
        return tuple(float(part) for part in text.split(","))
    except ValueError:
        raise MeshError(f"{what} must be comma-separated numbers like {example}, "
                        f"got {text!r}") from None


def check_lods(ratios) -> tuple[float, ...]:
    ratios = tuple(float(r) for r in ratios)
    if not all(0 < ratio <= 1 for ratio in ratios):
        raise MeshError(f"every LOD ratio must be in (0, 1], got {list(ratios)}")
    coverage_from_ratios(ratios)        # and strictly decreasing
    return ratios


def parse_errors(text: str) -> tuple[float, ...]:
    """Error bounds from ``"0.001,0.01"``: finest first, each >= 0, increasing."""
    return check_errors(_numbers(text, "LOD errors", "0.001,0.01"))


def check_errors(errors) -> tuple[float, ...]:
    """Error bounds (fractions of the bounding-box diagonal) of the levels, finest
    first: each finite and >= 0, strictly increasing."""
    errors = tuple(float(e) for e in errors)
    if not errors or not all(math.isfinite(e) and e >= 0 for e in errors):
        raise MeshError(f"every LOD error must be a non-negative number (a fraction of the "
                        f"bounding-box diagonal), got {list(errors)}")
    if any(b <= a for a, b in itertools.pairwise(errors)):
        raise MeshError(f"LOD errors must be strictly increasing, finest first, "
                        f"got {list(errors)}")
    return errors


@dataclass
class Exported:
    """One source's levels of detail, as written."""

    source: Path                # a str URL for an object-store folder
    outputs: list[Path]
    faces: list[int]            # per level, finest first
    coverage: list[float]       # MSFT_screencoverage per level
    seconds: float
    base_faces: int = 0         # the coarsest edge collapse reaches: ratios below it stop there
    clustered: list[int] = field(default_factory=list)   # levels made by clustering (reach)
    notes: list[str] = field(default_factory=list)       # what a scene's export did not keep
    # a scene's: triangles drawn per level (each part once per instance); empty for a
    # single mesh
    drawn: list[int] = field(default_factory=list)
    # each level's error: a scene's worst world error (world units), a single mesh's
    # collapse error (mesh units; None for a level made by clustering, not measured)
    errors: list = field(default_factory=list)
    diagonal: float = 0.0       # of the bounding box the errors are fractions of
    # seconds to encode and write each level's file (--separate; empty for one file)
    level_seconds: list[float] = field(default_factory=list)


# A level whose edge-collapse mesh overshoots its face budget by more than this is
# out of reach of edge collapse (locked, non-manifold or separate parts).
REACH_SLACK = 1.1
REACH_METHODS = ("none", "cluster", "merge")
# What a chain by ratios does where edge collapse stops short, unless told.
DEFAULT_REACH = "merge"


def check_reach(reach: str) -> str:
    if reach not in REACH_METHODS:
        raise MeshError(f"reach must be one of {', '.join(REACH_METHODS)}, got {reach!r}")
    return reach


# A baked atlas's side, in texels, at least and at most (a bake holds several
# float arrays per texel: the upper bound keeps it to a few hundred megabytes).
ATLAS_RANGE = (16, 2048)


def check_atlas(atlas: int | None) -> int | None:
    """``atlas`` (None, or a side within :data:`ATLAS_RANGE`), else ``MeshError``."""
    if atlas is not None and not (isinstance(atlas, int)
                                  and ATLAS_RANGE[0] <= atlas <= ATLAS_RANGE[1]):
        raise MeshError(f"the atlas size must be a whole number of texels from "
                        f"{ATLAS_RANGE[0]} to {ATLAS_RANGE[1]}, got {str(atlas)[:20]}")
    return atlas


def shared_materials(meshes: list[Mesh]) -> list[Mesh]:
    """The levels of one chain with one materials list: a baked level's own
    material, textures, samplers and images appended to the first level's (which
    ``io.glb.encode_lod_chain`` writes once for all), its indices moved along."""
    shared, moved = joined_materials(meshes[0].materials, meshes[1:])
    if shared is meshes[0].materials:
        return list(meshes)
    first = meshes[0]
    return [Mesh(first.positions, first.faces, first.attributes, first.face_material, shared),
            *(Mesh(m.positions, m.faces, m.attributes, used, shared) for m, used in moved)]


def joined_materials(base: Materials | None, meshes) -> tuple:
    """``base`` with the materials of ``meshes`` that have their own (a baked
    level's) appended: ``(materials, [(mesh, face_material into them)])``; ``base``
    itself, and each mesh's own ``face_material``, when none has its own."""
    gltf = {key: list((base.gltf if base is not None else {}).get(key) or [])
            for key in ("materials", "textures", "samplers", "images")}
    images = list(base.images) if base is not None else []
    moved, appended = [], {}
    for mesh in meshes:
        if mesh.materials is None or mesh.materials is base:
            moved.append((mesh, mesh.face_material))
            continue
        if id(mesh.materials) in appended:
            # parts baked together share one material list: appended once
            moved.append((mesh, None if mesh.face_material is None else np.where(
                mesh.face_material >= 0, mesh.face_material
                + appended[id(mesh.materials)], -1)))
            continue
        own = mesh.materials.gltf
        offsets = {key: len(gltf[key]) for key in gltf}
        appended[id(mesh.materials)] = offsets["materials"]
        for texture in own.get("textures", ()):
            texture = dict(texture)
            for key, kind in (("source", "images"), ("sampler", "samplers")):
                if key in texture:
                    texture[key] += offsets[kind]
            gltf["textures"].append(texture)
        for material in own.get("materials", ()):
            gltf["materials"].append(_moved_textures(material, offsets["textures"]))
        gltf["samplers"] += own.get("samplers", [])
        gltf["images"] += own.get("images", [])
        images += mesh.materials.images
        moved.append((mesh, None if mesh.face_material is None else np.where(
            mesh.face_material >= 0, mesh.face_material + offsets["materials"], -1)))
    if len(gltf["materials"]) == (base.count if base is not None else 0):
        return base, moved
    return Materials({key: value for key, value in gltf.items() if value}, tuple(images)), moved


def _moved_textures(record, offset: int):
    """A material record with every texture info's ``index`` moved by ``offset``."""
    if isinstance(record, dict):
        return {key: (value + offset if key == "index" and isinstance(value, int)
                      else _moved_textures(value, offset)) for key, value in record.items()}
    if isinstance(record, list):
        return [_moved_textures(value, offset) for value in record]
    return record


def lod_chain(pm: ProgressiveMesh, lods=DEFAULT_LODS, *, reach: str = DEFAULT_REACH,
              atlas: int | None = None):
    """The levels of ``pm`` at face ratios ``lods`` (finest first).

    Returns ``(meshes, coverage, clustered)``: the meshes, their screen coverage
    hints (:func:`gltf.coverage_from_ratios`) and the indices of the levels made
    by clustering (``reach``, as :class:`ChainOptions` says; ``atlas`` the side
    of a merged level's baked atlas, None: from its screen coverage). Raises
    :class:`MeshError` on bad ratios or ``reach``.
    """
    ratios = check_lods(lods)
    check_reach(reach)
    coverage = coverage_from_ratios(ratios)
    meshes, clustered = [], []
    for k, ratio in enumerate(ratios):
        mesh = pm.at(pm.level_for(ratio=ratio))
        budget = max(1, round(ratio * pm.face_count))
        if reach != "none" and out_of_reach(pm, budget):
            # drawn up to the finer level's coverage: the atlas is sized for that
            joined = reached_level(pm, budget, reach, atlas, coverage[k - 1] if k else 1.0)
            if joined is not None and joined.face_count < mesh.face_count:
                mesh = joined
                clustered.append(len(meshes))
        meshes.append(mesh)
    return meshes, coverage, clustered


def out_of_reach(pm: ProgressiveMesh, budget: int) -> bool:
    """Whether edge collapse's finest level within ``budget`` faces still has more
    than :data:`REACH_SLACK` times them (it stopped at its base above the budget)."""
    return pm.faces_at_level(pm.level_for(faces=max(1, int(budget)))) > REACH_SLACK * budget


def reached_level(pm: ProgressiveMesh, budget: int, reach: str, atlas: int | None = None,
                  coverage: float | None = 1.0) -> Mesh | None:
    """The level ``reach`` makes of ``pm``'s full mesh at ``budget`` faces (a merged
    level's atlas ``atlas`` texels a side, else sized for ``coverage``, None: the
    default size), or None where clustering keeps no face (a part of a few faces
    asked for fewer) or a merge cannot keep the mesh's morph targets. A skinned
    mesh's merged level keeps its skin (``bake.level.with_skin``)."""
    from .bake.level import merged_level, with_skin
    from .simplify.cluster import cluster

    full = pm.at(pm.vertex_count)
    names = [name for name, _ in full.attributes.layout] if full.attributes else []
    if reach == "merge" and any(name.startswith("TARGET") for name in names):
        return None     # a morphed part stays a part: clustering cannot keep its targets
    try:
        if reach != "merge":
            return cluster(Mesh(full.positions, full.faces), target_faces=budget)
        joined = merged_level(full, budget, atlas=atlas, coverage=coverage)
    except MeshError:
        return None
    # one skeleton: the level keeps its skin
    return with_skin(full, joined) if any(name.startswith("JOINTS_") for name in names) \
        else joined


def error_chain(pm: ProgressiveMesh, errors):
    """The levels of ``pm`` within error bounds ``errors`` (fractions of its
    bounding-box diagonal, finest first): ``(meshes, coverage)``, the hints from
    the levels' measured errors (:func:`budget.coverage_from_errors`)."""
    from .scene.budget import coverage_from_errors, part_diagonal

    diagonal = part_diagonal(pm)
    levels = [pm.level_for(error=e * diagonal) for e in check_errors(errors)]
    coverage = coverage_from_errors([pm.error_at_level(v) for v in levels], diagonal)
    return [pm.at(v) for v in levels], coverage


@dataclass(frozen=True)
class ChainOptions:
    """Which levels an export writes, and how: the options of the chain of levels,
    checked when made (``MeshError``, one sentence) and held checked.

    Attributes
    ----------
    lods : tuple of float
        Face ratios of the levels, finest first, strictly decreasing, in (0, 1];
        ``DEFAULT_LODS`` when neither ``lods`` nor ``errors`` is given, None with
        ``errors``. For a scene, ratios of the whole scene's triangles, each part
        once per instance, with one budget for all parts (:func:`budget.scene_levels`).
    errors : tuple of float, optional
        Instead of ``lods``: error bounds of the levels, finest first, strictly
        increasing, >= 0, as fractions of the bounding-box diagonal (a scene's
        world box); each mesh at its coarsest level within the bound (world
        error for a scene: the mesh's error times its largest instance scale).
    per_mesh : bool
        A scene's ``lods`` are each mesh's own face ratios instead of one
        budget for the whole scene. The same for a single mesh. Not with
        ``errors``.
    separate : bool
        Write ``OUT_lod0.glb``, ``OUT_lod1.glb``, ... instead of one file.
    compress : str
        How the GLB files store the levels (``io.glb.COMPRESSIONS``): ``"none"``
        (float32, the progressive mesh's order: lossless, the library's default),
        ``"quantize"`` (the command line's default, ``io.glb.DEFAULT_COMPRESS``) or
        ``"meshopt"``.
    naming : str
        How one file's levels are told apart (``io.glb.LOD_NAMINGS``): ``"msft"``
        (the ``MSFT_lod`` extension, nodes ``LOD0``...), ``"suffix"`` (nodes
        ``STEM_LOD0``... under a root ``STEM``, all in the scene) or ``"both"``. With
        ``separate`` each file's node is ``STEM_LODi`` whatever it says. A scene's
        levels are linked by ``MSFT_lod`` only.
    texture_scale : str or tuple of float, optional
        Texture levels (``scene.textures``): None keeps every image at full size
        in every level; ``"auto"`` scales each level's images to its screen size
        (the sides by ``sqrt`` of its share of the finest level's faces, a power
        of two, at least 64 px); or one scale in (0, 1] per level.
    reach : str, optional
        ``"merge"`` (the default with ``lods``): a level edge collapse cannot
        bring down to its budget is the full mesh remeshed by vertex clustering
        to within 10% of the budget (``bake.level.merged_level``), joining parts
        and closing small gaps, its look baked into one atlas and one material.
        ``"none"`` (the default with ``errors``): such a level stays at the
        coarsest edge collapse reaches. ``"cluster"``: such a level is made by
        vertex clustering of the full mesh instead (``cluster.cluster``), which joins
        parts and meets the budget but keeps positions only (no UVs, normals or
        materials: a textured asset's far level is drawn untextured). Not with
        ``errors``.
    impostor : bool
        The farthest level of a static asset is an octahedral impostor instead
        (``bake.impostor``; written by ``scene.impostor_level``): its own file,
        so only with ``separate``, of two levels or more by ``lods``.
    """

    lods: tuple[float, ...] | None = None
    errors: tuple[float, ...] | None = None
    per_mesh: bool = False
    separate: bool = False
    reach: str | None = None
    atlas: int | None = None
    compress: str = "none"
    naming: str = "msft"
    texture_scale: str | tuple[float, ...] | None = None
    impostor: bool = False

    def __post_init__(self):
        if self.reach is None:
            object.__setattr__(self, "reach", "none" if self.errors is not None
                               else DEFAULT_REACH)
        check_reach(self.reach)
        check_atlas(self.atlas)
        check_compress(self.compress)
        if self.naming not in LOD_NAMINGS:
            raise MeshError(f"LOD naming must be one of {', '.join(LOD_NAMINGS)}, "
                            f"got {str(self.naming)[:40]!r}")
        if self.lods is not None and self.errors is not None:
            raise MeshError("give LOD ratios or LOD errors, not both")
        if self.errors is not None:
            if self.per_mesh:
                raise MeshError("per-mesh levels are chosen by ratio; levels by error are "
                                "per mesh already")
            if self.reach != "none":
                raise MeshError("reach meets face budgets, and levels by error have none")
            object.__setattr__(self, "errors", check_errors(self.errors))
        else:
            lods = DEFAULT_LODS if self.lods is None else self.lods
            object.__setattr__(self, "lods", check_lods(lods))
        if self.impostor and (self.errors is not None or len(self.lods) < 2
                              or not self.separate):
            raise MeshError("an impostor is the farthest of two or more levels by ratio, "
                            "written as a file of its own (separate)")
        from .scene.textures import check_texture_scale
        levels = len(self.errors if self.errors is not None else self.lods)
        object.__setattr__(self, "texture_scale",
                           check_texture_scale(self.texture_scale, levels))

    @classmethod
    def of(cls, chain: ChainOptions | None, keywords: dict) -> ChainOptions:
        """``chain``, or one made of ``keywords`` (the fields by name, as
        ``export_lods`` and ``export_folder`` also take them); not both."""
        if chain is None:
            return cls(**keywords)
        if keywords:
            raise TypeError(f"give chain or {', '.join(sorted(keywords))}, not both")
        return chain
