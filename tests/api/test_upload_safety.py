"""Uploads through the real app: streamed into the data directory, parsed in a
bounded worker pool under a memory limit, and every failure (bad file, full
queue, memory bomb, full disk, corrupt artefact) answered with one sentence
that names no server path and leaves nothing behind."""

import errno
import json
import os
import sqlite3
import struct
import tempfile
import threading
import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from lodserver.service import store as store_module
from lodserver.api import upload as upload_module
from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.io.limits import LimitError

from ..conftest import record_calls
from ..meshes import DATA
from . import settled

SPOT = (DATA / "spot.obj").read_bytes()


def _client(tmp_path, **overrides):
    options = {"data_dir": tmp_path / "data", "warm_kernels": False, **overrides}
    return TestClient(create_app(Settings(**options)))


def _upload(client, content=SPOT, filename="spot.obj", **fields):
    return client.post("/meshes", files={"file": (filename, content)}, data=fields)


def _leftovers(data_dir):
    """Everything in data_dir/tmp and every partial (.tmp) file in sources/artefacts."""
    found = [p for p in (data_dir / "tmp").rglob("*")]
    for folder in ("sources", "artefacts"):
        found += [p for p in (data_dir / folder).glob(".*")]
    return found


def _no_server_path(message, *paths):
    for path in (*paths, tempfile.gettempdir(), "/tmp/"):
        assert str(path) not in message, message


def _padded_spot(size):
    """spot.obj padded with comment lines to about ``size`` bytes (over Starlette's
    1 MB in-memory spool, so a spooling parser would have to use a temp file)."""
    pad = b"# padding to make the upload larger than a memory spool\n"
    return SPOT + pad * max(0, (size - len(SPOT)) // len(pad))


@pytest.fixture
def no_system_tmp(tmp_path, monkeypatch):
    """Any temporary file made in the default temp dir fails while this is on."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "no-such-temp-dir"))


def test_upload_streams_into_data_dir_and_leaves_nothing(tmp_path, monkeypatch, no_system_tmp):
    seen = []
    finish = upload_module._FormWriter.finish

    def recording(writer):
        upload = finish(writer)
        seen.append((upload.path.parent.parent, upload.path.stat().st_size))
        return upload

    monkeypatch.setattr(upload_module._FormWriter, "finish", recording)
    data = tmp_path / "data"
    body = _padded_spot(3 * 2**20)
    with _client(tmp_path) as client:
        created = _upload(client, body)
        assert created.status_code == 202, created.text
        assert seen == [(data / "tmp", len(body))]        # streamed whole into data/tmp
        assert settled(client, created.json()["id"])["status"] == "ready"
        assert _leftovers(data) == []
        # a refused file, an unsupported type and a form error leave nothing either
        assert _upload(client, b"not a mesh\n", "notes.obj").status_code == 422
        assert _upload(client, body, "spot.fbx").status_code == 415
        assert _upload(client, body, boundary_weight="-1").status_code == 422
        assert _leftovers(data) == []
        assert len(client.get("/meshes").json()["meshes"]) == 1


def test_oversized_uploads_are_413_and_leave_nothing(tmp_path, no_system_tmp):
    data = tmp_path / "data"
    with _client(tmp_path, max_upload_bytes=2**20) as client:
        response = _upload(client, _padded_spot(3 * 2**20))
        assert response.status_code == 413 and str(2**20) in response.json()["message"]
        boundary = "b0undary"

        def chunks():       # no Content-Length: counted as it streams
            yield (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; "
                   f"filename=\"big.obj\"\r\n\r\n").encode()
            for _ in range(64):
                yield b"# " + b"x" * 65533 + b"\n"
            yield f"\r\n--{boundary}--\r\n".encode()

        response = client.post("/meshes", content=chunks(), headers={
            "content-type": f"multipart/form-data; boundary={boundary}"})
        assert response.status_code == 413
        assert _leftovers(data) == [] and client.get("/meshes").json()["meshes"] == []


@pytest.mark.parametrize("parts, message", [
    ([("name", "a")] * 2, "repeated"),
    ([(f"f{i}", "1") for i in range(17)], "more than 16 fields"),
    ([("name", "x" * 70_000)], "longer than"),
    # several files are a set (tests/api/test_upload_files.py): two meshes need 'main'
    ([("file", ("a.obj", SPOT)), ("file", ("b.obj", SPOT))], "form field 'main'"),
    ([("file", ("a.obj", SPOT)), ("file", ("a.obj", SPOT))], "two files named 'a.obj'"),
    ([("mesh", ("a.obj", SPOT))], "'file'"),
])
def test_malformed_forms_are_422_with_a_sentence(tmp_path, parts, message):
    files = [(name, value) for name, value in parts if isinstance(value, tuple)]
    fields = {}
    for name, value in parts:
        if not isinstance(value, tuple):
            fields.setdefault(name, []).append(value)
    if not files:
        files = [("file", ("spot.obj", SPOT))]
    with _client(tmp_path) as client:
        response = client.post("/meshes", files=files, data=fields)
        assert response.status_code == 422, response.text
        assert message in response.json()["message"]
        assert _leftovers(tmp_path / "data") == []


@pytest.mark.parametrize("headers, message", [
    (f"Content-Disposition: form-data; name=\"file\"; filename=\"{'a' * 20_000}.obj\"",
     "Maximum header size exceeded"),
    ("Content-Disposition: form-data; name=\"file\"; filename=\"a.obj\"\r\n"
     + "".join(f"X-{i}: 1\r\n" for i in range(20)), "Maximum header count exceeded"),
])
def test_oversized_part_headers_are_422(tmp_path, headers, message):
    """A part's headers are held in memory while parsed: python-multipart bounds
    their size and count, and a breach is a 422 like any malformed form."""
    boundary = "b0und4ry"
    body = (f"--{boundary}\r\n{headers}\r\n\r\n").encode() + SPOT + f"\r\n--{boundary}--\r\n".encode()
    with _client(tmp_path) as client:
        response = client.post("/meshes", content=body, headers={
            "content-type": f"multipart/form-data; boundary={boundary}"})
        assert response.status_code == 422, response.text
        assert message in response.json()["message"]
        assert _leftovers(tmp_path / "data") == []


def test_a_truncated_body_is_422(tmp_path):
    boundary = "zz"
    body = (f"--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; "
            f"filename=\"spot.obj\"\r\n\r\n").encode() + SPOT[:1000]
    with _client(tmp_path) as client:
        response = client.post("/meshes", content=body, headers={
            "content-type": f"multipart/form-data; boundary={boundary}"})
        assert response.status_code == 422 and "closing boundary" in response.json()["message"]
        assert _leftovers(tmp_path / "data") == []


def _occupy(parser, seconds):
    """Hold the parse pool's only worker for ``seconds`` (a sleep in the worker)."""
    thread = threading.Thread(target=parser.call, args=(time.sleep, seconds), daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while parser.admitted < 1:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    return thread


def test_a_full_parse_queue_is_503_with_retry_after(tmp_path):
    with _client(tmp_path, parse_workers=1, parse_queue=0) as client:
        busy = _occupy(client.app.state.jobs.parser, 3)
        response = _upload(client)
        assert response.status_code == 503, response.text
        assert int(response.headers["retry-after"]) > 0
        assert "try again" in response.json()["message"]
        assert _leftovers(tmp_path / "data") == []
        busy.join()
        created = _upload(client)       # the worker is free again
        assert created.status_code == 202, created.text
        assert settled(client, created.json()["id"])["status"] == "ready"


def test_uploads_wait_in_the_queue_rather_than_fail(tmp_path):
    with _client(tmp_path, parse_workers=1, parse_queue=2) as client:
        busy = _occupy(client.app.state.jobs.parser, 2)
        results = []
        threads = [threading.Thread(target=lambda: results.append(_upload(client).status_code))
                   for _ in range(2)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        busy.join()
        assert results == [202, 202]


def _instancing_bomb_glb(instances=60_000, grid=24):
    """A small GLB whose one mesh of 2 * grid**2 triangles is placed by ``instances``
    nodes: a few kilobytes that flatten to ~70 million triangles (gigabytes)."""
    x, y = np.meshgrid(np.arange(grid + 1, dtype=np.float32), np.arange(grid + 1, dtype=np.float32))
    positions = np.stack([x.ravel(), y.ravel(), np.zeros(x.size, np.float32)], 1)
    idx = np.arange((grid + 1) ** 2, dtype=np.uint32).reshape(grid + 1, grid + 1)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.uint32)
    blob = positions.tobytes() + faces.tobytes()
    document = {
        "asset": {"version": "2.0"},
        "buffers": [{"byteLength": len(blob)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": positions.nbytes},
                        {"buffer": 0, "byteOffset": positions.nbytes, "byteLength": faces.nbytes}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(positions), "type": "VEC3",
             "min": positions.min(0).tolist(), "max": positions.max(0).tolist()},
            {"bufferView": 1, "componentType": 5125, "count": faces.size, "type": "SCALAR"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "nodes": [{"mesh": 0, "translation": [0, 0, float(i)]} for i in range(instances)],
        "scenes": [{"nodes": list(range(instances))}], "scene": 0,
    }
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    blob += b"\0" * (-len(blob) % 4)
    chunks = (struct.pack("<I4s", len(text), b"JSON") + text
              + struct.pack("<I4s", len(blob), b"BIN\0") + blob)
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def _primitive_bomb_glb(primitives=4096, grid=64):
    """A small GLB whose one mesh, placed once, has ``primitives`` primitives all drawing
    one grid of 2 * grid**2 triangles: 300 kilobytes that decode to ~33 million
    triangles. (Many nodes placing one mesh, ``_instancing_bomb_glb``, is a scene
    now, kept as one mesh: no bomb.)"""
    glb = _instancing_bomb_glb(instances=1, grid=grid)
    length = struct.unpack_from("<I", glb, 12)[0]
    document = json.loads(glb[20:20 + length])
    document["meshes"][0]["primitives"] *= primitives
    text = json.dumps(document, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    chunks = struct.pack("<I4s", len(text), b"JSON") + text + glb[20 + length:]
    return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


def test_the_parse_memory_limit_turns_a_bomb_into_413(tmp_path):
    bomb = _primitive_bomb_glb()
    assert len(bomb) < 4 * 2**20
    with _client(tmp_path, max_triangles=200_000_000, parse_memory_bytes=2**30) as client:
        response = _upload(client, bomb, "bomb.glb")
        assert response.status_code == 413, response.text
        message = response.json()["message"]
        assert message.startswith("cannot load bomb.glb:") and "memory" in message
        assert message.count(". ") == 0                   # one sentence
        _no_server_path(message, tmp_path)
        assert client.get("/meshes").json()["meshes"] == []
        assert _leftovers(tmp_path / "data") == []
        # the worker survived or was replaced: the next upload is parsed
        created = _upload(client)
        assert created.status_code == 202, created.text


def test_a_dead_parse_worker_refuses_its_file_and_the_pool_restarts(tmp_path):
    with _client(tmp_path) as client:
        parser = client.app.state.jobs.parser
        with pytest.raises(LimitError, match="ran out of memory or crashed"):
            parser.call(os._exit, 1)
        created = _upload(client)
        assert created.status_code == 202, created.text


def _enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device", "/somewhere/secret")


def test_disk_full_while_receiving_is_507_and_leaves_nothing(tmp_path, monkeypatch):
    with _client(tmp_path) as client:
        kept = _upload(client)
        assert settled(client, kept.json()["id"])["status"] == "ready"
        before = client.get("/meshes").json()
        monkeypatch.setattr(upload_module._FormWriter, "_part_data", _enospc)
        response = _upload(client, _padded_spot(2 * 2**20))
        assert response.status_code == 507, response.text
        assert "disk space" in response.json()["message"]
        _no_server_path(response.json()["message"], "/somewhere")
        assert client.get("/meshes").json() == before
        assert _leftovers(tmp_path / "data") == []
        assert list((tmp_path / "data" / "sources").iterdir()) == []


def test_disk_full_while_storing_is_507_and_leaves_nothing(tmp_path, monkeypatch):
    with _client(tmp_path) as client:
        store = client.app.state.store
        monkeypatch.setattr(store_module.shutil, "move", _enospc)
        response = _upload(client)
        assert response.status_code == 507 and "disk space" in response.json()["message"]
        monkeypatch.undo()

        class FullCatalogue:
            """The catalogue connection, whose inserts find the disk full."""

            def __init__(self, db):
                self.db = db

            def execute(self, sql, *args):
                if sql.startswith("INSERT"):
                    raise sqlite3.OperationalError("database or disk is full")
                return self.db.execute(sql, *args)

            def __getattr__(self, name):
                return getattr(self.db, name)

        real = store.catalog._db
        store.catalog._db = FullCatalogue(real)
        try:
            response = _upload(client)
        finally:
            store.catalog._db = real
        assert response.status_code == 507 and "disk space" in response.json()["message"]
        assert client.get("/meshes").json()["meshes"] == []
        assert list((tmp_path / "data" / "sources").iterdir()) == []
        assert _leftovers(tmp_path / "data") == []


def test_disk_full_while_building_says_so(tmp_path, monkeypatch):
    monkeypatch.setattr(store_module, "save_asset", _enospc)
    with _client(tmp_path) as client:
        mesh_id = _upload(client).json()["id"]
        body = settled(client, mesh_id)
        assert body["status"] == "failed"
        assert body["failure"].startswith("the server ran out of disk space while building")
        assert list((tmp_path / "data" / "artefacts").iterdir()) == []
        assert list((tmp_path / "data" / "sources").iterdir()) == []


def test_a_corrupt_artefact_is_quarantined_once_and_answered_409(tmp_path, monkeypatch):
    with _client(tmp_path) as client:
        mesh_id = _upload(client).json()["id"]
        assert settled(client, mesh_id)["status"] == "ready"
    artefact, = (tmp_path / "data" / "artefacts").glob(f"{mesh_id}.*.pm")
    data = bytearray(artefact.read_bytes())
    data[len(data) // 2] ^= 0xFF
    artefact.write_bytes(bytes(data))
    reads = record_calls(monkeypatch, store_module, "load_artefact")
    with _client(tmp_path) as client:          # a restart: nothing loaded in memory
        for path in ("lod?ratio=0.5", "splits?from=4&to=10", "lod?vertices=100&format=glb",
                     "materials", "chain"):
            response = client.get(f"/meshes/{mesh_id}/{path}")
            assert response.status_code == 409, response.text
            message = response.json()["message"]
            assert "stored artefact is corrupt" in message and "checksum" in message
            _no_server_path(message, tmp_path)
        assert len(reads) == 1
        body = client.get(f"/meshes/{mesh_id}").json()
        assert body["status"] == "failed" and "corrupt" in body["failure"]
    assert not artefact.exists()
    assert (tmp_path / "data" / "quarantine" / artefact.name).read_bytes() == bytes(data)
    # the failure is stored: a second restart still does not read the file
    with _client(tmp_path) as client:
        assert client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 1}).status_code == 409
        assert len(reads) == 1


GLTF_REFERENCES = ["../../../../../etc/passwd", "/etc/passwd", "file:///etc/hostname",
                   "missing.bin", "%2e%2e/%2e%2e/secret.bin"]


@pytest.mark.parametrize("uri", GLTF_REFERENCES)
def test_messages_never_name_a_server_path(tmp_path, uri):
    document = {"asset": {"version": "2.0"}, "buffers": [{"uri": uri, "byteLength": 36}],
                "bufferViews": [{"buffer": 0, "byteLength": 36}],
                "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3,
                               "type": "VEC3"}],
                "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
                "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]}
    with _client(tmp_path) as client:
        response = _upload(client, json.dumps(document).encode(), "scene.gltf")
        assert 400 <= response.status_code < 500, response.text
        message = response.json()["message"]
        assert "scene.gltf" in message
        _no_server_path(message, tmp_path, tmp_path / "data")
        for bad in (b"v 0 0 0\nf 1 2 3\n", b"ply\nformat ascii 1.0\nelement vertex 9\n",
                    b"\x00" * 100, b"solid x\nfacet normal nan\n"):
            for name in ("a.obj", "b.ply", "c.stl", "d.off", "e.glb"):
                response = _upload(client, bad, name)
                assert 400 <= response.status_code < 500, response.text
                _no_server_path(response.json()["message"], tmp_path)
        assert _leftovers(tmp_path / "data") == []


def test_healthz_is_not_ready_until_the_kernels_are_warm(tmp_path, monkeypatch):
    from lodserver.service import jobs as jobs_module

    release = threading.Event()
    monkeypatch.setattr(jobs_module, "warm_up", lambda: release.wait(30))
    with _client(tmp_path, warm_kernels=True) as client:
        response = client.get("/healthz")
        assert response.status_code == 503
        assert response.json() == {"status": "ok", "ready": False}
        release.set()
        deadline = time.monotonic() + 10
        while (response := client.get("/healthz")).status_code != 200:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert response.json() == {"status": "ok", "ready": True}
        assert client.app.state.jobs.warmed_at is not None


def test_a_resumed_build_parses_its_source_alone(tmp_path):
    """A build resumed after a restart parses the stored source in the pool with the
    upload's root rule: it cannot read the other sources stored beside it."""
    other = tmp_path / "other.obj"
    other.write_bytes(SPOT)
    gltf = tmp_path / "scene.gltf"
    with _client(tmp_path) as client:
        store = client.app.state.store
        neighbour = store.create(name="other", source=other, file_type="obj", options={})
        document = {"asset": {"version": "2.0"},
                    "buffers": [{"uri": f"{neighbour.id}.obj", "byteLength": 36}],
                    "bufferViews": [{"buffer": 0, "byteLength": 36}],
                    "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3,
                                   "type": "VEC3"}],
                    "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
                    "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]}
        gltf.write_text(json.dumps(document))
        resumed = store.create(name="scene.gltf", source=gltf, file_type="gltf", options={})
    with _client(tmp_path) as client:           # the restart resumes both
        body = settled(client, resumed.id)
        assert body["status"] == "failed" and "scene.gltf" in body["failure"]
        _no_server_path(body["failure"], tmp_path)
        assert settled(client, neighbour.id)["status"] == "ready"
        assert _leftovers(tmp_path / "data") == []


def test_opening_the_store_removes_what_a_crash_left(tmp_path):
    """Scratch folders, partial files and sources or artefacts that no row names go;
    everything a row names stays."""
    with _client(tmp_path) as client:
        kept = _upload(client).json()["id"]
        assert settled(client, kept)["status"] == "ready"
    data = tmp_path / "data"
    stale = [data / "tmp" / "upload-x1" / "big.obj", data / "tmp" / "build-y2" / "a.gltf",
             data / "sources" / f".{'B' * 22}.obj.tmp",
             data / "artefacts" / f".{'C' * 22}.pm.x.tmp",
             data / "sources" / f"{'D' * 22}.obj", data / "artefacts" / f"{'E' * 22}.pm"]
    for path in stale:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"left by a crash")
    artefact, = (data / "artefacts").glob(f"{kept}.*.pm")
    before = artefact.read_bytes()
    with _client(tmp_path) as client:
        assert [path for path in stale if path.exists()] == []
        assert list((data / "tmp").iterdir()) == []
        assert artefact.read_bytes() == before
        assert client.get(f"/meshes/{kept}/lod", params={"ratio": 0.5}).status_code == 200
