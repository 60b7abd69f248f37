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
3. screenshots the viewer at about 1%, 10% and 100% of each mesh's vertices;
4. with ``--streaming``: time to the first frame and to full detail, and bytes,
   for the Stanford bunny and the 1.1M-face bunny (``--large``, an .npz of
   ``positions``/``faces`` as ``bench/simplify.py`` writes it, uploaded as PLY),
   with default settings, plain and throttled (50 ms, 20 Mbit/s), beside
   fetching the full-detail GLB, and fetching, parsing and drawing it with
   three.js's GLTFLoader (``glb.html``/``glb.js``, served from a temporary copy
   of the viewer's folder as ``/viewer/bench-glb.html``), ``--runs`` times
   each, in turn (``streaming.py``); ``--static DIR`` serves
   another copy of the viewer (e.g. ``git archive HEAD static`` unpacked), so
   two versions are measured side by side in one run (``--static`` twice with
   ``--label`` twice).

    python bench/viewer/run.py --streaming --only-streaming \
        --static /tmp/before/static --label before --static static --label after

``--geomorph`` alone: the largest per-frame pixel change while the bunny's
level moves to 3% and back, geomorphs of 0, 250 and 1000 ms
(``tests/viewer/test_geomorph.py`` measures it).

Writes ``result.json`` (``result-LABELS.json`` with ``--streaming``,
``result-geomorph.json`` with ``--geomorph``) and the PNGs
to ``bench/out/viewer/`` (gitignored).
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

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT))
from tests.server import serve

from streaming import measure_streaming

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


def write_ply(npz: Path, out: Path) -> Path:
    """The .npz's mesh as a binary PLY (float32 positions, int32 faces)."""
    import numpy as np

    data = np.load(npz)
    positions = np.ascontiguousarray(data["positions"], dtype="<f4")
    faces = np.ascontiguousarray(data["faces"], dtype="<i4")
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(positions)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    rows = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    rows["n"], rows["v"] = 3, faces
    with open(out, "wb") as file:
        file.write(header.encode("ascii"))
        file.write(positions.tobytes())
        file.write(rows.tobytes())
    return out


BENCH_PAGE = {"bench-glb.html": HERE / "glb.html", "bench-glb.js": HERE / "glb.js"}


def with_bench_page(static: Path, work: Path) -> Path:
    """A copy of the viewer's folder ``static`` under ``work`` with the GLB
    baseline page added (``BENCH_PAGE``), so one server serves both, the same
    three.js files under the same headers."""
    copy = work / f"static-{len(list(work.glob('static-*')))}"
    shutil.copytree(static, copy)
    for name, source in BENCH_PAGE.items():
        shutil.copyfile(source, copy / name)
    return copy


def run_streaming(args, browser_factory, out: Path) -> dict:
    """--streaming: one server per viewer copy (``--static``), the same meshes."""
    statics = args.static or [ROOT / "static"]
    labels = args.label or ([f"static{i}" for i in range(len(statics))] if args.static
                            else ["viewer"])
    results = {}
    with tempfile.TemporaryDirectory(prefix="lodserver-stream-") as work:
        sources = {"bunny": args.mesh}
        if args.large and args.large.is_file():
            sources["bunny_1.1M"] = write_ply(args.large, Path(work) / "bunny_loop2.ply")
        for label, static in zip(labels, statics):
            data = Path(work) / f"data-{label}"
            served = with_bench_page(Path(static).resolve(), Path(work))
            env = {"LODSERVER_STATIC_DIR": str(served)}
            with serve(data, warm_kernels=True, timeout=300, env=env) as client:
                meshes = {name: upload(client, path) for name, path in sources.items()}
                browser = browser_factory()
                try:
                    results[label] = measure_streaming(
                        browser, client, meshes, viewport=VIEWPORT, timeout_s=args.timeout,
                        out=out, label=label, runs=args.runs)
                finally:
                    browser.close()
    return results


def run_geomorph(args, browser_factory, out: Path) -> dict:
    """--geomorph: the largest per-frame pixel change while the bunny's level moves
    to 3% and back, geomorphs off and on (tests/viewer/test_geomorph.py)."""
    from tests.viewer.test_geomorph import measure_level_change, open_still

    result = {}
    with tempfile.TemporaryDirectory(prefix="lodserver-geomorph-") as data, \
            serve(Path(data), warm_kernels=True, timeout=300) as client:
        mesh = upload(client, args.mesh)
        browser = browser_factory()
        try:
            page = open_still(browser, str(client.base_url), mesh)
            coarse = round(0.03 * mesh["vertices"])
            for glide_ms in (0, 250, 1000):
                for level in (coarse, mesh["vertices"]):
                    m = measure_level_change(page, level, glide_ms)
                    result[f"{glide_ms}ms->{level}"] = {
                        "largest_changed_pixels": m["largest"],
                        "largest_energy": m["largestEnergy"], "frames_changed": len(m["changes"]),
                        "pixels": m["pixels"], "took_ms": round(m["tookMs"])}
                    print(f"geomorph {glide_ms} ms -> {level}: {result[f'{glide_ms}ms->{level}']}",
                          flush=True)
            page.screenshot(path=str(out / "geomorph-bunny.png"))
        finally:
            browser.close()
    return result


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
    parser.add_argument("--streaming", action="store_true",
                        help="also time streaming against the full GLB (see streaming.py)")
    parser.add_argument("--only-streaming", action="store_true",
                        help="skip the decoder rates and the screenshots")
    parser.add_argument("--large", type=Path, default=ROOT / "bench" / "out" / "bunny_loop2.npz",
                        help="the 1.1M-face bunny (.npz of positions, faces)")
    parser.add_argument("--static", type=Path, action="append",
                        help="a copy of static/ to serve (repeatable; default: the checkout's)")
    parser.add_argument("--label", action="append", help="a name per --static")
    parser.add_argument("--geomorph", action="store_true",
                        help="only: per-frame pixel change of a level change, geomorphs off/on")
    parser.add_argument("--runs", type=int, default=1,
                        help="--streaming: runs of each (viewer, GLB fetch, GLB drawn) in turn")
    parser.add_argument("--timeout", type=float, default=600,
                        help="seconds a streaming run may take before it counts as failed")
    args = parser.parse_args()
    executable = shutil.which("chromium") or shutil.which("chromium-browser")
    if executable is None:
        raise SystemExit("no chromium binary on PATH (Debian: apt-get install chromium)")
    args.out.mkdir(parents=True, exist_ok=True)
    if args.geomorph:
        with sync_playwright() as playwright:
            figures = run_geomorph(args, lambda: playwright.chromium.launch(
                executable_path=executable, args=CHROMIUM_ARGS), args.out)
        (args.out / "result-geomorph.json").write_text(json.dumps(figures, indent=2) + "\n")
        return
    if args.streaming:
        with sync_playwright() as playwright:
            def launch():
                return playwright.chromium.launch(executable_path=executable,
                                                  args=CHROMIUM_ARGS)
            streaming = {"machine": {"cpus": os.cpu_count(), "load_average": os.getloadavg()},
                         "streaming": run_streaming(args, launch, args.out)}
        streaming["machine"]["load_average_after"] = os.getloadavg()
        name = "-".join(args.label or ["streaming"])
        (args.out / f"result-{name}.json").write_text(json.dumps(streaming, indent=2) + "\n")
        print(json.dumps(streaming, indent=2))
        if args.only_streaming:
            return

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
