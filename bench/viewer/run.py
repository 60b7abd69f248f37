"""The viewer in Chromium: splits applied per second, and screenshots at three levels.

    python bench/viewer/run.py [--mesh PATH] [--shots PATH ...] [--repeats N] [--out DIR]

Starts ``lodserver serve`` on a free loopback port with a temporary data
directory, uploads the meshes, and in headless Chromium (Debian's
``chromium``, driven by Playwright):

1. imports the viewer's decoder (``static/vsplit.js``) into a page and times
   ``LodState.apply`` alone (``performance.now()``; fetching and inflating
   are timed apart) for the packet from the base level to full detail, the
   collapses back, and the same splits cut into the viewer's 4096-split
   packets; each on a fresh state, ``--repeats`` times after one cold run;
2. opens ``/viewer?mesh=ID`` and times it from the page load to full detail;
3. screenshots the viewer at about 1%, 10% and 100% of each mesh's vertices.

Writes ``result.json`` and the PNGs to ``bench/out/viewer/`` (gitignored).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import httpx
from playwright.sync_api import sync_playwright

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from tests.server import serve

SHARED = ROOT.parent / "shared" / "meshes"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync"]
VIEWPORT = {"width": 1200, "height": 800}
SHOT_RATIOS = (0.01, 0.1, 1.0)

# Runs in a page of the server's origin; times the decoder alone.
APPLY_JS = """async ({ id, repeats, chunk }) => {
  const { LodState } = await import('/viewer/vsplit.js');
  const info = await (await fetch(`/meshes/${id}`)).json();
  const [base, full] = [info.base_vertices, info.vertices];
  const document = await (await fetch(`/meshes/${id}/lod?vertices=${base}&format=json`)).json();
  const capacity = { vertexCapacity: full, faceCapacity: info.faces };
  const fresh = () => LodState.fromJson(document, capacity);
  const fetchPacket = async (from, to) =>
    new Uint8Array(await (await fetch(`/meshes/${id}/splits?from=${from}&to=${to}`)).arrayBuffer());

  const forwardBytes = await fetchPacket(base, full), backwardBytes = await fetchPacket(full, base);
  let started = performance.now();
  const forward = await LodState.readPacket(forwardBytes);
  const inflateMs = performance.now() - started;
  const backward = await LodState.readPacket(backwardBytes);
  const chunks = [];
  for (let from = base, to; from < full; from = to) {
    to = Math.min(full, (Math.floor(from / chunk) + 1) * chunk);    // as the viewer cuts them
    chunks.push(await LodState.readPacket(await fetchPacket(from, to)));
  }

  const runs = { forward: [], backward: [], chunked: [] };
  for (let r = 0; r <= repeats; r++) {
    let state = fresh();
    started = performance.now();
    state.apply(forward);
    const forwardMs = performance.now() - started;
    started = performance.now();
    state.apply(backward);
    const backwardMs = performance.now() - started;
    state = fresh();
    started = performance.now();
    for (const packet of chunks) state.apply(packet);
    const chunkedMs = performance.now() - started;
    runs.forward.push(forwardMs);
    runs.backward.push(backwardMs);
    runs.chunked.push(chunkedMs);
  }
  return { splits: full - base, base, full, faces: info.faces, forwardBytes: forwardBytes.length,
           backwardBytes: backwardBytes.length, chunks: chunks.length, inflateMs, runs };
}"""

SET_LEVEL_JS = """(level) => {
  const input = document.getElementById('level-input');
  input.value = level;
  input.dispatchEvent(new Event('change', { bubbles: true }));
}"""


def upload(client: httpx.Client, path: Path) -> dict:
    """Upload a mesh and wait for its build; its summary."""
    with open(path, "rb") as file:
        created = client.post("/meshes", files={"file": (path.name, file)})
    created.raise_for_status()
    mesh_id = created.json()["id"]
    while (summary := client.get(f"/meshes/{mesh_id}").json())["status"] != "ready":
        if summary["status"] == "failed":
            raise SystemExit(f"{path.name}: the build failed: {summary['failure']}")
        time.sleep(0.3)
    return summary


def _rates(splits: int, times_ms: list[float]) -> dict:
    """Cold run apart; millions of records per second, median and best of the warm runs."""
    warm = times_ms[1:]
    return {"cold_ms": round(times_ms[0], 2), "median_ms": round(statistics.median(warm), 2),
            "best_ms": round(min(warm), 2),
            "median_M_per_s": round(splits / statistics.median(warm) / 1e3, 3),
            "best_M_per_s": round(splits / min(warm) / 1e3, 3)}


def measure_apply(browser, client, mesh: dict, repeats: int, chunk: int) -> dict:
    page = browser.new_page()
    # a document under /viewer/ (the decoder's own file, so the viewer app does not start):
    # the viewer's CSP lets it import the decoder; the API's (/healthz) forbids scripts
    page.goto(f"{client.base_url}/viewer/vsplit.js")
    raw = page.evaluate(APPLY_JS, {"id": mesh["id"], "repeats": repeats, "chunk": chunk})
    page.close()
    splits = raw["splits"]
    return {"splits": splits, "faces": raw["faces"], "repeats": repeats,
            "packet_bytes": {"forward": raw["forwardBytes"], "backward": raw["backwardBytes"],
                             "forward_per_split": round(raw["forwardBytes"] / splits, 2)},
            "inflate_ms": round(raw["inflateMs"], 2),
            "rates": {"splits": _rates(splits, raw["runs"]["forward"]),
                      "collapses": _rates(splits, raw["runs"]["backward"]),
                      f"splits_in_{raw['chunks']}_packets": _rates(splits, raw["runs"]["chunked"])}}


def open_viewer(browser, client, mesh: dict):
    page = browser.new_page(viewport=VIEWPORT)
    page.on("pageerror", lambda error: print(f"page error: {error}", file=sys.stderr))
    started = time.perf_counter()
    page.goto(f"{client.base_url}/viewer?mesh={mesh['id']}")
    # a function, not an expression string: Playwright polls a string with eval(),
    # which the viewer's script-src (no 'unsafe-eval') refuses
    page.wait_for_function("() => window.lodViewer?.status().level != null")
    status = page.evaluate("lodViewer.settled()")
    return page, {"to_full_detail_s": round(time.perf_counter() - started, 3), **status}


def screenshots(browser, client, mesh: dict, name: str, out: Path) -> list[str]:
    page, _ = open_viewer(browser, client, mesh)
    written = []
    for ratio in SHOT_RATIOS:
        level = max(mesh["base_vertices"], round(ratio * mesh["vertices"]))
        page.evaluate(SET_LEVEL_JS, level)
        status = page.evaluate("lodViewer.settled()")
        path = out / f"{name}-{status['level']}.png"
        page.screenshot(path=str(path))
        written.append(path.name)
    page.close()
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=SHARED / "stanford-bunny.obj",
                        help="the mesh whose splits are timed (default: the Stanford bunny)")
    parser.add_argument("--shots", type=Path, nargs="*",
                        default=[SHARED / "Duck.glb",
                                 SHARED / "bunny10k_textured" / "bunny10k_textured.obj",
                                 SHARED / "stanford-bunny.obj"],
                        help="meshes to screenshot at three levels")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--chunk", type=int, default=4096, help="splits per packet, as the viewer")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "viewer")
    args = parser.parse_args()
    executable = shutil.which("chromium") or shutil.which("chromium-browser")
    if executable is None:
        raise SystemExit("no chromium binary on PATH (Debian: apt-get install chromium)")
    args.out.mkdir(parents=True, exist_ok=True)

    result = {"machine": {"cpus": os.cpu_count(), "load_average": os.getloadavg()}}
    with tempfile.TemporaryDirectory(prefix="lodserver-viewer-") as data, \
            serve(Path(data), warm_kernels=True, timeout=120) as client, sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=executable, args=CHROMIUM_ARGS)
        result["chromium"] = browser.version
        meshes = {path: upload(client, path) for path in dict.fromkeys([args.mesh, *args.shots])}
        result["apply"] = {"mesh": args.mesh.name,
                           **measure_apply(browser, client, meshes[args.mesh], args.repeats,
                                           args.chunk)}
        page, result["viewer"] = open_viewer(browser, client, meshes[args.mesh])
        page.close()
        result["screenshots"] = [shot for path in args.shots
                                 for shot in screenshots(browser, client, meshes[path], path.stem,
                                                         args.out)]
        browser.close()
    result["machine"]["load_average_after"] = os.getloadavg()
    (args.out / "result.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
