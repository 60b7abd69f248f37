"""A glTF scene exported whole: its meshes built once, levels chosen together, written as GLB.

``pipeline.export_lods`` of a ``.gltf`` or ``.glb`` source: each glTF mesh is
built into its own progressive mesh, the levels of all of them are chosen by
one budget (``budget.chain_levels``) or per mesh, levels edge collapse cannot
reach are made by clustering if asked (``ChainOptions.reach``), and the input
document is written back with every mesh replaced by its levels
(``io.scene_glb``).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from ..chains import REACH_SLACK, ChainOptions, Exported, joined_materials
from ..io import write_atomic
from ..io.glb import encode_glb
from ..io.scene_glb import encode_scene
from ..mesh import Mesh, MeshError
from .budget import chain_levels, coverage_from_errors, scene_instances, world_errors
from .groups import grouped_levels
from .textures import level_meshes, texture_levels

__all__ = ["export_scene"]


def _build_parts(scene, source: Path, options, progress) -> dict:
    """glTF mesh index -> its progressive mesh, each built once; a skinned or morphed
    mesh with its error measured in the poses it is seen in (``simplify.poses``)."""
    from ..build import build
    from ..simplify.poses import scene_poses

    pms = {}
    for index, mesh in scene.meshes.items():
        try:
            pms[index] = build(mesh, options, progress=progress,
                               poses=scene_poses(scene, index, mesh))
        except ValueError as exc:       # argument checks deep in the build
            raise MeshError(str(exc)) from exc
        except MeshError as exc:
            raise MeshError(f"cannot build mesh {index} of {source.name}: {exc}") from exc
    return pms


def export_scene(scene, source: Path, output: Path, chain: ChainOptions, options, progress,
                  start) -> Exported:
    """:func:`export_lods` of a glTF scene kept whole: each glTF mesh built once into a
    progressive mesh, the levels of all of them chosen together (``budget.chain_levels``)
    and written in place of them (``io.scene_glb``).

    ``Exported.faces`` counts each source mesh once per level (not per instance),
    ``Exported.drawn`` once per instance; ``errors`` is the worst world error of
    each level. ``base_faces`` sums the meshes' coarsest reachable levels;
    ``clustered`` lists the levels that clustering made for at least one mesh:
    with ``reach="cluster"``, a level whose drawn triangles overshoot its budget
    by more than ``REACH_SLACK`` has each mesh that stopped at its base made by
    clustering at its share (the level's ratio of its faces), if that has fewer
    faces. Meshes kept as they are (``scene.as_is``) are drawn at every level
    and are outside the budget: the ratios are of the simplified meshes' triangles.
    """
    if chain.naming != "msft":
        raise MeshError(f"{source.name} is a glTF scene, whose levels are linked by MSFT_lod: "
                        f"--lod-naming {chain.naming} applies to single meshes")
    if not scene.meshes and not scene.as_is:
        raise MeshError(f"cannot load {source.name}: it has no faces (no node of it places "
                        "a mesh)")
    pms = _build_parts(scene, source, options, progress)
    instances, diagonal = scene_instances(scene, pms)
    lods, per_mesh = chain.lods, chain.per_mesh
    count = len(chain.errors if chain.errors is not None else lods)
    chosen_levels = chain_levels(pms, instances, lods=lods, errors=chain.errors,
                                 per_mesh=per_mesh, diagonal=diagonal)
    levels = {index: [pm.at(chosen[index]) for chosen in chosen_levels]
              for index, pm in pms.items()}
    worst = [max(world_errors(pms, instances, chosen).values(), default=0.0)
             for chosen in chosen_levels]
    drawn = [sum(len(instances[index]) * levels[index][k].face_count for index in pms)
             for k in range(count)]
    clustered = set()
    collapsed = {index: list(chain_) for index, chain_ in levels.items()}
    merged = _merge_static(scene, chain, drawn, worst, diagonal) if lods else {}
    clustered.update(merged)
    if chain.reach != "none":
        full_drawn = sum(len(instances[index]) * pm.face_count for index, pm in pms.items())
        for k, ratio in enumerate(lods):
            # per mesh: each mesh over its own budget; scene: the meshes stopped at their
            # base, when the scene is over its budget
            if k in merged:
                continue
            if per_mesh or drawn[k] > REACH_SLACK * max(1, ratio * full_drawn):
                replaced = _cluster_stuck(pms, chosen_levels[k], levels, k, ratio, per_mesh,
                                          chain.reach)
                if replaced:
                    clustered.add(k)
                    # a clustered level has no collapse error: its measured distance
                    # to the full mesh stands in (world units, for the hints)
                    worst[k] = max(worst[k], *(max(instances[index], default=0.0) * error
                                               for index, error in replaced.items()))
        drawn = [sum(len(instances[index]) * levels[index][k].face_count for index in pms)
                 for k in range(count)]
    for k, (mesh, error) in merged.items():
        drawn[k], worst[k] = mesh.face_count, error
    kept_drawn = sum(scene.as_is_faces[index] * len(scene.mesh_nodes.get(index, ()))
                     for index in scene.as_is)
    coverage = coverage_from_errors(worst, diagonal) if count else []
    scenes, levels, notes = _scene_texture_levels(scene, levels, chain, drawn)
    # a partly animated scene: the parts that move together merged (scene.groups)
    grouped = grouped_levels(scenes, levels, collapsed, lods, instances, slack=REACH_SLACK,
                             atlas=chain.atlas, hints=[1.0, *coverage[:-1]], skip=merged) \
        if chain.reach == "merge" and chain.separate and not per_mesh and lods else {}
    for k, (_, _, drawn_k) in grouped.items():
        drawn[k] = drawn_k
        clustered.add(k)
    seconds = []
    if chain.separate:
        outputs = [output.with_name(f"{output.stem}_lod{i}{output.suffix}") for i in range(count)]
        blobs = []
        for i in range(count):
            begun = time.perf_counter()
            blobs.append(encode_glb(merged[i][0], chain.compress, name=f"{output.stem}_LOD{i}")
                         if i in merged else
                         encode_scene(*_with_baked(grouped[i][0], {index: [mesh] for index, mesh
                                                                   in grouped[i][1].items()},
                                                   [0], scene.materials),
                                      [coverage[i]], level=0, compress=chain.compress)
                         if i in grouped else
                         encode_scene(*_with_baked(scenes[i], levels, [i], scene.materials),
                                      coverage, level=i, compress=chain.compress))
            seconds.append(time.perf_counter() - begun)
    else:
        outputs, blobs = [output], [encode_scene(*_with_baked(scenes[0], levels, range(count)),
                                                 coverage, compress=chain.compress)]
    output.parent.mkdir(parents=True, exist_ok=True)
    for i, (path, blob) in enumerate(zip(outputs, blobs)):
        begun = time.perf_counter()
        write_atomic(path, blob)
        if seconds:
            seconds[i] += time.perf_counter() - begun
    kept = sum(scene.as_is_faces.values())
    faces = [merged[k][0].face_count if k in merged else
             kept + sum(mesh.face_count for mesh in grouped[k][1].values()) if k in grouped else
             kept + sum(chain_[k].face_count for chain_ in levels.values()) for k in range(count)]
    base = sum(pm.faces_at_level(pm.base_vertices) for pm in pms.values())
    # base_faces: the coarsest the simplified meshes reach, with the kept ones beside them
    # (0 when nothing was simplified: no "simplifies no further" for a skinned asset)
    return Exported(source, outputs, faces, coverage, time.perf_counter() - start,
                    base + kept if levels else 0, sorted(clustered), [*scene.notes, *notes],
                    [kept_drawn + d for d in drawn], worst, diagonal, seconds)


def _merge_static(scene, chain: ChainOptions, drawn: list, worst: list, diagonal: float) -> dict:
    """Levels of a static scene (``merge.static_reason``) that edge collapse leaves
    over budget, as one mesh each: every part placed in the world, remeshed and
    baked (``bake.level.merged_level``). Only with ``reach="merge"``, a whole-scene
    budget and ``separate`` files: one file's ``MSFT_lod`` chains are per node, so a
    chain keeps each part's own levels. Returns level -> (mesh, its error: the
    sampled two-sided Hausdorff distance to the full scene, world units)."""
    from ..bake.level import merged_level
    from ..metrics.surface import surface_distance
    from .merge import static_reason, world_mesh

    if chain.reach != "merge" or chain.per_mesh or not chain.separate \
            or static_reason(scene) is not None:
        return {}
    world, merged = None, {}
    hints = coverage_from_errors(worst, diagonal)
    for k, ratio in enumerate(chain.lods):
        if world is None:
            world = world_mesh(scene)
        budget = max(1, round(ratio * world.face_count))
        if drawn[k] <= REACH_SLACK * budget:
            continue
        try:
            mesh = merged_level(world, budget, atlas=chain.atlas,
                                coverage=hints[k - 1] if k else 1.0)
        except MeshError:
            continue        # a scene of a few faces asked for fewer
        try:
            distance = surface_distance(Mesh(world.positions, world.faces),
                                        Mesh(mesh.positions, mesh.faces), samples=20_000)
            error = distance["hausdorff"] * distance["diagonal"]
        except ValueError:      # flat or degenerate: no area to sample
            error = worst[k]
        merged[k] = (mesh, max(error, worst[k - 1] if k else 0.0))
    return merged


def _with_baked(scene, levels: dict, written, unbaked=None) -> tuple:
    """``(scene, levels)`` to write levels ``written``: the materials of the baked
    levels among them (``bake.level``, each with its own) appended to the scene's,
    those levels' faces pointing at them (``chains.joined_materials``). ``unbaked``:
    the materials the other levels name, when not ``scene``'s own (a file's texture
    level: the same materials in the same order, its images scaled)."""
    unbaked = scene.materials if unbaked is None else unbaked
    baked = [(index, k) for index in levels for k in written
             if levels[index][k].materials is not None
             and levels[index][k].materials is not unbaked
             and levels[index][k].materials is not scene.materials]
    if not baked:
        return scene, levels
    materials, moved = joined_materials(scene.materials, [levels[i][k] for i, k in baked])
    levels = {index: list(chain_) for index, chain_ in levels.items()}
    for (index, k), (mesh, used) in zip(baked, moved):
        levels[index][k] = Mesh(mesh.positions, mesh.faces, mesh.attributes, used, materials)
    for index, chain_ in levels.items():     # every level's faces into the one list
        for k in written:
            mesh = chain_[k]
            if mesh.materials is not materials and mesh.face_material is not None:
                chain_[k] = Mesh(mesh.positions, mesh.faces, mesh.attributes,
                                 mesh.face_material, materials)
    return dataclasses.replace(scene, materials=materials), levels


def _cluster_stuck(pms: dict, chosen: dict, levels: dict, k: int, ratio: float,
                   per_mesh: bool, reach: str = "cluster") -> dict:
    """Replace level ``k`` of the meshes edge collapse left short, by clustering of
    the full mesh at ``ratio`` of its faces where that has fewer faces. Short: over
    ``REACH_SLACK`` times its own budget (``per_mesh``, as :func:`lod_chain` does),
    else stopped at its base. ``reach`` names the method (``ChainOptions.reach``);
    with ``merge`` the level's clustered parts are baked together, one atlas and
    one material for all of them (:func:`_baked_together`). Returns mesh index ->
    the clustered level's error, mesh units: its sampled two-sided Hausdorff
    distance to the full mesh."""
    from ..chains import reached_level
    from ..metrics.surface import surface_distance

    replaced, fulls, joins = {}, {}, {}
    for index, pm in pms.items():
        budget = max(1, round(ratio * pm.face_count))
        short = (levels[index][k].face_count > REACH_SLACK * budget if per_mesh
                 else chosen[index] == pm.base_vertices)
        if not short:
            continue
        fulls[index] = pm.at(pm.vertex_count)
        # None: a morphed part, or a tiny part (a few faces) clustering cannot bring down;
        # merged parts are clustered here and baked together below
        joins[index] = (_clustered(fulls[index], budget) if reach == "merge"
                        else reached_level(pm, budget, reach))
    if reach == "merge":
        joins = _baked_together(fulls, joins)
    for index, joined in joins.items():
        full = fulls[index]
        if joined is not None and joined.face_count < levels[index][k].face_count:
            levels[index][k] = joined
            try:
                distance = surface_distance(Mesh(full.positions, full.faces), joined,
                                            samples=20_000)
                replaced[index] = distance["hausdorff"] * distance["diagonal"]
            except ValueError:      # a flat or degenerate part: no area to sample
                replaced[index] = pm.error_at_level(pm.base_vertices)
    return replaced


def _clustered(full: Mesh, budget: int) -> Mesh | None:
    """``full``'s geometry clustered within ``bake.level.REACH_WINDOW`` of ``budget``
    faces, or None for a morphed mesh (clustering cannot keep its targets) or where
    clustering keeps no face."""
    from ..bake.level import REACH_WINDOW
    from ..simplify.cluster import cluster_within

    names = [name for name, _ in full.attributes.layout] if full.attributes else []
    if any(name.startswith("TARGET") for name in names):
        return None
    try:
        return cluster_within(Mesh(full.positions, full.faces), budget, REACH_WINDOW)
    except MeshError:
        return None


def _baked_together(fulls: dict, joins: dict) -> dict:
    """The clustered levels ``joins`` (mesh index -> level or None) of the full
    meshes ``fulls`` baked into one atlas and material (``merge.baked_together``):
    one bake for every part a level merges; a skinned part keeps its skin
    (``bake.level.with_skin``). Parts with nothing to bake (no attributes, no
    materials) keep their clustered geometry."""
    from ..bake.level import with_skin
    from .merge import baked_together

    looks = [index for index, joined in joins.items() if joined is not None
             and (fulls[index].attributes is not None or fulls[index].materials is not None)]
    if not looks:
        return joins
    materials = next((fulls[i].materials for i in looks if fulls[i].materials is not None), None)
    baked = baked_together([fulls[i] for i in looks], [joins[i] for i in looks], materials)
    joins = dict(joins)
    for index, level in zip(looks, baked):
        layout = fulls[index].attributes.layout if fulls[index].attributes else ()
        joins[index] = (with_skin(fulls[index], level)
                        if any(name.startswith("JOINTS_") for name, _ in layout) else level)
    return joins


def _scene_texture_levels(scene, levels: dict, chain: ChainOptions, drawn: list):
    """A scene's texture levels: (the scene to write each output from, the levels
    of each mesh to write, notes). ``--separate``: file k's scene holds level k's
    images; one file: every level's materials, each mesh's level k naming its own."""
    count = len(drawn)
    found = texture_levels(scene.materials, chain.texture_scale, drawn) if count else None
    if found is None:
        return [scene] * max(count, 1), levels, []
    if chain.separate:
        return ([dataclasses.replace(scene, materials=materials)
                 for materials in found.separate], levels, found.notes)
    levels = {index: level_meshes(chain_, found, separate=False)
              for index, chain_ in levels.items()}
    return [dataclasses.replace(scene, materials=found.chain)], levels, found.notes
