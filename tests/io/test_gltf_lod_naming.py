"""How an exported chain's levels are told apart: MSFT_lod, the _LODn suffix engines
import LOD groups by, or both; ``--separate`` files name their node by the suffix."""

import pytest

from lodserver.cli import main
from lodserver.io import load_mesh
from lodserver.io.glb import LOD_NAMINGS, coverage_from_ratios, encode_lod_chain
from lodserver.mesh import MeshError
from lodserver.pipeline import ChainOptions

from ..conftest import SHARED_MESHES
from ..meshes import DATA
from .test_gltf import assert_valid, gltf_validator  # noqa: F401 (a fixture)
from .test_gltf_compressed_output import split_glb


def _export(tmp_path, *flags, name="chair.glb"):
    out = tmp_path / name
    assert main(["export", str(DATA / "spot.obj"), "-o", str(out), "--lods", "1,0.4,0.1",
                 *flags]) == 0
    return out


def test_each_naming_in_one_file(tmp_path, gltf_validator):  # noqa: F811
    found = {}
    for naming in LOD_NAMINGS:
        out = _export(tmp_path, "--lod-naming", naming, name=f"{naming}.glb")
        document, _ = split_glb(out.read_bytes())
        found[naming] = document
        assert_valid(gltf_validator, out.read_bytes(), f"--lod-naming {naming}")
    msft, suffix, both = found["msft"], found["suffix"], found["both"]
    # msft: as before, node 0 alone in the scene, the others named by MSFT_lod
    assert [n["name"] for n in msft["nodes"]] == ["LOD0", "LOD1", "LOD2"]
    assert msft["scenes"][0]["nodes"] == [0]
    assert msft["nodes"][0]["extensions"]["MSFT_lod"]["ids"] == [1, 2]
    # suffix: a root named by the file, its children the levels, every one in the scene
    root = suffix["nodes"][suffix["scenes"][0]["nodes"][0]]
    assert root["name"] == "suffix"
    assert [suffix["nodes"][c]["name"] for c in root["children"]] == \
        ["suffix_LOD0", "suffix_LOD1", "suffix_LOD2"]
    assert "MSFT_lod" not in suffix.get("extensionsUsed", [])
    assert len(root["extras"]["MSFT_screencoverage"]) == 3
    # both: MSFT_lod, and the suffix names
    assert [n["name"] for n in both["nodes"]] == ["both_LOD0", "both_LOD1", "both_LOD2"]
    assert both["nodes"][0]["extensions"]["MSFT_lod"]["ids"] == [1, 2]


def test_suffix_file_draws_every_level(tmp_path):
    out = _export(tmp_path, "--lod-naming", "suffix", "--compress", "none")
    single = _export(tmp_path, "--compress", "none", name="msft.glb")
    # a reader without LOD support draws the levels on top of each other; with
    # MSFT_lod it draws the finest only
    assert load_mesh(out)[0].face_count > load_mesh(single)[0].face_count


def test_separate_files_name_their_node(tmp_path):
    _export(tmp_path, "--separate", name="chair.glb")
    for level in range(3):
        document, _ = split_glb((tmp_path / f"chair_lod{level}.glb").read_bytes())
        assert [n["name"] for n in document["nodes"]] == [f"chair_LOD{level}"]


def test_unknown_naming_is_refused(tmp_path, capsys):
    with pytest.raises(SystemExit) as caught:
        main(["export", str(DATA / "spot.obj"), "-o", str(tmp_path / "x.glb"),
              "--lod-naming", "unity"])
    assert caught.value.code == 2
    with pytest.raises(MeshError, match="LOD naming must be one of msft, suffix, both"):
        ChainOptions(naming="unity")
    mesh, _ = load_mesh(DATA / "spot.obj")
    with pytest.raises(MeshError, match="LOD naming must be one of"):
        encode_lod_chain([mesh], coverage_from_ratios([1.0]), naming="x")


@pytest.mark.skipif(not SHARED_MESHES.is_dir(), reason="shared meshes not found")
def test_scene_keeps_msft_lod(tmp_path, capsys):
    out = tmp_path / "box.glb"
    code = main(["export", str(SHARED_MESHES / "scenes" / "BoxAnimated.glb"), "-o", str(out),
                 "--lods", "1,0.5", "--lod-naming", "suffix"])
    assert code != 0 and not out.exists()
    assert "--lod-naming suffix applies to single meshes" in capsys.readouterr().err
