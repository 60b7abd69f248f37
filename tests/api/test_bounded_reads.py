"""Bounded reads through the real app: body files, the heavy-request limit,
packets at other bits, security headers, image media types (api/bodies.py,
api/caching.py, api/headers.py)."""

import base64
import hashlib
import math
import re
import shutil
import threading
import time

import pytest
from fastapi.testclient import TestClient

from lodserver.api import caching
from lodserver.api.main import create_app
from lodserver.api.routes import lods, materials
from lodserver.api.settings import Settings
from lodserver.service.levels import chain_bytes, level_bytes

from ..conftest import headless_chromium
from ..meshes import DATA, textured_spot_glb
from ..server import serve as serve_process
from ..server import upload_and_wait


def _app(data_dir, **overrides):
    return create_app(Settings(data_dir=data_dir, warm_kernels=False, **overrides))


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A data dir holding spot, built once; (data dir, mesh id)."""
    data = tmp_path_factory.mktemp("built") / "data"
    with TestClient(_app(data)) as client:
        created = client.post("/meshes", files={"file": ("spot.obj", (DATA / "spot.obj")
                                                          .read_bytes())})
        assert created.status_code == 202, created.text
        mesh_id = created.json()["id"]
        deadline = time.monotonic() + 120
        while client.get(f"/meshes/{mesh_id}").json()["status"] != "ready":
            assert time.monotonic() < deadline, "spot was not built"
            time.sleep(0.1)
    return data, mesh_id


@pytest.fixture
def serve(built, tmp_path):
    """Start an app with these settings on a copy of the built data dir, stopping
    the one started before (a restart): ``serve(**settings)`` -> (TestClient,
    mesh id, data dir)."""
    source, mesh_id = built
    data = tmp_path / "data"
    shutil.copytree(source, data, ignore=shutil.ignore_patterns("bodies"))
    running = []

    def stop():
        while running:
            running.pop().__exit__(None, None, None)

    def start(raise_server_exceptions=True, **settings):
        stop()
        client = TestClient(_app(data, **settings),
                            raise_server_exceptions=raise_server_exceptions)
        client.__enter__()
        running.append(client)
        return client, mesh_id, data

    yield start
    stop()


def _counting(monkeypatch, module, name):
    """Replace ``module.name`` (or ``module[name]``, a table's entry) by a wrapper
    counting its calls; the count list."""
    table = isinstance(module, dict)
    calls, real = [], module[name] if table else getattr(module, name)

    def counted(*args, **kwargs):
        calls.append(args[1:])
        return real(*args, **kwargs)

    (monkeypatch.setitem if table else monkeypatch.setattr)(module, name, counted)
    return calls


def _body_files(data_dir):
    folder = data_dir / "bodies"
    return {p.name: p.stat().st_size for p in folder.iterdir()} if folder.is_dir() else {}


# ---- body files --------------------------------------------------------------------
def test_a_large_chain_is_encoded_once_written_to_a_file_and_streamed_from_it(serve,
                                                                            monkeypatch):
    encodes = _counting(monkeypatch, lods, "encode_lod_chain")
    client, mesh_id, data = serve(body_file_bytes=1024)
    params = {"lods": "1,0.5,0.25,0.1"}
    first = client.get(f"/meshes/{mesh_id}/chain", params=params)
    assert first.status_code == 200 and len(first.content) > 1024
    name = first.headers["etag"].strip('"')
    assert _body_files(data) == {name: len(first.content)}
    assert (data / "bodies" / name).read_bytes() == first.content
    again = client.get(f"/meshes/{mesh_id}/chain", params=params)
    assert again.status_code == 200 and again.content == first.content
    assert len(encodes) == 1
    for response in (first, again):
        assert response.headers["etag"] == first.headers["etag"]
        assert "max-age=60" in response.headers["cache-control"]   # unversioned (test_cdn.py)
        assert response.headers["content-type"] == "model/gltf-binary"
        assert response.headers["content-length"] == str(len(first.content))
        assert response.headers["content-disposition"] == f'inline; filename="{mesh_id}-lods.glb"'
    # streamed from the file: byte ranges work too
    part = client.get(f"/meshes/{mesh_id}/chain", params=params, headers={"Range": "bytes=4-11"})
    assert part.status_code == 206 and part.content == first.content[4:12]
    # a level above the threshold goes the same way; a small one stays in memory
    level = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 1, "format": "json"})
    small = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": 4, "format": "json"})
    assert level.headers["etag"].strip('"') in _body_files(data)
    assert len(small.content) < 1024 and small.headers["etag"].strip('"') not in _body_files(data)
    assert len(encodes) == 1


def test_body_files_outlive_a_restart_and_temporary_files_do_not(serve, monkeypatch):
    encodes = _counting(monkeypatch, lods, "encode_lod_chain")
    client, mesh_id, data = serve(body_file_bytes=1024)
    first = client.get(f"/meshes/{mesh_id}/chain")
    (data / "bodies" / ".tmp-interrupted").write_bytes(b"half a body")
    client, _, _ = serve(body_file_bytes=1024)
    assert not (data / "bodies" / ".tmp-interrupted").exists()
    again = client.get(f"/meshes/{mesh_id}/chain")
    assert again.content == first.content and len(encodes) == 1


def test_the_body_files_stay_under_their_byte_bound(serve):
    client, mesh_id, data = serve(body_file_bytes=1024)
    size = len(client.get(f"/meshes/{mesh_id}/chain", params={"lods": "1,0.5"}).content)
    bound = int(2.5 * size)      # room for two chains of about that size
    client, _, _ = serve(body_file_bytes=1024, body_cache_bytes=bound)
    chains = ["1,0.5", "1,0.6", "1,0.4", "1,0.55", "1,0.45"]
    bodies = {}
    for lods_ in chains:
        response = client.get(f"/meshes/{mesh_id}/chain", params={"lods": lods_})
        assert response.status_code == 200
        bodies[lods_] = response.content
        held = _body_files(data)
        assert sum(held.values()) <= bound, held
        assert response.headers["etag"].strip('"') in held    # the newest is kept
    assert len(_body_files(data)) == 2
    # an evicted body is encoded again, the same bytes
    assert client.get(f"/meshes/{mesh_id}/chain", params={"lods": chains[0]}).content == \
        bodies[chains[0]]
    assert sum(_body_files(data).values()) <= bound
    # a body larger than the whole bound is sent from memory and not kept
    client, _, _ = serve(body_file_bytes=1024, body_cache_bytes=1000)
    assert _body_files(data) == {}              # shrunk to the new bound at start
    response = client.get(f"/meshes/{mesh_id}/chain", params={"lods": chains[1]})
    assert response.status_code == 200 and response.content == bodies[chains[1]]
    assert _body_files(data) == {}


def test_a_leased_file_is_not_removed_to_make_room(tmp_path):
    files = caching.BodyFiles(tmp_path / "bodies", capacity=10)
    a, b = '"' + "a" * 32 + '"', '"' + "b" * 32 + '"'
    assert files.store(a, b"12345678")
    path, size = files.lease(a)
    assert size == 8
    assert not files.store(b, b"87654321")      # a is being sent: no room for b
    assert path.read_bytes() == b"12345678"
    files.release(a)
    assert files.store(b, b"87654321") and files.lease(a) is None
    assert files.size == 8


def test_json_written_in_slices_is_the_bytes_orjson_writes_whole():
    """export.json_in_slices (orjson frees the GIL only between calls) changes no byte."""
    import numpy as np
    import orjson

    from lodserver.service.levels import JSON_SLICE_ROWS, json_in_slices

    rng = np.random.default_rng(1)
    for rows in (3, JSON_SLICE_ROWS, JSON_SLICE_ROWS + 1, 3 * JSON_SLICE_ROWS + 7):
        document = {"level": 5, "positions": rng.integers(0, 2**16, (rows, 3), dtype=np.int32),
                    "faces": rng.integers(0, 2**31, (rows, 3)), "error": 0.25,
                    "face_material": rng.integers(-1, 4, rows, dtype=np.int32),
                    "materials": "/meshes/x/materials"}
        whole = orjson.dumps(document, option=orjson.OPT_SERIALIZE_NUMPY)
        assert json_in_slices(document) == whole
        view = json_in_slices(document, copy=False)
        assert bytes(view) == whole and (rows <= JSON_SLICE_ROWS or view.readonly)


# ---- the heavy-request limit ---------------------------------------------------------
# spot is small: slots of 1 KiB make every body of it heavy (light: at most 32 bytes)
TINY_SLOTS = 1024


def test_heavy_requests_past_the_limit_are_503_with_retry_after(serve):
    # a wait long against any request's own time on a loaded machine, so that "it
    # waited for a slot" and "it did not" are told apart by the clock without doubt
    wait = 2.0
    client, mesh_id, _ = serve(heavy_requests=1, heavy_wait_seconds=wait, body_file_bytes=1024,
                               heavy_slot_bytes=TINY_SLOTS)
    cached = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": 500})
    filed = client.get(f"/meshes/{mesh_id}/chain")
    heavy = client.app.state.bodies.heavy
    with heavy.hold(1, timeout=0):             # every slot taken, deterministically
        for path, params in (("lod", {"vertices": 600}), ("chain", {"lods": "1,0.3"}),
                             ("splits", {"from": 100, "to": 200, "bits": 12})):
            began = time.monotonic()
            response = client.get(f"/meshes/{mesh_id}/{path}", params=params)
            waited = time.monotonic() - began
            assert response.status_code == 503, (path, response.text)
            assert response.headers["retry-after"] == str(math.ceil(wait))
            assert "busy" in response.json()["message"]
            assert response.headers["x-content-type-options"] == "nosniff"
            assert wait * 0.9 < waited < wait + 30
        # what a cache holds, in memory or in a file, is answered without waiting
        began = time.monotonic()
        again = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": 500})
        assert again.status_code == 200 and again.content == cached.content
        again = client.get(f"/meshes/{mesh_id}/chain")
        assert again.status_code == 200 and again.content == filed.content
        assert time.monotonic() - began < wait     # neither waited for the slot
    assert client.get(f"/meshes/{mesh_id}/lod", params={"vertices": 600}).status_code == 200
    assert heavy.free == 1


def test_a_request_waits_briefly_for_a_slot(serve):
    client, mesh_id, _ = serve(heavy_requests=1, heavy_wait_seconds=5,
                               heavy_slot_bytes=TINY_SLOTS)
    heavy = client.app.state.bodies.heavy
    held, go = threading.Event(), threading.Event()

    def hold():
        with heavy.hold(1, timeout=0):
            held.set()
            go.wait(5)

    holder = threading.Thread(target=hold)
    holder.start()
    held.wait(5)
    threading.Timer(0.3, go.set).start()
    response = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": 700})
    holder.join()
    assert response.status_code == 200


def test_concurrent_requests_for_one_body_encode_it_once(serve, monkeypatch):
    real = lods.encode_lod_chain
    calls = []

    def slow(*args):
        calls.append(1)
        time.sleep(0.5)        # long enough for every request below to arrive meanwhile
        return real(*args)

    monkeypatch.setattr(lods, "encode_lod_chain", slow)
    # light work is not shared, just done: tiny slots make the chain heavy
    client, mesh_id, _ = serve(heavy_requests=2, heavy_wait_seconds=10,
                               heavy_slot_bytes=TINY_SLOTS)
    results = []

    def get():
        results.append(client.get(f"/meshes/{mesh_id}/chain", params={"lods": "1,0.2"}))

    threads = [threading.Thread(target=get) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert [r.status_code for r in results] == [200] * 4
    assert len({r.content for r in results}) == 1 and len(calls) == 1


def test_bodies_take_slots_by_their_estimated_bytes(serve):
    """A level estimated at one slot's bytes takes one slot; a chain estimated
    past every slot's bytes takes them all, and waits while one is held."""
    client, mesh_id, _ = serve()
    pm = client.app.state.store.load(mesh_id=mesh_id).single
    level, ratios = pm.level_for(ratio=0.1), [1.0, 0.5, 0.25, 0.125]
    slot = level_bytes(pm, level, "json")
    chain = chain_bytes(pm, [pm.level_for(ratio=r) for r in ratios])
    assert chain > 3 * slot                     # so the chain needs all 3 slots
    client, mesh_id, _ = serve(heavy_requests=3, heavy_wait_seconds=0.2, heavy_slot_bytes=slot)
    heavy = client.app.state.bodies.heavy
    assert heavy.weight(slot) == 1 and heavy.weight(chain) == 3
    assert heavy.weight(slot // 32) == 0       # light: no slot at all
    with heavy.hold(2, timeout=0):             # two slots busy: one left, for the level
        assert client.get(f"/meshes/{mesh_id}/lod", params={"vertices": level}).status_code \
            == 200
        chained = client.get(f"/meshes/{mesh_id}/chain",
                             params={"lods": ",".join(map(str, ratios))})
        assert chained.status_code == 503 and chained.headers["retry-after"] == "1"
    assert heavy.free == 3


# ---- packets at other bits -------------------------------------------------------------
def test_packets_at_other_bits_are_encoded_once(serve, monkeypatch):
    encodes = _counting(monkeypatch, lods.PACKET_WRITERS, 3)    # version 3, the default
    client, mesh_id, _ = serve()
    params = {"from": 50, "to": 2500, "bits": 11}
    first = client.get(f"/meshes/{mesh_id}/splits", params=params)
    again = client.get(f"/meshes/{mesh_id}/splits", params=params)
    assert first.status_code == again.status_code == 200 and again.content == first.content
    assert len(encodes) == 1
    default = client.get(f"/meshes/{mesh_id}/splits", params={"from": 50, "to": 2500})
    assert default.content != first.content and len(encodes) == 2


# ---- headers -------------------------------------------------------------------------
def test_every_response_says_nosniff(serve, monkeypatch):
    client, mesh_id, _ = serve(raise_server_exceptions=False)
    ok = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5})
    not_modified = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.5},
                              headers={"If-None-Match": ok.headers["etag"]})
    missing = client.get("/meshes/no-such-mesh/lod", params={"ratio": 0.5})
    invalid = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 7})

    def broken(*args, **kwargs):
        raise RuntimeError("an encoder bug")

    monkeypatch.setattr(lods, "encode_level", broken)
    failed = client.get(f"/meshes/{mesh_id}/lod", params={"ratio": 0.3})
    statuses = [r.status_code for r in (ok, not_modified, missing, invalid, failed)]
    assert statuses == [200, 304, 404, 422, 500]
    for response in (ok, not_modified, missing, invalid, failed):
        assert response.headers["x-content-type-options"] == "nosniff", response.status_code
        assert response.headers["content-security-policy"] == \
            "default-src 'none'; frame-ancestors 'none'"
    assert "x-content-type-options" in client.get("/healthz").headers


def _importmap_source(html: str) -> str:
    text = re.search(r'<script type="importmap">(.*?)</script>', html, re.S).group(1)
    digest = hashlib.sha256(text.replace("\r\n", "\n").encode()).digest()
    return f"'sha256-{base64.b64encode(digest).decode()}'"


def test_the_viewer_has_a_strict_content_security_policy(serve, tmp_path):
    client, _, _ = serve()
    page = client.get("/viewer/")
    assert page.status_code == 200
    policy = dict(part.strip().split(" ", 1) for part in
                  page.headers["content-security-policy"].split(";"))
    assert policy["default-src"] == "'self'"
    assert policy["script-src"].split() == ["'self'", _importmap_source(page.text)]
    assert policy["style-src"].split()[0] == "'self'"
    assert all(s.startswith("'sha256-") for s in policy["style-src"].split()[1:])
    assert "'unsafe-inline'" not in page.headers["content-security-policy"]
    assert "'unsafe-eval'" not in page.headers["content-security-policy"]
    assert policy["object-src"] == "'none'" and policy["frame-ancestors"] == "'none'"
    assert page.headers["x-frame-options"] == "DENY"
    assert page.headers["referrer-policy"] == "no-referrer"
    assert page.headers["x-content-type-options"] == "nosniff"
    script = client.get("/viewer/main.js")
    assert script.headers["content-security-policy"] == page.headers["content-security-policy"]
    redirect = client.get("/viewer", follow_redirects=False)
    assert redirect.status_code == 307 and "content-security-policy" in redirect.headers


def test_the_policy_follows_the_import_map_of_the_served_page(serve, tmp_path):
    static = tmp_path / "static"
    static.mkdir()
    html = ('<!doctype html><html><head><script type="importmap">\r\n{"imports": {"three": '
            '"./three.js"}}\r\n</script><style>body { margin: 0 }</style></head></html>')
    (static / "index.html").write_text(html, newline="")
    client, _, _ = serve(static_dir=static)
    # the page as served: its URLs moved into its versioned path (routes/viewer_files.py)
    page = client.get("/viewer/")
    policy = page.headers["content-security-policy"]
    assert "./v/" in page.text and _importmap_source(page.text) in policy
    style = hashlib.sha256(b"body { margin: 0 }").digest()
    assert f"style-src 'self' 'sha256-{base64.b64encode(style).decode()}'" in policy
    changed = html.replace("three.js", "three.module.js")
    (static / "index.html").write_text(changed + " ", newline="")
    again = client.get("/viewer/")
    policy = again.headers["content-security-policy"]
    assert "three.module.js" in again.text
    assert _importmap_source(again.text) in policy and _importmap_source(page.text) not in policy


def test_the_viewer_runs_under_its_policy_in_chromium(tmp_path):
    """A real server's viewer page loads a textured mesh to full detail with the
    server's own CSP, and Chromium's console reports no violation of it."""
    path = tmp_path / "spot.glb"
    path.write_bytes(textured_spot_glb())
    with serve_process(tmp_path / "data") as client, headless_chromium() as browser:
        mesh = upload_and_wait(client, path)
        page = browser.new_page()
        console, errors, loaded = [], [], []
        page.on("console", lambda message: console.append(f"{message.type}: {message.text}"))
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.on("requestfinished", lambda request: loaded.append(request.url))
        full = mesh["vertices"]     # full detail asked for: the default stops at 1 px
        response = page.goto(f"{client.base_url}/viewer/?mesh={mesh['id']}&level={full}")
        assert "script-src 'self' 'sha256-" in response.all_headers()["content-security-policy"]
        page.wait_for_function("() => window.lodViewer?.status().level != null")
        status = page.evaluate("lodViewer.settled()")
        assert status["level"] == mesh["vertices"] and status["error"] is None, status
        # at the mesh's version: /images/0?v=...
        page.wait_for_function("() => performance.getEntriesByType('resource')"
                               ".some((entry) => /\\/images\\/0(\\?|$)/.test(entry.name))")
    assert any(url.split("?")[0].endswith(f"/meshes/{mesh['id']}/images/0") for url in loaded)
    assert any("/vendor/three/" in url for url in loaded)     # the import map resolved
    violations = [line for line in console if "Content Security Policy" in line
                  or "Refused to" in line]
    assert not violations and not errors, (violations, errors)


# ---- images ----------------------------------------------------------------------------
@pytest.mark.parametrize("media", ["text/html", "image/svg+xml", "application/octet-stream"])
def test_an_image_of_another_type_is_never_served_as_that_type(serve, monkeypatch, media):
    monkeypatch.setattr(materials, "image_of",
                        lambda pm, index: (b"<script>alert(document.cookie)</script>", media))
    client, mesh_id, _ = serve()
    response = client.get(f"/meshes/{mesh_id}/images/0")
    assert response.status_code == 404
    assert response.headers["content-type"] == "application/json"
    assert "not a PNG, JPEG, WebP or KTX2 image" in response.json()["message"]
    assert b"<script>" not in response.content
    monkeypatch.setattr(materials, "image_of", lambda pm, index: (b"\x89PNG\r\n\x1a\n", "image/png"))
    served = client.get(f"/meshes/{mesh_id}/images/0")
    assert served.status_code == 200 and served.headers["content-type"] == "image/png"
    assert served.headers["x-content-type-options"] == "nosniff"
