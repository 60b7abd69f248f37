"""``io.fileset.open_set``: a set's archive checked whole, its main file extracted,
and every other file only when a reference of the mesh names it."""

import io
import zipfile

import pytest

from lodserver.io import load_mesh
from lodserver.io.fileset import open_set, pack_set
from lodserver.mesh import MeshError

from ..meshes import DATA

SPOT_FILES = ("spot.obj", "spot.mtl", "spot_texture.png")


def _files(folder):
    return sorted(str(path.relative_to(folder)) for path in folder.rglob("*") if path.is_file())


def _archive(tmp_path, entries):
    path = tmp_path / "set.zip"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries:
            archive.writestr(name, data)
    return path


def test_only_the_files_the_mesh_names_are_extracted(tmp_path):
    obj = (DATA / "spot.obj").read_bytes().replace(b"mtllib spot.mtl", b"mtllib ../maps/spot.mtl")
    mtl = (DATA / "spot.mtl").read_bytes().replace(b"spot_texture.png", b"../maps/tex.png")
    archive = _archive(tmp_path, [("models/spot.obj", obj), ("maps/spot.mtl", mtl),
                                  ("maps/tex.png", (DATA / "spot_texture.png").read_bytes()),
                                  ("unused/big.bin", bytes(2**20)), ("notes.txt", b"hello")])
    folder = tmp_path / "set"
    folder.mkdir()
    with open_set(archive, folder) as main:
        assert main == folder / "models" / "spot.obj"
        assert _files(folder) == ["models/spot.obj"]
        mesh, report = load_mesh(main, root=folder)
    assert report.missing_files == []
    assert mesh.materials is not None
    assert _files(folder) == ["maps/spot.mtl", "maps/tex.png", "models/spot.obj"]


def test_the_main_file_named_by_pack_set_is_the_one_opened(tmp_path):
    for name in SPOT_FILES:
        (tmp_path / name).write_bytes((DATA / name).read_bytes())
    (tmp_path / "other.obj").write_bytes(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    archive = tmp_path / "set.zip"
    pack_set(tmp_path, [*SPOT_FILES, "other.obj"], archive, main="other.obj")
    folder = tmp_path / "out"
    folder.mkdir()
    with open_set(archive, folder) as main:
        assert main.name == "other.obj"
        assert load_mesh(main, root=folder)[0].face_count == 1
    assert _files(folder) == ["other.obj"]


def test_a_hostile_entry_is_refused_before_anything_is_extracted(tmp_path):
    archive = _archive(tmp_path, [("spot.obj", (DATA / "spot.obj").read_bytes()),
                                  ("../evil.png", b"x")])
    folder = tmp_path / "out"
    folder.mkdir()
    with pytest.raises(MeshError, match="leads out"):
        with open_set(archive, folder):
            pass
    assert _files(folder) == []
