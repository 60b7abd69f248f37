"""A scene written back as one GLB: the document, each part at its level or its chain."""

from __future__ import annotations

import dataclasses

from ..io.scene import Scene
from ..io.scene_glb import encode_scene
from .asset import SceneAsset, instances_and_diagonal, instances_of
from .budget import chain_levels
from .textures import level_meshes, texture_levels

__all__ = ["merged_scene_budget", "merged_scene_glb", "scene_chain_glb", "scene_glb"]


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


def scene_glb(asset: SceneAsset, levels: dict, compress: str = "none") -> bytes:
    """The GLB of the whole scene with part ``p`` at level ``levels[p]`` (node tree,
    skins, animations, cameras kept); each part's glTF mesh has
    ``extras.lodserver_part``. ``compress``: ``io.glb.COMPRESSIONS``, as for a
    scene's export."""
    meshes = {part.mesh: [part.pm.at(levels[part.index])] for part in asset.parts}
    return encode_scene(_labelled(asset), meshes, [1.0], level=0, compress=compress)


def scene_chain_glb(asset: SceneAsset, ratios, coverage, *, compress: str = "none",
                    texture_scale=None) -> bytes:
    """The ``MSFT_lod`` scene: level k of every part at scene ratio ``ratios[k]``,
    stored as ``compress`` says (``io.glb.COMPRESSIONS``); with ``texture_scale`` (``"auto"`` or one per level, ``textures.texture_levels``)
    each level drawn with its own images, scaled by the triangles it draws (each
    part once per instance)."""
    # each part only coarsens along the chain (budget.chain_levels)
    instances, diagonal = instances_and_diagonal(asset)
    chain = chain_levels(asset.pms, instances, lods=list(ratios), diagonal=diagonal)
    meshes = {part.mesh: [part.pm.at(levels[part.index]) for levels in chain]
              for part in asset.parts}
    scene = _labelled(asset)
    drawn = [sum(len(instances[part.index]) * meshes[part.mesh][k].face_count
                 for part in asset.parts) for k in range(len(chain))]
    found = texture_levels(scene.materials, texture_scale, drawn)
    if found is not None:
        meshes = {index: level_meshes(levels, found, separate=False)
                  for index, levels in meshes.items()}
        scene = dataclasses.replace(scene, materials=found.chain)
    return encode_scene(scene, meshes, list(coverage), compress=compress)


def merged_scene_budget(asset: SceneAsset, ratio: float, levels: dict) -> int | None:
    """The whole scene's face budget at ``ratio`` (each instance counted) when its
    parts at ``levels`` (part index -> vertex count, ``scene_levels_for``) draw
    more than ``chains.REACH_SLACK`` times it and the scene can be drawn as one
    mesh (``merge.static_reason``); else None (edge collapse's level stands)."""
    from ..chains import REACH_SLACK
    from .merge import static_reason

    instances = instances_of(asset)
    full = sum(len(instances[p.index]) * p.pm.face_count for p in asset.parts)
    drawn = sum(len(instances[p.index]) * p.pm.faces_at_level(levels[p.index])
                for p in asset.parts)
    budget = max(1, round(ratio * full))
    if drawn <= REACH_SLACK * budget:
        return None
    parts = {p.mesh: (p.pm.attribute_layout, p.pm.face_count) for p in asset.parts}
    return budget if static_reason(asset.scene, parts) is None else None


def merged_scene_glb(asset: SceneAsset, budget: int, compress: str = "none",
                     coverage: float = 1.0) -> bytes:
    """The GLB of a static scene's far level as one mesh (``merged_scene_budget``):
    every part's full detail placed in the world (``merge.world_mesh``), remeshed to
    ``budget`` faces and baked for a level drawn up to ``coverage`` of the screen
    (``bake.level.merged_level``): one node, one primitive, one material."""
    from ..bake.level import merged_level
    from ..io.glb import encode_glb
    from .merge import world_mesh

    full = dataclasses.replace(asset.scene, meshes={
        part.mesh: part.pm.at(part.pm.vertex_count) for part in asset.parts})
    return encode_glb(merged_level(world_mesh(full), budget, coverage=coverage), compress)
