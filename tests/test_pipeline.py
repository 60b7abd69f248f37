"""The asset pipeline: a folder of meshes in, a folder of LOD chains out (``lodserver export``)."""

import json
import shutil

import numpy as np
import pytest
import trimesh

from lodserver.cli import main
from lodserver.io import load_mesh
from lodserver.mesh import MeshError
from lodserver.options import BuildOptions
from lodserver.pipeline import MANIFEST, export_folder, export_lods, find_sources

from .conftest import glb_chunks
from .meshes import DATA


def _glb_json(path):
    return glb_chunks(path.read_bytes())[0]


def _assets(root):
    """spot (UVs), a sphere in a subfolder, a file that is not a mesh, and a note."""
    (root / "props").mkdir(parents=True)
    shutil.copy(DATA / "spot.obj", root / "spot.obj")
    sphere = trimesh.creation.icosphere(3)
    (root / "props" / "ball.ply").write_bytes(sphere.export(file_type="ply"))
    (root / "props" / "broken.stl").write_bytes(b"solid nothing\nendsolid\n")
    (root / "README.txt").write_text("not a mesh")
    return root


def _files(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_a_folder_becomes_lod_chains_in_the_same_layout(tmp_path):
    source, out = _assets(tmp_path / "assets"), tmp_path / "lods"
    seen = []
    report = export_folder(source, out, lods=(1, 0.5, 0.1),
                           progress=lambda path, outcome: seen.append(str(path)))
    assert sorted(str(e.source.relative_to(source)) for e in report.written) == [
        "props/ball.ply", "spot.obj"]
    assert [str(p) for p in report.failed] == ["props/broken.stl"]
    assert "broken.stl" in next(iter(report.failed.values()))     # the loader's reason
    assert sorted(seen) == ["props/ball.ply", "props/broken.stl", "spot.obj"]
    # outputs mirror the layout; the failed source left nothing, and nothing temporary is left
    assert _files(out) == [MANIFEST, "props/ball.glb", "spot.glb"]
    for name, full_faces in (("spot.glb", 5856), ("props/ball.glb", 1280)):
        document = _glb_json(out / name)
        assert document["nodes"][0]["extensions"]["MSFT_lod"]["ids"] == [1, 2]
        faces = [sum(document["accessors"][p["indices"]]["count"] // 3 for p in m["primitives"])
                 for m in document["meshes"]]
        assert faces[0] == full_faces and faces[0] > faces[1] > faces[2]
    spot, _ = load_mesh(out / "spot.glb")            # the finest level, with its UVs
    assert spot.face_count == 5856 and spot.attributes is not None


def test_a_second_run_rebuilds_only_what_changed(tmp_path):
    source, out = _assets(tmp_path / "assets"), tmp_path / "lods"
    (source / "props" / "broken.stl").unlink()
    first = export_folder(source, out)
    assert len(first.written) == 2 and not first.up_to_date
    before = (out / "spot.glb").read_bytes()

    again = export_folder(source, out)
    assert not again.written and sorted(map(str, again.up_to_date)) == ["props/ball.ply",
                                                                          "spot.obj"]
    # one source edited: only it is rebuilt
    sphere = trimesh.creation.icosphere(2)
    (source / "props" / "ball.ply").write_bytes(sphere.export(file_type="ply"))
    edited = export_folder(source, out)
    assert [str(e.source.relative_to(source)) for e in edited.written] == ["props/ball.ply"]
    assert (out / "spot.glb").read_bytes() == before
    # other options (LODs or build options), a missing output or force: rebuilt
    assert len(export_folder(source, out, lods=(1, 0.25)).written) == 2
    changed = BuildOptions(boundary_weight=2)
    assert len(export_folder(source, out, lods=(1, 0.25), options=changed).written) == 2
    assert not export_folder(source, out, lods=(1, 0.25), options=changed).written
    assert len(export_folder(source, out, lods=(1, 0.25)).written) == 2
    (out / "spot.glb").unlink()
    assert [str(e.source.relative_to(source))
            for e in export_folder(source, out, lods=(1, 0.25)).written] == ["spot.obj"]
    assert len(export_folder(source, out, lods=(1, 0.25), force=True).written) == 2


def test_separate_levels_and_parallel_builds(tmp_path):
    source, out = _assets(tmp_path / "assets"), tmp_path / "lods"
    (source / "props" / "broken.stl").unlink()
    report = export_folder(source, out, lods=(1, 0.2), separate=True, jobs=2)
    assert len(report.written) == 2 and not report.failed
    assert _files(out) == [MANIFEST, "props/ball_lod0.glb", "props/ball_lod1.glb",
                           "spot_lod0.glb", "spot_lod1.glb"]
    coarse, _ = load_mesh(out / "spot_lod1.glb")
    assert coarse.face_count <= round(0.2 * 5856)


def test_sources_that_would_write_one_file_fail_with_the_reason(tmp_path):
    source, out = tmp_path / "assets", tmp_path / "lods"
    source.mkdir()
    shutil.copy(DATA / "spot.obj", source / "cow.obj")
    (source / "cow.ply").write_bytes(trimesh.creation.icosphere(1).export(file_type="ply"))
    report = export_folder(source, out)
    assert not report.written and len(report.failed) == 2
    assert all("would both be written to cow.glb" in r for r in report.failed.values())


def test_an_output_folder_inside_the_source_is_not_read_back(tmp_path):
    source = _assets(tmp_path / "assets")
    (source / "props" / "broken.stl").unlink()
    export_folder(source, source / "lods")
    assert [str(p) for p in find_sources(source)] == ["props/ball.ply", "spot.obj"]
    again = export_folder(source, source / "lods")
    assert len(again.up_to_date) == 2 and not again.failed


def test_bad_folders_and_options_are_refused(tmp_path):
    with pytest.raises(MeshError, match="is not a folder"):
        export_folder(tmp_path / "none", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("")
    with pytest.raises(MeshError, match="holds no mesh file"):
        export_folder(tmp_path / "empty", tmp_path / "out")
    source = _assets(tmp_path / "assets")
    with pytest.raises(MeshError, match="strictly decreasing"):
        export_folder(source, tmp_path / "out", lods=(0.5, 1))
    with pytest.raises(MeshError, match="jobs"):
        export_folder(source, tmp_path / "out", jobs=0)


def test_cli_exports_a_folder_and_exits_1_naming_the_failures(tmp_path, capsys):
    source, out = _assets(tmp_path / "assets"), tmp_path / "lods"
    code = main(["export", str(source), "-o", str(out), "--lods", "1,0.3", "--jobs", "2"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err
    assert "3 assets" in err and "2 written, 0 up to date, 1 failed" in err
    assert err.strip().splitlines()[-1].startswith("lodserver export: 1 of 3 assets failed: "
                                                   "props/broken.stl: ")
    assert (out / "spot.glb").is_file() and (out / "props" / "ball.glb").is_file()

    (source / "props" / "broken.stl").unlink()
    assert main(["export", str(source), "-o", str(out), "--lods", "1,0.3"]) == 0
    assert "0 written, 2 up to date, 0 failed" in capsys.readouterr().err
    assert main(["export", str(source), "-o", str(tmp_path / "x.glb")]) == 1
    assert "names the folder to write into" in capsys.readouterr().err


def test_manifest_records_sources_options_and_outputs(tmp_path):
    source, out = _assets(tmp_path / "assets"), tmp_path / "lods"
    export_folder(source, out, lods=(1, 0.5))
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["version"] == 2 and sorted(manifest["sources"]) == ["props/ball.ply",
                                                                        "spot.obj"]
    entry = manifest["sources"]["spot.obj"]
    assert entry["options"] == {"lods": [1.0, 0.5], "separate": False, "reach": "merge",
                                "build": BuildOptions().recorded()}
    assert entry["outputs"] == ["spot.glb"] and len(entry["sha256"]) == 64
    # an unreadable manifest only means everything is rebuilt
    (out / MANIFEST).write_text("{not json")
    assert len(export_folder(source, out, lods=(1, 0.5)).written) == 2
    assert len(json.loads((out / MANIFEST).read_text())["sources"]) == 2


def _soup(path, count=300):
    """``count`` separate triangles on a plane: edge collapse cannot merge any."""
    rng = np.random.default_rng(3)
    corners = rng.random((count, 1, 3)) * [10, 10, 0] + rng.random((count, 3, 3)) * [0.3, 0.3, 0]
    positions = corners.reshape(-1, 3)
    faces = np.arange(3 * count).reshape(-1, 3)
    path.write_bytes(trimesh.Trimesh(positions, faces, process=False).export(file_type="ply"))
    return path


def test_reach_cluster_meets_budgets_edge_collapse_cannot(tmp_path):
    source = _soup(tmp_path / "soup.ply")
    stuck = export_lods(source, tmp_path / "stuck.glb", lods=(1, 0.2), reach="none")
    assert stuck.faces == [300, 300] and stuck.clustered == [] and stuck.base_faces == 300
    reached = export_lods(source, tmp_path / "reached.glb", lods=(1, 0.2), reach="cluster")
    assert reached.faces[0] == 300 and reached.faces[1] <= 1.1 * 60
    assert reached.clustered == [1]
    document = _glb_json(tmp_path / "reached.glb")
    assert document["nodes"][0]["extensions"]["MSFT_lod"]["ids"] == [1]
    with pytest.raises(MeshError, match="reach must be one of"):
        export_lods(source, tmp_path / "x.glb", reach="sloppy")


def test_cli_says_which_levels_were_clustered(tmp_path, capsys):
    source = _soup(tmp_path / "soup.ply")
    assert main(["export", str(source), "-o", str(tmp_path / "a.glb"), "--lods", "1,0.2",
                 "--reach", "none"]) == 0
    assert "--reach merge meets the budget" in capsys.readouterr().err
    assert main(["export", str(source), "-o", str(tmp_path / "b.glb"), "--lods", "1,0.2",
                 "--reach", "cluster"]) == 0
    assert "level 1 by vertex clustering" in capsys.readouterr().err


def test_an_unreadable_source_fails_alone(tmp_path, monkeypatch):
    from lodserver import folders

    source, out = _assets(tmp_path / "assets"), tmp_path / "lods"
    real = folders._sha256

    def refuse(path):
        if path.name == "ball.ply":
            raise PermissionError(13, "Permission denied")
        return real(path)

    monkeypatch.setattr(folders, "_sha256", refuse)
    report = export_folder(source, out)
    assert report.failed[next(p for p in report.failed if p.name == "ball.ply")] == (
        "cannot read it: Permission denied")
    assert [str(e.source.relative_to(source)) for e in report.written] == ["spot.obj"]
    # a source that is gone is dropped from the manifest, its output left alone
    (source / "spot.obj").unlink()
    monkeypatch.setattr(folders, "_sha256", real)
    export_folder(source, out)
    assert sorted(json.loads((out / MANIFEST).read_text())["sources"]) == ["props/ball.ply"]
    assert (out / "spot.glb").is_file()


def test_export_takes_the_build_options_and_creates_the_output_folder(tmp_path, capsys):
    """export of a mesh file builds with the build flags; -o's folder need not exist."""
    out = tmp_path / "new" / "deeper" / "spot.glb"
    assert main(["export", str(DATA / "spot.obj"), "-o", str(out), "--lods", "1,0.1",
                 "--no-attributes", "--min-vertices", "2000", "--reach", "none"]) == 0
    document = _glb_json(out)
    coarse = document["meshes"][1]["primitives"][0]
    # positions only (no TEXCOORD_0), and the build stopped at 2000 vertices
    assert set(coarse["attributes"]) == {"POSITION"}
    assert document["accessors"][coarse["attributes"]["POSITION"]]["count"] >= 2000
    finest, _ = load_mesh(out)
    assert finest.attributes is None
    capsys.readouterr()
    assert main(["export", str(DATA / "spot.obj"), "-o", str(tmp_path / "x.glb"),
                 "--uv-weight", "0"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == "lodserver export: --uv-weight must be a positive number, got 0.0"


def test_scene_level_choice_is_part_of_the_manifest(tmp_path):
    """per_mesh changes only a glTF scene's levels, so only it is rebuilt; errors
    change every source's."""
    from .test_scene_budget import bolt_and_hull_glb

    source, out = _assets(tmp_path / "assets"), tmp_path / "lods"
    (source / "props" / "broken.stl").unlink()
    (source / "ship.glb").write_bytes(bolt_and_hull_glb())
    first = export_folder(source, out, lods=(1, 0.5))
    assert len(first.written) == 3
    scene = next(e for e in first.written if e.source.name == "ship.glb")
    assert scene.drawn[1] <= 0.5 * scene.drawn[0]           # one budget for the scene
    entries = json.loads((out / MANIFEST).read_text())["sources"]
    assert entries["ship.glb"]["options"]["levels"] == "scene"
    assert "levels" not in entries["spot.obj"]["options"]
    assert not export_folder(source, out, lods=(1, 0.5)).written
    again = export_folder(source, out, lods=(1, 0.5), per_mesh=True)
    assert [e.source.name for e in again.written] == ["ship.glb"]
    entries = json.loads((out / MANIFEST).read_text())["sources"]
    assert entries["ship.glb"]["options"]["levels"] == "per mesh"
    by_error = export_folder(source, out, errors=(0.001, 0.01))
    assert len(by_error.written) == 3
    assert all(len(e.faces) == 2 for e in by_error.written)
    entries = json.loads((out / MANIFEST).read_text())["sources"]
    assert entries["spot.obj"]["options"]["errors"] == [0.001, 0.01]
    assert not export_folder(source, out, errors=(0.001, 0.01)).written
    with pytest.raises(MeshError, match="not both"):
        export_folder(source, out, lods=(1, 0.5), errors=(0.01,))


def test_chain_options_are_checked_when_made_and_passed_whole(tmp_path):
    from lodserver.chains import DEFAULT_LODS, ChainOptions
    assert ChainOptions().lods == DEFAULT_LODS and ChainOptions().errors is None
    assert ChainOptions(errors=[0, 0.01]).errors == (0.0, 0.01)
    assert ChainOptions(errors=[0]).lods is None
    with pytest.raises(MeshError, match="not both"):
        ChainOptions(lods=(1, 0.5), errors=(0.01,))
    with pytest.raises(MeshError, match="reach"):
        ChainOptions(reach="sloppy")
    with pytest.raises(MeshError, match="per mesh already"):
        ChainOptions(errors=(0.01,), per_mesh=True)
    source = tmp_path / "ball.ply"
    source.write_bytes(trimesh.creation.icosphere(2).export(file_type="ply"))
    whole = export_lods(source, tmp_path / "whole.glb", ChainOptions(lods=(1, 0.25)))
    loose = export_lods(source, tmp_path / "loose.glb", lods=(1, 0.25))
    assert whole.faces == loose.faces
    assert (tmp_path / "whole.glb").read_bytes() == (tmp_path / "loose.glb").read_bytes()
    with pytest.raises(TypeError, match="not both"):
        export_lods(source, tmp_path / "x.glb", ChainOptions(), lods=(1, 0.5))
