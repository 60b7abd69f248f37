"""The report of ``export`` and ``extract`` (``--report``, ``scene.report``): its
schema for a single mesh, separate files, a scene, a folder and an extract; the
counts and bytes it reads back from the files; written whole or not at all."""

import json
import math

import pytest

from lodserver.cli import main
from lodserver.io import load_mesh
from lodserver.io.glb_levels import glb_levels
from lodserver.scene.report import REPORT_VERSION

from ..conftest import SHARED_MESHES
from ..meshes import DATA

TOP = {"lodserver_report", "command", "seconds", "assets"}
ASSET = {"source", "status", "outputs", "seconds", "diagonal", "warnings", "levels"}
LEVEL = {"level", "triangles", "vertices", "error", "error_fraction", "coverage",
         "pixel_coverage", "bytes", "seconds"}


def _number(value, *, none=False) -> bool:
    if value is None:
        return none
    return isinstance(value, (int, float)) and math.isfinite(value) and value >= 0


def check_schema(document: dict, command: str) -> None:
    """Every key of the report (docs/pipeline.md, "The report") with its type."""
    assert set(document) == TOP and document["lodserver_report"] == REPORT_VERSION
    assert document["command"] == command and _number(document["seconds"])
    for asset in document["assets"]:
        assert ASSET <= set(asset) <= ASSET | {"reason", "drawn"}
        assert asset["status"] in ("written", "up to date", "failed")
        assert all(isinstance(w, str) for w in asset["warnings"])
        if asset["status"] != "written":
            assert asset["levels"] == [] and asset["outputs"] == []
            assert ("reason" in asset) == (asset["status"] == "failed")
            continue
        assert _number(asset["seconds"]) and _number(asset["diagonal"])
        for k, level in enumerate(asset["levels"]):
            assert set(level) == LEVEL and level["level"] == k
            assert isinstance(level["triangles"], int) and level["triangles"] > 0
            assert isinstance(level["vertices"], int) and level["vertices"] >= 3
            assert _number(level["error"], none=True)
            assert _number(level["error_fraction"], none=True)
            if level["error"] is not None and asset["diagonal"] > 0:
                assert level["error_fraction"] == pytest.approx(level["error"]
                                                                / asset["diagonal"])
            assert _number(level["coverage"], none=True)
            assert level["pixel_coverage"] is None or 0 < level["pixel_coverage"] <= 1
            assert set(level["bytes"]) == {"geometry", "images"}
            assert _number(level["bytes"]["geometry"]) and level["bytes"]["geometry"] > 0
            assert _number(level["bytes"]["images"], none=True)
            assert _number(level["seconds"], none=True)
        triangles = [level["triangles"] for level in asset["levels"]]
        assert triangles == sorted(triangles, reverse=True)


def test_single_mesh_report(tmp_path):
    out, report = tmp_path / "spot.glb", tmp_path / "reports" / "spot.json"
    assert main(["export", str(DATA / "spot.obj"), "-o", str(out), "--lods", "1,0.2,0.05",
                 "--report", str(report)]) == 0
    document = json.loads(report.read_text())
    check_schema(document, "export")
    [asset] = document["assets"]
    assert asset["outputs"] == [str(out)]
    levels = asset["levels"]
    # counts and bytes are those of the file
    found = glb_levels(out.read_bytes())
    assert [level["triangles"] for level in levels] == [f["triangles"] for f in found]
    assert levels[0]["triangles"] == 5856
    assert levels[0]["error"] == 0 and levels[0]["pixel_coverage"] is None
    assert 0 < levels[1]["error"] < levels[2]["error"]
    assert levels[1]["pixel_coverage"] > levels[2]["pixel_coverage"]
    # one file of every level: each level names the one texture
    assert len({level["bytes"]["images"] for level in levels}) == 1
    total = sum(level["bytes"]["geometry"] for level in levels) + levels[0]["bytes"]["images"]
    assert total < out.stat().st_size < total + 20000      # and the JSON, headers, padding


def test_separate_files_with_texture_levels_report_each_file(tmp_path, capsys):
    out = tmp_path / "spot.glb"
    capsys.readouterr()
    assert main(["export", str(DATA / "spot.obj"), "-o", str(out), "--lods", "1,0.2",
                 "--separate", "--texture-scale", "auto", "--compress", "meshopt",
                 "--report", "-"]) == 0
    document = json.loads(capsys.readouterr().out)
    check_schema(document, "export")
    levels = document["assets"][0]["levels"]
    assert all(level["seconds"] is not None for level in levels)
    assert levels[1]["bytes"]["images"] < levels[0]["bytes"]["images"]
    for k, level in enumerate(levels):
        [found] = glb_levels((tmp_path / f"spot_lod{k}.glb").read_bytes())
        assert level["triangles"] == found["triangles"]
        assert level["bytes"] == {"geometry": found["geometry"], "images": found["images"]}


@pytest.mark.skipif(not SHARED_MESHES.is_dir(), reason="shared meshes not found")
def test_scene_and_folder_reports(tmp_path):
    folder = tmp_path / "assets"
    folder.mkdir()
    (folder / "Fox.glb").write_bytes((SHARED_MESHES / "scenes" / "Fox.glb").read_bytes())
    (folder / "Duck.glb").write_bytes((SHARED_MESHES / "Duck.glb").read_bytes())
    (folder / "broken.obj").write_text("v 0 0 0\n")
    report = tmp_path / "report.json"
    argv = ["export", str(folder), "-o", str(tmp_path / "lods"), "--lods", "1,0.3",
            "--report", str(report)]
    assert main(argv) == 1
    document = json.loads(report.read_text())
    check_schema(document, "export")
    by_name = {entry["source"].rsplit("/", 1)[-1]: entry for entry in document["assets"]}
    assert by_name["broken.obj"]["status"] == "failed" and by_name["broken.obj"]["reason"]
    assert by_name["Duck.glb"]["status"] == "written"
    assert len(by_name["Duck.glb"]["levels"]) == 2
    fox = by_name["Fox.glb"]
    # a scene: what is drawn (each mesh once per instance), its worst world errors
    assert len(fox["drawn"]) == 2 and fox["levels"][1]["error"] > 0
    # a second run: up to date
    assert main(argv) == 1
    again = {entry["source"].rsplit("/", 1)[-1]: entry["status"]
             for entry in json.loads(report.read_text())["assets"]}
    assert again == {"broken.obj": "failed", "Duck.glb": "up to date", "Fox.glb": "up to date"}


def test_extract_report(tmp_path, capsys):
    asset = tmp_path / "spot.pm"
    assert main(["build", str(DATA / "spot.obj"), "-o", str(asset)]) == 0
    for name in ("spot.glb", "spot.ply"):
        out = tmp_path / name
        capsys.readouterr()
        assert main(["extract", str(asset), "--ratio", "0.25", "-o", str(out),
                     "--compress", "quantize" if name.endswith("glb") else "none",
                     "--report", "-"]) == 0
        document = json.loads(capsys.readouterr().out)
        check_schema(document, "extract")
        [level] = document["assets"][0]["levels"]
        assert level["triangles"] == load_mesh(out)[0].face_count
        assert level["error"] > 0 and level["coverage"] is None
        assert (level["bytes"]["images"] is None) == name.endswith("ply")


def test_a_report_is_written_whole_or_not_at_all(tmp_path, monkeypatch, capsys):
    report = tmp_path / "report.json"
    report.write_text("the last run's report")
    argv = ["export", str(DATA / "spot.obj"), "-o", str(tmp_path / "spot.glb"),
            "--lods", "1,0.5", "--report", str(report)]

    import os
    replace = os.replace

    def full_disk(source, target):
        # the report's rename fails as on a full disk (the GLB's goes through)
        if str(target) == str(report):
            raise OSError(28, "No space left on device")
        return replace(source, target)

    monkeypatch.setattr(os, "replace", full_disk)
    capsys.readouterr()
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err
    assert err.splitlines()[-1] == (f"lodserver export: cannot write the report {report}: "
                                    f"No space left on device")
    assert report.read_text() == "the last run's report"
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []
