"""The meshes of the codec bench, built once and kept as .pm files in bench/out/codec/.

spot (tests/data), the Stanford bunny, Duck and Avocado (/work/shared/meshes), and
bunny_loop2: the Stanford bunny Loop-subdivided twice, as bench/simplify.py makes it;
for the issue's table also bunny_loop3 (three times: 4.4M faces, a stand-in for a 4M-face
scan), the skinned Fox (its scene's one mesh, built with the scene's poses as the
service builds it) and the terrain ``mountain``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
SHARED = REPO.parent / "shared" / "meshes"
OUT = REPO / "bench" / "out" / "codec"

SOURCES = {
    "spot": REPO / "tests" / "data" / "spot.obj",
    "stanford-bunny": SHARED / "stanford-bunny.obj",
    "Duck": SHARED / "Duck.glb",
    "Avocado": SHARED / "Avocado" / "Avocado.gltf",
    "bunny_loop2": None,
}
# Built on request only (bench/codec.py --table): slower to build, or a scene.
MORE_SOURCES = {
    "bunny_loop3": None,
    "Fox": SHARED / "scenes" / "Fox.glb",
    "mountain": SHARED / "mountain.obj",
}


def bunny_loop2(mesh_dir: Path = SHARED, out: Path = REPO / "bench" / "out", iterations=2):
    """The Stanford bunny Loop-subdivided twice (1.1M faces), as bench/simplify.py
    makes it, cached in ``out``/bunny_loop2.npz (``iterations`` times: bunny_loopN)."""
    from lodserver.io import clean_mesh, load_mesh
    npz = out / f"bunny_loop{iterations}.npz"
    if npz.exists():
        data = np.load(npz)
        return clean_mesh(data["positions"], data["faces"])[0]
    import trimesh
    bunny, _ = load_mesh(mesh_dir / "stanford-bunny.obj")
    positions, faces = trimesh.remesh.subdivide_loop(bunny.positions, bunny.faces,
                                                     iterations=iterations)
    mesh = clean_mesh(positions, faces)[0]
    out.mkdir(parents=True, exist_ok=True)
    np.savez(npz, positions=mesh.positions, faces=mesh.faces)
    return mesh


def source_mesh(name: str):
    """The full-detail :class:`~lodserver.mesh.Mesh` of ``name``."""
    from lodserver.io import load_mesh
    if name.startswith("bunny_loop"):
        return bunny_loop2(iterations=int(name.removeprefix("bunny_loop")))
    return load_mesh({**SOURCES, **MORE_SOURCES}[name])[0]


def _build(name: str):
    """Build ``name``: a scene's mesh with the scene's poses (as the service does)."""
    from lodserver import build
    if name == "Fox":
        from lodserver.io.scene import load_scene
        from lodserver.simplify.poses import scene_poses
        loaded = load_scene(MORE_SOURCES[name])
        index, mesh = next(iter(loaded.meshes.items()))
        return build(mesh, poses=scene_poses(loaded, index, mesh))
    return build(source_mesh(name))


def progressive(name: str):
    """The built progressive mesh of ``name``, from bench/out/codec/ when there."""
    from lodserver.progressive.mesh import ProgressiveMesh
    path = OUT / f"{name}.pm"
    if path.exists():
        return ProgressiveMesh.load(path)
    OUT.mkdir(parents=True, exist_ok=True)
    began = time.perf_counter()
    pm = _build(name)
    print(f"built {name} in {time.perf_counter() - began:.1f} s", file=sys.stderr)
    pm.save(path)
    return pm


if __name__ == "__main__":
    for name in sys.argv[1:] or list(SOURCES):
        pm = progressive(name)
        print(name, pm.base_vertices, pm.vertex_count)
