"""How fast the browser decodes and applies a version 4 packet, against version 3,
in one run of headless Chromium (Playwright over Debian's binary, software GL).

For each mesh, the base -> full packet (one packet, all splits) is encoded both
ways (``encode_packet``, ``encode_packet_v4`` at its default flags), and the page
(``static/`` served on loopback by ``static_server.py``) times, per repeat and
alternating the versions: ``LodState.readPacket`` (v3: inflate and cut the
streams; v4: checksum, rANS symbols, back to version 3's streams) and
``LodState.apply`` (the records), each on a fresh state made from the base
level's json form. Prints milliseconds and splits per second, median of the
repeats (the first repeat, JIT warm-up, dropped). The v4 result is checked
against the v3 result (the same positions and faces).

    PYTHONPATH=$PWD python bench/codec_browser.py bunny_loop2 stanford-bunny
    PYTHONPATH=$PWD python bench/codec_browser.py bunny_loop2 --repeats 7
"""

from __future__ import annotations

import argparse
import base64
import shutil
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from codec_meshes import progressive  # noqa: E402
from static_server import serve  # noqa: E402

from lodserver.packets import encode_packet, grid_of, quantized_level  # noqa: E402
from lodserver.packets.encode_v4 import encode_packet_v4  # noqa: E402

STATIC = Path(__file__).resolve().parents[1] / "static"
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

TIME_JS = """async ({ document, capacity, packets, repeats }) => {
  const { LodState } = await import('/vsplit.js');
  const bytesOf = (b64) => Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
  const data = packets.map(bytesOf);
  const times = data.map(() => ({ read: [], apply: [] }));
  const ends = [];
  for (let r = 0; r < repeats; r++) {
    for (let i = 0; i < data.length; i++) {
      const state = LodState.fromJson(document, capacity);
      const t0 = performance.now();
      const packet = await LodState.readPacket(data[i].slice());
      const t1 = performance.now();
      state.apply(packet);
      const t2 = performance.now();
      times[i].read.push(t1 - t0);
      times[i].apply.push(t2 - t1);
      if (r === 0) {
        let h = 0;
        const p = state.positions, f = state.faces;
        for (let k = 0; k < 3 * state.vertexCount; k++) h = (Math.imul(h, 31) + p[k]) | 0;
        for (let k = 0; k < 3 * state.faceCount; k++) h = (Math.imul(h, 31) + f[k]) | 0;
        ends.push([state.vertexCount, state.faceCount, h]);
      }
    }
  }
  return { times, ends };
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


def measure(page, name, repeats, bits):
    pm = progressive(name)
    n0, n = pm.base_vertices, pm.vertex_count
    grid = grid_of(pm, bits=bits)
    base = quantized_level(pm, n0, grid)
    full = quantized_level(pm, n, grid)
    packets = {"v3": encode_packet(pm, n0, n, bits=bits),
               "v4": encode_packet_v4(pm, n0, n, bits=bits)}
    result = page.evaluate(TIME_JS, {
        "document": document_of(base, 0 if full.wedges is None else len(full.wedges)),
        "capacity": {"vertexCapacity": n, "faceCapacity": int(pm.face_counts[-1])},
        "packets": [base64.b64encode(p).decode() for p in packets.values()],
        "repeats": repeats})
    ends = result["ends"]
    assert ends[0] == ends[1], f"v3 and v4 end on different states: {ends}"
    assert ends[0][:2] == [n, int(pm.face_counts[-1])], ends
    splits = n - n0
    print(f"{name}: {splits} splits, bits {grid.bits}, repeats {repeats} (first dropped)")
    for (version, data), times in zip(packets.items(), result["times"]):
        read = statistics.median(times["read"][1:])
        apply = statistics.median(times["apply"][1:])
        total = statistics.median([a + b for a, b in zip(times["read"][1:],
                                                         times["apply"][1:])])
        print(f"  {version}: {len(data) / 1024:8.1f} KB  read {read:7.1f} ms  apply "
              f"{apply:7.1f} ms  read+apply {total:7.1f} ms = "
              f"{splits / total * 1e3 / 1e6:.2f} M splits/s "
              f"(all read+apply: {', '.join(f'{a + b:.0f}' for a, b in zip(times['read'], times['apply']))} ms)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("meshes", nargs="*", default=["bunny_loop2"])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--bits", type=int, default=None)
    args = parser.parse_args()
    from playwright.sync_api import sync_playwright
    executable = shutil.which("chromium") or shutil.which("chromium-browser")
    if executable is None:
        raise SystemExit("no chromium binary on PATH (Debian: apt-get install chromium)")
    with serve(STATIC) as url, sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=executable, args=ARGS)
        try:
            page = browser.new_page()
            page.goto(f"{url}/packet.js")
            for name in args.meshes:
                measure(page, name, args.repeats, args.bits)
        finally:
            browser.close()


if __name__ == "__main__":
    main()
