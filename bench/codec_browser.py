"""How fast the browser decodes and applies a version 4 packet, against version 3,
in one run of headless Chromium (Playwright over Debian's binary, software GL).

For each mesh, the base -> full packet (one packet, all splits) is encoded three
ways (``encode_packet``, ``encode_packet_v4`` at its default flags, and as
``v4 edge`` with the split edge alone, without ``RING_POSITIONS``: what the ring
prediction costs the browser), and the page
(``static/`` served on loopback by ``static_server.py``) times, per repeat and
alternating the versions: ``LodState.readPacket`` (v3: inflate and cut the
streams; v4: checksum, rANS symbols, back to version 3's streams) and
``LodState.apply`` (the records), each on a fresh state made from the base
level's json form. Prints milliseconds and splits per second, median of the
repeats (the first repeat, JIT warm-up, dropped). The v4 result is checked
against the v3 result (the same positions and faces). The full -> base packet
(collapses, version 3) is timed too, applied to the state the v3 packet left,
and so is ``LevelMesh.update`` (``static/levelmesh.js``) of the full level the
v3 packet reached: what the viewer does to its buffers before three.js uploads
them (positions to floats, vertex normals), without the GL calls.

``--against DIR`` serves another build's ``static/`` (say the main checkout's)
on a second page of the same browser and times it too, the two pages
alternating repeat by repeat, and prints each packet's paired ratio (the
median over repeats of the other build's read + apply over this one's): the
machine's load changes both alike.

    PYTHONPATH=$PWD python bench/codec_browser.py bunny_loop2 stanford-bunny
    PYTHONPATH=$PWD python bench/codec_browser.py bunny_loop2 --repeats 7
    PYTHONPATH=$PWD python bench/codec_browser.py bunny_loop2 --against /work/main/static
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import shutil
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from codec_meshes import progressive  # noqa: E402
from static_server import serve  # noqa: E402

from lodserver.packets import encode_packet, grid_of, quantized_level  # noqa: E402
from lodserver.packets.encode_v4 import encode_packet_v4  # noqa: E402
from lodserver.packets.format import EDGE_POSITIONS  # noqa: E402

STATIC = Path(__file__).resolve().parents[1] / "static"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

# A blank page with the viewer's import map (three.js from static/vendor/).
PAGE = ('<!doctype html><script type="importmap">{"imports": {"three": '
        '"/vendor/three/build/three.module.js", "three/addons/": "/vendor/three/examples/jsm/"}}'
        '</script>')

# One repeat: each packet up (base -> full) on a fresh state, then the packet
# down applied to the state the first one left; the time of each read and apply
# and a hash of each end state.
TIME_JS = """async ({ document, capacity, packets, down }) => {
  const { LodState } = await import('/vsplit.js');
  const { LevelMesh } = await import('/levelmesh.js');
  const bytesOf = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const hash = (state) => {
    let h = 0;
    const p = state.positions, f = state.faces;
    for (let k = 0; k < 3 * state.vertexCount; k++) h = (Math.imul(h, 31) + p[k]) | 0;
    for (let k = 0; k < 3 * state.faceCount; k++) h = (Math.imul(h, 31) + f[k]) | 0;
    return [state.vertexCount, state.faceCount, h];
  };
  const times = [], ends = [];
  let first = null;
  const run = async (state, bytes) => {
    const t0 = performance.now();
    const packet = await LodState.readPacket(bytes);
    const t1 = performance.now();
    state.apply(packet);
    const t2 = performance.now();
    times.push({ read: t1 - t0, apply: t2 - t1 });
    ends.push(hash(state));
  };
  for (const b64 of packets) {
    const state = LodState.fromJson(document, capacity);
    await run(state, bytesOf(b64));
    first = first || state;
  }
  const mesh = new LevelMesh(first);
  const t0 = performance.now();
  mesh.update(first.takeDirty());
  const update = performance.now() - t0;
  mesh.dispose();
  await run(first, bytesOf(down));
  return { times, ends, update };
}"""


def document_of(state, wedge_capacity):
    """The json level document of a quantized state (docs/packets.md, "Exactness")."""
    document = {"grid": {"origin": list(state.grid.origin), "step": state.grid.step,
                         "bits": state.grid.bits},
                "positions": state.positions.tolist(), "faces": state.faces.tolist()}
    if state.attribute_grids:
        document["layout"] = [[g.name, g.width] for g in state.attribute_grids]
        document["attribute_grid"] = {g.name: {"encoding": g.encoding, "origin": list(g.origin),
                                               "step": g.step, "bits": g.bits}
                                      for g in state.attribute_grids}
        document["wedge_capacity"] = wedge_capacity
        document["wedges"] = state.wedges.tolist()
        document["corners"] = state.corners.tolist()
    if state.face_material is not None:
        document["face_material"] = state.face_material.tolist()
    return document


def measure(pages, name, repeats, bits):
    """Times the packets of ``name`` on each page (``{build: page}``), the pages
    alternating repeat by repeat; prints medians and, with two builds, ratios."""
    pm = progressive(name)
    n0, n = pm.base_vertices, pm.vertex_count
    grid = grid_of(pm, bits=bits)
    base = quantized_level(pm, n0, grid)
    full = quantized_level(pm, n, grid)
    packets = {"v3": encode_packet(pm, n0, n, bits=bits),
               "v4": encode_packet_v4(pm, n0, n, bits=bits),
               "v4 edge": encode_packet_v4(pm, n0, n, bits=bits, flags=EDGE_POSITIONS),
               "v3 down": encode_packet(pm, n, n0, bits=bits)}
    up = list(packets)[:-1]
    argument = {
        "document": document_of(base, 0 if full.wedges is None else len(full.wedges)),
        "capacity": {"vertexCapacity": n, "faceCapacity": int(pm.face_counts[-1])},
        "packets": [base64.b64encode(packets[v]).decode() for v in up],
        "down": base64.b64encode(packets["v3 down"]).decode()}
    totals = {build: {v: [] for v in packets} for build in pages}
    reads = {build: {v: [] for v in packets} for build in pages}
    updates = {build: [] for build in pages}
    for _ in range(repeats):
        for build, page in pages.items():
            result = page.evaluate(TIME_JS, argument)
            ends = result["ends"]
            assert all(e == ends[0] for e in ends[1:-1]), \
                f"{build}: v3 and v4 end on different states: {ends}"
            assert ends[0][:2] == [n, int(pm.face_counts[-1])], ends
            assert ends[-1][:2] == [n0, int(pm.face_counts[0])], ends
            updates[build].append(result["update"])
            for version, times in zip(packets, result["times"]):
                totals[build][version].append(times["read"] + times["apply"])
                reads[build][version].append(times["read"])
    splits = n - n0
    print(f"{name}: {splits} splits, bits {grid.bits}, repeats {repeats} (first dropped)")
    for build in pages:
        for version, data in packets.items():
            total = statistics.median(totals[build][version][1:])
            read = statistics.median(reads[build][version][1:])
            print(f"  {build:5s} {version:7s}: {len(data) / 1024:8.1f} KB  read {read:7.1f} ms  "
                  f"apply {total - read:7.1f} ms  read+apply {total:7.1f} ms = "
                  f"{splits / total * 1e3 / 1e6:.2f} M splits/s (all: "
                  f"{', '.join(f'{x:.0f}' for x in totals[build][version])} ms)")
        print(f"  {build:5s} LevelMesh.update of the full level: "
              f"{statistics.median(updates[build][1:]):7.1f} ms")
    if len(pages) == 2:
        here, other = pages
        for version in packets:
            ratios = [b / a for a, b in zip(totals[here][version][1:], totals[other][version][1:])]
            print(f"  {other}/{here} {version}: read+apply x{statistics.median(ratios):.2f} "
                  f"(paired repeats: {', '.join(f'{r:.2f}' for r in ratios)})")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("meshes", nargs="*", default=["bunny_loop2"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--bits", type=int, default=None)
    parser.add_argument("--against", type=Path, default=None,
                        help="another build's static/ folder, timed alternating with this one")
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright
    executable = shutil.which("chromium") or shutil.which("chromium-browser")
    if executable is None:
        raise SystemExit("no chromium binary on PATH (Debian: apt-get install chromium)")
    builds = {"this": STATIC}
    if args.against is not None:
        builds["other"] = args.against
    with contextlib.ExitStack() as stack, sync_playwright() as playwright:
        urls = {build: stack.enter_context(serve(folder)) for build, folder in builds.items()}
        browser = playwright.chromium.launch(executable_path=executable, args=ARGS)
        try:
            pages = {}
            for build, url in urls.items():
                pages[build] = browser.new_page()
                pages[build].route(f"{url}/bench.html", lambda route: route.fulfill(
                    body=PAGE, content_type="text/html"))
                pages[build].goto(f"{url}/bench.html")
            for name in args.meshes:
                measure(pages, name, args.repeats, args.bits)
        finally:
            browser.close()


if __name__ == "__main__":
    main()
