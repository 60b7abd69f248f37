"""Streaming in the real viewer: time to the first frame and to full detail, and
the bytes, against fetching the full-detail GLB, plain and throttled.

Used by ``bench/viewer/run.py`` (``--streaming``). Each run is a fresh browser
context (a cold HTTP cache), with the default viewer settings, opening
``/viewer/?mesh=ID`` and timed inside the page (``performance.now()``, from the
navigation's start):

* ``first_frame_ms``: the first frame drawn holding a level (the first
  animation frame after ``lodViewer.status().level`` is set);
* ``full_detail_ms``: ``lodViewer.settled()`` resolving at the mesh's full
  detail (its textures and the image-based light in place, the frame showing
  it drawn);
* ``last_geometry_byte_ms``: the last byte of geometry received (the
  ``/meshes/`` resource that ended last): what the GLB's ``ms`` compares with,
  the frames drawn after it aside (under software GL, headless Chromium, one
  frame of the 1.1M-face bunny blocks the main thread for seconds);
* ``geometry_bytes``: what the page fetched under ``/meshes/`` (resource
  timing's ``transferSize``: on the wire, headers included, compressed if the
  server compressed), ``static_bytes`` what it fetched under ``/viewer/``;
* ``glb``: a fresh context fetching ``/lod?vertices=FULL&format=glb`` (bytes and
  time to its last byte: no parsing or drawing counted, the GLB's best case);
* ``glb_drawn``: the fair baseline, a fresh context opening
  ``/viewer/bench-glb.html`` (``glb.html``/``glb.js``, which ``run.py`` adds to
  the served copy of ``static/``): the same three.js fetches that GLB, parses it
  with GLTFLoader and draws it once with the viewer's look; ``first_frame_ms``
  (= ``full_detail_ms``: a GLB has one level) from the navigation's start, as
  the viewer's, and its steps (``marks``).

``next_frame_ms`` (viewer and ``glb_drawn``): the animation frame after the one
drawing full detail, which waits for that frame's software-GL work.

Throttled runs use the DevTools protocol's ``Network.emulateNetworkConditions``
(latency per request, throughput shared by the page's requests).
"""

from __future__ import annotations

import time
from urllib.parse import quote

from playwright.sync_api import Error as PlaywrightError

# 50 ms latency, 20 Mbit/s both ways (the throttled link)
THROTTLE = {"offline": False, "latency": 50, "downloadThroughput": 20e6 / 8,
            "uploadThroughput": 20e6 / 8}

# Before the page's scripts: a bigger resource-timing buffer (a slow viewer
# fetches hundreds of packets) and a watcher noting the first frame with a level.
WATCH_JS = """performance.setResourceTimingBufferSize(100000);
window.benchFirstFrame = null;
(function watch() {
  const status = window.lodViewer?.status();
  if (status && status.level != null) {
    requestAnimationFrame(() => { window.benchFirstFrame = performance.now(); });
    return;
  }
  requestAnimationFrame(watch);
})();"""

FULL_DETAIL_JS = """async (full) => {
  for (;;) {
    const status = await lodViewer.settled();
    if (status.level === full || status.error) {
      const at = performance.now();
      await new Promise((resolve) => requestAnimationFrame(resolve));
      return { ...status, at, next: performance.now() };
    }
    await new Promise((resolve) => setTimeout(resolve, 20));
  }
}"""

BYTES_JS = """() => {
  let geometry = 0, statics = 0, requests = 0, lastByte = 0;
  for (const entry of performance.getEntriesByType('resource')) {
    const path = new URL(entry.name).pathname;
    if (path.startsWith('/meshes/')) {
      geometry += entry.transferSize;
      requests++;
      lastByte = Math.max(lastByte, entry.responseEnd);
    } else if (path.startsWith('/viewer/')) statics += entry.transferSize;
  }
  const page = performance.getEntriesByType('navigation')[0];
  return { geometry, statics: statics + (page ? page.transferSize : 0), requests, lastByte };
}"""

GLB_JS = """async (url) => {
  const started = performance.now();
  const response = await fetch(url);
  const bytes = (await response.arrayBuffer()).byteLength;
  return { ms: performance.now() - started, bytes,
           encoding: response.headers.get('content-encoding') };
}"""


def _context(browser, viewport, throttled: bool, bypass_csp: bool = False):
    context = browser.new_context(viewport=viewport, bypass_csp=bypass_csp)
    page = context.new_page()
    if throttled:
        cdp = context.new_cdp_session(page)
        cdp.send("Network.enable")
        cdp.send("Network.emulateNetworkConditions", THROTTLE)
    return context, page


def stream_once(browser, base_url: str, mesh: dict, *, throttled: bool, viewport: dict,
                timeout_s: float, shot=None) -> dict:
    """One cold open of the viewer on ``mesh`` until full detail; the figures above."""
    context, page = _context(browser, viewport, throttled)
    errors = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.add_init_script(WATCH_JS)
    page.set_default_timeout(timeout_s * 1000)
    wall = time.perf_counter()
    try:
        # full detail asked for: by default the viewer stops where the error is under a pixel
        page.goto(f"{base_url}/viewer/?mesh={mesh['id']}&level={mesh['vertices']}")
        status = page.evaluate(FULL_DETAIL_JS, mesh["vertices"])
        first = page.evaluate("window.benchFirstFrame")
        sent = page.evaluate(BYTES_JS)
        if shot is not None:
            page.screenshot(path=str(shot))
        return {"first_frame_ms": round(first, 1) if first is not None else None,
                "full_detail_ms": round(status["at"], 1),
                "next_frame_ms": round(status["next"], 1),
                "wall_s": round(time.perf_counter() - wall, 2),
                "level": status["level"], "error": status["error"],
                "geometry_bytes": sent["geometry"], "geometry_requests": sent["requests"],
                "last_geometry_byte_ms": round(sent["lastByte"], 1),
                "static_bytes": sent["statics"], "page_errors": errors[:3]}
    except Exception as error:     # a timeout: the figure is "more than timeout_s"
        return {"failed": f"{type(error).__name__}: {str(error).splitlines()[0]}",
                "wall_s": round(time.perf_counter() - wall, 2), "page_errors": errors[:3]}
    finally:
        context.close()


def fetch_glb(browser, base_url: str, mesh: dict, *, throttled: bool, viewport: dict) -> dict:
    """Time to the last byte of the full-detail GLB in a fresh context."""
    context, page = _context(browser, viewport, throttled)
    try:
        # a document of the viewer's origin whose CSP allows fetch (connect-src 'self')
        page.goto(f"{base_url}/viewer/vsplit.js")
        url = f"/meshes/{mesh['id']}/lod?vertices={mesh['vertices']}&format=glb"
        raw = page.evaluate(GLB_JS, url)
        return {"ms": round(raw["ms"], 1), "bytes": raw["bytes"], "encoding": raw["encoding"]}
    finally:
        context.close()


def draw_glb(browser, base_url: str, mesh: dict, *, throttled: bool, viewport: dict,
             timeout_s: float, shot=None) -> dict:
    """The full-detail GLB fetched, parsed by GLTFLoader and drawn once, in a
    fresh context (``glb.js``); times in ms from the navigation's start."""
    # the page's import map is inline: the viewer's CSP only hashes index.html's
    context, page = _context(browser, viewport, throttled, bypass_csp=True)
    errors = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.set_default_timeout(timeout_s * 1000)
    try:
        url = f"/meshes/{mesh['id']}/lod?vertices={mesh['vertices']}&format=glb"
        page.goto(f"{base_url}/viewer/bench-glb.html?glb={quote(url, safe='')}")
        page.wait_for_function("() => window.bench?.done")
        raw = page.evaluate("window.bench")
        if raw["error"]:
            return {"failed": raw["error"], "page_errors": errors[:3]}
        if shot is not None:
            page.screenshot(path=str(shot))
        marks = {name: round(ms, 1) for name, ms in raw["marks"].items()}
        return {"first_frame_ms": marks["drawn"], "full_detail_ms": marks["drawn"],
                "next_frame_ms": marks["next_frame"], "marks": marks,
                "glb_bytes": raw["bytes"], "triangles": raw["triangles"],
                "page_errors": errors[:3]}
    except PlaywrightError as error:     # a timeout: the figure is "more than timeout_s"
        return {"failed": f"{type(error).__name__}: {str(error).splitlines()[0]}",
                "page_errors": errors[:3]}
    finally:
        context.close()


def measure_streaming(browser, client, meshes: dict, *, viewport: dict, timeout_s: float,
                      out, label: str, throttle_modes=(False, True), runs: int = 1) -> dict:
    """For each named mesh, plain and throttled, ``runs`` times in turn: the
    viewer's run, the GLB's fetch, and the GLB fetched and drawn. Each mode's
    row holds the first run's figures and, with ``runs`` > 1, all of them
    (``runs``)."""
    result = {}
    for name, mesh in meshes.items():
        # warm the server's caches once, untimed: the GLB body, and the packet
        # records of both directions (a server prepares them after a build in the
        # background; the first packet of a direction waits for them)
        client.get(f"/meshes/{mesh['id']}/lod",
                   params={"vertices": mesh["vertices"], "format": "glb"}).raise_for_status()
        base, full = mesh["base_vertices"], mesh["vertices"]
        for start, stop in ((base, base + 1), (full, full - 1)):
            client.get(f"/meshes/{mesh['id']}/splits",
                       params={"from": start, "to": stop}).raise_for_status()
        rows = {}
        for throttled in throttle_modes:
            mode = "throttled" if throttled else "plain"
            done = []
            for run in range(runs):
                shot = out / f"stream-{label}-{name}-{mode}.png" if run == 0 else None
                glb_shot = out / f"glb-{label}-{name}-{mode}.png" if run == 0 else None
                row = {
                    "viewer": stream_once(browser, str(client.base_url), mesh,
                                          throttled=throttled, viewport=viewport,
                                          timeout_s=timeout_s, shot=shot),
                    "glb": fetch_glb(browser, str(client.base_url), mesh, throttled=throttled,
                                     viewport=viewport),
                    "glb_drawn": draw_glb(browser, str(client.base_url), mesh,
                                          throttled=throttled, viewport=viewport,
                                          timeout_s=timeout_s, shot=glb_shot)}
                print(f"{label} {name} {mode} run {run}: {row}", flush=True)
                done.append(row)
            rows[mode] = {**done[0], **({"runs": done} if runs > 1 else {})}
        result[name] = {"vertices": mesh["vertices"], "faces": mesh["faces"],
                        "base_vertices": mesh["base_vertices"], **rows}
    return result
