"""A partly animated scene's far level: the parts that move together merged, the rest kept.

Where a scene is animated or skinned, its parts cannot all be drawn as one mesh
(``merge.static_reason``), but those that never move relative to each other
can. :func:`rigid_groups` finds them, by the rule of the table below, one row
per kind of node that places a mesh:

==========================================  =========================================
node                                        group
==========================================  =========================================
instanced (``EXT_mesh_gpu_instancing``),    none: kept as a part
a mesh kept as it is, a morphed mesh
skinned (``skin`` s)                        every mesh of skin s, in its bind space
otherwise                                   every node under the same nearest animated
                                            ancestor-or-self A (none: the scene's
                                            static world), placed in A's frame
==========================================  =========================================

(animated: a channel moves its translation, rotation or scale). A group of
at least two drawn meshes is merged at a level where its meshes' levels draw
more than ``chains.REACH_SLACK`` times its share of the budget
(:func:`grouped_level`): its meshes placed in one frame (``merge.placed_mesh``),
remeshed and baked (``bake.level.merged_level``; a skinned group keeps its
skin, ``bake.level.with_skin``), and drawn by a new node: a child of A, or a
root of the scene (the static world; a skinned mesh, whose node's transform
glTF ignores). The grouped nodes lose their meshes at that level; animations
still move A, and with it the merged mesh.
"""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass, field

import numpy as np

from ..io.animation import node_parents, node_worlds

# the channel paths that move a node
_MOVING = ("translation", "rotation", "scale")


@dataclass
class Group:
    """Meshes that move together: ``members`` (node, glTF mesh), each placed by its
    (4, 4) matrix of ``matrices`` in the frame of node ``anchor`` (None: the world;
    a skinned group's frame is its bind space) or drawn with skin ``skin``;
    the merged mesh's node goes into scene ``scene``'s roots when it has no anchor."""

    anchor: int | None
    skin: int | None
    scene: int | None
    members: list = field(default_factory=list)
    matrices: list = field(default_factory=list)


def _moving_nodes(document: dict) -> set | None:
    """Nodes an animation moves; None when a channel targets something other than
    a node's path (an extension's pointer): then nothing is known to stay still."""
    moving = set()
    for animation in document.get("animations", ()):
        for channel in animation.get("channels", ()):
            target = channel.get("target", {})
            if target.get("node") is None:
                return None
            if target.get("path") in _MOVING:
                moving.add(int(target["node"]))
    return moving


def _scene_of_roots(document: dict) -> dict:
    """Root node -> the one scene listing it (roots listed by several scenes or
    none are left out: a new root could not follow them)."""
    count = {}
    for number, record in enumerate(document.get("scenes", ())):
        for root in record.get("nodes", ()):
            count.setdefault(int(root), []).append(number)
    return {root: scenes[0] for root, scenes in count.items() if len(scenes) == 1}


def rigid_groups(scene) -> list[Group]:
    """The groups of ``scene`` (a ``io.scene.Scene`` whose ``meshes`` hold the
    meshes) with at least two drawn meshes, in a fixed order (by their first
    node)."""
    document = scene.document
    moving = _moving_nodes(document)
    if moving is None:
        return []
    nodes = document.get("nodes", [])
    parent = node_parents(document)
    world = node_worlds(document, scene.carried)
    roots = _scene_of_roots(document)
    groups = {}
    for number, node in enumerate(nodes):
        index = node.get("mesh")
        if index is None or index not in scene.meshes or "weights" in node \
                or "EXT_mesh_gpu_instancing" in (node.get("extensions") or {}):
            continue
        mesh = scene.meshes[index]
        names = [name for name, _ in mesh.attributes.layout] if mesh.attributes else []
        if any(name.startswith("TARGET") for name in names):
            continue        # a morphed mesh stays a part: clustering cannot keep its targets
        if "skin" in node:
            if not any(name.startswith("JOINTS_") for name in names):
                continue
            key, anchor, skin, frame = ("skin", node["skin"]), None, int(node["skin"]), None
        else:
            anchor = number
            while anchor != -1 and anchor not in moving:
                anchor = int(parent[anchor])
            anchor = None if anchor == -1 else anchor
            key, skin = ("rigid", anchor), None
            frame = np.eye(4) if anchor is None else np.linalg.inv(world[anchor])
        root = number
        while parent[root] != -1:
            root = int(parent[root])
        if root not in roots:
            continue
        key = (*key, roots[root])
        group = groups.setdefault(key, Group(anchor, skin, roots[root]))
        group.members.append((number, index))
        group.matrices.append(np.eye(4) if frame is None else frame @ world[number])
    return [group for _, group in sorted(groups.items(), key=lambda item: item[1].members[0])
            if len(group.members) > 1]


def grouped_level(scene, levels: dict, ratio: float, *, slack: float, collapsed=None,
                  atlas=None, coverage: float | None = None):
    """Scene ``scene`` at one level, its groups merged where their meshes stay over
    their budget: ``(scene, levels, merged)``, the scene's document with the
    grouped nodes' meshes taken off and a node per merged group added, its
    ``meshes`` and ``levels`` (glTF mesh index -> that level's mesh) holding the
    meshes still drawn and the merged ones (new glTF mesh indices after the
    document's), and ``merged`` the count of groups merged. ``levels``: glTF mesh
    index -> the mesh's level as drawn when kept; ``collapsed``: its edge-collapse
    level, which says whether a group is over its budget (default ``levels``);
    ``ratio``: the level's share of the full detail's faces, each group's budget
    that share of its own; ``slack``: how far over its budget a group may stay
    unmerged; ``atlas``, ``coverage``: as ``bake.level.merged_level`` takes them."""
    from ..bake.level import merged_level, with_skin
    from ..chains import joined_materials
    from ..mesh import Mesh, MeshError
    from .merge import MAX_WORLD_FACES, placed_mesh

    document = copy.deepcopy(scene.document)
    nodes, meshes = document.setdefault("nodes", []), document.setdefault("meshes", [])
    made = []
    for group in rigid_groups(scene):
        full = sum(scene.meshes[index].face_count for _, index in group.members)
        drawn = sum((collapsed or levels)[index].face_count for _, index in group.members)
        budget = max(1, round(ratio * full))
        if drawn <= slack * budget or full > MAX_WORLD_FACES:
            continue
        pieces = [(scene.meshes[index], matrix[None]) for (_, index), matrix
                  in zip(group.members, group.matrices)]
        joined = placed_mesh(pieces, scene.materials)
        try:
            mesh = merged_level(joined, budget, atlas=atlas, coverage=coverage)
        except MeshError:
            continue        # a group of a few faces asked for fewer
        if group.skin is not None:
            skinned = [(scene.meshes[index], np.eye(4)[None]) for _, index in group.members]
            mesh = with_skin(_skinned(skinned, scene.materials), mesh)
        if mesh.face_count >= drawn:
            continue
        record = {"name": "merged", "mesh": len(meshes)}
        meshes.append({"name": "merged", "primitives": []})
        if group.skin is not None:
            record["skin"] = group.skin
        nodes.append(record)
        if group.anchor is None:
            document["scenes"][group.scene].setdefault("nodes", []).append(len(nodes) - 1)
        else:
            nodes[group.anchor].setdefault("children", []).append(len(nodes) - 1)
        for number, _ in group.members:
            nodes[number].pop("mesh", None)
        made.append((len(meshes) - 1, mesh))
    if not made:
        return scene, levels, 0
    used = {node["mesh"] for node in nodes if "mesh" in node}
    kept = {index: level for index, level in levels.items() if index in used}
    materials, moved = joined_materials(scene.materials, [mesh for _, mesh in made])
    for (index, mesh), (_, face_material) in zip(made, moved):
        kept[index] = Mesh(mesh.positions, mesh.faces, mesh.attributes, face_material, materials)
    full = {index: scene.meshes.get(index, kept[index]) for index in kept}
    return (dataclasses.replace(scene, document=document, meshes=full, materials=materials),
            kept, len(made))


def _skinned(pieces: list, materials):
    """The skinned meshes of one skin as one mesh in their bind space, with every
    ``JOINTS_n``/``WEIGHTS_n`` column kept (``merge.placed_mesh`` keeps only the
    columns a bake reads)."""
    from ..mesh import Attributes, Mesh
    from .merge import placed_mesh

    joined = placed_mesh(pieces, materials)
    names = [(name, width) for name, width in pieces[0][0].attributes.layout
             if name.startswith(("JOINTS_", "WEIGHTS_"))]
    names = [(name, width) for name, width in names
             if all(m.attributes.columns(name) is not None for m, _ in pieces)]
    skin = np.concatenate([m.attributes.values[:, np.r_[tuple(
        m.attributes.columns(name) for name, _ in names)]] for m, _ in pieces])
    values = np.concatenate([joined.attributes.values, skin], axis=1)
    return Mesh(joined.positions, joined.faces,
                Attributes(joined.attributes.layout + tuple(names), values,
                           joined.attributes.corners), joined.face_material, materials)


def grouped_levels(scenes: list, levels: dict, collapsed: dict, lods, instances: dict, *,
                   slack: float, atlas=None, hints=None, skip=()) -> dict:
    """:func:`grouped_level` of every level ``k`` of ``lods`` (not in ``skip``) whose
    edge-collapse meshes (``collapsed``: glTF mesh index -> its levels) draw more
    than ``slack`` times its budget and that merges a group: ``k -> (scene, levels,
    drawn)``, ``drawn`` the triangles it draws (each mesh once per instance).
    ``scenes``: the scene each level is written from; ``levels``: each mesh's
    levels as drawn when kept; ``instances``: glTF mesh index -> its instances'
    scales (``budget.scene_instances``); ``hints``: the screen coverage each level
    is drawn up to (its atlas's size)."""
    out = {}
    for k, ratio in enumerate(lods):
        scene = scenes[k]
        full = sum(len(instances[i]) * mesh.face_count for i, mesh in scene.meshes.items())
        edge = sum(len(instances[i]) * chain[k].face_count for i, chain in collapsed.items())
        if k in skip or edge <= slack * max(1, ratio * full):
            continue
        grouped, kept, merged = grouped_level(
            scene, {i: chain[k] for i, chain in levels.items()}, ratio, slack=slack,
            collapsed={i: chain[k] for i, chain in collapsed.items()}, atlas=atlas,
            coverage=None if hints is None else hints[k])
        if not merged:
            continue
        before, after = scene.mesh_nodes, grouped.mesh_nodes
        # a kept mesh is drawn by the nodes that still hold it, each as many times as before
        drawn = sum(mesh.face_count * (len(instances[i]) * len(after.get(i, ()))
                                       // max(1, len(before.get(i, ())))
                                       if i in instances else len(after.get(i, ())))
                    for i, mesh in kept.items())
        out[k] = (grouped, kept, drawn)
    return out
