"""Scenes in the viewer (issue 13 item 2, static/animated.js): a glTF scene the
server keeps with its node tree is loaded as the GLB of its first level, its
animations played by three.js's AnimationMixer (clip chooser, play/pause, a time
scrubber), and each part refined by its own packet stream, the skinned mesh still
animating. Uses ../shared/meshes/scenes/Fox.glb (one skinned mesh, 24 joints,
three clips) uploaded to a real ``lodserver serve``; a single mesh is unchanged.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from ..meshes import DATA, SHARED
from ..server import upload_and_wait
from .test_viewer import RECORD_VIOLATIONS_JS, VIEWPORT, _expected

FOX = SHARED / "scenes" / "Fox.glb"
CLIPS = ["Survey", "Walk", "Run"]
# Grid values stored per wedge by encoding (docs/packets.md), else the width.
ENCODING_COMPONENTS = {"octahedral": 2, "tangent": 3}

# The part's skinned mesh as drawn: its vertex count, whether it is skinned, its
# skin attributes' counts, and the world positions of the skeleton's joints.
MESH_JS = """() => {
  const { root } = lodViewer.animated.three;
  let mesh = null;
  root.traverse((o) => { if (o.isMesh && o.userData.lodserver_part === 0) mesh = o; });
  const g = mesh.geometry;
  root.updateMatrixWorld(true);
  const joints = mesh.isSkinnedMesh ? mesh.skeleton.bones.map((b) =>
    b.getWorldPosition(new lodViewer.scene.three.THREE.Vector3()).toArray()) : [];
  return { vertices: g.getAttribute('position').count, skinned: !!mesh.isSkinnedMesh,
           skinIndex: g.getAttribute('skinIndex')?.count ?? 0,
           skinWeight: g.getAttribute('skinWeight')?.count ?? 0,
           faces: g.index.count / 3, joints };
}"""


def _box(page):
    box = page.evaluate("lodViewer.animated.box(0)")
    return np.array(box["min"]), np.array(box["max"])


def _pose_at(page, seconds):
    """(box min, box max, joints, pixels hash) of part 0 posed at `seconds` of the clip."""
    page.evaluate("(t) => lodViewer.animated.setTime(t)", seconds)
    page.evaluate("lodViewer.scene.rendered()")
    low, high = _box(page)
    drawn = page.evaluate("""() => {
        const { data } = lodViewer.scene.pixels();
        let sum = 0;
        for (let i = 0; i < data.length; i += 97) sum = (sum * 31 + data[i]) % 1000000007;
        return sum;
    }""")
    return low, high, np.array(page.evaluate(MESH_JS)["joints"]), drawn


def _assert_moves_with_joints(page):
    """Two poses of the clip: the skinned box and the joints both move, and each
    pose's box holds its joints (within a tenth of the box's diagonal)."""
    duration = page.evaluate("lodViewer.status().animation.clips[lodViewer.status()"
                             ".animation.clip].duration")
    first = _pose_at(page, 0.1 * duration)
    second = _pose_at(page, 0.6 * duration)
    diagonal = np.linalg.norm(first[1] - first[0])
    moved = max(np.abs(first[0] - second[0]).max(), np.abs(first[1] - second[1]).max())
    assert moved > 0.01 * diagonal, (first[:2], second[:2])
    assert np.abs(first[2] - second[2]).max() > 0.01 * diagonal     # the joints moved
    assert first[3] != second[3]                                    # and so did the picture
    for low, high, joints, _ in (first, second):
        slack = 0.1 * np.linalg.norm(high - low)
        assert np.all(joints >= low - slack) and np.all(joints <= high + slack)


SKIN_JS = """() => {
  const { root } = lodViewer.animated.three;
  let mesh = null;
  root.traverse((o) => { if (o.isMesh && o.userData.lodserver_part === 0) mesh = o; });
  const g = mesh.geometry;
  return { joints: Array.from(g.getAttribute('skinIndex').array),
           weights: Array.from(g.getAttribute('skinWeight').array) };
}"""


def _assert_skin_is_the_levels(page, document, part):
    """With JOINTS_0/WEIGHTS_0 in the part's layout, the drawn skin is the streamed
    level's, wedge for wedge (the json level's grid values, dequantized); without,
    it was kept from the GLB (partgeometry.js: transfer)."""
    names = [name for name, _ in document.get("layout", [])]
    if "JOINTS_0" not in names:
        assert set(part["attributes"]["kept"]) >= {"skinIndex", "skinWeight"}, part
        return
    assert {"skinIndex", "skinWeight"} <= set(part["attributes"]["streamed"]), part
    wedges = np.asarray(document["wedges"], dtype=np.float64)
    drawn = page.evaluate(SKIN_JS)
    column = 0
    for name, width in document["layout"]:
        grid = document["attribute_grid"][name]
        if name in ("JOINTS_0", "WEIGHTS_0"):
            assert grid["encoding"] == "linear"
            values = np.asarray(grid["origin"]) + wedges[:, column:column + width] * grid["step"]
            got = np.asarray(drawn["joints" if name == "JOINTS_0" else "weights"]).reshape(-1, 4)
            assert np.allclose(got, values, atol=1e-6), name
        column += ENCODING_COMPONENTS.get(grid["encoding"], width)
    joints = np.asarray(drawn["joints"])
    assert np.array_equal(joints, np.round(joints))         # exact joint indices


@pytest.fixture(scope="module")
def fox(server):
    if not FOX.is_file():
        pytest.skip(f"shared scene not found at {FOX}")
    summary = upload_and_wait(server, FOX)
    assert summary["scene"] is True, "the server does not keep Fox.glb as a scene"
    return summary


def _open(chromium, server, mesh_id, *, hold_splits=False, level=None):
    """A page showing mesh `mesh_id` (at `level` when given: the URL's), its errors and
    CSP violations recorded; with hold_splits, the parts' packet requests are held
    (page.held) until released."""
    page = chromium.new_page(viewport=VIEWPORT)
    page.failures, page.requests, page.held = [], [], []
    page.on("pageerror", lambda error: page.failures.append(error))
    page.on("request", lambda request: page.requests.append(request.url))
    page.add_init_script(RECORD_VIOLATIONS_JS)
    if hold_splits:
        page.released = False
        page.route("**/parts/*/splits?*", lambda route: (
            route.continue_() if page.released else page.held.append(route)))
    page.goto(f"{server.base_url}/viewer?mesh={mesh_id}" + (f"&level={level}" if level else ""))
    return page


def test_a_skinned_scene_animates_while_it_streams(chromium, server, fox):
    page = _open(chromium, server, fox["id"], hold_splits=True, level=fox["vertices"])
    try:
        # the scene as one versioned GLB, its clips listed and the first playing
        page.wait_for_function("() => lodViewer.status().animation?.parts.length > 0")
        page.wait_for_function("() => document.querySelector('#clip-select').options.length > 0")
        status = page.evaluate("lodViewer.status()")
        animation = status["animation"]
        assert status["scene"] is True and [c["name"] for c in animation["clips"]] == CLIPS
        assert animation["playing"] and animation["clip"] == 0
        assert page.evaluate("document.getElementById('animation').hidden") is False
        glb = [url for url in page.requests if "format=glb" in url]
        assert len(glb) == 1 and f"v={fox['version']}" in glb[0]
        # while the part's packets are held back: the GLB's skinned mesh plays
        deadline = time.monotonic() + 30
        while not page.held and time.monotonic() < deadline:
            page.wait_for_timeout(100)
        assert page.held, "the part's stream asked for no packet"
        shown = page.evaluate(MESH_JS)
        assert shown["skinned"] and shown["skinIndex"] == shown["vertices"]
        times = [page.evaluate("lodViewer.status().animation.time")]
        page.wait_for_timeout(600)
        times.append(page.evaluate("lodViewer.status().animation.time"))
        assert times[1] != times[0]                     # the clock runs as it streams
        assert page.evaluate("lodViewer.status().animation.parts[0]")["level"] is None
        page.evaluate("lodViewer.animated.pause()")
        _assert_moves_with_joints(page)
        # the packets let through: the part reaches full detail, still skinned
        page.released = True
        for route in page.held:
            route.continue_()
        page.evaluate("lodViewer.animated.play()")
        status = page.evaluate("lodViewer.settled()")
        part = status["animation"]["parts"][0]
        assert part["error"] is None, part
        assert part["level"] == part["vertices"] == fox["parts"][0]["vertices"]
        assert part["refined"] >= 1
        shown = page.evaluate(MESH_JS)
        document = server.get(f"/meshes/{fox['id']}/parts/0/lod",
                              params={"vertices": part["level"], "format": "json"}).json()
        drawn = len(document["wedges"]) if "layout" in document else document["vertex_count"]
        assert shown["vertices"] == drawn and shown["faces"] == document["face_count"]
        assert shown["skinned"] and shown["skinIndex"] == shown["skinWeight"] == drawn
        _assert_skin_is_the_levels(page, document, part)
        page.evaluate("lodViewer.animated.pause()")
        _assert_moves_with_joints(page)
        assert not page.failures, page.failures
        assert page.evaluate("window.cspViolations") == []
    finally:
        page.close()


def test_clip_choice_pause_and_scrub(chromium, server, fox):
    page = _open(chromium, server, fox["id"])
    try:
        page.wait_for_function("() => document.querySelector('#clip-select').options.length > 0")
        page.evaluate("lodViewer.settled()")
        # the scene is the three.js module's ProgressiveScene, its mixer the one played
        assert page.evaluate("""() => [lodViewer.viewed.object.type,
            lodViewer.viewed.object.mixer === lodViewer.animated.three.mixer]""") == [
            "ProgressiveScene", True]
        page.select_option("#clip-select", "1")                 # Walk
        animation = page.evaluate("lodViewer.status().animation")
        assert animation["clip"] == 1 and animation["playing"]
        # paused: the clock stops and nothing is drawn (frames on demand only)
        page.click("#play-pause")
        assert page.text_content("#play-pause") == "play"
        paused = page.evaluate("lodViewer.status().animation")
        assert not paused["playing"]
        draws = page.evaluate("lodViewer.scene.draws")
        page.wait_for_timeout(800)
        assert page.evaluate("lodViewer.status().animation.time") == paused["time"]
        assert page.evaluate("lodViewer.scene.draws") == draws
        # the scrubber sets the time and draws that pose
        duration = animation["clips"][1]["duration"]
        boxes = []
        for fraction in (0.25, 0.75):
            page.evaluate("""(value) => {
                const scrubber = document.getElementById('time-scrubber');
                scrubber.value = value;
                scrubber.dispatchEvent(new Event('input', { bubbles: true }));
            }""", fraction)
            page.evaluate("lodViewer.scene.rendered()")
            time_now = page.evaluate("lodViewer.status().animation.time")
            assert time_now == pytest.approx(fraction * duration, abs=1e-3)
            boxes.append(_box(page))
        assert max(np.abs(boxes[0][0] - boxes[1][0]).max(),
                   np.abs(boxes[0][1] - boxes[1][1]).max()) > 0
        assert page.evaluate("lodViewer.scene.draws") > draws
        # playing again runs the clock from there
        page.click("#play-pause")
        before = page.evaluate("lodViewer.status().animation.time")
        page.wait_for_timeout(500)
        assert page.evaluate("lodViewer.status().animation.time") != before
        # another clip starts at its beginning
        page.select_option("#clip-select", "2")                 # Run
        assert page.evaluate("lodViewer.status().animation.clip") == 2
        assert not page.failures, page.failures
    finally:
        page.close()


def test_a_single_mesh_is_shown_as_before(chromium, server):
    mesh = upload_and_wait(server, DATA / "spot.obj")
    assert mesh["scene"] is False
    page = _open(chromium, server, mesh["id"], level=mesh["vertices"])
    try:
        page.wait_for_function("() => window.lodViewer?.status().level != null")
        status = page.evaluate("lodViewer.settled()")
        assert "scene" not in status and status["level"] == mesh["vertices"]
        assert page.evaluate("document.getElementById('animation').hidden") is True
        assert page.evaluate("lodViewer.animated.open") is False
        faces, digest = _expected(server, mesh["id"], status["level"])
        assert status["faces"] == faces and page.evaluate("lodViewer.hash()") == digest
        # streamed as one mesh: no GLB, no part URLs
        assert not [url for url in page.requests if "format=glb" in url or "/parts/" in url]
        assert not page.failures, page.failures
    finally:
        page.close()


NEAREST_JS = """async ([points, query]) => {
  const { nearestPoints } = await import('/viewer/nearest.js');
  return Array.from(nearestPoints(Float32Array.from(points), Float32Array.from(query)));
}"""


def test_nearest_points_match_brute_force(chromium, server):
    """nearestPoints (the skin transfer of a level whose vertex count differs from
    the GLB's) against brute force, on clustered points with far-off queries."""
    rng = np.random.default_rng(3)
    points = np.concatenate([rng.normal(0, 1, (300, 3)), rng.normal(8, 0.1, (40, 3))])
    query = np.concatenate([rng.normal(0, 2, (200, 3)), rng.uniform(-30, 30, (20, 3))])
    points, query = points.astype(np.float32), query.astype(np.float32)
    page = chromium.new_page()
    try:
        page.goto(f"{server.base_url}/viewer/nearest.js")
        got = page.evaluate(NEAREST_JS, [points.ravel().tolist(), query.ravel().tolist()])
    finally:
        page.close()
    distances = ((query[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    best = distances.min(1)
    assert np.allclose(distances[np.arange(len(query)), got], best)
