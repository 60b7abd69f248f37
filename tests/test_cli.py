"""The command line, run in-process and once as the installed entry point."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from lodserver.cli import main
from lodserver.io import load_mesh

from .meshes import DATA


def test_build_extract_info(tmp_path, capsys):
    asset = tmp_path / "spot.pm"
    assert main(["build", str(DATA / "spot.obj"), "-o", str(asset)]) == 0
    for flag, value in (("--ratio", "0.1"), ("--faces", "500"), ("--vertices", "300"),
                        ("--error", "0.01")):
        out = tmp_path / f"lod{flag}.ply"
        assert main(["extract", str(asset), flag, value, "-o", str(out)]) == 0
        mesh, _ = load_mesh(out)
        if flag == "--faces":
            assert mesh.face_count <= 500
        if flag == "--vertices":
            assert mesh.vertex_count <= 300
    capsys.readouterr()
    assert main(["info", str(asset)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["vertices"] == 2930 and info["faces"] == 5856
    assert info["metadata"]["source"] == "spot.obj"


def test_lock_border_keeps_border_vertices(tmp_path):
    grid = tmp_path / "grid.obj"
    x, y = np.meshgrid(np.arange(6.0), np.arange(5.0))
    lines = [f"v {a} {b} {0.1 * a * b}" for a, b in zip(x.ravel(), y.ravel())]
    idx = np.arange(30).reshape(5, 6) + 1
    for i in range(4):
        for j in range(5):
            a, b, c, d = idx[i, j], idx[i, j + 1], idx[i + 1, j + 1], idx[i + 1, j]
            lines += [f"f {a} {b} {c}", f"f {a} {c} {d}"]
    grid.write_text("\n".join(lines) + "\n")
    asset = tmp_path / "grid.pm"
    assert main(["build", str(grid), "--lock-border", "-o", str(asset)]) == 0
    out = tmp_path / "base.obj"
    assert main(["extract", str(asset), "--vertices", "1", "-o", str(out)]) == 0
    base, _ = load_mesh(out)
    border = {(a, b) for a, b in zip(x.ravel(), y.ravel()) if a in (0, 5) or b in (0, 4)}
    assert border <= {(p[0], p[1]) for p in base.positions}


@pytest.mark.parametrize("argv, message", [
    (["build", "missing.obj", "-o", "x.pm"], "cannot load"),
    (["extract", "missing.pm", "--ratio", "0.5", "-o", "x.ply"], "cannot read"),
    (["extract", "{asset}", "--ratio", "2", "-o", "x.ply"], "ratio"),
    (["extract", "{asset}", "--ratio", "0.5", "-o", "x.xyz"], "xyz"),
])
def test_errors_are_one_sentence_and_exit_1(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    asset = tmp_path / "spot.pm"
    assert main(["build", str(DATA / "spot.obj"), "-o", str(asset)]) == 0
    capsys.readouterr()
    code = main([a.replace("{asset}", str(asset)) for a in argv])
    err = capsys.readouterr().err
    assert code == 1
    assert message in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1


def test_installed_entry_point(tmp_path):
    exe = shutil.which("lodserver")
    command = [exe] if exe else [sys.executable, "-m", "lodserver.cli"]
    result = subprocess.run(command + ["info", str(tmp_path / "none.pm")], capture_output=True,
                            text=True)
    assert result.returncode == 1
    assert "cannot read" in result.stderr


@pytest.mark.parametrize("method", ["qem", "cluster"])
def test_simplify_one_shot(tmp_path, method):
    out = tmp_path / f"spot_{method}.obj"
    assert main(["simplify", str(DATA / "spot.obj"), "--ratio", "0.1", "--method", method,
                 "-o", str(out)]) == 0
    mesh, _ = load_mesh(out)
    assert 0.5 * 586 <= mesh.face_count <= 586
