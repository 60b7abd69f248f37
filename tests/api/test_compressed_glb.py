"""Compressed uploads and compressed GLB levels over HTTP: a gltfpack-style meshopt
upload is built like any other, and ``compress=`` gives a level or a chain quantized
or meshopt-compressed, under its own ETag; other formats refuse it in a sentence."""

import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.io import load_mesh
from lodserver.io.glb import encode_glb

from ..meshes import DATA
from ..server import upload, wait_ready
from ..io.test_gltf_compressed_output import split_glb
from . import settled


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A client with spot uploaded as a meshopt-compressed GLB, built."""
    folder = tmp_path_factory.mktemp("compressed")
    mesh, _ = load_mesh(DATA / "spot.obj")
    encoded = encode_glb(mesh, "meshopt")
    with TestClient(create_app(Settings(data_dir=folder / "data", warm_kernels=False))) as client:
        mesh_id = upload(client, "spot.glb", encoded)
        wait_ready(client, mesh_id)
        yield client, mesh_id


def test_meshopt_upload_builds(served):
    client, mesh_id = served
    assert client.get(f"/meshes/{mesh_id}").json()["faces"] == 5856


@pytest.mark.parametrize("compress, required", [
    ("none", []), ("quantize", ["KHR_mesh_quantization"]),
    ("meshopt", ["KHR_mesh_quantization", "EXT_meshopt_compression"])])
def test_level_and_chain_in_each_compression(served, tmp_path, compress, required):
    client, mesh_id = served
    for route, query in (("lod", {"ratio": 0.5, "format": "glb"}), ("chain", {"lods": "1,0.2"})):
        response = client.get(f"/meshes/{mesh_id}/{route}", params={**query,
                                                                      "compress": compress})
        assert response.status_code == 200, response.text
        document, _ = split_glb(response.content)
        assert document.get("extensionsRequired", []) == required
        path = tmp_path / f"{route}.glb"
        path.write_bytes(response.content)
        assert load_mesh(path)[0].face_count > 0


def test_each_compression_has_its_own_etag(served):
    client, mesh_id = served
    tags = {client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5, "format": "glb",
                                                          "compress": c}).headers["etag"]
            for c in ("none", "quantize", "meshopt")}
    assert len(tags) == 3


def test_compress_applies_to_glb_only(served):
    client, mesh_id = served
    response = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5, "format": "obj",
                                                             "compress": "meshopt"})
    assert response.status_code == 422
    assert response.json()["message"] == "compress=meshopt applies to format=glb only"
    response = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5, "format": "glb",
                                                             "compress": "zip"})
    assert response.status_code == 422


def test_draco_upload_builds_and_a_bomb_is_refused(served):
    from ..io.test_gltf_compressed_hostile import draco_glb

    client, _ = served
    created = client.post("/meshes", files={"file": ("grid.glb", draco_glb(size=8))})
    assert created.status_code == 202, created.text
    assert settled(client, created.json()["id"])["status"] == "ready"

    def bomb(document, stream):
        return b"DRACO\x02\x02\x01\x00\x00\x00" + b"\x80\x94\xeb\xdc\x03" * 2 + bytes(32)

    # the upload is parsed before it is accepted: refused with a sentence
    response = client.post("/meshes", files={"file": ("bomb.glb", draco_glb(edit=bomb))})
    assert response.status_code == 422, response.text
    message = response.json()["message"]
    assert "Draco bitstream 1000000000 triangles" in message and "/" not in message
