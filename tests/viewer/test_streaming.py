"""Streaming in the viewer (static/stream.js): failed packets retried with
backoff, packets pipelined and grown, one draw per frame at most, and the level
reached exactly the server's, in headless Chromium against a real server."""

import json

import pytest

from ..meshes import DATA
from ..server import upload_and_wait
from .test_viewer import _expected

VIEWPORT = {"width": 640, "height": 480}
# Before the page's scripts: the status line's texts, and animation frames counted.
WATCH_JS = """window.statusTexts = [];
window.framesSeen = 0;
(function count() { window.framesSeen++; requestAnimationFrame(count); })();
new MutationObserver(() => {
  const status = document.getElementById('status');
  if (status && status.textContent !== window.statusTexts.at(-1)) {
    window.statusTexts.push(status.textContent);
  }
}).observe(document, { subtree: true, childList: true, characterData: true });"""
SETTLED_JS = """async (full) => {
  for (let i = 0; i < 600; i++) {
    const status = await lodViewer.settled();
    if (status.level === full || status.error) return status;
    await new Promise((resolve) => setTimeout(resolve, 50));
  }
  return lodViewer.status();
}"""


@pytest.fixture(scope="module")
def sphere(server, tmp_path_factory):
    """An icosphere of 40,962 vertices: several packets of the default size."""
    import trimesh

    path = tmp_path_factory.mktemp("sphere") / "sphere.ply"
    path.write_bytes(trimesh.creation.icosphere(6).export(file_type="ply"))
    return upload_and_wait(server, path)


@pytest.fixture(scope="module")
def spot(server):
    return upload_and_wait(server, DATA / "spot.obj")


def _open(chromium, server, mesh, route=None, listeners=()):
    page = chromium.new_page(viewport=VIEWPORT)
    errors, packets = [], []
    for event, listener in listeners:
        page.on(event, listener)
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on("request", lambda request: "/splits?" in request.url and packets.append(request.url))
    page.add_init_script(WATCH_JS)
    if route is not None:
        page.route("**/splits?*", route)
    # full detail asked for: these tests follow the stream all the way
    page.goto(f"{server.base_url}/viewer/?mesh={mesh['id']}&level={mesh['vertices']}")
    page.wait_for_function("() => window.lodViewer?.status().level != null")
    return page, errors, packets


def _check_exact(page, server, mesh, status):
    faces, digest = _expected(server, mesh["id"], status["level"])
    assert status["faces"] == faces
    assert page.evaluate("lodViewer.hash()") == digest


@pytest.mark.parametrize("failure", ["503", "network"])
def test_a_failed_packet_is_retried_and_streaming_goes_on(failure, chromium, server, spot):
    """The first packet request fails (a 503, or the connection drops); the
    viewer says it retries, asks again after a backoff, and reaches full detail
    exactly. (Before: one failed packet stopped streaming for good.)"""
    failed = []

    def route(request_route):
        if not failed:
            failed.append(request_route.request.url)
            if failure == "503":
                request_route.fulfill(status=503, content_type="application/json",
                                      body=json.dumps({"message": "busy, try again"}))
            else:
                request_route.abort("connectionreset")
        else:
            request_route.continue_()

    page, errors, packets = _open(chromium, server, spot, route)
    try:
        status = page.evaluate(SETTLED_JS, spot["vertices"])
        assert failed, "no packet was requested"
        assert status["error"] is None and status["level"] == spot["vertices"], status
        _check_exact(page, server, spot, status)
        texts = page.evaluate("window.statusTexts")
        assert any("retrying in" in text for text in texts), texts
        assert packets.count(failed[0]) >= 2          # the failed packet was asked again
        assert not errors, errors
    finally:
        page.close()


def test_a_refused_packet_stops_the_mesh_with_its_reason(chromium, server, spot):
    """A 4xx other than 408/429 is not retried: the status names the reason."""
    def route(request_route):
        request_route.fulfill(status=404, content_type="application/json",
                              body=json.dumps({"message": "no mesh with this id"}))

    page, errors, packets = _open(chromium, server, spot, route)
    try:
        page.wait_for_function("() => lodViewer.status().error !== null")
        status = page.evaluate("lodViewer.status()")
        assert "no mesh with this id" in status["error"]
        assert len(set(packets)) == len(packets)      # none asked twice
        assert "error: no mesh with this id" in page.evaluate("window.statusTexts").pop()
        assert not errors, errors
    finally:
        page.close()


def test_packets_are_pipelined_grow_and_land_exactly(chromium, server, sphere):
    """Several packets in flight at once, later ones bigger than the first, each
    cut at a multiple of its size; at most one draw per animation frame; the
    level reached is the server's, to the bit, forward and back."""
    in_flight, most = set(), [0]

    def started(request):
        if "/splits?" in request.url:
            in_flight.add(request.url)
            most[0] = max(most[0], len(in_flight))

    page, errors, packets = _open(chromium, server, sphere, listeners=[
        ("request", started),
        ("requestfinished", lambda request: in_flight.discard(request.url))])
    try:
        status = page.evaluate(SETTLED_JS, sphere["vertices"])
        assert status["error"] is None and status["level"] == sphere["vertices"], status
        _check_exact(page, server, sphere, status)
        spans = []
        for url in packets:
            query = dict(part.split("=") for part in url.split("?", 1)[1].split("&"))
            start, stop = int(query["from"]), int(query["to"])
            spans.append((start, stop))
        chunk = page.evaluate("lodViewer.settings.chunkSplits")
        assert spans[0][1] - spans[0][0] <= chunk
        sizes = [stop - start for start, stop in spans]
        assert max(sizes) > chunk, spans                # the packets grew
        # the first packet takes the base to the level chosen for the view
        # (stream.js open()), the others are cut at multiples of a size
        assert spans[0][0] == sphere["base_vertices"], spans
        for start, stop in spans[1:]:
            assert stop == sphere["vertices"] or any(
                stop % (chunk << k) == 0 and stop - start <= chunk << k for k in range(8))
        assert most[0] >= 2, "never more than one packet in flight"
        # the view's draws (the renderer's own count has the environment's
        # PMREM passes too)
        draws = page.evaluate("lodViewer.scene.draws")
        assert draws <= page.evaluate("window.framesSeen"), "more draws than frames"
        # back to the base and up again: exact both ways
        for level in (sphere["base_vertices"] + 7, sphere["vertices"] - 11):
            page.evaluate("""(level) => {
                const input = document.getElementById('level-input');
                input.value = level;
                input.dispatchEvent(new Event('change', { bubbles: true }));
            }""", level)
            status = page.evaluate("lodViewer.settled()")
            assert status["level"] == level, status
            _check_exact(page, server, sphere, status)
        assert not errors, errors
    finally:
        page.close()


@pytest.fixture(scope="module")
def textured(server, tmp_path_factory):
    """A UV sphere with a material using five images (test_materials.py)."""
    from lodserver.io.glb import encode_glb

    from .test_materials import every_channel_sphere

    path = tmp_path_factory.mktemp("textured") / "every_channel.glb"
    path.write_bytes(encode_glb(every_channel_sphere()))
    return upload_and_wait(server, path)


def test_geometry_materials_and_images_are_fetched_at_the_mesh_version(chromium, server,
                                                                       textured):
    """Every level, packet, materials and image request carries the mesh's
    version (``v=``, from GET /meshes/{id}'s urls) and is answered immutable;
    the first level is the base level and one packet from it, both asked for
    before either arrives (one round trip). (Before: unversioned URLs, cached
    for a minute, and the first level as one json document.)"""
    events = []

    def requested(request):
        if "/meshes/" in request.url:
            events.append(("request", request.url))

    def answered(response):
        if "/meshes/" in response.url:
            events.append(("response", response.url, response.headers.get("cache-control")))

    page, errors, packets = _open(chromium, server, textured, listeners=[
        ("request", requested), ("response", answered)])
    try:
        status = page.evaluate(SETTLED_JS, textured["vertices"])
        assert status["error"] is None and status["level"] == textured["vertices"], status
        assert page.evaluate("lodViewer.status().textureBytes") > 0
    finally:
        page.close()
    assert not errors, errors
    version = server.get(f"/meshes/{textured['id']}").json()["version"]
    summary = f"/meshes/{textured['id']}"
    data = [event for event in events if not event[1].split("?")[0].endswith(summary)]
    routes = {event[1].split(summary + "/", 1)[1].split("?")[0].split("/")[0] for event in data}
    assert {"lod", "splits", "materials", "images"} <= routes, routes
    for event in data:
        assert f"v={version}" in event[1], event
        if event[0] == "response":
            assert "immutable" in event[2], event
    requests = [event[1] for event in data if event[0] == "request"]
    first_response = next(i for i, event in enumerate(data) if event[0] == "response")
    early = requests[:sum(1 for event in data[:first_response] if event[0] == "request")]
    base = textured["base_vertices"]
    assert any(f"/lod?" in url and f"vertices={base}" in url for url in early), early
    assert any("/splits?" in url and f"from={base}&" in url for url in early), early
