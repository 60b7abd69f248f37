"""Geomorphs (static/geomorph.js, Hoppe 1996): a level change glides instead of
popping. Measured in headless Chromium as the largest number of pixels that
change from one animation frame to the next while the level moves, with the
geomorph off and on; the level reached is exactly the server's either way.

``measure_level_change`` is also what ``bench/viewer/run.py --geomorph`` reports.
"""

import pytest

from ..meshes import DATA, SHARED
from ..server import upload_and_wait
from .test_viewer import _expected

VIEWPORT = {"width": 480, "height": 360}
GLIDE_MS = 4000
# Before the page's scripts: WebGL contexts keep their drawing buffer (so a
# frame can be read back from any callback), and the last one made is kept.
PRESERVE_JS = """(() => {
  const original = HTMLCanvasElement.prototype.getContext;
  HTMLCanvasElement.prototype.getContext = function (kind, options) {
    const context = original.call(this, kind,
      kind.startsWith('webgl') ? { ...(options || {}), preserveDrawingBuffer: true } : options);
    if (kind.startsWith('webgl') && context) window.benchGl = context;
    return context;
  };
})();"""
# Moves the level and reads every frame back until the level is reached and
# `tailMs` more have passed: between consecutive frames, the changed pixels (any
# channel off by more than `threshold`) and the change's energy (the sum over
# pixels of the largest channel change, in units of a full 0-255 step).
LEVEL_CHANGE_JS = """async ({ level, geomorphMs, tailMs, threshold }) => {
  lodViewer.settings.geomorphMs = geomorphMs;
  const gl = window.benchGl;
  const { drawingBufferWidth: w, drawingBufferHeight: h } = gl;
  let previous = new Uint8Array(4 * w * h), current = new Uint8Array(4 * w * h);
  gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, previous);
  const changes = [], energy = [];     // per changed frame: pixels, sum of |change| / 255
  let running = true;
  const sample = () => {
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, current);
    let changed = 0, sum = 0;
    for (let i = 0; i < current.length; i += 4) {
      const d = Math.max(Math.abs(current[i] - previous[i]),
                         Math.abs(current[i + 1] - previous[i + 1]),
                         Math.abs(current[i + 2] - previous[i + 2]));
      if (d > threshold) changed++;
      sum += d;
    }
    if (changed) {
      changes.push(changed);
      energy.push(Math.round(sum / 255));
    }
    [previous, current] = [current, previous];
    if (running) requestAnimationFrame(sample);
  };
  requestAnimationFrame(sample);
  const started = performance.now();
  const input = document.getElementById('level-input');
  input.value = level;
  input.dispatchEvent(new Event('change', { bubbles: true }));
  const status = await lodViewer.settled();
  const tookMs = performance.now() - started;
  await new Promise((resolve) => setTimeout(resolve, tailMs));
  running = false;
  await new Promise((resolve) => requestAnimationFrame(resolve));
  return { status, tookMs, changes, largest: Math.max(0, ...changes), energy,
           largestEnergy: Math.max(0, ...energy),
           total: changes.reduce((a, b) => a + b, 0), pixels: w * h };
}"""


def open_still(browser, base_url: str, mesh: dict):
    """A page showing ``mesh`` at full detail with the camera held still (a
    one-pixel drag: the view no longer follows the level)."""
    page = browser.new_page(viewport=VIEWPORT)
    page.add_init_script(PRESERVE_JS)
    page.goto(f"{base_url}/viewer/?mesh={mesh['id']}&level={mesh['vertices']}")
    page.wait_for_function("() => window.lodViewer?.status().level != null")
    page.evaluate("""async (full) => {
      while ((await lodViewer.settled()).level !== full) {
        await new Promise((resolve) => setTimeout(resolve, 50));
      }
    }""", mesh["vertices"])
    box = page.locator("#viewport canvas").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 1, y)
    page.mouse.up()
    page.evaluate("lodViewer.settled()")
    return page


def measure_level_change(page, level: int, geomorph_ms: float, *, tail_ms: float = 400,
                         threshold: int = 12) -> dict:
    """Move the page's level to ``level`` with geomorphs of ``geomorph_ms`` (0: off);
    the per-frame pixel changes (see LEVEL_CHANGE_JS)."""
    return page.evaluate(LEVEL_CHANGE_JS, {"level": level, "geomorphMs": geomorph_ms,
                                           "tailMs": tail_ms, "threshold": threshold})


@pytest.mark.parametrize("name", ["spot", "bunny"])
def test_geomorphs_spread_a_level_change_over_frames(name, chromium, server):
    """Coarsening to 3% and refining back: without geomorphs the change lands in
    one frame; with them (4 s: long enough to span several frames on software GL
    under load) no frame changes more than 75% of the pixels, nor of the change's
    energy, that frame did, and the level reached is the server's exactly. spot is drawn per wedge (UVs), the bunny
    per vertex: the two paths of geomorph.js."""
    path = {"spot": DATA / "spot.obj", "bunny": SHARED / "stanford-bunny.obj"}[name]
    if not path.is_file():
        pytest.skip(f"shared mesh not found at {path}")
    mesh = upload_and_wait(server, path)
    page = open_still(chromium, str(server.base_url), mesh)
    errors = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    try:
        coarse, full = max(mesh["base_vertices"] + 1, round(0.03 * mesh["vertices"])), \
            mesh["vertices"]
        figures = {}
        for morph in (0, GLIDE_MS):
            for level in (coarse, full):
                measured = measure_level_change(page, level, morph)
                status = measured["status"]
                assert status["level"] == level and status["error"] is None, status
                faces, digest = _expected(server, mesh["id"], level)
                assert status["faces"] == faces
                assert page.evaluate("lodViewer.hash()") == digest
                figures[morph, level] = measured
        # the figures, for `pytest -s` (bench/viewer/run.py --geomorph reports them too)
        print(name, {f"{'on' if m else 'off'}->{lv}": (f["largest"], len(f["changes"]))
                     for (m, lv), f in figures.items()})
        for level in (coarse, full):
            off, on = figures[0, level], figures[GLIDE_MS, level]
            assert off["largest"] > 0.002 * off["pixels"], (level, off)   # it did pop
            assert len(on["changes"]) >= 3, (level, on["changes"])         # it glided
            assert on["largest"] < 0.75 * off["largest"], (level, off["changes"],
                                                             on["changes"])
            assert on["largestEnergy"] < 0.75 * off["largestEnergy"], (level, off["energy"],
                                                                       on["energy"])
            assert on["tookMs"] >= GLIDE_MS   # settled() waits for the glide
        assert not errors, errors
    finally:
        page.close()
