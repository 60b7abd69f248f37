"""A scene written back as one GLB: the document, each part at its level or its chain."""

from __future__ import annotations

from ..io.scene import Scene
from ..io.scene_glb import encode_scene
from .asset import SceneAsset, instances_and_diagonal
from .budget import chain_levels

__all__ = ["scene_chain_glb", "scene_glb"]


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
    instances, diagonal = instances_and_diagonal(asset)
    chain = chain_levels(asset.pms, instances, lods=list(ratios), diagonal=diagonal)
    meshes = {part.mesh: [part.pm.at(levels[part.index]) for levels in chain]
              for part in asset.parts}
    return encode_scene(_labelled(asset), meshes, list(coverage))
