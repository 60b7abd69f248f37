"""Compressed and quantized glTF in: what gltfpack and glTF-Transform write loads as
the uncompressed asset, within the quantization step.

The shared assets are converted by the npm tools (``tests/io/gltf_tools.py``):
``gltfpack -cc`` (EXT_meshopt_compression with filters, KHR_mesh_quantization,
UV ranges in KHR_texture_transform), ``gltf-transform draco``
(KHR_draco_mesh_compression), ``meshopt`` and ``quantize``. Each is read back by
``load_mesh`` (flattened, wedges compared face by face) and ``load_scene`` (every
vertex posed in world space through node transforms, skins and morph weights) and
compared with the uncompressed file.

Tolerances are the tools' quantization steps: positions 14 bits over the asset's
largest side (two steps allowed: one from each rounding of a placed vertex), UVs
12 bits (one step of 1/4095), normals and tangents 8-bit octahedral (about one
degree; two allowed). Animated poses add the tools' 16-bit rotation keyframes
through chains of joints (eight position steps allowed); gltfpack also resamples
animations, so its files are compared in the rest pose.
"""

from pathlib import Path

import numpy as np
import pytest

from lodserver.io import load_mesh
from lodserver.io.scene import load_scene

from ..conftest import SHARED_MESHES
from .gltf_tools import attribute_errors, convert, extent, hausdorff, posed_vertices

POSITION_STEPS = 2 / (2 ** 14 - 1)
POSED_STEPS = 8 / (2 ** 14 - 1)
UV_STEP = 1 / (2 ** 12 - 1)
DEGREES = 2.0

FLAT = ["Duck.glb", "Avocado/Avocado.gltf"]
SCENES = ["scenes/Fox.glb", "scenes/RiggedSimple.glb", "scenes/AnimatedMorphCube.glb",
          "scenes/BoxAnimated.glb"]
TOOLS = ["gltfpack -cc", "draco", "meshopt", "quantize"]


@pytest.fixture(scope="module")
def converted(tmp_path_factory):
    """``converted(name, how)``: the shared asset ``name`` through conversion ``how``,
    converted once per module."""
    folder = tmp_path_factory.mktemp("converted")
    done = {}

    def get(name: str, how: str) -> Path:
        if (name, how) not in done:
            output = folder / f"{Path(name).stem}-{how.replace(' ', '')}.glb"
            done[name, how] = convert(SHARED_MESHES / name, how, output)
        return done[name, how]

    return get


@pytest.mark.parametrize("how", TOOLS)
@pytest.mark.parametrize("name", FLAT)
def test_flattened_mesh_loads_as_the_uncompressed_one(shared_meshes, converted, name, how):
    original, _ = load_mesh(shared_meshes / name)
    decoded, report = load_mesh(converted(name, how))
    assert decoded.face_count == original.face_count
    assert decoded.vertex_count == original.vertex_count
    errors = attribute_errors(original, decoded, POSITION_STEPS * extent(original.positions))
    assert set(errors) == {n for n, _ in original.attributes.layout}
    for attribute, error in errors.items():
        bound = DEGREES if attribute in ("NORMAL", "TANGENT") else UV_STEP
        assert error <= bound, f"{name} by {how}: {attribute} off by {error:.3g}"
    assert report.dropped_attributes == []


@pytest.mark.parametrize("how", TOOLS)
def test_many_part_engine_loads_within_the_step(shared_meshes, converted, how):
    # the tools drop the engine's few degenerate triangles, and its parts hold vertices
    # closer than a step apart, so its faces are compared by count and surface
    original, _ = load_mesh(shared_meshes / "2CylinderEngine.glb")
    decoded, _ = load_mesh(converted("2CylinderEngine.glb", how))
    assert abs(decoded.face_count - original.face_count) <= 0.001 * original.face_count
    distance = hausdorff(original.positions, decoded.positions)
    assert distance <= POSITION_STEPS * extent(original.positions)


@pytest.mark.parametrize("how", TOOLS)
@pytest.mark.parametrize("name", SCENES)
def test_scene_loads_as_the_uncompressed_one_posed(shared_meshes, converted, name, how):
    original = load_scene(shared_meshes / name)
    decoded = load_scene(converted(name, how))
    assert sorted(m.face_count for m in decoded.meshes.values()) == \
        sorted(m.face_count for m in original.meshes.values())
    for mesh in decoded.meshes.values():
        layout = dict(mesh.attributes.layout) if mesh.attributes is not None else {}
        source = dict(next(m for m in original.meshes.values()
                           if m.face_count == mesh.face_count).attributes.layout)
        # skins and morph targets are read (gltfpack drops tangents without a normal
        # map, and the targets' normals and tangents with them)
        kept = {k for k in source if k.startswith(("JOINTS", "WEIGHTS"))
                or k.startswith("TARGET") and k.endswith("POSITION")}
        assert kept <= set(layout)
    size = extent(posed_vertices(original))
    poses = [(None, 0.0)]
    if how != "gltfpack -cc":        # gltfpack resamples animations: rest pose only
        clips = len(original.document.get("animations", ()))
        poses += [(clip, 0.37) for clip in range(min(clips, 2))]
    for clip, time in poses:
        bound = (POSITION_STEPS if clip is None else POSED_STEPS) * size
        distance = hausdorff(posed_vertices(original, clip, time),
                             posed_vertices(decoded, clip, time))
        assert distance <= bound, f"{name} by {how}, clip {clip}: off by {distance:.3g}"
    assert not [note for note in decoded.notes if "extensions are not kept" in note]
