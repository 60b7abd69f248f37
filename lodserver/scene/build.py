"""Building an asset: one progressive mesh per part, nothing kept on failure.

An upload is read as a ``Mesh`` (a single mesh) or a ``Scene`` (``scene.load``);
either is built into the one asset model, ``asset.SceneAsset``: a scene part by
part (:func:`build_scene`), a single mesh as the scene of one part.
"""

from __future__ import annotations

import numpy as np

from ..io.scene import Scene
from ..mesh import Mesh, MeshError
from ..simplify.poses import scene_poses
from ..simplify.topology import census
from .asset import SceneAsset, ScenePart

__all__ = ["build_asset", "build_scene"]


def build_asset(source: Mesh | Scene, *, build, options: dict, lock_border: bool = False,
                progress=None, cancel=None) -> SceneAsset | None:
    """Build ``source`` with ``build`` (``lodserver.build.build``, given ``options``
    by keyword): a Scene by :func:`build_scene`, a Mesh as the scene of one part
    (``SceneAsset.of_mesh``). ``lock_border`` locks the boundary vertices of every
    mesh. None when ``cancel`` was set; a MeshError of a part is raised, nothing kept.
    """
    if isinstance(source, Scene):
        return build_scene(source, build=build, options=options, lock_border=lock_border,
                           progress=progress, cancel=cancel)
    pm = build(source, locked=_border(source) if lock_border else None, progress=progress,
               cancel=cancel, **options)
    if cancel is not None and cancel.is_set():
        return None     # a cut-short decimation is not the mesh's progressive mesh
    return SceneAsset.of_mesh(pm)


def _border(mesh: Mesh) -> np.ndarray:
    """The vertices of ``mesh`` on its boundary, as a lock mask (n,) bool."""
    locked = np.zeros(mesh.vertex_count, dtype=bool)
    locked[census(mesh.faces, mesh.vertex_count).on_boundary] = True
    return locked


def build_scene(scene: Scene, *, build, options: dict, lock_border: bool = False,
                progress=None, cancel=None) -> SceneAsset | None:
    """Build every part of ``scene`` with ``build`` (``lodserver.build.build``).

    A skinned or morphed part is built with its poses
    (``simplify.poses.scene_poses``: its error is measured in its animated
    poses too). ``progress(done, expected)`` is over the whole scene: faces of the parts
    built, plus the running part's fraction of its faces. None when ``cancel``
    was set (a cut-short part is not the mesh's progressive mesh). A part that
    fails raises its MeshError, naming the part; nothing is kept.
    """
    order = sorted(scene.meshes)
    total = sum(scene.meshes[m].face_count for m in order) or 1
    users = scene.mesh_nodes
    records = scene.document.get("meshes", [])
    parts, before = [], 0
    for index, mesh_index in enumerate(order):
        mesh = scene.meshes[mesh_index]

        def part_progress(done, expected, before=before, faces=mesh.face_count):
            if progress is not None:
                progress(before + faces * min(done / max(expected, 1), 1.0), total)

        locked = _border(mesh) if lock_border else None
        name = records[mesh_index].get("name") if isinstance(records[mesh_index], dict) else None
        name = name if isinstance(name, str) else f"mesh {mesh_index}"
        try:
            # a skinned or morphed part is simplified for its animated poses too
            poses = scene_poses(scene, mesh_index, mesh)
            extra = {} if poses is None else {"poses": poses}
            pm = build(mesh, locked=locked, progress=part_progress, cancel=cancel, **options,
                       **extra)
        except MeshError as exc:
            raise MeshError(f"part {index} ({name}): {exc}") from exc
        if cancel is not None and cancel.is_set():
            return None
        parts.append(ScenePart(index, mesh_index, name, list(users.get(mesh_index, [])), pm))
        before += mesh.face_count
    kept = Scene(scene.document, meshes=dict.fromkeys(order), materials=scene.materials,
                 carried=scene.carried, notes=list(scene.notes), as_is=dict(scene.as_is),
                 as_is_faces=dict(scene.as_is_faces))
    return SceneAsset(kept, parts)
