"""Levels beyond edge collapse's reach through the HTTP API (issue 28): ``/lod`` and
``/chain`` by ratio or faces below the coarsest level edge collapse reaches are
merged and baked by default (``reach=merge``), as ``lodserver export --lods``
makes them; cached and ETagged like other levels; ``reach=none`` and the json
form keep edge collapse's level; a static scene's far level is one mesh."""

from __future__ import annotations

import io
import json
import struct

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.routes import lods as lods_route
from lodserver.api.settings import Settings
from lodserver.chains import REACH_SLACK
from lodserver.io.glb import encode_glb
from lodserver.mesh import Attributes, Materials, Mesh

from ..io import test_gltf
from ..io.test_gltf import assert_valid
from ..scene.test_groups import assembled_scene
from . import settled

gltf_validator = test_gltf.gltf_validator    # the session fixture, shared
WINDOW = 0.1


def _png(pixels: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return buffer.getvalue()


def textured_balls(count=60, seed=5) -> bytes:
    """A GLB of one mesh: ``count`` separate small spheres (80 faces each) with
    normals, UVs and one textured material; edge collapse keeps every sphere."""
    rng = np.random.default_rng(seed)
    ball = trimesh.creation.icosphere(1)
    unit = ball.vertices / np.linalg.norm(ball.vertices, axis=1, keepdims=True)
    uv = np.stack([0.5 + np.arctan2(unit[:, 1], unit[:, 0]) / (2 * np.pi),
                   0.5 + np.arcsin(np.clip(unit[:, 2], -1, 1)) / np.pi], axis=1)
    positions, faces, values = [], [], []
    for k in range(count):
        positions.append(ball.vertices * 0.4 + rng.random(3) * 10)
        faces.append(ball.faces + k * len(ball.vertices))
        values.append(np.concatenate([unit, uv], axis=1))
    faces = np.concatenate(faces)
    s, t = np.meshgrid(np.linspace(0, 1, 32), np.linspace(0, 1, 32))
    pixels = np.rint(np.stack([s, t, 0.5 + 0.5 * np.sin(6 * s), np.ones_like(s)], 2) * 255)
    materials = Materials({"materials": [{"pbrMetallicRoughness": {
        "baseColorTexture": {"index": 0}, "metallicFactor": 0.0}}],
        "textures": [{"source": 0}], "images": [{"mimeType": "image/png"}]},
        (_png(pixels.astype(np.uint8)),))
    attributes = Attributes((("NORMAL", 3), ("TEXCOORD_0", 2)), np.concatenate(values), faces)
    return encode_glb(Mesh(np.concatenate(positions), faces, attributes,
                           np.zeros(len(faces), np.int32), materials))


def static_scene(parts=3, balls=20, seed=7) -> bytes:
    """A GLB scene of ``parts`` meshes on their own nodes, each ``balls`` separate
    spheres: no animation, so its far level may be one mesh."""
    rng = np.random.default_rng(seed)
    scene = trimesh.Scene()
    for p in range(parts):
        pieces = [trimesh.creation.icosphere(1).apply_scale(0.4).apply_translation(
            rng.random(3) * 10) for _ in range(balls)]
        scene.add_geometry(trimesh.util.concatenate(pieces), node_name=f"part{p}",
                           geom_name=f"mesh{p}",
                           transform=trimesh.transformations.translation_matrix([p * 12, 0, 0]))
    return scene.export(file_type="glb")


def _document(glb: bytes) -> dict:
    length, _ = struct.unpack_from("<I4s", glb, 12)
    return json.loads(glb[20:20 + length])


def _faces(document: dict, mesh: int = 0) -> int:
    return sum(document["accessors"][p["indices"]]["count"] // 3
               for p in document["meshes"][mesh]["primitives"])


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A client with the textured spheres uploaded and built, and the summary."""
    options = {"data_dir": tmp_path_factory.mktemp("far") / "data", "warm_kernels": False}
    with TestClient(create_app(Settings(**options))) as client:
        created = client.post("/meshes", files={"file": ("balls.glb", textured_balls())})
        assert created.status_code == 202, created.text
        body = settled(client, created.json()["id"], timeout=180)
        assert body["status"] == "ready", body["failure"]
        yield client, body


def test_a_level_beyond_reach_is_merged_and_baked(served, gltf_validator):
    client, body = served
    budget = round(0.02 * body["faces"])
    assert body["base_faces"] > REACH_SLACK * budget       # out of edge collapse's reach
    response = client.get(f"/meshes/{body['id']}/lod", params={"ratio": 0.02, "format": "glb"})
    assert response.status_code == 200, response.text
    document = _document(response.content)
    assert abs(_faces(document) - budget) <= WINDOW * budget
    # one primitive, one material: the baked atlas
    assert len(document["meshes"]) == 1 and len(document["meshes"][0]["primitives"]) == 1
    assert len(document["materials"]) == 1
    assert "baseColorTexture" in document["materials"][0]["pbrMetallicRoughness"]
    assert_valid(gltf_validator, response.content, "merged level")
    # by faces: the same budget, the same level
    by_faces = client.get(f"/meshes/{body['id']}/lod", params={"faces": budget, "format": "glb"})
    assert by_faces.content == response.content
    # a part's level is the mesh's, byte for byte
    part = client.get(f"/meshes/{body['id']}/parts/0/lod", params={"ratio": 0.02,
                                                                  "format": "glb"})
    assert part.content == response.content and part.headers["etag"] == response.headers["etag"]


def test_reach_none_and_the_json_form_keep_edge_collapse(served):
    client, body = served
    mesh_id = body["id"]
    kept = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.02, "format": "glb",
                                                        "reach": "none"})
    assert kept.status_code == 200 and _faces(_document(kept.content)) == body["base_faces"]
    # packets apply to the json form: it stays the base level
    state = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.02}).json()
    assert state["face_count"] == body["base_faces"]
    clustered = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.02, "format": "glb",
                                                             "reach": "cluster"})
    budget = round(0.02 * body["faces"])
    assert abs(_faces(_document(clustered.content)) - budget) <= WINDOW * budget
    assert "materials" not in _document(clustered.content)     # positions only
    bad = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.02, "format": "glb",
                                                       "reach": "sloppy"})
    assert bad.status_code == 422 and "reach" in bad.text


def test_a_merged_level_is_cached_and_etagged(served, monkeypatch):
    client, body = served
    made = []
    real = lods_route.reached_level
    monkeypatch.setattr(lods_route, "reached_level",
                        lambda *args, **kwargs: made.append(1) or real(*args, **kwargs))
    params = {"ratio": 0.01, "format": "glb"}
    first = client.get(f"/meshes/{body['id']}/lod", params=params)
    assert first.status_code == 200 and made == [1]
    again = client.get(f"/meshes/{body['id']}/lod", params=params,
                       headers={"If-None-Match": first.headers["etag"]})
    assert again.status_code == 304 and again.headers["etag"] == first.headers["etag"]
    fresh = client.get(f"/meshes/{body['id']}/lod", params=params)
    assert fresh.content == first.content and made == [1]      # from the cache, not made again
    other = client.get(f"/meshes/{body['id']}/lod", params={**params, "reach": "none"})
    assert other.headers["etag"] != first.headers["etag"]


def test_a_chain_reaches_its_budgets_with_the_baked_material_joined(served, gltf_validator):
    client, body = served
    response = client.get(f"/meshes/{body['id']}/chain", params={"lods": "1,0.1,0.02"})
    assert response.status_code == 200, response.text
    document = _document(response.content)
    faces = [_faces(document, m) for m in range(len(document["meshes"]))]
    assert faces[0] == body["faces"]
    for ratio, count in zip((0.1, 0.02), faces[1:]):
        budget = round(ratio * body["faces"])
        assert abs(count - budget) <= WINDOW * budget, (ratio, count, budget)
    # the source's material and each merged level's baked one, in one list (0.1 is
    # within edge collapse's reach: one sphere's coarsest is 4 of its 80 faces)
    merged = [r for r in (0.1, 0.02) if body["base_faces"] > REACH_SLACK * r * body["faces"]]
    assert merged == [0.02] and len(document["materials"]) == 1 + len(merged)
    assert_valid(gltf_validator, response.content, "chain with merged levels")
    stuck = client.get(f"/meshes/{body['id']}/chain", params={"lods": "1,0.1,0.02",
                                                               "reach": "none"})
    assert _faces(_document(stuck.content), 2) == body["base_faces"]
    # a chain edge collapse reaches is the same whatever reach says, ETag too
    near = [client.get(f"/meshes/{body['id']}/chain", params={"lods": "1,0.9", "reach": r})
            for r in ("none", "merge")]
    assert near[0].headers["etag"] == near[1].headers["etag"]
    assert near[0].content == near[1].content


def test_a_static_scene_far_level_is_one_mesh(tmp_path, gltf_validator):
    options = {"data_dir": tmp_path / "data", "warm_kernels": False}
    with TestClient(create_app(Settings(**options))) as client:
        created = client.post("/meshes", files={"file": ("scene.glb", static_scene())})
        assert created.status_code == 202, created.text
        body = settled(client, created.json()["id"], timeout=180)
        assert body["status"] == "ready" and body["scene"], body["failure"]
        mesh_id = body["id"]
        budget = round(0.02 * body["faces"])
        response = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.02,
                                                                "format": "glb"})
        assert response.status_code == 200, response.text
        document = _document(response.content)
        assert len(document["meshes"]) == 1 and len(document["meshes"][0]["primitives"]) == 1
        assert abs(_faces(document) - budget) <= WINDOW * budget
        assert_valid(gltf_validator, response.content, "merged scene level")
        # reach=none: every part at its coarsest, one mesh each
        kept = _document(client.get(f"/meshes/{mesh_id}/lod", params={
            "ratio": 0.02, "format": "glb", "reach": "none"}).content)
        assert len(kept["meshes"]) == 3
        assert sum(_faces(kept, m) for m in range(3)) == body["base_faces"]
        # a scene's chain keeps edge collapse's levels (MSFT_lod is per node)
        chain = client.get(f"/meshes/{mesh_id}/chain", params={"lods": "1,0.02"})
        assert chain.status_code == 200


def test_a_moving_scene_far_level_merges_what_moves_together(tmp_path, gltf_validator):
    """The assembled scene of ``tests/scene/test_groups.py`` (static walls, an
    animated carrier of two meshes, a spinner): its far level holds one merged
    node per group and the spinner as a part, as ``export --separate`` writes it."""
    options = {"data_dir": tmp_path / "data", "warm_kernels": False}
    with TestClient(create_app(Settings(**options))) as client:
        created = client.post("/meshes", files={"file": ("moving.glb", assembled_scene())})
        assert created.status_code == 202, created.text
        body = settled(client, created.json()["id"], timeout=180)
        assert body["status"] == "ready", body["failure"]
        response = client.get(f"/meshes/{body['id']}/lod", params={"ratio": 0.02,
                                                                   "format": "glb"})
        assert response.status_code == 200, response.text
        assert_valid(gltf_validator, response.content, "a moving scene's far level")
        document = _document(response.content)
        nodes = document["nodes"]
        assert sum(node.get("name") == "merged" for node in nodes) == 2
        assert "mesh" in nodes[7] and all("mesh" not in nodes[n] for n in (1, 2, 3, 5, 6))
        assert sorted(c["target"]["node"] for c in document["animations"][0]["channels"]) \
            == [4, 7]
