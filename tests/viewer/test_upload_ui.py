"""The viewer's upload (static/upload.js) in headless Chromium against a real
``lodserver serve``: files dropped onto the canvas (a DataTransfer), several
files and a zip through the picker, reached and opened from the keyboard,
byte progress then queue and build progress shown, load warnings listed,
refusals shown with the server's sentence and a suggestion but no server
path, and the model of the mesh shown before hidden while the new one builds."""

import base64
import json
import zipfile

import pytest

from ..meshes import DATA
from ..server import upload_and_wait

VIEWPORT = {"width": 960, "height": 640}
SPOT_FILES = ("spot.obj", "spot.mtl", "spot_texture.png")
# Every text the upload status line shows, in order (an init script: it runs
# before the page's own, exempt from its CSP).
RECORD_STATUS_JS = """window.uploadTexts = [];
new MutationObserver(() => {
  const line = document.getElementById('upload-status');
  if (line && line.textContent && window.uploadTexts.at(-1) !== line.textContent) {
    window.uploadTexts.push(line.textContent);
  }
}).observe(document, { subtree: true, childList: true, characterData: true });"""


@pytest.fixture
def page(chromium, server):
    """The viewer with spot (uploaded whole) shown and drawn."""
    mesh = upload_and_wait(server, DATA / "spot.obj")
    page = chromium.new_page(viewport=VIEWPORT)
    errors = []
    page.on("pageerror", lambda error: errors.append(error))
    page.add_init_script(RECORD_STATUS_JS)
    page.goto(f"{server.base_url}/viewer?mesh={mesh['id']}")
    page.wait_for_function("() => window.lodViewer?.status().level != null")
    page.evaluate("lodViewer.settled()")
    page.shown = mesh
    yield page
    page.close()
    assert not errors, errors


def _texts(page):
    return page.evaluate("window.uploadTexts")


def _wait_for_new_mesh(page, old_id, timeout=120_000):
    """Wait until the page shows a mesh other than ``old_id``, settled; its status."""
    page.wait_for_function("(old) => { const s = lodViewer.status(); "
                           "return s.mesh && s.mesh !== old && s.level != null; }",
                           arg=old_id, timeout=timeout)
    return page.evaluate("lodViewer.settled()")


def _no_server_path(text, server):
    for path in (str(server.data_dir), "/tmp/", "/work/"):
        assert path not in text, text


def _drawn(page) -> float:
    """Fraction of the view's pixels that differ from the background, with the
    panel hidden (a screenshot decoded in the page)."""
    page.evaluate("document.getElementById('panel').classList.add('test-hidden')")
    png = page.screenshot()
    page.evaluate("document.getElementById('panel').classList.remove('test-hidden')")
    return page.evaluate("""async (png) => {
        const bytes = Uint8Array.from(atob(png), (c) => c.charCodeAt(0));
        const bitmap = await createImageBitmap(new Blob([bytes], { type: 'image/png' }));
        const canvas = new OffscreenCanvas(bitmap.width, bitmap.height);
        const g = canvas.getContext('2d');
        g.drawImage(bitmap, 0, 0);
        const pixels = g.getImageData(0, 0, bitmap.width, bitmap.height).data;
        let drawn = 0;
        for (let i = 0; i < pixels.length; i += 4) {
          const d = Math.abs(pixels[i] - 0x1d) + Math.abs(pixels[i + 1] - 0x20)
                  + Math.abs(pixels[i + 2] - 0x26);
          if (d > 24) drawn++;
        }
        return drawn / (pixels.length / 4);
    }""", base64.b64encode(png).decode())


def _hide_panel_rule(page):
    """A stylesheet rule hiding the panel for screenshots (added from the test: the
    page's CSP forbids inline styles, not a rule in a constructed sheet)."""
    page.evaluate("""() => {
        const sheet = new CSSStyleSheet();
        sheet.replaceSync('#panel.test-hidden { visibility: hidden; }');
        document.adoptedStyleSheets = [...document.adoptedStyleSheets, sheet];
    }""")


def test_several_files_through_the_picker_with_progress(page, server):
    """OBJ + MTL + PNG chosen together: byte progress, then queue/build, then the
    textured mesh shown; the old model is hidden while the new one builds."""
    _hide_panel_rule(page)
    assert _drawn(page) > 0.03
    # hold the new mesh at "building" (answers patched by the test) to look at the page
    held = {"on": True}

    def hold(route):
        response = route.fetch()
        body = response.json()
        if held["on"] and body.get("id") != page.shown["id"]:
            body.update(status="building", progress=0.4)
        route.fulfill(response=response, body=json.dumps(body))

    page.route("**/meshes/*", hold)
    page.set_input_files("#upload", [str(DATA / name) for name in SPOT_FILES])
    page.wait_for_function("() => document.getElementById('upload-status')"
                           ".textContent.includes('building 40%')")
    assert page.evaluate("document.getElementById('viewport').classList.contains('stale')")
    assert page.evaluate("document.getElementById('stats').rows.length") == 0
    assert _drawn(page) < 0.005, "the previous model is still on screen while building"
    note = page.evaluate("document.getElementById('view-note').textContent")
    assert "building 40%" in note
    assert page.evaluate("document.getElementById('upload-progress').value") == pytest.approx(0.4)
    held["on"] = False
    status = _wait_for_new_mesh(page, page.shown["id"])
    page.unroute("**/meshes/*")
    assert status["error"] is None and status["textureBytes"] > 0
    assert not page.evaluate("document.getElementById('viewport').classList.contains('stale')")
    texts = _texts(page)
    assert any(text.startswith("uploading 3 files:") and "(100%)" in text for text in texts), texts
    assert any("building" in text for text in texts), texts
    page.wait_for_function("() => document.getElementById('upload-status')"
                           ".textContent.endsWith('built')")
    assert page.evaluate("document.getElementById('upload-warnings').children.length") == 0
    assert _drawn(page) > 0.03


def test_a_file_dropped_onto_the_canvas(page, server):
    """A DataTransfer dropped on the canvas uploads its files (here spot.obj alone,
    whose missing .mtl is listed as a warning)."""
    data = base64.b64encode((DATA / "spot.obj").read_bytes()).decode()
    transfer = page.evaluate_handle("""(data) => {
        const bytes = Uint8Array.from(atob(data), (c) => c.charCodeAt(0));
        const transfer = new DataTransfer();
        transfer.items.add(new File([bytes], 'spot.obj', { type: 'text/plain' }));
        return transfer;
    }""", data)
    for kind in ("dragenter", "dragover"):
        page.dispatch_event("#viewport canvas", kind, {"dataTransfer": transfer})
    assert page.evaluate("document.getElementById('viewport').classList.contains('dropping')")
    page.dispatch_event("#viewport canvas", "drop", {"dataTransfer": transfer})
    status = _wait_for_new_mesh(page, page.shown["id"])
    assert status["error"] is None
    warnings = page.evaluate("[...document.querySelectorAll('#upload-warnings li')]"
                             ".map((li) => li.textContent)")
    assert any("'spot.mtl'" in warning and "not uploaded" in warning for warning in warnings)
    assert any(text.startswith("uploading spot.obj:") for text in _texts(page)), _texts(page)


def _choose_by_enter(page):
    """Press Enter on the focused button; the file chooser it opened. The Enter must
    click the button and the button the hidden input, every time. Chromium's report
    that a chooser opened (the DevTools event Playwright waits for) is itself missed
    now and then (microsoft/playwright#28023), so a second Enter is pressed, once,
    only when both clicks were seen and no chooser was reported."""
    for attempt in range(2):
        page.evaluate("window.clicked = []")
        try:
            with page.expect_file_chooser(timeout=15_000) as chooser:
                page.keyboard.press("Enter")
            return chooser.value
        except Exception as error:
            clicks = page.evaluate("window.clicked")
            if clicks != ["upload-button", "upload"] or attempt:
                raise AssertionError(f"no file chooser after Enter; clicks {clicks}") from error
    raise AssertionError("unreachable")


def test_the_upload_button_is_reached_and_used_by_keyboard(page, server, tmp_path):
    archive = tmp_path / "spot.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as out:
        for name in SPOT_FILES:
            out.write(DATA / name, f"spot/{name}")
    # Which clicks the Enter key caused, so that a chooser that never opens says why.
    page.evaluate("""window.clicked = [];
        for (const id of ['upload-button', 'upload']) {
          document.getElementById(id).addEventListener('click', () => clicked.push(id));
        }""")
    page.evaluate("document.activeElement.blur()")
    for _ in range(12):
        page.keyboard.press("Tab")
        if page.evaluate("document.activeElement.id") == "upload-button":
            break
    assert page.evaluate("document.activeElement.id") == "upload-button"
    outline = page.evaluate("getComputedStyle(document.activeElement).outlineStyle")
    assert outline not in ("", "none"), "the focused upload button shows no focus ring"
    chooser = _choose_by_enter(page)
    assert chooser.is_multiple()
    chooser.set_files(str(archive))
    status = _wait_for_new_mesh(page, page.shown["id"])
    assert status["error"] is None and status["textureBytes"] > 0


@pytest.mark.parametrize("files, message, suggestion", [
    ({"quad.gltf": json.dumps({
        "asset": {"version": "2.0"}, "buffers": [{"uri": "quad.bin", "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}]}).encode()},
     "'quad.bin' is missing", "include the .bin file named in the .gltf"),
    ({"notes.txt": b"hello"}, "cannot read 'notes.txt'", "choose a mesh file"),
    ({"bad.zip": b"PK\x03\x04 not a zip"}, "not a zip file", "make the .zip again"),
])
def test_refusals_show_the_sentence_and_a_suggestion_without_paths(page, server, tmp_path,
                                                                   files, message, suggestion):
    paths = []
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
        paths.append(str(tmp_path / name))
    page.set_input_files("#upload", paths)
    page.wait_for_function("() => document.getElementById('upload-status')"
                           ".classList.contains('error')")
    text = page.evaluate("document.getElementById('upload-status').textContent")
    assert text.startswith("upload refused:") and message in text and suggestion in text, text
    _no_server_path(text, server)
    # nothing was opened: the mesh shown before is still shown, not marked stale
    assert page.evaluate("lodViewer.status().mesh") == page.shown["id"]
    assert not page.evaluate("document.getElementById('viewport').classList.contains('stale')")


def test_suggestions_cover_the_statuses(page):
    got = page.evaluate("""async () => {
        const { suggestionFor } = await import('/viewer/upload.js');
        return [413, 415, 503, 507, 401, 0].map((status) => suggestionFor(status, ''))
          .concat([suggestionFor(422, "the upload holds 2 mesh files (...); name the one to "
                                      + "build in the form field 'main'")]);
    }""")
    assert all(got) and len(set(got)) == len(got), got


def test_several_meshes_offer_a_choice_of_main_file(page, server, tmp_path):
    """Two mesh files in one upload: the server's 422 asks for 'main'; the page
    offers one button per mesh file, which uploads the set again naming it."""
    paths = [str(DATA / name) for name in SPOT_FILES]
    copy = tmp_path / "copy.obj"
    copy.write_bytes((DATA / "spot.obj").read_bytes())
    page.set_input_files("#upload", paths + [str(copy)])
    page.wait_for_function("() => document.querySelectorAll('#upload-choices button')"
                           ".length === 2")
    text = page.evaluate("document.getElementById('upload-status').textContent")
    assert "2 mesh files" in text and "choose the one to build" in text, text
    page.click("#upload-choices button:has-text('build copy.obj')")
    status = _wait_for_new_mesh(page, page.shown["id"])
    assert status["error"] is None and status["textureBytes"] > 0
    name = page.evaluate("document.getElementById('upload-status').textContent")
    page.wait_for_function("() => document.getElementById('upload-status')"
                           ".textContent.startsWith('copy.obj')")
    assert page.evaluate("document.querySelectorAll('#upload-choices button').length") == 0, name
