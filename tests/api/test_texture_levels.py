"""Texture levels of the server's chains: ``/chain?texture_scale=auto`` draws each
level with its images scaled as ``lodserver export --texture-scale auto`` does,
under its own ETag."""

import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.io import load_mesh
from lodserver.io.glb import encode_glb
from lodserver.io.image_scale import image_size
from lodserver.scene.textures import scaled_size, texture_scales

from ..conftest import SHARED_MESHES
from ..meshes import DATA
from ..server import upload, wait_ready
from ..io.test_gltf_compressed_output import split_glb


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A client with textured spot uploaded as a GLB (its 1024 px texture embedded)."""
    folder = tmp_path_factory.mktemp("textures")
    mesh, _ = load_mesh(DATA / "spot.obj")
    with TestClient(create_app(Settings(data_dir=folder / "data", warm_kernels=False))) as client:
        mesh_id = upload(client, "spot.glb", encode_glb(mesh))
        wait_ready(client, mesh_id)
        yield client, mesh_id


def _level_images(data: bytes) -> list[tuple[int, int]]:
    """The size of the base colour image each mesh (level) of a chain draws with."""
    document, binary = split_glb(data)
    sizes = []
    for mesh in document["meshes"]:
        material = document["materials"][mesh["primitives"][0]["material"]]
        texture = document["textures"][material["pbrMetallicRoughness"]["baseColorTexture"]
                                       ["index"]]
        view = document["bufferViews"][document["images"][texture["source"]]["bufferView"]]
        start = view.get("byteOffset", 0)
        sizes.append(image_size(binary[start:start + view["byteLength"]]))
    return sizes


@pytest.mark.parametrize("compress", ["none", "meshopt"])
def test_chain_with_texture_levels(served, compress):
    client, mesh_id = served
    query = {"lods": "1,0.2,0.05", "compress": compress}
    plain = client.get(f"/meshes/{mesh_id}/chain", params=query)
    scaled = client.get(f"/meshes/{mesh_id}/chain", params={**query, "texture_scale": "auto"})
    assert plain.status_code == 200 and scaled.status_code == 200, scaled.text
    assert plain.headers["etag"] != scaled.headers["etag"]
    assert _level_images(plain.content) == [(1024, 1024)] * 3
    document, _ = split_glb(scaled.content)
    faces = [sum(document["accessors"][p["indices"]]["count"] // 3 for p in mesh["primitives"])
             for mesh in document["meshes"]]
    wanted = [scaled_size((1024, 1024), s) for s in texture_scales("auto", faces)]
    assert _level_images(scaled.content) == wanted and wanted[-1] < wanted[0]
    assert len(document["images"]) == len(set(wanted))
    again = client.get(f"/meshes/{mesh_id}/chain", params={**query, "texture_scale": "auto"},
                       headers={"If-None-Match": scaled.headers["etag"]})
    assert again.status_code == 304


def test_unknown_texture_scale_is_refused(served):
    client, mesh_id = served
    response = client.get(f"/meshes/{mesh_id}/chain", params={"texture_scale": "half"})
    assert response.status_code == 422


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """A client with Duck uploaded as it is: a scene (its node tree and camera kept)."""
    source = SHARED_MESHES / "Duck.glb"
    if not source.is_file():
        pytest.skip(f"shared mesh not found at {source}")
    folder = tmp_path_factory.mktemp("scene")
    with TestClient(create_app(Settings(data_dir=folder / "data", warm_kernels=False))) as client:
        mesh_id = upload(client, "Duck.glb", source.read_bytes())
        wait_ready(client, mesh_id)
        assert client.get(f"/meshes/{mesh_id}").json()["scene"] is True
        yield client, mesh_id


def test_a_scenes_level_and_chain_compress_and_scale_their_textures(scene, tmp_path):
    from lodserver.io.scene import load_scene

    client, mesh_id = scene
    tags = set()
    for compress in ("none", "meshopt"):
        level = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5, "format": "glb",
                                                              "compress": compress})
        assert level.status_code == 200, level.text
        tags.add(level.headers["etag"])
        document, _ = split_glb(level.content)
        assert ("EXT_meshopt_compression" in document.get("extensionsRequired", [])) == \
            (compress == "meshopt")
        assert "cameras" in document
    assert len(tags) == 2
    chain = client.get(f"/meshes/{mesh_id}/chain", params={
        "lods": "1,0.2,0.05", "compress": "meshopt", "texture_scale": "auto"})
    assert chain.status_code == 200, chain.text
    document, binary = split_glb(chain.content)
    assert "EXT_meshopt_compression" in document["extensionsRequired"]
    sizes = []
    for image in document["images"]:
        view = document["bufferViews"][image["bufferView"]]
        start = view.get("byteOffset", 0)
        sizes.append(image_size(binary[start:start + view["byteLength"]]))
    # Duck's 512 px texture at each level's size (its 20% and 5% levels: 1/2 and 1/4)
    assert sorted(sizes) == [(128, 128), (256, 256), (512, 512)]
    path = tmp_path / "chain.glb"
    path.write_bytes(chain.content)
    assert load_scene(path).meshes
