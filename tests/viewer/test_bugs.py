"""The viewer's bugs of issue 13, each driven in headless Chromium the way a
user meets it (each test failed before its fix):

* a mesh id that is a path (``?mesh=..%2F..%2Fhealthz``) polled ``/healthz`` for ever;
* arrow keys on the focused mesh dropdown switched meshes;
* the dropdown's statuses never refreshed ("queued" after the mesh was ready);
* clearing the level box jumped to the base level;
* an unknown id stayed in the dropdown with the level slider enabled;
* "received" counted geometry but not textures.
"""

import pytest

from ..meshes import DATA, textured_spot_glb
from ..server import upload_and_wait

VIEWPORT = {"width": 960, "height": 640}


@pytest.fixture(scope="module")
def meshes(server, tmp_path_factory):
    """Two built meshes: spot (OBJ, no texture) and the textured spot (GLB)."""
    folder = tmp_path_factory.mktemp("bug-meshes")
    textured = folder / "textured_spot.glb"
    textured.write_bytes(textured_spot_glb())
    built = {"spot": upload_and_wait(server, DATA / "spot.obj"),
             "textured": upload_and_wait(server, textured)}
    _warm(server, built)
    return built


def _warm(server, built):
    """Ask each mesh for a level and a packet once: a server whose kernel cache
    is cold compiles them on first use (tens of seconds), which no page waits for."""
    for mesh in built.values():
        server.get(f"/meshes/{mesh['id']}/lod", params={"ratio": 0.5, "format": "json"})
        server.get(f"/meshes/{mesh['id']}/splits",
                   params={"from": mesh["base_vertices"], "to": mesh["vertices"]})


def _open(chromium, server, query, *, wait=True):
    page = chromium.new_page(viewport=VIEWPORT)
    page.errors = []
    page.on("pageerror", lambda error: page.errors.append(error))
    page.goto(f"{server.base_url}/viewer/?{query}")
    if wait:
        page.wait_for_function("() => window.lodViewer?.status().level != null")
        page.evaluate("lodViewer.settled()")
    return page


def test_a_path_given_as_the_mesh_id_is_refused_not_followed(chromium, server, meshes):
    page = chromium.new_page(viewport=VIEWPORT)
    requests = []
    page.on("request", lambda request: requests.append(request.url))
    try:
        page.goto(f"{server.base_url}/viewer?mesh=..%2F..%2Fhealthz")
        page.wait_for_function("() => document.getElementById('status').textContent.includes("
                               "'no mesh')")
        page.wait_for_timeout(1500)       # the old page polled every 500 ms
        assert not any(url.endswith("/healthz") for url in requests), requests
        assert page.evaluate("document.getElementById('level-slider').disabled")
        assert "/" not in page.evaluate("document.getElementById('status').textContent")
    finally:
        page.close()


def test_arrow_keys_on_the_mesh_dropdown_move_the_level_not_the_mesh(chromium, server, meshes):
    mesh = meshes["spot"]
    page = _open(chromium, server, f"mesh={mesh['id']}")
    try:
        page.focus("#mesh-select")
        for key in ("ArrowDown", "ArrowUp", "ArrowLeft"):
            before = page.evaluate("lodViewer.status()")
            page.keyboard.press(key)
            status = page.evaluate("lodViewer.settled()")
            assert status["mesh"] == mesh["id"], key          # the same mesh
            assert page.evaluate("document.getElementById('mesh-select').value") == mesh["id"]
            moved = {"ArrowDown": lambda a, b: b < a, "ArrowUp": lambda a, b: b > a,
                     "ArrowLeft": lambda a, b: b < a}[key]
            assert moved(before["level"], status["level"]), (key, before, status)
        assert not page.errors
    finally:
        page.close()


def test_the_dropdown_statuses_refresh(chromium, server, meshes):
    """The list first answers that the mesh is queued (as when the page opened
    during its build); the dropdown must come to say ready by itself."""
    mesh = meshes["spot"]
    page = chromium.new_page(viewport=VIEWPORT)
    answered = []

    def stale_list(route):
        response = route.fetch()
        body = response.json()
        if not answered:          # the first listing only
            for each in body["meshes"]:
                each.update(status="queued", vertices=None)
        answered.append(True)
        # (not response=: its headers may name an encoding this body no longer has)
        route.fulfill(status=response.status, json=body)

    try:
        page.route("**/meshes?limit=*", stale_list)
        page.goto(f"{server.base_url}/viewer/?mesh={meshes['textured']['id']}")
        page.wait_for_function("""(id) => [...document.getElementById('mesh-select').options]
            .some((o) => o.value === id && o.textContent.includes('ready'))""",
                               arg=mesh["id"], timeout=30000)
        assert len(answered) >= 2
    finally:
        page.close()


def test_clearing_the_level_box_keeps_the_level(chromium, server, meshes):
    mesh = meshes["spot"]
    page = _open(chromium, server, f"mesh={mesh['id']}&level={mesh['vertices']}")
    try:
        before = page.evaluate("lodViewer.status()")
        assert before["level"] == mesh["vertices"]
        page.fill("#level-input", "")
        page.dispatch_event("#level-input", "change")
        status = page.evaluate("lodViewer.settled()")
        assert status["level"] == before["level"], status
        assert page.input_value("#level-input") == str(before["level"])
        page.fill("#level-input", str(mesh["base_vertices"] + 100))      # a number still works
        page.dispatch_event("#level-input", "change")
        assert page.evaluate("lodViewer.settled()")["level"] == mesh["base_vertices"] + 100
    finally:
        page.close()


def test_an_unknown_id_is_not_listed_and_the_level_stays_disabled(chromium, server, meshes):
    unknown = "A" * 22               # an id's shape, no such mesh
    page = _open(chromium, server, f"mesh={unknown}", wait=False)
    try:
        page.wait_for_function("() => document.getElementById('status').textContent.includes("
                               "'no mesh')")
        values = page.evaluate("[...document.getElementById('mesh-select').options]"
                               ".map((o) => o.value)")
        assert unknown not in values and meshes["spot"]["id"] in values
        assert page.evaluate("document.getElementById('level-slider').disabled")
        assert page.evaluate("document.getElementById('level-input').disabled")
        assert "mesh=" not in page.url
        # choosing a real mesh enables the level again
        page.select_option("#mesh-select", meshes["spot"]["id"])
        page.wait_for_function("() => window.lodViewer.status().level != null")
        page.evaluate("lodViewer.settled()")
        assert not page.evaluate("document.getElementById('level-slider').disabled")
    finally:
        page.close()


def test_received_counts_textures(chromium, server, meshes):
    mesh = meshes["textured"]
    image = server.get(f"/meshes/{mesh['id']}/images/0").content
    page = _open(chromium, server, f"mesh={mesh['id']}")
    try:
        status = page.evaluate("lodViewer.status()")
        assert status["textureBytes"] == len(image), status
        rows = dict(page.evaluate("""[...document.querySelectorAll('#stats tr')]
            .map((row) => [row.cells[0].textContent, row.cells[1].textContent])"""))
        assert "textures" in rows["received"], rows
        kib = (status["bytes"] + status["textureBytes"]) / 1024
        shown = rows["received"].split(" (")[0]
        value = float(shown.split()[0]) * (1024 if "MiB" in shown else 1)
        assert value == pytest.approx(kib, abs=0.1 if "KiB" in shown else 11), rows
    finally:
        page.close()
