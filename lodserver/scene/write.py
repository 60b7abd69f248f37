"""A scene written back as one GLB: the document, each part at its level or its chain."""

from __future__ import annotations

import dataclasses

from ..io.scene import Scene
from ..io.scene_glb import encode_scene
from .asset import SceneAsset, instances_and_diagonal, instances_of
from .budget import chain_levels
from .textures import level_meshes, texture_levels

__all__ = ["far_scene_glb", "scene_budget_beyond_reach", "scene_chain_glb", "scene_glb"]


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



def scene_budget_beyond_reach(asset: SceneAsset, ratio: float, levels: dict) -> int | None:
    """The whole scene's face budget at ``ratio`` (each instance counted) when its
    parts at ``levels`` (part index -> vertex count, ``scene_levels_for``) draw
    more than ``chains.REACH_SLACK`` times it, else None (edge collapse reaches it)."""
    from ..chains import REACH_SLACK

    instances = instances_of(asset)
    full = sum(len(instances[p.index]) * p.pm.face_count for p in asset.parts)
    drawn = sum(len(instances[p.index]) * p.pm.faces_at_level(levels[p.index])
                for p in asset.parts)
    budget = max(1, round(ratio * full))
    return budget if drawn > REACH_SLACK * budget else None


def far_scene_glb(asset: SceneAsset, ratio: float, levels: dict, compress: str = "none") -> bytes:
    """The GLB of the scene's level at ``ratio`` beyond edge collapse's reach
    (``scene_budget_beyond_reach``; ``levels`` edge collapse's), merged as an
    export with ``--separate`` merges it: a static scene (``merge.static_reason``)
    as one mesh, every part placed in the world, remeshed and baked (one node, one
    primitive, one material); a moving one by groups (``groups.grouped_level``:
    the meshes that move together merged, the rest at ``levels``). Its atlases
    are sized for the coverage a chain from full detail to ``ratio`` draws it up
    to. MeshError where clustering keeps no face."""
    from ..bake.level import merged_level
    from ..chains import REACH_SLACK
    from ..io.glb import coverage_from_ratios, encode_glb
    from .groups import grouped_level
    from .merge import static_reason, world_mesh

    coverage = coverage_from_ratios([1.0, ratio])[0]
    scene = _labelled(asset)
    full = dataclasses.replace(scene, meshes={
        part.mesh: part.pm.at(part.pm.vertex_count) for part in asset.parts})
    if static_reason(full) is None:
        budget = scene_budget_beyond_reach(asset, ratio, levels)
        return encode_glb(merged_level(world_mesh(full), budget, coverage=coverage), compress)
    drawn = {part.mesh: part.pm.at(levels[part.index]) for part in asset.parts}
    grouped, kept, _ = grouped_level(full, drawn, ratio, slack=REACH_SLACK, coverage=coverage)
    return encode_scene(grouped, {index: [mesh] for index, mesh in kept.items()}, [1.0],
                        level=0, compress=compress)
