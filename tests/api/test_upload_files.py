"""Uploads of several files through the real app: an OBJ with its MTL and texture,
a .gltf with its .bin and images, or one .zip of them, resolved only inside that
set; hostile names and archives refused with one sentence, leaving nothing."""

import io
import json
import stat
import struct
import time
import zipfile

import numpy as np
import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.io.fileset import FileSetLimits, pack_set, pick_main, unpack_zip
from lodserver.mesh import MeshError
from lodserver.service.store import Store

from ..meshes import DATA
from . import settled

SPOT_FILES = ("spot.obj", "spot.mtl", "spot_texture.png")
TEXTURE = (DATA / "spot_texture.png").read_bytes()


def _client(tmp_path, **overrides):
    options = {"data_dir": tmp_path / "data", "warm_kernels": False, **overrides}
    return TestClient(create_app(Settings(**options)))


def _post(client, files, **fields):
    """POST /meshes with ``files`` as (name, bytes) pairs, all in the field 'file'."""
    return client.post("/meshes", files=[("file", item) for item in files], data=fields)


def _spot(names=SPOT_FILES):
    return [(name, (DATA / name).read_bytes()) for name in names]


def _zip(entries, compression=zipfile.ZIP_DEFLATED) -> bytes:
    """A zip of (name, bytes) pairs, or (ZipInfo, bytes) for hand-made entries."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression) as archive:
        for name, data in entries:
            archive.writestr(name, data)
    return buffer.getvalue()


def _leftovers(data_dir):
    found = list((data_dir / "tmp").rglob("*"))
    return found + [p for folder in ("sources", "artefacts") for p in (data_dir / folder).glob(".*")]


def _one_sentence_without_paths(message, *paths):
    assert message.count(". ") == 0, message
    for path in (*paths, "/tmp/"):
        assert str(path) not in message, message


def _triangle_gltf(buffer_uri="tri.bin", image_uri="tex.png"):
    """A textured quad as .gltf + .bin (+ the spot texture as its image): the
    document and the buffer's bytes."""
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    blob = positions.tobytes() + uvs.tobytes() + indices.tobytes()
    document = {
        "asset": {"version": "2.0"},
        "buffers": [{"uri": buffer_uri, "byteLength": len(blob)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 48},
                        {"buffer": 0, "byteOffset": 48, "byteLength": 32},
                        {"buffer": 0, "byteOffset": 80, "byteLength": 12}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3",
             "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5126, "count": 4, "type": "VEC2"},
            {"bufferView": 2, "componentType": 5123, "count": 6, "type": "SCALAR"}],
        "images": [{"uri": image_uri}], "textures": [{"source": 0}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1},
                                    "indices": 2, "material": 0}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0,
    }
    return json.dumps(document).encode(), blob


# ---- sets that work -----------------------------------------------------------------
def test_obj_with_its_mtl_and_texture_in_one_request(tmp_path):
    with _client(tmp_path) as client:
        created = _post(client, _spot())
        assert created.status_code == 202, created.text
        body = created.json()
        assert body["main"] == "spot.obj" and body["files"] == list(SPOT_FILES)
        assert body["warnings"] == []
        ready = settled(client, body["id"])
        assert ready["status"] == "ready", ready["failure"]
        assert ready["name"] == "spot.obj" and ready["warnings"] == []
        materials = client.get(f"/meshes/{body['id']}/materials").json()
        assert len(materials["images"]) == 1
        image = client.get(f"/meshes/{body['id']}/images/0")
        assert image.status_code == 200 and image.content == TEXTURE
        # the same OBJ alone: built without its library, and the response says so
        alone = _post(client, _spot(["spot.obj"]))
        assert alone.status_code == 202, alone.text
        assert any("'spot.mtl'" in warning and "not uploaded" in warning
                   for warning in alone.json()["warnings"])
        ready = settled(client, alone.json()["id"])
        assert any("'spot.mtl'" in warning for warning in ready["warnings"])
        assert client.get(f"/meshes/{alone.json()['id']}/images/0").status_code == 404
        assert _leftovers(tmp_path / "data") == []


def test_generated_gltf_with_its_bin_and_image(tmp_path):
    document, blob = _triangle_gltf()
    with _client(tmp_path) as client:
        created = _post(client, [("quad.gltf", document), ("tri.bin", blob), ("tex.png", TEXTURE)])
        assert created.status_code == 202, created.text
        ready = settled(client, created.json()["id"])
        assert ready["status"] == "ready", ready["failure"]
        assert ready["faces"] == 2 and ready["file_type"] == "zip"
        assert client.get(f"/meshes/{created.json()['id']}/images/0").content == TEXTURE
        # without its .bin: refused, naming the missing file as written
        refused = _post(client, [("quad.gltf", document), ("tex.png", TEXTURE)])
        assert refused.status_code == 422
        message = refused.json()["message"]
        assert "'tri.bin'" in message and "missing" in message
        _one_sentence_without_paths(message, tmp_path)
        assert _leftovers(tmp_path / "data") == []


def test_avocado_gltf_bin_and_images(tmp_path, shared_meshes):
    folder = shared_meshes / "Avocado"
    files = [(path.name, path.read_bytes()) for path in sorted(folder.iterdir())]
    with _client(tmp_path) as client:
        created = _post(client, files)
        assert created.status_code == 202, created.text
        assert created.json()["main"] == "Avocado.gltf"
        ready = settled(client, created.json()["id"])
        assert ready["status"] == "ready", ready["failure"]
        materials = client.get(f"/meshes/{created.json()['id']}/materials").json()
        assert len(materials["images"]) == 3
        served = client.get(f"/meshes/{created.json()['id']}/images/0").content
        assert served in {data for _, data in files}


def test_a_zip_with_sub_folders(tmp_path):
    document, blob = _triangle_gltf("../buffers/tri.bin", "../images/tex.png")
    archive = _zip([("asset/scene/quad.gltf", document), ("asset/buffers/tri.bin", blob),
                    ("asset/images/tex.png", TEXTURE), ("__MACOSX/._quad.gltf", b"junk"),
                    ("asset/.DS_Store", b"junk"), ("asset/README.txt", b"hello")])
    with _client(tmp_path) as client:
        created = _post(client, [("quad.zip", archive)])
        assert created.status_code == 202, created.text
        body = created.json()
        assert body["main"] == "quad.gltf"
        assert sorted(body["files"]) == ["asset/README.txt", "asset/buffers/tri.bin",
                                         "asset/images/tex.png", "asset/scene/quad.gltf"]
        ready = settled(client, body["id"])
        assert ready["status"] == "ready", ready["failure"]
        assert client.get(f"/meshes/{body['id']}/images/0").content == TEXTURE
        assert _leftovers(tmp_path / "data") == []


def test_a_stored_set_is_built_again_after_a_restart(tmp_path):
    """The store keeps a set as one archive; a build resumed after a restart
    unpacks it and resolves the same files."""
    folder = tmp_path / "set"
    folder.mkdir()
    for name, data in _spot():
        (folder / name).write_bytes(data)
    archive = tmp_path / "set.zip"
    pack_set(folder, list(SPOT_FILES), archive, main="spot.obj")
    with _client(tmp_path, workers=0) as client:       # stored, not built
        record = client.app.state.store.create(name="spot.obj", source=archive,
                                               file_type="zip", options={})
    with _client(tmp_path) as client:           # the restart resumes the build
        ready = settled(client, record.id)
        assert ready["status"] == "ready", ready["failure"]
        assert client.get(f"/meshes/{record.id}/images/0").content == TEXTURE
        assert _leftovers(tmp_path / "data") == []


# ---- the main file --------------------------------------------------------------------
def test_several_mesh_files_need_the_main_field(tmp_path):
    files = _spot() + [("copy.obj", (DATA / "spot.obj").read_bytes())]
    with _client(tmp_path) as client:
        refused = _post(client, files)
        assert refused.status_code == 422
        message = refused.json()["message"]
        assert "2 mesh files" in message and "'main'" in message
        _one_sentence_without_paths(message, tmp_path)
        for main, expected in (("spot.png", "not one of"), ("spot.mtl", "not a mesh file")):
            response = _post(client, files, main=main)
            assert response.status_code == 422 and expected in response.json()["message"]
        created = _post(client, files, main="copy.obj")
        assert created.status_code == 202, created.text
        assert created.json()["main"] == "copy.obj"
        # copy.obj names spot.mtl, which is in the set: the texture is found
        assert settled(client, created.json()["id"])["status"] == "ready"
        assert client.get(f"/meshes/{created.json()['id']}/images/0").content == TEXTURE
        none = _post(client, [("spot.mtl", (DATA / "spot.mtl").read_bytes()),
                              ("spot_texture.png", TEXTURE)])
        assert none.status_code == 415 and "no mesh file" in none.json()["message"]
        assert _leftovers(tmp_path / "data") == []


def test_pick_main_rules():
    assert pick_main(["a/b.gltf", "a/b.bin"]) == "a/b.gltf"
    assert pick_main(["a/x.obj", "b/x.ply"], "b/x.ply") == "b/x.ply"
    assert pick_main(["a/x.obj", "b/y.ply"], "y.ply") == "b/y.ply"
    with pytest.raises(MeshError, match="more than one of"):
        pick_main(["a/x.obj", "b/x.obj"], "x.obj")
    with pytest.raises(MeshError, match="no mesh file"):
        pick_main(["a.png"])


# ---- names and sets that are refused -----------------------------------------------------
def test_part_names_are_reduced_to_their_base_name(tmp_path):
    document, blob = _triangle_gltf()
    with _client(tmp_path) as client:
        created = _post(client, [("../../up/quad.gltf", document), ("/etc/tri.bin", blob),
                                 ("C:\\textures\\tex.png", TEXTURE)])
        assert created.status_code == 202, created.text
        assert created.json()["files"] == ["quad.gltf", "tri.bin", "tex.png"]
        assert settled(client, created.json()["id"])["status"] == "ready"
        for files, expected in (
                ([("quad.gltf", document), ("tri.bin", blob), ("dir/tri.bin", blob)],
                 "two files named 'tri.bin'"),
                ([("quad.gltf", document), (".tri.bin", blob)], "starts with a dot"),
                ([("quad.gltf", document), ("tri:1.bin", blob)], "a colon"),
                ([("quad.gltf", document)] + [(f"f{i}.png", b"x") for i in range(64)],
                 "more than 64 files"),
                ([("quad.zip", _zip(_spot())), ("tri.bin", blob)], "either one .zip")):
            response = _post(client, files)
            assert response.status_code == 422, (expected, response.text)
            assert expected in response.json()["message"]
            _one_sentence_without_paths(response.json()["message"], tmp_path)
        assert _leftovers(tmp_path / "data") == []
        assert len(client.get("/meshes").json()["meshes"]) == 1


def _symlink_entry(name, target):
    info = zipfile.ZipInfo(name)
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    return info, target


def _bomb(size=64 * 2**20):
    """A zip entry of ``size`` zero bytes, deflated to about a thousandth of that."""
    return _zip([("spot.obj", (DATA / "spot.obj").read_bytes()), ("zeros.bin", bytes(size))])


@pytest.mark.parametrize("archive, status, expected", [
    (lambda: _zip(_spot() + [("../evil.png", TEXTURE)]), 422, "leads out of the archive's folder"),
    (lambda: _zip(_spot() + [("a/../../evil.png", TEXTURE)]), 422, "leads out"),
    (lambda: _zip(_spot() + [("/etc/evil.png", TEXTURE)]), 422, "is an absolute path"),
    (lambda: _zip(_spot() + [("C:/evil.png", TEXTURE)]), 422, "is an absolute path"),
    (lambda: _zip(_spot() + [_symlink_entry("link.png", b"/etc/passwd")]), 422, "symbolic link"),
    (lambda: _zip(_spot() + [("spot.mtl", b"again")]), 422, "more than once"),
    (lambda: _zip(_spot() + [("spot.obj/inner.png", TEXTURE)]), 422, "which is a file"),
    (lambda: _zip(_spot() + [("/".join("d" * 10) + "/x.png", TEXTURE)]), 422, "folders deep"),
    (lambda: _bomb(), 413, "expands"),
    (lambda: _zip(_spot() + [(f"many/{i}.png", b"") for i in range(1100)], zipfile.ZIP_STORED),
     413, "entries"),
    (lambda: b"PK\x03\x04 this is not really a zip", 422, "not a zip file"),
], ids=["dotdot", "nested-dotdot", "absolute", "drive", "symlink", "duplicate", "file-as-folder",
        "too-deep", "bomb", "too-many-entries", "not-a-zip"])
def test_hostile_zips_are_refused_and_leave_nothing(tmp_path, archive, status, expected):
    with _client(tmp_path) as client:
        response = _post(client, [("upload.zip", archive())])
        assert response.status_code == status, response.text
        message = response.json()["message"]
        assert expected in message, message
        _one_sentence_without_paths(message, tmp_path)
        assert client.get("/meshes").json()["meshes"] == []
        assert _leftovers(tmp_path / "data") == []


def test_a_zip_declaring_too_many_entries_is_refused_before_it_is_read(tmp_path):
    """The count in the end record is checked before zipfile builds an entry object."""
    archive = bytearray(_zip(_spot()))
    end = archive.rfind(b"PK\x05\x06")
    struct.pack_into("<HH", archive, end + 8, 60000, 60000)
    with pytest.raises(MeshError, match="declares 60000 entries"):
        unpack_zip(_write(tmp_path / "a.zip", bytes(archive)), _folder(tmp_path / "out"))
    assert list((tmp_path / "out").iterdir()) == []


def test_a_corrupt_entry_is_refused(tmp_path):
    archive = bytearray(_zip(_spot(), zipfile.ZIP_STORED))
    at = archive.find(b"newmtl")                 # inside spot.mtl's stored bytes
    archive[at] ^= 0x20
    with pytest.raises(MeshError, match="CRC"):
        unpack_zip(_write(tmp_path / "a.zip", bytes(archive)), _folder(tmp_path / "out"))


def test_the_unpacked_total_is_bounded(tmp_path):
    archive = _write(tmp_path / "a.zip", _zip(_spot()))
    limits = FileSetLimits(max_unpacked_bytes=1000)
    with pytest.raises(MeshError, match="more than 1000 bytes uncompressed"):
        unpack_zip(archive, _folder(tmp_path / "out"), limits)
    assert list((tmp_path / "out").iterdir()) == []


def _write(path, data):
    path.write_bytes(data)
    return path


def _folder(path):
    path.mkdir()
    return path


@pytest.mark.parametrize("uri", ["../outside.bin", "../../elsewhere/outside.bin", "/etc/passwd",
                                 "sub/../../outside.bin"])
def test_references_leaving_the_set_are_refused(tmp_path, uri):
    """A file the set's mesh names must be one of the set: even a file sitting
    beside the upload in the server's folders is out of reach."""
    document, blob = _triangle_gltf(uri)
    with _client(tmp_path) as client:
        for files in ([("quad.gltf", document), ("tex.png", TEXTURE), ("outside.bin", blob)],
                      [("set.zip", _zip([("quad.gltf", document), ("tex.png", TEXTURE),
                                         ("outside.bin", blob)]))]):
            response = _post(client, files)
            assert response.status_code == 422, response.text
            message = response.json()["message"]
            assert repr(uri) in message, message
            _one_sentence_without_paths(message, tmp_path)
        assert client.get("/meshes").json()["meshes"] == []
        assert _leftovers(tmp_path / "data") == []


# ---- the queue ---------------------------------------------------------------------------
def test_queue_position_counts_the_uploads_queued_before(tmp_path):
    with _client(tmp_path, workers=0) as client:       # nothing is built: they wait
        store = client.app.state.store
        ids = []
        for i in range(3):
            source = _write(tmp_path / f"s{i}.obj", (DATA / "spot.obj").read_bytes())
            ids.append(store.create(name=f"s{i}", source=source, file_type="obj",
                                    options={}).id)
            time.sleep(0.002)       # distinct creation times
        assert [client.get(f"/meshes/{i}").json()["queue_position"] for i in ids] == [0, 1, 2]
        listed = {m["id"]: m["queue_position"] for m in client.get("/meshes").json()["meshes"]}
        assert [listed[i] for i in ids] == [0, 1, 2]
        # the store's generic version (paging through list) agrees with its query
        assert [Store.queue_position(store, mesh_id=i) for i in ids] == [0, 1, 2]
        store.mark_building(mesh_id=ids[0])
        assert client.get(f"/meshes/{ids[0]}").json()["queue_position"] is None
        assert [client.get(f"/meshes/{i}").json()["queue_position"] for i in ids[1:]] == [0, 1]
