"""The progressive file on a plain static host: written by ``lodserver export
--progressive``, served by a few lines of HTTP server with ``Range`` support and
the CORS headers a CDN sends (another origin than the app's page), opened by the
README's example page with the file's URL. The mesh stops at the level whose
error projects within 1 CSS pixel and reaches full detail, each with exactly
the json level's state; the host's log shows range requests (206), never a whole
file; a skinned, animated scene does the same while its clip plays; and a host
that ignores ``Range`` (200) is read with one GET.
"""

from __future__ import annotations

import functools
import http.server
import json
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import trimesh

from lodserver.packets import apply_packet, decode_any, state_from_json
from lodserver.packets.grids import default_bits
from lodserver.progressive.mesh import ProgressiveMesh
from lodserver.service.progressive_file import read_index
from lodserver.service.levels import encode_level

from ..meshes import SHARED
from .test_three import HASH_JS, PAGE, REFUSALS_JS, SETTLED_JS, STATIC, VIEWPORT, _Quiet
from .test_three import _per_unit
from .test_viewer import _expected

REPO = Path(__file__).resolve().parents[2]
FOX = SHARED / "scenes" / "Fox.glb"
_RANGE = re.compile(r"bytes=(\d+)-(\d*)")


class _FileHost(http.server.SimpleHTTPRequestHandler):
    """A static host as a CDN answers: Range honoured (one range, 206) unless
    ``ranges`` is off, CORS for any origin, every request logged."""

    ranges = True
    log: list

    def end_headers(self):
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Access-Control-Expose-Headers", "Content-Range, Content-Length")
        super().end_headers()

    def do_OPTIONS(self):
        self.send_response(204)
        self.send_header("Access-Control-Allow-Headers", "Range")
        self.send_header("Access-Control-Allow-Methods", "GET, HEAD")
        self.end_headers()

    def do_GET(self):
        path = Path(self.translate_path(self.path))
        asked = self.headers.get("Range")
        if not path.is_file():
            self.log.append(("GET", self.path, asked, 404))
            return self.send_error(404)
        data = path.read_bytes()
        match = _RANGE.fullmatch(asked or "") if self.ranges else None
        if match:
            start = int(match[1])
            stop = min(len(data), int(match[2]) + 1 if match[2] else len(data))
            if start >= len(data):
                self.log.append(("GET", self.path, asked, 416))
                self.send_response(416)
                self.send_header("Content-Range", f"bytes */{len(data)}")
                self.end_headers()
                return
            self.log.append(("GET", self.path, asked, 206))
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{stop - 1}/{len(data)}")
            body = data[start:stop]
        else:
            self.log.append(("GET", self.path, asked, 200))
            self.send_response(200)
            body = data
        self.send_header("Content-Type", "model/gltf-binary")
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Accept-Ranges", "bytes")
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


def _serve(handler):
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd, f"http://127.0.0.1:{httpd.server_address[1]}"


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    """The app's own origin: its page (PAGE, importing the module from its own
    copy of static/, as an app that copied it would) and three.js."""
    folder = tmp_path_factory.mktemp("static-app")
    (folder / "three").symlink_to(STATIC / "vendor" / "three", target_is_directory=True)
    (folder / "lodserver").symlink_to(STATIC, target_is_directory=True)
    (folder / "index.html").write_text(PAGE.replace("LODSERVER/viewer/", "/lodserver/"))
    httpd, origin = _serve(functools.partial(_Quiet, directory=str(folder)))
    yield origin
    httpd.shutdown()
    httpd.server_close()


@pytest.fixture(scope="module")
def host(tmp_path_factory):
    """The static host of the files: (folder, origin, handler class)."""
    folder = tmp_path_factory.mktemp("static-host")
    handler = type("Host", (_FileHost,), {"log": [], "ranges": True})
    httpd, origin = _serve(functools.partial(handler, directory=str(folder)))
    yield folder, origin, handler
    httpd.shutdown()
    httpd.server_close()


def _cli(*args):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    result = subprocess.run([sys.executable, "-m", "lodserver.cli", *map(str, args)],
                            capture_output=True, text=True, env=env, timeout=900)
    assert result.returncode == 0, result.stderr
    return result


@pytest.fixture(scope="module")
def sphere(host, tmp_path_factory):
    """An icosphere of 10,242 vertices built to a .pm, and its progressive file
    on the host: (ProgressiveMesh, file name)."""
    folder = tmp_path_factory.mktemp("static-sphere")
    (folder / "sphere.ply").write_bytes(trimesh.creation.icosphere(5).export(file_type="ply"))
    _cli("build", folder / "sphere.ply", "-o", folder / "sphere.pm")
    _cli("export", folder / "sphere.pm", "--progressive", "-o", host[0] / "sphere.glb")
    return ProgressiveMesh.load(folder / "sphere.pm"), "sphere.glb"


class _Levels:
    """The json level of a progressive mesh as a client fetches it (for _expected),
    at the grid of ``bits`` (the default's when None)."""

    def __init__(self, pm, bits=None):
        self.pm, self.bits = pm, bits

    def get(self, route, params):
        data = bytes(encode_level(self.pm, params["vertices"], file_type="json",
                                  bits=self.bits))
        return type("Reply", (), {"json": lambda _: json.loads(data)})()


class _Decoded:
    """The state the reference decoder reaches from a progressive file's base
    through its split chunks up to ``level``, as a json level (for _expected)."""

    def __init__(self, data: bytes, part: int):
        self.data, self.part = data, part

    def get(self, route, params):
        record, start = read_index(self.data)
        part = next(p for p in record["parts"] if p["part"] == self.part)
        base, at, length = part["base"]
        state = state_from_json(json.loads(self.data[start + at:start + at + length]))
        for _, end, at, length in part["splits"]:
            if end > params["vertices"]:
                break
            state = apply_packet(state, decode_any(self.data[start + at:start + at + length]))
        document = {"vertex_count": state.level, "face_count": len(state.faces),
                    "positions": state.positions, "faces": state.faces}
        if state.attribute_grids:
            document.update(layout=True, wedges=state.wedges, corners=state.corners)
        if state.face_material is not None:
            document["face_material"] = state.face_material
        return type("Reply", (), {"json": lambda _: document})()


def _open(chromium, app, url):
    page = chromium.new_page(viewport=VIEWPORT)
    page.errors = []
    page.on("pageerror", lambda error: page.errors.append(error))
    page.on("console", lambda message: message.type == "error" and page.errors.append(message.text))
    page.goto(f"{app}/index.html?mesh={url}")
    page.wait_for_function("() => window.object?.target != null || window.object?.error",
                           timeout=120_000)
    return page


def _state(page, expression="window.object.state"):
    return page.evaluate(HASH_JS.join(["(", f")({expression})"]))


def test_a_page_streams_the_file_from_a_static_host_with_range_requests(chromium, app, host,
                                                                         sphere):
    folder, origin, handler = host
    pm, name = sphere
    handler.log.clear()
    page = _open(chromium, app, f"{origin}/{name}")
    try:
        status = page.evaluate(SETTLED_JS)
        assert status["error"] is None and status["full"] == pm.vertex_count, status
        level = status["level"]
        assert pm.base_vertices < level < pm.vertex_count, status
        # the 1 px level: within the budget, as with a server (the file holds
        # chunk ends, so the level is the first chunk end whose error is within it)
        bounds = {"min": pm.positions.min(axis=0).tolist(),
                  "max": pm.positions.max(axis=0).tolist()}
        assert pm.error_at_level(level) * _per_unit(page, bounds) <= 1.5
        assert _state(page) == dict(zip(("faces", "hash"), _expected(_Levels(pm), "", level)))

        page.evaluate(f"window.object.setLevel({pm.vertex_count})")
        full = page.evaluate(SETTLED_JS)
        assert full["level"] == pm.vertex_count and full["error"] is None, full
        assert _state(page) == dict(zip(("faces", "hash"), _expected(_Levels(pm), "",
                                                                     pm.vertex_count)))
        # and back down: the collapse chunks
        page.evaluate(f"window.object.setLevel({pm.base_vertices})")
        base = page.evaluate(SETTLED_JS)
        assert base["level"] == pm.base_vertices, base
        assert _state(page) == dict(zip(("faces", "hash"), _expected(_Levels(pm), "",
                                                                     pm.base_vertices)))
        assert not page.errors, page.errors
        size = (folder / name).stat().st_size
        statuses = [entry[3] for entry in handler.log]
        assert statuses and set(statuses) == {206}, handler.log
        assert all(entry[2] and entry[2] != f"bytes=0-{size - 1}" for entry in handler.log)
        # header and JSON, the base, the first level's chunks, then the rest
        assert handler.log[0][2].startswith("bytes=0-"), handler.log
        print("range requests of the session:", handler.log)
    finally:
        page.close()


def test_a_host_that_ignores_range_is_read_with_one_get(chromium, app, host, sphere):
    folder, origin, handler = host
    pm, name = sphere
    handler.log.clear()
    handler.ranges = False
    try:
        page = _open(chromium, app, f"{origin}/{name}")
        page.evaluate(f"window.object.setLevel({pm.vertex_count})")
        full = page.evaluate(SETTLED_JS)
        assert full["level"] == pm.vertex_count and full["error"] is None, full
        assert _state(page) == dict(zip(("faces", "hash"), _expected(_Levels(pm), "",
                                                                     pm.vertex_count)))
        assert [entry[3] for entry in handler.log] == [200], handler.log
        assert not page.errors, page.errors
        page.close()
    finally:
        handler.ranges = True


def test_a_file_on_another_grid_reaches_the_json_levels_at_its_bits(chromium, app, host,
                                                                     sphere, tmp_path):
    """``export --progressive --bits K``: the page reaches the 1 px level and full
    detail with the state of ``/lod?format=json&bits=K`` there."""
    folder, origin, _ = host
    pm, _ = sphere
    bits = default_bits(pm) - 3
    pm.save(tmp_path / "sphere.pm")
    _cli("export", tmp_path / "sphere.pm", "--progressive", "--bits", bits,
         "-o", folder / "sphere-bits.glb")
    assert read_index((folder / "sphere-bits.glb").read_bytes())[0]["parts"][0]["bits"] == bits
    page = _open(chromium, app, f"{origin}/sphere-bits.glb")
    try:
        status = page.evaluate(SETTLED_JS)
        level = status["level"]
        assert status["error"] is None and pm.base_vertices < level < pm.vertex_count, status
        assert _state(page) == dict(zip(("faces", "hash"), _expected(_Levels(pm, bits), "",
                                                                     level)))
        # not the default grid's state: the file's grid is what the page holds
        assert _state(page) != dict(zip(("faces", "hash"), _expected(_Levels(pm), "", level)))
        page.evaluate(f"window.object.setLevel({pm.vertex_count})")
        full = page.evaluate(SETTLED_JS)
        assert full["level"] == pm.vertex_count and full["error"] is None, full
        assert _state(page) == dict(zip(("faces", "hash"), _expected(_Levels(pm, bits), "",
                                                                     pm.vertex_count)))
        assert not page.errors, page.errors
    finally:
        page.close()


@pytest.fixture(scope="module")
def fox(host, tmp_path_factory):
    if not FOX.is_file():
        pytest.skip(f"shared scene not found at {FOX}")
    _cli("export", FOX, "--progressive", "-o", host[0] / "fox.glb")
    return "fox.glb"


def test_a_skinned_scene_streams_from_its_file_and_plays(chromium, app, host, fox):
    folder, origin, handler = host
    handler.log.clear()
    page = _open(chromium, app, f"{origin}/{fox}")
    try:
        info = page.evaluate("""() => ({ type: window.object.type,
            clips: window.object.animations.map((clip) => clip.name) })""")
        assert info["type"] == "ProgressiveScene" and info["clips"], info
        status = page.evaluate(SETTLED_JS)
        assert status["error"] is None, status
        page.evaluate(f"window.object.setLevel({status['full']})")
        full = page.evaluate(SETTLED_JS)
        assert full["level"] == full["full"], full
        time = page.evaluate("window.object.mixer.time")
        page.wait_for_function(f"() => window.object.mixer.time > {time}")
        shown = page.evaluate("""() => {
            const mesh = window.object.parts[0].meshes[0];
            return { skinned: mesh.isSkinnedMesh, faces: mesh.geometry.index.count / 3 };
        }""")
        data = (folder / fox).read_bytes()
        part = read_index(data)[0]["summary"]["parts"][0]
        assert shown == {"skinned": True, "faces": part["faces"]}, shown
        # the part's state: the file's base json level and its chunks, as the
        # reference decoder applies them (tests/api/test_progressive_file.py:
        # each chunk's end is the json level there)
        faces, digest = _expected(_Decoded(data, 0), "", part["vertices"])
        assert _state(page, "window.object.parts[0].levels.state") == {"faces": faces,
                                                                        "hash": digest}
        assert {entry[3] for entry in handler.log} == {206}, handler.log
        assert not page.errors, page.errors
    finally:
        page.close()


def test_a_damaged_file_or_a_plain_glb_is_refused_with_its_reason(chromium, app, host, sphere):
    folder, origin, handler = host
    pm, name = sphere
    data = bytearray((folder / name).read_bytes())
    record, start = read_index(bytes(data))
    at, length = record["parts"][0]["splits"][-1][2:]
    data[start + at + length // 2] ^= 0xFF          # inside the last split chunk
    (folder / "damaged.glb").write_bytes(bytes(data))
    (folder / "plain.glb").write_bytes(bytes(data[:20]) + b"{}")
    page = _open(chromium, app, f"{origin}/damaged.glb")
    try:
        page.evaluate(f"window.object.setLevel({pm.vertex_count})")
        status = page.evaluate(SETTLED_JS)
        assert status["error"] and "checksum" in status["error"], status
        assert status["level"] < pm.vertex_count       # what arrived before it stays drawn
        refusals = page.evaluate(REFUSALS_JS, [f"{origin}/plain.glb",
                                               f"{origin}/no-such-file.glb"])
        assert all(r and r.startswith("not a lodserver mesh URL") for r in refusals), refusals
        assert "cut short" in refusals[0], refusals
        assert "404" in refusals[1], refusals
    finally:
        page.close()


def test_a_textured_files_images_are_let_go_on_dispose(chromium, app, host, tmp_path):
    """spot's texture comes out of the file as a blob: URL the page's material
    loads; dispose() revokes it (a page opening and closing meshes would hold
    every image it ever showed otherwise)."""
    folder, origin, _ = host
    _cli("export", REPO / "tests" / "data" / "spot.obj", "--progressive",
         "-o", folder / "spot.glb")
    page = _open(chromium, app, f"{origin}/spot.glb")
    try:
        status = page.evaluate(SETTLED_JS)
        assert status["error"] is None, status
        assert not page.errors, page.errors
        fetched = page.evaluate("""async () => {
          const urls = window.object.source.imageUrls.slice();
          const read = (url) => fetch(url).then((r) => r.blob()).then((b) => b.size, () => null);
          const before = await Promise.all(urls.map(read));
          window.object.dispose();
          return { before, after: await Promise.all(urls.map(read)) };
        }""")
        assert fetched["before"] and all(size for size in fetched["before"]), fetched
        assert fetched["after"] == [None] * len(fetched["before"]), fetched
        # (the browser logs each read of a revoked URL as a resource it could not load)
        assert all("ERR_FILE_NOT_FOUND" in str(error) for error in page.errors), page.errors
    finally:
        page.close()


# The request plan of a file session on a simulated link: the stream's packet
# sizer (packetsizer.js, the stream's default settings but for its first size,
# the file's chunk) and the file's cut of runs of chunks (staticsource.js), fed
# one run after another with what the link and the page would have measured:
# each chunk's bytes from the file's index, the link's round trip and rate, a
# drawn frame's cost, records applied at a fixed rate.
PLAN_JS = """async ({ record, link, frameCostMs, recordsPerMs }) => {
  const { PacketSizer } = await import('/lodserver/packetsizer.js');
  const { StaticSource } = await import('/lodserver/staticsource.js');
  const { STREAM_DEFAULTS } = await import('/lodserver/stream.js');
  const part = record.parts[0];
  const source = new StaticSource(null, record.summary, part);
  const settings = { ...STREAM_DEFAULTS, chunkSplits: part.chunkSplits };
  const sizer = new PacketSizer((key) => settings[key]);
  sizer.linkOf = () => link;
  const full = source.levels[source.levels.length - 1];
  const runs = [];
  for (let level = source.levels[0]; level < full;) {
    const to = source.nextStop(level, full, sizer.size);
    const chunks = part.splits.filter(([from, end]) => from >= level && end <= to);
    runs.push(chunks.length);
    const bytes = chunks.reduce((sum, chunk) => sum + chunk[3], 0);
    sizer.measure('', bytes, to - level, (to - level) / recordsPerMs, frameCostMs);
    level = to;
  }
  return runs;
}"""


@pytest.mark.parametrize("frame_ms, latency_ms", [(1000, 150), (16, 400)])
def test_a_file_session_asks_for_growing_runs_of_chunks(chromium, app, host, sphere, frame_ms,
                                                        latency_ms):
    """Over a link that carries one chunk in 200 ms (about what bunny_loop2's
    chunks of 70 KB took under bench/static_file.py's 5 Mbit/s), with frames as slow as software GL draws a million triangles
    (a level shows only at a report, so a packet sooner than the reports shows
    nothing sooner) or a round trip longer than the stream's packet pace (the
    bodies in flight must cover it), the runs grow past one chunk and full
    detail takes a few requests, not one per chunk; with fast frames and a
    short round trip a request still holds the link for about its pace."""
    _, name = sphere
    record, _ = read_index((host[0] / name).read_bytes())
    chunks = record["parts"][0]["splits"]
    per_chunk = sum(chunk[3] for chunk in chunks) / len(chunks)
    page = chromium.new_page()
    try:
        # an empty page of the app's origin, which serves the modules
        page.route(f"{app}/blank.html", lambda route: route.fulfill(
            body="<!doctype html>", content_type="text/html"))
        page.goto(f"{app}/blank.html")
        plan = page.evaluate(PLAN_JS, {"record": record, "frameCostMs": frame_ms,
                                       "recordsPerMs": 500,
                                       "link": {"latencyMs": latency_ms,
                                                "bytesPerMs": per_chunk / 200}})
        fast = page.evaluate(PLAN_JS, {"record": record, "frameCostMs": 16, "recordsPerMs": 500,
                                       "link": {"latencyMs": 50, "bytesPerMs": per_chunk / 200}})
    finally:
        page.close()
    print("runs of chunks:", plan, "with fast frames and a short round trip:", fast)
    assert sum(plan) == len(chunks), plan
    assert max(plan[1:]) >= 2 and len(plan) < len(chunks) / 1.5, plan
    if frame_ms >= 1000:
        # the runs grow as the sizer does (at most 4x a packet) up to the file's end
        assert max(plan) >= 8 and len(plan) <= 6, plan
    assert sum(fast) == len(chunks) and max(fast) <= 2, fast
