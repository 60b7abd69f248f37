"""Octahedral impostors (issue 28 point 3): the mapping, the bake, the export.

- the octahedral mapping, full and hemi, gives each direction back from its
  point and each view's point back from its direction; each view's basis is
  right-handed and orthonormal;
- a cube of six coloured sides, baked, shows in its view from +z that side's
  colour, normal and depth, covering the share of the view its square does,
  and no colour bleeds from the background (alpha 0 there, colour dilated);
- ``export --impostor`` writes the farthest level as a two-triangle quad
  whose file the Khronos validator passes, the same bytes twice and in a
  fresh process; an animated scene keeps its level and says why; bad flags
  and layouts are refused with one sentence.

The drawing of the impostor (static/impostor.js) is checked in Chromium by
tests/viewer/test_impostor.py.
"""

from __future__ import annotations

import json
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lodserver.bake.impostor import (bake_impostor, check_layout, decode, encode,
                                     impostor_glb, nearest_view, view_basis, view_points)
from lodserver.bake.textures import linear_to_srgb
from lodserver.chains import ChainOptions
from lodserver.mesh import Materials, Mesh, MeshError
from lodserver.pipeline import export_lods

from ..conftest import SHARED_MESHES
from ..io import test_gltf
from ..io.test_gltf import assert_valid

gltf_validator = test_gltf.gltf_validator    # the session fixture, shared
REPO = Path(__file__).resolve().parents[2]
SPOT = REPO / "tests" / "data" / "spot.obj"


def _directions(count=2000, seed=11) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(count, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@pytest.mark.parametrize("kind", ["full", "hemi"])
def test_the_octahedral_mapping_round_trips(kind):
    d = _directions()
    if kind == "hemi":
        d[:, 1] = np.abs(d[:, 1])
    p = encode(d, kind)
    assert np.abs(p).max() <= 1.0 + 1e-12
    assert np.allclose(decode(p, kind), d, atol=1e-12)
    points = view_points(9)
    views = decode(points, kind)
    # a point on the full square's edge and its mirror are one direction:
    # compare directions, which the views are
    assert np.allclose(decode(encode(views, kind), kind), views, atol=1e-12)
    inside = np.abs(points).max(axis=1) < 1
    assert np.allclose(encode(views, kind)[inside], points[inside], atol=1e-12)
    cells = nearest_view(views, 9, kind)
    assert np.allclose(decode(cells / 8 * 2 - 1, kind), views, atol=1e-12)


def test_each_view_basis_is_right_handed_and_orthonormal():
    for d in [*_directions(200), [0, 1, 0], [0, -1, 0], [0, 0.9999, 0.01414]]:
        d = np.asarray(d, dtype=np.float64) / np.linalg.norm(d)
        right, up = view_basis(d)
        frame = np.stack([right, up, d])
        assert np.allclose(frame @ frame.T, np.eye(3), atol=1e-12)
        assert np.allclose(np.cross(right, up), d, atol=1e-12)


SIDES = {(0, 0, 1): (0.8, 0.1, 0.1), (0, 0, -1): (0.1, 0.8, 0.1), (1, 0, 0): (0.1, 0.1, 0.8),
         (-1, 0, 0): (0.8, 0.8, 0.1), (0, 1, 0): (0.1, 0.8, 0.8), (0, -1, 0): (0.8, 0.1, 0.8)}


def coloured_cube() -> Mesh:
    """The cube [-1, 1]^3, each side a material of its own colour (SIDES)."""
    positions, faces, owner = [], [], []
    for k, normal in enumerate(SIDES):
        n = np.array(normal, dtype=np.float64)
        a = np.roll(n, 1)
        b = np.cross(n, a)
        base = len(positions)
        positions += [n + s * a + t * b for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
        owner += [k, k]
    materials = Materials({"materials": [
        {"pbrMetallicRoughness": {"baseColorFactor": [*colour, 1.0]}}
        for colour in SIDES.values()]}, ())
    return Mesh(np.array(positions), np.array(faces), None, np.array(owner, np.int32),
                materials)


def test_a_baked_cube_shows_each_side_with_its_colour_normal_and_depth():
    grid, frame = 5, 64
    impostor = bake_impostor(coloured_cube(), grid, frame)
    assert impostor.color.shape == (grid * frame, grid * frame, 4)
    assert impostor.normal.shape == (grid * frame // 2, grid * frame // 2, 4)
    assert np.allclose(impostor.center, 0) and np.isclose(impostor.radius, np.sqrt(3))
    for normal, colour in SIDES.items():
        column, row = nearest_view(np.array([normal], dtype=np.float64), grid)[0]
        cell = np.s_[row * frame:(row + 1) * frame, column * frame:(column + 1) * frame]
        color = impostor.color[cell]
        half = frame // 2
        shading = impostor.normal[row * half:(row + 1) * half, column * half:(column + 1) * half]
        middle = frame // 2
        wanted = np.rint(linear_to_srgb(np.array(colour)) * 255)
        assert np.abs(color[middle, middle, :3].astype(int) - wanted).max() <= 1
        assert color[middle, middle, 3] == 255
        assert np.allclose(shading[half // 2, half // 2, :3] / 255 * 2 - 1, normal, atol=0.01)
        # the side is at 1 from the centre, towards the viewer: depth 1 / radius
        assert abs(shading[half // 2, half // 2, 3] / 255 - (0.5 + 0.5 / np.sqrt(3))) < 0.01
        # seen square on, the cube covers (2 / (2 sqrt 3))^2 of its view
        covered = (color[..., 3].astype(np.float64) / 255).mean()
        assert abs(covered - 1 / 3) < 0.02
        # the background is transparent, its colour the edge's (no dark fringe)
        assert color[0, 0, 3] == 0
        edge = color[middle, :, 3] > 0
        beside = np.flatnonzero(edge)[0] - 1
        assert np.abs(color[middle, beside, :3].astype(int)
                      - color[middle, beside + 2, :3].astype(int)).max() <= 2


def _document(glb: bytes) -> dict:
    length = struct.unpack("<I", glb[12:16])[0]
    return json.loads(glb[20:20 + length])


def test_export_writes_the_farthest_level_as_a_valid_repeatable_impostor(
        tmp_path, gltf_validator):
    first = export_lods(SPOT, tmp_path / "a" / "spot.glb", lods=(1.0, 0.1, 0.01),
                        separate=True, impostor=True)
    assert first.faces[-1] == 2 and first.faces[:2] == [5856, 586]
    assert first.outputs[-1].name == "spot_lod2.glb"
    assert first.errors[-1] is None and first.coverage[-1] == 0.0
    data = first.outputs[-1].read_bytes()
    document = _document(data)
    layout = document["meshes"][0]["extras"]["impostor"]
    assert layout["grid"] == 12 and layout["kind"] == "full" and layout["radius"] > 0
    assert document["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] == {"index": 0}
    assert len(document["meshes"][0]["primitives"]) == 1
    assert_valid(gltf_validator, data, "an impostor")
    second = export_lods(SPOT, tmp_path / "b" / "spot.glb", lods=(1.0, 0.1, 0.01),
                         separate=True, impostor=True)
    assert second.outputs[-1].read_bytes() == data
    script = ("import sys; from lodserver.pipeline import export_lods; "
              "export_lods(sys.argv[1], sys.argv[2], lods=(1.0, 0.1, 0.01), separate=True, "
              "impostor=True)")
    subprocess.run([sys.executable, "-c", script, str(SPOT), str(tmp_path / "c" / "spot.glb")],
                   check=True, cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"})
    assert (tmp_path / "c" / "spot_lod2.glb").read_bytes() == data


def test_the_impostor_glb_of_a_bake_names_its_layout():
    impostor = bake_impostor(coloured_cube(), 4, 16, "hemi")
    document = _document(impostor_glb(impostor, name="cube"))
    layout = document["materials"][0]["extras"]["impostor"]
    assert layout["kind"] == "hemi" and layout["grid"] == 4 and layout["frame"] == 16
    assert document["textures"][layout["normalTexture"]]["source"] == layout["normalImage"]


@pytest.mark.skipif(not SHARED_MESHES.is_dir(), reason="shared meshes not found")
def test_an_animated_scene_keeps_its_farthest_level_and_says_why(tmp_path):
    done = export_lods(SHARED_MESHES / "scenes" / "Fox.glb", tmp_path / "fox.glb",
                       lods=(1.0, 0.1), separate=True, impostor=True)
    assert len(done.outputs) == 2 and done.faces[-1] > 2
    assert "no impostor: it is animated" in done.notes


def test_bad_impostor_options_are_refused_with_a_sentence(tmp_path):
    for keywords in ({"lods": (1.0, 0.1)}, {"lods": (1.0,), "separate": True},
                     {"errors": (0.0, 0.01), "separate": True}):
        with pytest.raises(MeshError, match="impostor"):
            ChainOptions(impostor=True, **keywords)
    for grid, frame, kind in ((1, 64, "full"), (12, 4, "full"), (12, 63, "full"), (32, 512, "full"), (12, 64, "sphere"),
                              (12.5, 64, "full")):
        with pytest.raises(MeshError, match="impostor"):
            check_layout(grid, frame, kind)
    with pytest.raises(MeshError, match="a point"):
        bake_impostor(Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]])))
    result = subprocess.run(
        [sys.executable, "-m", "lodserver.cli", "export", str(SPOT), "-o",
         str(tmp_path / "x.glb"), "--lods", "1,0.1", "--impostor"],
        capture_output=True, text=True, cwd=REPO, env={"PYTHONPATH": str(REPO),
                                                       "PATH": "/usr/bin:/bin"})
    assert result.returncode == 2
    assert "--separate" in result.stderr and "Traceback" not in result.stderr
    assert not list(tmp_path.iterdir())


def test_a_folder_export_records_the_impostor_and_redoes_an_asset_for_it(tmp_path):
    from lodserver.pipeline import export_folder

    source = tmp_path / "assets"
    source.mkdir()
    (source / "spot.obj").write_bytes(SPOT.read_bytes())
    for name in ("spot.mtl", "spot_texture.png"):
        if (SPOT.parent / name).is_file():
            (source / name).write_bytes((SPOT.parent / name).read_bytes())
    plain = export_folder(source, tmp_path / "out", lods=(1.0, 0.1), separate=True)
    assert len(plain.written) == 1 and plain.written[0].faces[-1] > 2
    again = export_folder(source, tmp_path / "out", lods=(1.0, 0.1), separate=True,
                          impostor=True)
    assert len(again.written) == 1 and not again.up_to_date
    assert again.written[0].faces[-1] == 2
    level = tmp_path / "out" / "spot_lod1.glb"
    assert "impostor" in _document(level.read_bytes())["meshes"][0]["extras"]
