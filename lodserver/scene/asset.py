"""A stored asset: a scene of parts, each part a mesh with its own progressive mesh.

Every asset the store keeps, every build and every route takes is one
:class:`SceneAsset`. A glTF scene (``scene.load``) holds the scene read by
``io.scene.load_scene`` (document, carried accessors, materials, meshes kept as
they are) and its *parts*: each glTF mesh of ``Scene.meshes`` with its own
:class:`~lodserver.progressive.mesh.ProgressiveMesh`, in glTF mesh order (part
``p`` is the ``p``-th such mesh). A single mesh (OBJ, PLY, STL, OFF, a glTF of
one mesh placed once) is a scene of one part without a document
(:meth:`SceneAsset.of_mesh`): what a document adds (a whole-scene level, world
instances, the scene artefact) it does not have, and it is stored and served as
that one mesh (:attr:`SceneAsset.single`). Its summary, its instances, its
levels under one budget (``scene.budget``) are here; which uploads are scenes is
``scene.load``, building is ``scene.build``, the stored form ``scene.artefact``,
the GLB of the whole scene ``scene.write``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io.animation import node_worlds
from ..io.scene import Scene
from ..mesh import Materials
from ..progressive.mesh import ProgressiveMesh
from .budget import scene_instances, scene_levels

__all__ = ["PartError", "ScenePart", "SceneAsset", "artefact_summary", "instances_and_diagonal",
           "instances_of", "part_of", "scene_levels_for"]


class PartError(LookupError):
    """A part index the mesh does not have (HTTP 404)."""


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
    """A built asset: ``scene`` (document, carried accessors, materials, meshes kept
    as they are; ``scene.meshes`` maps each part's glTF mesh to None, the
    geometry being the parts'), or None for a single mesh; its ``parts`` in
    order (a single mesh's one part: index 0, glTF mesh 0, no nodes); and
    ``metadata`` (a single mesh's is its progressive mesh's, the same dict, which
    its ``.pm`` file stores)."""

    scene: Scene | None
    parts: list
    metadata: dict = field(default_factory=dict)
    _instances: tuple | None = field(default=None, repr=False)   # (instances, diagonal)

    @classmethod
    def of_mesh(cls, pm: ProgressiveMesh) -> SceneAsset:
        """A single mesh as the scene of one part without a document."""
        return cls(None, [ScenePart(0, 0, "mesh 0", [], pm)], pm.metadata)

    @property
    def single(self) -> ProgressiveMesh | None:
        """The one progressive mesh of an asset without a glTF document (a single
        mesh: stored as its ``.pm`` file, its levels and packets the mesh's), else
        None (a scene: its levels are GLB files of the whole document)."""
        return self.parts[0].pm if self.scene is None else None

    @property
    def materials(self) -> Materials | None:
        return self.parts[0].pm.materials if self.scene is None else self.scene.materials

    @property
    def pms(self) -> dict:
        return {part.index: part.pm for part in self.parts}

    def summary(self) -> dict:
        """A single mesh's ``ProgressiveMesh.summary``; for a scene the same for the
        whole scene (counts summed over the parts, world bounds, a scene error
        curve by :func:`scene_levels_for`), with ``scene: True`` and ``parts``:
        each part's index, name, glTF mesh, nodes and its own summary (without
        metadata)."""
        if self.scene is None:
            return self.parts[0].pm.summary()
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


def artefact_summary(asset: SceneAsset) -> dict:
    """The catalogue summary of ``asset``: its ``summary()`` with only the load
    report and options of its metadata."""
    summary = {key: value for key, value in asset.summary().items() if key != "metadata"}
    summary["metadata"] = {name: asset.metadata[name] for name in ("load_report", "options")
                           if name in asset.metadata}
    return summary


def part_of(asset: SceneAsset, index: int) -> ProgressiveMesh:
    """Part ``index``'s progressive mesh; PartError (one sentence) if there is none."""
    count = len(asset.parts)
    if not 0 <= index < count:
        raise PartError(f"this mesh has {count} part{'s' if count > 1 else ''} "
                        f"(0 to {count - 1}); there is no part {index}")
    return asset.parts[index].pm


def instances_and_diagonal(asset: SceneAsset) -> tuple[dict, float]:
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
    return instances_and_diagonal(asset)[0]


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
    instances, diagonal = instances_and_diagonal(asset)
    return {int(p): int(v) for p, v in scene_levels(asset.pms, instances, ratio=ratio,
                                                    error=error, diagonal=diagonal).items()}
