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


def test_version_and_no_command(capsys):
    import lodserver

    with pytest.raises(SystemExit) as exited:
        main(["--version"])
    assert exited.value.code == 0
    assert capsys.readouterr().out.strip() == f"lodserver {lodserver.__version__}"
    assert main([]) == 2
    err = capsys.readouterr().err
    for command in ("build", "extract", "simplify", "export", "info", "serve"):
        assert f"    {command} " in err
    assert err.strip().splitlines()[-1] == ("lodserver: name a command, such as "
                                            "'lodserver build MESH -o ASSET.pm'.")


@pytest.mark.parametrize("command", ["", "build", "extract", "simplify", "export", "info",
                                     "serve"])
def test_help_is_plain_text_with_examples(capsys, command):
    with pytest.raises(SystemExit):
        main(([command] if command else []) + ["--help"])
    text = capsys.readouterr().out
    assert "``" not in text and ":class:" not in text and ":func:" not in text
    assert ("examples:" if not command else "example:") in text
    examples = text.split("example")[1].splitlines()[1:]
    assert any(line.strip().startswith("lodserver ") for line in examples)


def test_every_command_creates_its_output_folder(tmp_path, capsys):
    spot = str(DATA / "spot.obj")
    asset = tmp_path / "a" / "b" / "spot.pm"
    assert main(["build", spot, "-o", str(asset)]) == 0 and asset.is_file()
    outputs = {"extract": tmp_path / "c" / "d" / "lod.glb",
               "simplify": tmp_path / "e" / "f" / "lod.obj",
               "export": tmp_path / "g" / "h" / "chain.glb"}
    assert main(["extract", str(asset), "--ratio", "0.2", "-o", str(outputs["extract"])]) == 0
    assert main(["simplify", spot, "--ratio", "0.2", "-o", str(outputs["simplify"])]) == 0
    assert main(["export", str(asset), "--lods", "1,0.2", "-o", str(outputs["export"])]) == 0
    assert all(path.is_file() for path in outputs.values())
    folder = tmp_path / "assets"
    folder.mkdir()
    shutil.copy(DATA / "spot.obj", folder)
    assert main(["export", str(folder), "--lods", "1,0.2", "-o", str(tmp_path / "i" / "j")]) == 0
    assert (tmp_path / "i" / "j" / "spot.glb").is_file()


def test_the_extracted_sample_is_textured(tmp_path):
    """The README's first command: spot.obj names spot.mtl, which names its texture."""
    asset, glb = tmp_path / "spot.pm", tmp_path / "spot_10.glb"
    assert main(["build", str(DATA / "spot.obj"), "-o", str(asset)]) == 0
    assert main(["extract", str(asset), "--ratio", "0.1", "-o", str(glb)]) == 0
    level, _ = load_mesh(glb)
    assert level.materials is not None
    assert level.materials.images == ((DATA / "spot_texture.png").read_bytes(),)
    assert [name for name, _ in level.attributes.layout] == ["TEXCOORD_0"]


def test_errors_name_the_users_paths_not_temporary_ones(tmp_path, capsys):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("")
    asset = tmp_path / "spot.pm"
    assert main(["build", str(DATA / "spot.obj"), "-o", str(asset)]) == 0
    capsys.readouterr()
    for argv in (["build", str(DATA / "spot.obj"), "-o", str(blocker / "x.pm")],
                 ["extract", str(asset), "--ratio", "0.5", "-o", str(blocker / "x.ply")],
                 ["export", str(asset), "-o", str(blocker / "x.glb")]):
        assert main(argv) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and ".tmp" not in err and "Traceback" not in err
        assert str(blocker) in err


@pytest.mark.parametrize("command", ["build", "simplify", "extract", "info"])
def test_a_folder_given_as_a_mesh_says_so(tmp_path, capsys, command):
    extra = {"build": ["-o", "x.pm"], "simplify": ["--ratio", "0.5", "-o", "x.obj"],
             "extract": ["--ratio", "0.5", "-o", "x.obj"], "info": []}[command]
    assert main([command, str(tmp_path)] + extra) == 1
    err = capsys.readouterr().err.strip()
    assert err == (f"lodserver {command}: {tmp_path} is a folder; pass a mesh file (or use "
                   f"`lodserver export FOLDER/ -o OUT/`)")


def test_info_into_a_closed_pipe_exits_quietly(tmp_path):
    """`lodserver info x.pm | head -1`: the reader is gone before the JSON is written."""
    asset = tmp_path / "spot.pm"
    assert main(["build", str(DATA / "spot.obj"), "-o", str(asset)]) == 0
    process = subprocess.Popen([sys.executable, "-m", "lodserver.cli", "info", str(asset)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    process.stdout.close()          # as head does after its line
    err = process.stderr.read().decode()
    assert process.wait(timeout=120) == 141
    assert err == ""


def test_a_cold_numba_cache_is_detected(tmp_path):
    """An empty NUMBA_CACHE_DIR: the next build compiles (the CLI says so first); after a
    build in this process the kernels are cached."""
    from lodserver.build import build, kernels_cold

    probe = "from lodserver.build import kernels_cold; print(kernels_cold(), kernels_cold('cluster'))"
    env = {**__import__("os").environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                            env=env, timeout=120)
    assert result.stdout.split() == ["True", "True"], result.stderr
    build(DATA / "spot.obj", min_vertices=2900)
    assert kernels_cold() is False


def test_untrusted_refuses_a_reference_outside_the_files_folder(tmp_path, capsys):
    """--untrusted loads as the server loads an upload: a .gltf naming a file
    outside its folder is refused with a sentence naming the reference."""
    import json

    secret = tmp_path / "secret.bin"
    secret.write_bytes(bytes(36))
    folder = tmp_path / "assets"
    folder.mkdir()
    document = {"asset": {"version": "2.0"}, "buffers": [{"uri": "../secret.bin", "byteLength": 36}],
                "bufferViews": [{"buffer": 0, "byteLength": 36}],
                "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                               "min": [0, 0, 0], "max": [0, 0, 0]}],
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
                "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]}
    source = folder / "tri.gltf"
    source.write_text(json.dumps(document))
    for command in (["build", str(source), "-o", str(tmp_path / "x.pm")],
                    ["simplify", str(source), "--ratio", "0.5", "-o", str(tmp_path / "x.obj")],
                    ["export", str(source), "-o", str(tmp_path / "x.glb")]):
        assert main([*command, "--untrusted"]) == 1
        message = capsys.readouterr().err
        assert "'../secret.bin'" in message and str(tmp_path) not in message
    assert not (tmp_path / "x.pm").exists() and not (tmp_path / "x.glb").exists()
