"""Hostile scene files of issue 23, written once for the tests and ``bench/abuse_scenes.py``:
small uploads whose cost sits in data that triangle counts do not see.

- :func:`instanced_glb`: one small mesh drawn by ``EXT_mesh_gpu_instancing`` with
  millions of translations;
- :func:`aliased_animation_glb`: many animation outputs that are accessors over one
  and the same bufferView (the bytes stored once, named many times);
- :func:`aliased_morph_glb`: a grid whose one primitive has up to 255 morph targets
  all naming one accessor of deltas.

Each returns the GLB's bytes; :func:`animated_glb` is an honest scene whose carried
animation is as large as its bytes in the upload (no alias), for tests that need a
scene level weighing more than its triangles.
"""

from __future__ import annotations

import json
import struct

import numpy as np

_DTYPES = {5126: "<f4", 5125: "<u4", 5123: "<u2", 5121: "<u1"}


class GlbWriter:
    """A glTF document and its binary chunk under construction."""

    def __init__(self):
        self.document = {"asset": {"version": "2.0"}, "bufferViews": [], "accessors": []}
        self.binary = bytearray()

    def view(self, values, component: int = 5126) -> int:
        """Append ``values`` as a new bufferView (4-byte aligned); its index."""
        self.binary.extend(b"\0" * (-len(self.binary) % 4))
        data = np.ascontiguousarray(values, dtype=_DTYPES[component]).tobytes()
        self.document["bufferViews"].append(
            {"buffer": 0, "byteOffset": len(self.binary), "byteLength": len(data)})
        self.binary.extend(data)
        return len(self.document["bufferViews"]) - 1

    def accessor(self, view: int, count: int, kind: str, component: int = 5126,
                 **extra) -> int:
        """A new accessor over bufferView ``view``; its index."""
        self.document["accessors"].append({"bufferView": view, "componentType": component,
                                           "count": int(count), "type": kind, **extra})
        return len(self.document["accessors"]) - 1

    def add(self, values, kind: str, component: int = 5126, **extra) -> int:
        """A new bufferView of ``values`` and an accessor over it; the accessor's index."""
        return self.accessor(self.view(values, component), len(values), kind, component,
                             **extra)

    def glb(self) -> bytes:
        binary = bytes(self.binary) + b"\0" * (-len(self.binary) % 4)
        document = {**self.document, "buffers": [{"byteLength": len(binary)}]}
        header = json.dumps(document).encode()
        header += b" " * (-len(header) % 4)
        return b"".join([struct.pack("<4sII", b"glTF", 2, 28 + len(header) + len(binary)),
                         struct.pack("<I4s", len(header), b"JSON"), header,
                         struct.pack("<I4s", len(binary), b"BIN\x00"), binary])


def grid(size: int):
    """A wavy ``size`` x ``size`` grid: (size^2, 3) float positions, (2 (size-1)^2, 3) faces."""
    u, v = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size))
    z = 0.05 * np.sin(9 * u) * np.cos(7 * v)
    positions = np.column_stack([u.ravel(), v.ravel(), z.ravel()])
    i, j = np.meshgrid(np.arange(size - 1), np.arange(size - 1), indexing="ij")
    a = (i * size + j).ravel()
    b, c, d = a + 1, a + size + 1, a + size
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return positions, faces


def _mesh(glb: GlbWriter, size: int, **primitive) -> dict:
    """The grid of ``size`` as mesh 0's one primitive; the primitive record."""
    positions, faces = grid(size)
    position = glb.add(positions, "VEC3", min=positions.min(0).tolist(),
                       max=positions.max(0).tolist())
    record = {"attributes": {"POSITION": position},
              "indices": glb.add(faces.ravel(), "SCALAR", 5125), "mode": 4, **primitive}
    glb.document["meshes"] = [{"name": "grid", "primitives": [record]}]
    return record


def instanced_glb(instances: int, *, size: int = 10) -> bytes:
    """One ``size`` x ``size`` grid (162 triangles at 10) drawn ``instances`` times by
    ``EXT_mesh_gpu_instancing`` (one TRANSLATION each, 12 bytes)."""
    glb = GlbWriter()
    _mesh(glb, size)
    rng = np.random.default_rng(23)
    translations = rng.uniform(-100, 100, (instances, 3)).astype(np.float32)
    accessor = glb.add(translations, "VEC3")
    glb.document.update(
        scene=0, scenes=[{"nodes": [0]}], extensionsUsed=["EXT_mesh_gpu_instancing"],
        nodes=[{"mesh": 0, "extensions": {"EXT_mesh_gpu_instancing": {
            "attributes": {"TRANSLATION": accessor}}}}])
    return glb.glb()


def aliased_animation_glb(outputs: int = 60, megabytes: float = 12, *, size: int = 10) -> bytes:
    """A grid and ``outputs`` animations, each rotating the grid's node by its own
    sampler whose output is an accessor over one shared bufferView of ``megabytes``
    MB of quaternions (the keyframe times likewise shared)."""
    glb = GlbWriter()
    _mesh(glb, size)
    keys = int(megabytes * 1e6) // 16
    angles = np.linspace(0, np.pi, keys)
    quaternions = np.column_stack([np.zeros(keys), np.zeros(keys), np.sin(angles / 2),
                                   np.cos(angles / 2)])
    times_view = glb.view(np.linspace(0.0, 10.0, keys))
    rotations_view = glb.view(quaternions)
    animations = []
    for _ in range(outputs):
        times = glb.accessor(times_view, keys, "SCALAR", min=[0.0], max=[10.0])
        rotations = glb.accessor(rotations_view, keys, "VEC4")
        animations.append({"samplers": [{"input": times, "output": rotations}],
                           "channels": [{"sampler": 0,
                                         "target": {"node": 0, "path": "rotation"}}]})
    glb.document.update(scene=0, scenes=[{"nodes": [0]}], nodes=[{"mesh": 0}],
                        animations=animations)
    return glb.glb()


def animated_glb(keys: int, *, size: int = 10) -> bytes:
    """A grid and one animation of ``keys`` rotation keyframes (20 bytes each with
    its time), its own bytes: a scene level carrying about ``20 * keys`` bytes."""
    glb = GlbWriter()
    _mesh(glb, size)
    angles = np.linspace(0, np.pi, keys)
    times = glb.add(np.linspace(0.0, 10.0, keys), "SCALAR", min=[0.0], max=[10.0])
    rotations = glb.add(np.column_stack([np.zeros(keys), np.zeros(keys), np.sin(angles / 2),
                                         np.cos(angles / 2)]), "VEC4")
    glb.document.update(scene=0, scenes=[{"nodes": [0]}], nodes=[{"mesh": 0}], animations=[
        {"samplers": [{"input": times, "output": rotations}],
         "channels": [{"sampler": 0, "target": {"node": 0, "path": "rotation"}}]}])
    return glb.glb()


def aliased_morph_glb(targets: int = 255, *, size: int = 100) -> bytes:
    """A ``size`` x ``size`` grid (10k vertices at 100) with ``targets`` morph targets,
    every one naming the same accessor of POSITION deltas."""
    glb = GlbWriter()
    positions, _ = grid(size)
    deltas = np.zeros_like(positions)
    deltas[:, 2] = 0.1 * positions[:, 0]
    delta = glb.add(deltas, "VEC3", min=deltas.min(0).tolist(), max=deltas.max(0).tolist())
    _mesh(glb, size, targets=[{"POSITION": delta}] * targets)
    glb.document["meshes"][0]["weights"] = [0.0] * targets
    glb.document.update(scene=0, scenes=[{"nodes": [0]}], nodes=[{"mesh": 0}])
    return glb.glb()
