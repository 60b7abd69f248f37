"""The HTTP API through the real app (TestClient), with a temporary data directory."""

import json
import struct
import time

import numpy as np
import pytest
import schemathesis
import trimesh
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.service.store import LOADED_BYTES_PER_TRIANGLE
from lodserver.io import load_mesh
from lodserver import packets
from lodserver.packets import apply_packet, state_from_json

from ..meshes import DATA, textured_spot_glb
from . import settled as _wait_ready

SPOT = (DATA / "spot.obj").read_bytes()
TOKEN = "s3cret-token"


def _client(tmp_path, **overrides):
    options = {"data_dir": tmp_path / "data", "warm_kernels": False, **overrides}
    return TestClient(create_app(Settings(**options)))


def _upload(client, content=SPOT, filename="spot.obj", headers=None, **fields):
    return client.post("/meshes", files={"file": (filename, content)}, data=fields,
                       headers=headers or {})


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A client with spot uploaded and built (shared: building costs a second)."""
    with _client(tmp_path_factory.mktemp("api")) as client:
        created = _upload(client, name="cow")
        assert created.status_code == 202, created.text
        mesh_id = created.json()["id"]
        assert created.headers["location"] == f"/meshes/{mesh_id}"
        assert _wait_ready(client, mesh_id)["status"] == "ready"
        yield client, mesh_id


def test_ready_mesh_reports_counts_and_error_curve(served):
    client, mesh_id = served
    body = client.get(f"/meshes/{mesh_id}").json()
    assert body["name"] == "cow" and body["progress"] == 1.0 and body["failure"] is None
    assert body["vertices"] == 2930 and body["faces"] == 5856
    assert body["splits"] == body["vertices"] - body["base_vertices"]
    errors = [point["error"] for point in body["error_curve"]]
    assert errors == sorted(errors)  # coarser ratios, larger errors
    assert mesh_id in [m["id"] for m in client.get("/meshes").json()["meshes"]]


@pytest.mark.parametrize("fmt", ["glb", "obj", "ply"])
def test_lod_files_hold_the_level(served, fmt, tmp_path):
    client, mesh_id = served
    response = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": 500, "format": fmt})
    assert response.status_code == 200
    # through lodserver's loader, which welds the render vertices of a seam
    # (one per wedge in GLB and OBJ) back into positions
    path = tmp_path / f"level.{fmt}"
    path.write_bytes(response.content)
    mesh, _ = load_mesh(path)
    assert mesh.vertex_count == 500
    if fmt != "ply":            # PLY carries positions only
        assert mesh.attributes is not None and mesh.attributes.columns("TEXCOORD_0") is not None


def test_lod_criteria_pick_levels(served):
    client, mesh_id = served

    def by(**query):
        return client.get(f"/meshes/{mesh_id}/lod", params=query).json()

    assert by(vertices=300)["vertex_count"] == 300
    assert by(faces=1000)["face_count"] <= 1000
    assert by(ratio=1.0)["face_count"] == 5856
    assert by(error=0.0)["vertex_count"] == 2930
    assert by(error=0.05)["error"] <= 0.05


def test_packets_between_lods_are_exact(served):
    client, mesh_id = served

    def lod(vertices):
        return client.get(f"/meshes/{mesh_id}/lod", params={"vertices": vertices}).json()

    def splits(a, b):
        return client.get(f"/meshes/{mesh_id}/splits", params={"from": a, "to": b}).content

    state = state_from_json(lod(100))
    assert [g.name for g in state.attribute_grids] == ["TEXCOORD_0"]   # spot has UVs
    for target in (1500, 2930, 4, 700, 100):
        state = apply_packet(state, splits(state.level, target))
        expected = state_from_json(lod(target))
        assert np.array_equal(state.positions, expected.positions)
        assert np.array_equal(state.faces, expected.faces)
        assert np.array_equal(state.wedges, expected.wedges)
        assert np.array_equal(state.corners, expected.corners)


@pytest.fixture(scope="module")
def textured(served):
    """spot with its texture, uploaded as a GLB beside the plain spot."""
    client, _ = served
    created = _upload(client, content=textured_spot_glb(), filename="spot.glb")
    assert created.status_code == 202, created.text
    mesh_id = created.json()["id"]
    assert _wait_ready(client, mesh_id)["status"] == "ready"
    return client, mesh_id


def test_json_levels_hold_wedges_materials_and_where_to_find_them(textured):
    client, mesh_id = textured
    document = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5}).json()
    assert document["layout"] == [["TEXCOORD_0", 2]]
    grid = document["attribute_grid"]["TEXCOORD_0"]
    assert grid["encoding"] == "linear" and grid["bits"] == 12
    wedges, corners = np.array(document["wedges"]), np.array(document["corners"])
    assert wedges.shape[1] == 2 and 0 <= wedges.min() and wedges.max() < 2**12
    assert corners.shape == (document["face_count"], 3) and corners.max() < len(wedges)
    assert document["face_material"] == [0] * document["face_count"]
    assert document["material_faces"] == [5856, 0]
    assert document["materials"] == f"/meshes/{mesh_id}/materials"
    state = state_from_json(document)
    there = state_from_json(client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 1}).json())
    state = apply_packet(state, client.get(f"/meshes/{mesh_id}/splits", params={
        "from": state.level, "to": there.level}).content)
    for name in ("positions", "faces", "wedges", "corners", "face_material"):
        assert np.array_equal(getattr(state, name), getattr(there, name)), name


def test_materials_and_images_are_served_with_their_types(textured):
    client, mesh_id = textured
    response = client.get(f"/meshes/{mesh_id}/materials")
    # unversioned URLs: cached briefly, then revalidated (versions: tests/api/test_cdn.py)
    assert response.status_code == 200 and "max-age=60" in response.headers["cache-control"]
    document = response.json()
    assert document["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"] == {"index": 0}
    assert document["textures"] == [{"source": 0, "sampler": 0}]
    (image,) = document["images"]
    assert image["uri"] == "images/0" and image["mimeType"] == "image/png"
    png = client.get(f"/meshes/{mesh_id}/{image['uri']}")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.content == (DATA / "spot_texture.png").read_bytes()
    assert "max-age=60" in png.headers["cache-control"]
    again = client.get(f"/meshes/{mesh_id}/images/0", headers={"If-None-Match": png.headers["etag"]})
    assert again.status_code == 304
    missing = client.get(f"/meshes/{mesh_id}/images/1")
    assert missing.status_code == 404 and "no image 1" in missing.json()["message"]


def test_a_mesh_without_materials_says_so(served):
    client, _ = served
    plain = SPOT.replace(b"mtllib spot.mtl\nusemtl spot\n", b"")   # spot, no material
    mesh_id = _wait_ready(client, _upload(client, plain).json()["id"])["id"]
    response = client.get(f"/meshes/{mesh_id}/materials")
    assert response.status_code == 404 and "no materials" in response.json()["message"]
    assert client.get(f"/meshes/{mesh_id}/images/0").status_code == 404
    document = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5}).json()
    assert "materials" not in document and "face_material" not in document


@pytest.mark.parametrize("path, params", [("lod", {"ratio": 0.1}), ("lod", {"vertices": 9,
                         "format": "glb"}), ("splits", {"from": 10, "to": 20}),
                         ("chain", {"lods": "1,0.3"})])
def test_immutable_responses_carry_etags_and_answer_304(served, path, params):
    client, mesh_id = served
    first = client.get(f"/meshes/{mesh_id}/{path}", params=params)
    assert first.status_code == 200
    assert "max-age=60" in first.headers["cache-control"]      # unversioned (test_cdn.py)
    again = client.get(f"/meshes/{mesh_id}/{path}", params=params,
                       headers={"If-None-Match": first.headers["etag"]})
    assert again.status_code == 304 and again.headers["etag"] == first.headers["etag"]
    other = client.get(f"/meshes/{mesh_id}/{path}", params=params,
                       headers={"If-None-Match": '"something-else"'})
    assert other.status_code == 200 and other.content == first.content


def test_chain_is_one_glb_of_linked_levels(served):
    client, mesh_id = served
    response = client.get(f"/meshes/{mesh_id}/chain", params={"lods": "1,0.5,0.1"})
    assert response.status_code == 200
    assert response.headers["content-type"] == "model/gltf-binary"
    data = response.content
    length, _ = struct.unpack_from("<I4s", data, 12)
    document = json.loads(data[20:20 + length])
    assert document["nodes"][0]["extensions"]["MSFT_lod"]["ids"] == [1, 2]
    faces = [document["accessors"][m["primitives"][0]["indices"]]["count"] // 3
             for m in document["meshes"]]
    assert faces[0] == 5856 and faces[0] > faces[1] > faces[2]
    # the same levels as the lod endpoint's glb
    level = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5, "format": "glb"}).content
    length, _ = struct.unpack_from("<I4s", level, 12)
    single = json.loads(level[20:20 + length])
    assert single["accessors"][single["meshes"][0]["primitives"][0]["indices"]]["count"] == (
        3 * faces[1])


@pytest.mark.parametrize("path, params, status, message", [
    ("lod", {}, 422, "exactly one"),
    ("lod", {"vertices": 10, "faces": 10}, 422, "exactly one"),
    ("lod", {"ratio": 0}, 422, "ratio"),
    ("lod", {"ratio": "nan"}, 422, "ratio"),
    ("lod", {"ratio": 1.5}, 422, "ratio"),
    ("lod", {"vertices": -3}, 422, "vertices"),
    ("lod", {"faces": "many"}, 422, "faces"),
    ("lod", {"error": -1}, 422, "error"),
    ("lod", {"ratio": 0.5, "format": "fbx"}, 422, "format"),
    ("lod", {"ratio": 0.5, "bits": 40}, 422, "bits"),
    ("splits", {"from": 10}, 422, "to"),
    ("splits", {"from": 1, "to": 20}, 422, "from must be a level"),
    ("splits", {"from": 10, "to": 999999}, 422, "to must be a level"),
    ("chain", {"lods": "1,2"}, 422, "(0, 1]"),
    ("chain", {"lods": "0.2,0.5"}, 422, "strictly decreasing"),
    ("chain", {"lods": "1,half"}, 422, "comma-separated"),
    ("chain", {"lods": ",".join(str(1 - i / 20) for i in range(17))}, 422, "at most 16"),
    ("chain", {"lods": "1,0.9,0.8,0.7,0.6,0.5"}, 422, "at most 4 times the mesh's faces"),
    ("chain", {"reach": "sloppy"}, 422, "reach"),
])
def test_bad_level_parameters_are_422_with_a_message(served, path, params, status, message):
    client, mesh_id = served
    response = client.get(f"/meshes/{mesh_id}/{path}", params=params)
    assert response.status_code == status
    assert message in response.json()["message"]


@pytest.mark.parametrize("mesh_id", ["AAAAAAAAAAAAAAAAAAAAAA", "nope", "..%2F..%2Fetc"])
def test_unknown_ids_are_404(served, mesh_id):
    client, _ = served
    for path in ("", "/lod?ratio=0.5", "/splits?from=4&to=5", "/chain", "/materials",
                 "/images/0"):
        response = client.get(f"/meshes/{mesh_id}{path}")
        assert response.status_code == 404 and response.json()["message"]
    assert client.delete("/meshes/AAAAAAAAAAAAAAAAAAAAAA").status_code == 404


NAN_OBJ = b"v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n"
# spot cut off inside a face line: a truncated download, not a smaller mesh
_HALF = SPOT[: len(SPOT) // 2]
TRUNCATED_OBJ = _HALF[: _HALF.rindex(b"\nf ")] + b"\nf 739/1 735/"


@pytest.mark.parametrize("content, filename, status, message", [
    (b"this is not a mesh at all\n", "notes.obj", 422, "no faces"),
    (b"\x00\x01binary junk" * 50, "junk.ply", 422, "cannot load"),
    (TRUNCATED_OBJ, "spot.obj", 422, "cannot load spot.obj: line 6526 is a face with fewer"),
    (NAN_OBJ, "nan.obj", 422, "NaN"),
    (b"", "empty.obj", 422, "empty"),
    (SPOT, "spot.fbx", 415, "must end in"),
])
def test_bad_uploads_are_4xx_with_a_message(served, content, filename, status, message):
    client, _ = served
    before = len(client.get("/meshes").json()["meshes"])
    response = _upload(client, content, filename)
    assert response.status_code == status, response.text
    assert message in response.json()["message"]
    assert filename in response.json()["message"]
    assert len(client.get("/meshes").json()["meshes"]) == before


def test_malformed_forms_are_refused(served):
    client, _ = served
    assert client.post("/meshes", json={"file": "x"}).status_code == 415
    response = client.post("/meshes", files={"other": ("a.obj", b"x")})
    assert response.status_code == 422 and "'file'" in response.json()["message"]
    response = _upload(client, boundary_weight="-1")
    assert response.status_code == 422 and "boundary_weight" in response.json()["message"]
    response = _upload(client, colour="red")
    assert response.status_code == 422 and "colour" in response.json()["message"]


def test_limits_on_bytes_and_triangles(tmp_path):
    with _client(tmp_path, max_upload_bytes=10_000, max_triangles=100) as client:
        response = _upload(client)
        assert response.status_code == 413 and "10000" in response.json()["message"]
        small = trimesh.creation.icosphere(2)   # 320 triangles
        obj = trimesh.exchange.obj.export_obj(small).encode()
        response = _upload(client, obj, "ball.obj")
        assert response.status_code == 413 and "320 triangles" in response.json()["message"]
        assert client.get("/meshes").json()["meshes"] == []


def test_upload_limit_holds_without_content_length(tmp_path):
    with _client(tmp_path, max_upload_bytes=10_000) as client:
        boundary = "xyz"
        head = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; "
                f"filename=\"spot.obj\"\r\n\r\n").encode()

        def chunks():
            yield head
            for i in range(0, len(SPOT), 4096):
                yield SPOT[i:i + 4096]
            yield f"\r\n--{boundary}--\r\n".encode()

        response = client.post("/meshes", content=chunks(),
                               headers={"content-type": f"multipart/form-data; boundary={boundary}"})
        assert response.status_code == 413


def test_write_endpoints_need_the_token(tmp_path):
    with _client(tmp_path, token=TOKEN) as client:
        assert _upload(client).status_code == 401
        wrong = _upload(client, headers={"Authorization": "Bearer nope"})
        assert wrong.status_code == 401 and "wrong" in wrong.json()["message"]
        assert wrong.headers["www-authenticate"] == "Bearer"
        good = _upload(client, headers={"Authorization": f"Bearer {TOKEN}"})
        assert good.status_code == 202
        mesh_id = good.json()["id"]
        assert client.get(f"/meshes/{mesh_id}").status_code == 200   # reads stay open
        assert client.delete(f"/meshes/{mesh_id}").status_code == 401
        deleted = client.delete(f"/meshes/{mesh_id}", headers={"Authorization": f"Bearer {TOKEN}"})
        assert deleted.status_code == 204
        assert client.get(f"/meshes/{mesh_id}").status_code == 404


def test_not_ready_and_failed_meshes_are_409(tmp_path):
    with _client(tmp_path) as client:
        store = client.app.state.store
        source = tmp_path / "x.obj"
        source.write_bytes(SPOT)
        # registered but never submitted: stays queued
        record = store.create(name="x", source=source, file_type="obj", options={})
        response = client.get(f"/meshes/{record.id}/lod", params={"ratio": 0.5})
        assert response.status_code == 409 and "not built yet" in response.json()["message"]
        store.mark_failed(mesh_id=record.id, reason="it was a teapot")
        assert client.get(f"/meshes/{record.id}").json()["failure"] == "it was a teapot"
        response = client.get(f"/meshes/{record.id}/splits", params={"from": 4, "to": 5})
        assert response.status_code == 409 and "teapot" in response.json()["message"]


def test_restart_serves_ready_meshes_and_resumes_interrupted_builds(tmp_path):
    with _client(tmp_path) as client:
        ready_id = _upload(client).json()["id"]
        assert _wait_ready(client, ready_id)["status"] == "ready"
        lod = client.get(f"/meshes/{ready_id}/lod", params={"ratio": 0.2})
        store = client.app.state.store
        source = tmp_path / "y.obj"
        source.write_bytes(SPOT)
        # as if the process died mid-build
        interrupted = store.create(name="y", source=source, file_type="obj", options={})
        store.mark_building(mesh_id=interrupted.id)
    with _client(tmp_path) as client:
        # after a restart nothing has encoded the mesh's packet records ...
        pm = client.app.state.store.load(mesh_id=ready_id).single
        assert pm not in packets.record_cache
        again = client.get(f"/meshes/{ready_id}/lod", params={"ratio": 0.2})
        assert again.status_code == 200 and again.content == lod.content
        assert again.headers["etag"] == lod.headers["etag"]
        assert _wait_ready(client, interrupted.id)["status"] == "ready"
        # ... and fetching a json level, where packet clients start, begins that
        deadline = time.monotonic() + 60
        while not packets.records_ready(pm):
            assert time.monotonic() < deadline, "the packet records were not prepared"
            time.sleep(0.05)


def test_delete_removes_the_mesh_and_its_files(tmp_path):
    with _client(tmp_path) as client:
        mesh_id = _upload(client).json()["id"]
        _wait_ready(client, mesh_id)
        assert client.delete(f"/meshes/{mesh_id}").status_code == 204
        assert client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 1}).status_code == 404
        assert not list((tmp_path / "data").rglob(f"{mesh_id}*"))


def test_cors_and_health(tmp_path):
    with _client(tmp_path, cors_origins="https://viewer.example") as client:
        assert client.get("/healthz").json() == {"status": "ok", "ready": True}
        response = client.get("/healthz", headers={"Origin": "https://viewer.example"})
        assert response.headers["access-control-allow-origin"] == "https://viewer.example"
        response = client.get("/healthz", headers={"Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in response.headers


@settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
@given(params=st.dictionaries(
    st.sampled_from(["vertices", "faces", "ratio", "error", "format", "bits", "from", "to",
                     "lods", "reach", "version"]),
    st.one_of(st.integers(-2**40, 2**40), st.floats(allow_nan=True), st.text(max_size=5),
              st.sampled_from(["json", "glb", "inf", "-0", "1e309"])), max_size=4),
       path=st.sampled_from(["lod", "splits", "chain", "progressive"]))
def test_random_level_queries_never_fail_the_server(served, params, path):
    client, mesh_id = served
    response = client.get(f"/meshes/{mesh_id}/{path}", params=params)
    assert response.status_code in (200, 422), response.text
    if response.status_code == 422:
        assert response.json()["message"]


def test_schema_fuzz_finds_no_server_errors(tmp_path):
    """Schemathesis cases for every operation in the OpenAPI schema, a few each."""
    app = create_app(Settings(data_dir=tmp_path / "data", warm_kernels=False))
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    for result in schema.get_all_operations():
        operation = result.ok()

        @settings(max_examples=10, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(case=operation.as_strategy())
        def check(case):
            response = case.call()
            assert response.status_code < 500, f"{case.method} {case.path}: {response.text}"
            if response.status_code >= 400:
                assert response.json()["message"]

        check()


def test_build_options_reach_the_build(tmp_path):
    """method, attributes, weights and volume from the form land in the build."""
    with _client(tmp_path) as client:
        clustered = _upload(client, method="cluster").json()["id"]
        plain = _upload(client, attributes="false", preserve_volume="false").json()["id"]
        weighted = _upload(client, uv_weight="0.05", normal_weight="0.01").json()["id"]
        for mesh_id in (clustered, plain, weighted):
            assert _wait_ready(client, mesh_id)["status"] == "ready"

        def options(mesh_id):
            return client.get(f"/meshes/{mesh_id}").json()["options"]

        assert options(clustered)["method"] == "cluster"
        assert options(plain)["attributes"] is False and options(plain)["preserve_volume"] is False
        assert (options(weighted)["normal_weight"], options(weighted)["uv_weight"]) == (0.01, 0.05)
        # what was built: octree clustering merges down to a triangle (edge
        # collapse stops at a tetrahedron-like base), and the geometry-only
        # build serves no wedges while the others do
        bases = {i: client.get(f"/meshes/{i}").json()["base_vertices"]
                 for i in (clustered, weighted)}
        assert bases[clustered] == 3 and bases[weighted] >= 4
        assert "wedges" not in client.get(f"/meshes/{plain}/lod", params={"ratio": 0.5}).json()
        assert "wedges" in client.get(f"/meshes/{weighted}/lod", params={"ratio": 0.5}).json()
        assert _upload(client, method="voxels").status_code == 422
        assert _upload(client, uv_weight="0").status_code == 422


def test_loaded_meshes_setting_reaches_the_store(tmp_path, monkeypatch):
    monkeypatch.setenv("LODSERVER_LOADED_MESHES", "3")
    assert Settings(data_dir=tmp_path / "data").loaded_meshes == 3
    with _client(tmp_path, loaded_meshes=2) as client:
        assert client.app.state.store.loaded_meshes == 2
    monkeypatch.setenv("LODSERVER_LOADED_MESHES", "0")
    with pytest.raises(ValueError):
        Settings(data_dir=tmp_path / "data")


def test_loaded_bytes_setting_defaults_to_a_mesh_at_the_triangle_limit(tmp_path, monkeypatch):
    assert Settings(data_dir=tmp_path / "data", max_triangles=10**7).loaded_bytes == \
        LOADED_BYTES_PER_TRIANGLE * 10**7
    assert Settings(data_dir=tmp_path / "data", max_triangles=100).loaded_bytes == 2**26
    monkeypatch.setenv("LODSERVER_LOADED_BYTES", str(300 * 2**20))
    with _client(tmp_path) as client:
        assert client.app.state.store.loaded_bytes == 300 * 2**20
    monkeypatch.setenv("LODSERVER_LOADED_BYTES", "1000")
    with pytest.raises(ValueError):
        Settings(data_dir=tmp_path / "data")
