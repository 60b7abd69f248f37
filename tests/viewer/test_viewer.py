"""The browser viewer (static/): its routes, and the real thing in headless Chromium.

The browser test drives a real ``lodserver serve`` through the viewer's UI and
checks that the level the page holds after streaming packets back and forth
is exactly ``GET /lod?format=json`` at that level (counts and a SHA-256 of the
integer positions and faces, and with attributes of the wedges' values, the
corners' wedges and the faces' materials), and that the mesh is drawn, with
its texture when it has one, under the server's Content-Security-Policy and
without violating it. It needs Debian's
``chromium`` and the Python ``playwright`` package (never ``playwright
install``), and skips without them.
"""

import base64
import hashlib
import re
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings

from ..meshes import DATA, SHARED, textured_spot_glb
from ..server import upload_and_wait

VIEWPORT = {"width": 960, "height": 640}
BACKGROUND = (0x1D, 0x20, 0x26)     # settings.background in static/main.js
# Slider positions (0 = base, 1000 = full detail), visited in order from full detail.
SLIDER_PATH = [350, 0, 1000, 620, 820, 150]
STATIC = Path(__file__).resolve().parents[2] / "static"
# Records each violation of the page's Content-Security-Policy (Playwright's init
# scripts are exempt from it).
RECORD_VIOLATIONS_JS = """window.cspViolations = [];
document.addEventListener('securitypolicyviolation', (event) => {
  window.cspViolations.push(`${event.effectiveDirective} ${event.blockedURI}`);
});"""


# ---- routes -------------------------------------------------------------------
def _client(tmp_path):
    return TestClient(create_app(Settings(data_dir=tmp_path / "data", warm_kernels=False)))


def test_root_and_viewer_lead_to_the_page(tmp_path):
    with _client(tmp_path) as client:
        for path, location in (("/", "viewer/"), ("/viewer", "viewer/"),
                               ("/viewer?mesh=abc", "viewer/?mesh=abc")):
            response = client.get(path, follow_redirects=False)
            assert response.status_code == 307 and response.headers["location"] == location
        page = client.get("/viewer?mesh=abc")
        assert page.status_code == 200 and '<script type="importmap">' in page.text
        assert str(page.url).endswith("/viewer/?mesh=abc")
        three = client.get("/viewer/vendor/three/build/three.module.js")
        assert three.status_code == 200 and "javascript" in three.headers["content-type"]


def test_the_page_needs_no_inline_style_or_handlers():
    """Under style-src 'self' and a hashed import map, the page may hold no
    <style>, no style= or on*= attribute and no inline script but the import
    map; the modules may not write markup or style attributes either."""
    page = (STATIC / "index.html").read_text()
    assert not re.search(r"<style|\sstyle=|\son[a-z]+=", page, re.I)
    scripts = re.findall(r"<script([^>]*)>(.*?)</script>", page, re.S)
    inline = [attributes for attributes, body in scripts if body.strip()]
    assert inline == [' type="importmap"'], inline
    assert all('src="./' in attributes for attributes, body in scripts if not body.strip())
    assert '<link rel="stylesheet" href="./viewer.css">' in page
    assert (STATIC / "viewer.css").is_file()
    unsafe = re.compile(r"innerHTML|outerHTML|insertAdjacentHTML|document\.write|"
                        r"setAttribute\(\s*['\"]style|\beval\(|new Function\b")
    for module in STATIC.glob("*.js"):
        assert not unsafe.search(module.read_text()), module.name


def test_viewer_without_its_files_says_where_it_looked(tmp_path, monkeypatch):
    monkeypatch.setenv("LODSERVER_STATIC_DIR", str(tmp_path / "nowhere"))
    with _client(tmp_path) as client:
        response = client.get("/viewer")
        assert response.status_code == 404
        assert "LODSERVER_STATIC_DIR" in response.json()["message"]   # no server path in it
        assert client.get("/healthz").status_code == 200


# ---- the browser ----------------------------------------------------------------
def _expected(client, mesh_id, level):
    """(faces, SHA-256) of the server's quantized level, hashed as the page does."""
    document = client.get(f"/meshes/{mesh_id}/lod",
                          params={"vertices": level, "format": "json"}).json()
    assert document["vertex_count"] == level
    data = (np.asarray(document["positions"], dtype="<i4").tobytes()
            + np.asarray(document["faces"], dtype="<u4").tobytes())
    if "layout" in document:
        data += (np.asarray(document["wedges"], dtype="<i4").tobytes()
                 + np.asarray(document["corners"], dtype="<u4").tobytes())
    if "face_material" in document:
        data += np.asarray(document["face_material"], dtype="<i4").tobytes()
    return document["face_count"], hashlib.sha256(data).hexdigest()


def _detail(page) -> str:
    """What the panel says the level stops at ("1 px", "full detail", ...)."""
    return page.evaluate("""() => [...document.querySelectorAll('#stats tr')]
        .find((row) => row.cells[0].textContent === 'detail').cells[1].textContent""")


def _pixel_fractions(page, png: bytes) -> tuple[float, float]:
    """(drawn, dark) for a screenshot, decoded in the page: the fraction of its
    pixels that are not the background, and the fraction of those that are dark
    (luminance under 90): about 5% for the untextured, lit spot, about 20% with
    its texture's black patches."""
    # decoded from a Blob, not fetched as a data: URL, which connect-src 'self' forbids
    drawn, dark = page.evaluate("""async ([png, background]) => {
        const bytes = Uint8Array.from(atob(png), (c) => c.charCodeAt(0));
        const blob = new Blob([bytes], { type: 'image/png' });
        const bitmap = await createImageBitmap(blob);
        const canvas = new OffscreenCanvas(bitmap.width, bitmap.height);
        const g = canvas.getContext('2d');
        g.drawImage(bitmap, 0, 0);
        const pixels = g.getImageData(0, 0, bitmap.width, bitmap.height).data;
        let drawn = 0, dark = 0;
        for (let i = 0; i < pixels.length; i += 4) {
          const [r, gr, b] = [pixels[i], pixels[i + 1], pixels[i + 2]];
          const d = Math.abs(r - background[0]) + Math.abs(gr - background[1])
                  + Math.abs(b - background[2]);
          if (d <= 24) continue;
          drawn++;
          if (0.299 * r + 0.587 * gr + 0.114 * b < 90) dark++;
        }
        return [drawn / (pixels.length / 4), drawn ? dark / drawn : 0];
    }""", [base64.b64encode(png).decode(), list(BACKGROUND)])
    return drawn, dark


@pytest.mark.parametrize("name", ["spot", "conrod", "textured-spot"])
def test_viewer_levels_equal_the_server_levels(name, chromium, server, tmp_path):
    # conrod (non-manifold, welded from an STL) has splits whose moved corners
    # are listed rather than predicted: the decoder's other path. spot.obj has
    # UVs (wedges, no material); textured-spot is a GLB of spot with its texture.
    path = {"spot": DATA / "spot.obj", "conrod": SHARED / "conrod.stl",
            "textured-spot": tmp_path / "spot.glb"}[name]
    if name == "textured-spot":
        path.write_bytes(textured_spot_glb())
    if not path.is_file():
        pytest.skip(f"shared mesh not found at {path}")
    mesh = upload_and_wait(server, path)
    page = chromium.new_page(viewport=VIEWPORT)
    failures, requests = [], []
    page.on("pageerror", lambda error: failures.append(error))
    page.on("request", lambda request: requests.append(request.url))
    page.add_init_script(RECORD_VIOLATIONS_JS)
    try:
        response = page.goto(f"{server.base_url}/viewer?mesh={mesh['id']}")
        # the viewer runs under the server's policy (script-src 'self' and the import
        # map's hash, style-src 'self', ...), and breaks none of it (checked at the end)
        assert "content-security-policy" in response.all_headers()
        # a function, not an expression string: Playwright polls a string with eval(),
        # which the viewer's script-src (no 'unsafe-eval') refuses
        page.wait_for_function("() => window.lodViewer?.status().level != null")
        status = page.evaluate("lodViewer.settled()")

        def check(status):
            assert status["error"] is None and status["level"] == status["target"], status
            faces, digest = _expected(server, mesh["id"], status["level"])
            assert status["faces"] == faces
            assert page.evaluate("lodViewer.hash()") == digest, f"level {status['level']}"

        # streamed to what the screen shows (the 1 px budget), then full detail a click away
        check(status)
        assert _detail(page) == "1 px"
        page.click("#full-detail")
        status = page.evaluate("lodViewer.settled()")
        assert status["level"] == mesh["vertices"], status
        check(status)
        assert _detail(page) == "full detail"
        visited = [status["level"]]
        for position in SLIDER_PATH:
            page.evaluate("""(position) => {
                const slider = document.getElementById('level-slider');
                slider.value = position;
                slider.dispatchEvent(new Event('input', { bubbles: true }));
            }""", position)
            status = page.evaluate("lodViewer.settled()")
            check(status)
            visited.append(status["level"])
        # keys: one collapse, a step up, back to the base
        for key, moved in (("Shift+ArrowLeft", lambda a, b: b == a - 1),
                           ("ArrowRight", lambda a, b: b > a),
                           ("Home", lambda a, b: b == mesh["base_vertices"])):
            before = status["level"]
            page.keyboard.press(key)
            status = page.evaluate("lodViewer.settled()")
            check(status)
            assert moved(before, status["level"]), (key, before, status["level"])
            visited.append(status["level"])
        assert visited[2] == mesh["base_vertices"] and visited[3] == mesh["vertices"]
        assert visited[-1] == mesh["base_vertices"]
        # one level fetched whole (the base); everything after it came as packets
        geometry = [url for url in requests if f"/meshes/{mesh['id']}/" in url]
        assert sum("/lod?" in url for url in geometry) == 1
        assert sum("/splits?" in url for url in geometry) >= len(visited) - 1

        page.keyboard.press("End")
        page.evaluate("lodViewer.settled()")
        page.evaluate("document.getElementById('panel').style.visibility = 'hidden'")
        png = page.screenshot(path=str(tmp_path / f"{name}.png"))
        assert _pixel_fractions(page, png)[0] > 0.03, f"the mesh is not drawn: see {tmp_path}"
        if name == "textured-spot":
            # at the mesh's version (stream.js: the summary's urls)
            version = server.get(f"/meshes/{mesh['id']}").json()["version"]
            assert f"{server.base_url}/meshes/{mesh['id']}/materials?v={version}" in requests
            assert f"{server.base_url}/meshes/{mesh['id']}/images/0?v={version}" in requests
            assert _pixel_fractions(page, png)[1] > 0.1, f"the texture is not drawn: see {tmp_path}"
        assert not failures, failures
        assert page.evaluate("window.cspViolations") == []
    finally:
        page.close()


# The panel's vertices line ("A / B", "A / B → C").
VERTICES_JS = """() => [...document.querySelectorAll('#stats tr')]
    .find((row) => row.cells[0].textContent === 'vertices').cells[1].textContent"""


def test_the_panel_is_ui_around_the_module_object(chromium, server):
    """The viewer shows the three.js module's ProgressiveMesh (issue 26 point 3):
    the object the page holds is the module's, and a level set on it as an app
    sets one (setLevel) is the level the panel shows and the server's level."""
    mesh = upload_and_wait(server, DATA / "spot.obj")
    page = chromium.new_page(viewport=VIEWPORT)
    failures = []
    page.on("pageerror", lambda error: failures.append(error))
    try:
        page.goto(f"{server.base_url}/viewer/?mesh={mesh['id']}")
        page.wait_for_function("() => window.lodViewer?.status().level != null")
        status = page.evaluate("lodViewer.settled()")
        held = page.evaluate("""() => { const object = lodViewer.viewed.object;
            return { type: object.type, level: object.level, full: object.fullLevel,
                     inScene: object.parent === lodViewer.scene.three.scene,
                     drawn: object.mesh === lodViewer.scene.three.mesh }; }""")
        assert held == {"type": "ProgressiveMesh", "level": status["level"],
                        "full": mesh["vertices"], "inScene": True, "drawn": True}, held
        level = (mesh["base_vertices"] + mesh["vertices"]) // 3
        page.evaluate("(n) => lodViewer.viewed.object.setLevel(n)", level)
        status = page.evaluate("lodViewer.settled()")
        assert status["level"] == level and status["error"] is None, status
        assert page.evaluate(VERTICES_JS) == f"{level:,} / {mesh['vertices']:,}"
        faces, digest = _expected(server, mesh["id"], level)
        assert status["faces"] == faces and page.evaluate("lodViewer.hash()") == digest
        assert not failures, failures
    finally:
        page.close()


LONG_PACKETS_JS = """async ({ id, levels, vertexCapacity, faceCapacity }) => {
  const { LodState } = await import('/viewer/vsplit.js');
  const document = await (await fetch(`/meshes/${id}/lod?vertices=${levels[0]}&format=json`)).json();
  const state = LodState.fromJson(document, { vertexCapacity, faceCapacity });
  const hash = async () => {
    const bytes = new Uint8Array(12 * (state.vertexCount + state.faceCount));
    bytes.set(new Uint8Array(state.positions.buffer, 0, 12 * state.vertexCount));
    bytes.set(new Uint8Array(state.faces.buffer, 0, 12 * state.faceCount), 12 * state.vertexCount);
    const digest = new Uint8Array(await crypto.subtle.digest('SHA-256', bytes));
    return Array.from(digest, (b) => b.toString(16).padStart(2, '0')).join('');
  };
  const reached = [];
  for (let i = 1; i < levels.length; i++) {
    const response = await fetch(`/meshes/${id}/splits?from=${levels[i - 1]}&to=${levels[i]}`);
    state.apply(await LodState.readPacket(new Uint8Array(await response.arrayBuffer())));
    reached.push([state.vertexCount, state.faceCount, await hash()]);
  }
  return reached;
}"""


def test_the_decoder_reads_packets_chained_from_pre_deflated_chunks(chromium, server, tmp_path):
    """Packets longer than a chunk of records are deflated from pre-deflated
    segments (docs/packets.md); the browser's decoder reads them both ways and
    lands exactly on the server's levels."""
    import trimesh

    from lodserver.packets import CHUNK_RECORDS

    path = tmp_path / "sphere.ply"
    path.write_bytes(trimesh.creation.icosphere(5).export(file_type="ply"))   # 10,242 vertices
    mesh = upload_and_wait(server, path)
    base, full = mesh["base_vertices"], mesh["vertices"]
    assert full - base > CHUNK_RECORDS
    levels = [base, full, base + 3, full - 5, base]
    page = chromium.new_page()
    try:
        # a document under /viewer/ (the decoder's own file, so the viewer app does not
        # start): its CSP lets the page import the decoder; the API's forbids scripts
        page.goto(f"{server.base_url}/viewer/vsplit.js")
        reached = page.evaluate(LONG_PACKETS_JS, {"id": mesh["id"], "levels": levels,
                                                  "vertexCapacity": full,
                                                  "faceCapacity": mesh["faces"]})
    finally:
        page.close()
    for level, (vertices, faces, digest) in zip(levels[1:], reached):
        assert vertices == level
        assert (faces, digest) == _expected(server, mesh["id"], level), f"level {level}"


ATTRIBUTE_PACKETS_JS = """async ({ document, packets, damaged, vertexCapacity, faceCapacity }) => {
  const { LodState, dequantize } = await import('/viewer/vsplit.js');
  const bytesOf = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const state = LodState.fromJson(document, { vertexCapacity, faceCapacity });
  const reached = [];
  for (const packet of packets) {
    state.apply(await LodState.readPacket(bytesOf(packet)));
    const k = state.components;
    const floats = state.attributes.map((a) => {
      const out = new Float64Array(a.width * state.wedgeCount);
      for (let w = 0; w < state.wedgeCount; w++) {
        dequantize(a, state.wedges, k * w + a.offset, out, a.width * w);
      }
      return Array.from(out);
    });
    reached.push({
      positions: Array.from(state.positions.subarray(0, 3 * state.vertexCount)),
      faces: Array.from(state.faces.subarray(0, 3 * state.faceCount)),
      wedges: Array.from(state.wedges.subarray(0, k * state.wedgeCount)),
      corners: Array.from(state.corners.subarray(0, 3 * state.faceCount)),
      floats,
    });
  }
  let refused = null;
  try {
    await LodState.readPacket(bytesOf(damaged));
  } catch (error) {
    refused = `${error.name}: ${error.message}`;
  }
  return { reached, refused };
}"""


def test_the_decoder_reads_every_vertex_attribute(chromium, server):
    """A mesh with tangents, skin, two morph targets, TEXCOORD_2 and a custom ``_ID``
    (tests/packets/test_attributes.py): from its json level, the browser's decoder
    applies version 3 packets forward and back to the same integers as reference.py,
    and dequantizes every attribute to the floats grids.py gives (joints and the
    tangent's handedness exactly); a record naming an unknown attribute is refused, and
    version 2 packets (kind codes, a normal + UV mesh) still decode."""
    import orjson

    from lodserver.packets import apply_packet, encode_packet, state_from_json
    from lodserver.service.levels import encode_level

    from ..meshes import progressive
    from ..packets.test_attributes import _built, _v2

    def decoded(pm, levels, data, damaged):
        document = orjson.loads(bytes(encode_level(pm, levels[0], file_type="json")))
        return document, page.evaluate(ATTRIBUTE_PACKETS_JS, {
            "document": document, "packets": [base64.b64encode(d).decode() for d in data],
            "damaged": base64.b64encode(damaged).decode(),
            "vertexCapacity": pm.vertex_count, "faceCapacity": pm.face_counts[-1].item()})

    pm = _built()
    n0, n = pm.base_vertices, pm.vertex_count
    levels = [n0 + 3, n, (n0 + n) // 2, n0]
    data = [encode_packet(pm, a, b) for a, b in pairwise(levels)]
    name = data[0].index(b"TANGENT")
    damaged = data[0][:name] + b"TANGENX" + data[0][name + 7:]
    # and today's version 2 packets of a normal + UV mesh still decode
    old = progressive("textured_sphere")
    old_levels = [old.base_vertices, old.vertex_count, old.base_vertices + 9]
    old_data = [_v2(encode_packet(old, a, b)) for a, b in pairwise(old_levels)]
    page = chromium.new_page()
    try:
        page.goto(f"{server.base_url}/viewer/vsplit.js")
        document, result = decoded(pm, levels, data, damaged)
        old_document, old_result = decoded(old, old_levels, old_data,
                                           old_data[0][:60] + bytes([7]) + old_data[0][61:])
    finally:
        page.close()
    assert result["refused"].startswith("PacketError: ")
    assert "unknown attribute TANGENX" in result["refused"]
    assert old_result["refused"] == "PacketError: the packet names an unknown attribute (7)"
    old_state = state_from_json(old_document)
    for packet, got in zip(old_data, old_result["reached"]):
        old_state = apply_packet(old_state, packet)
        np.testing.assert_array_equal(np.reshape(got["wedges"], old_state.wedges.shape),
                                      old_state.wedges)
        np.testing.assert_array_equal(np.reshape(got["faces"], (-1, 3)), old_state.faces)
    assert old_state.level == old_levels[-1]
    state = state_from_json(document)
    for level, packet, got in zip(levels[1:], data, result["reached"]):
        state = apply_packet(state, packet)
        assert state.level == level
        np.testing.assert_array_equal(np.reshape(got["positions"], (-1, 3)), state.positions)
        np.testing.assert_array_equal(np.reshape(got["faces"], (-1, 3)), state.faces)
        np.testing.assert_array_equal(np.reshape(got["wedges"], state.wedges.shape), state.wedges)
        np.testing.assert_array_equal(np.reshape(got["corners"], (-1, 3)), state.corners)
        at = 0
        for grid, floats in zip(state.attribute_grids, got["floats"]):
            expected = grid.dequantize(state.wedges[:, at:at + grid.components])
            at += grid.components
            floats = np.reshape(floats, expected.shape)
            np.testing.assert_allclose(floats, expected, rtol=0, atol=1e-12, err_msg=grid.name)
            if grid.name in ("JOINTS_0", "TANGENT"):
                exact = floats if grid.name == "JOINTS_0" else floats[:, 3]
                assert set(np.unique(exact)) <= ({0.0, 37.0, 300.0, 1000.0} if grid.name ==
                                                 "JOINTS_0" else {-1.0, 1.0})
                np.testing.assert_array_equal(
                    exact, expected if grid.name == "JOINTS_0" else expected[:, 3])
