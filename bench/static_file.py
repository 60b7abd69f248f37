"""The progressive file against the server's packets and gltfpack -cc: bytes, chunks, requests.

For each mesh (built once into bench/out/codec/ by ``bench/codec_meshes.py``), at
the mesh's default grid: the progressive file (``lodserver export --progressive``'s
bytes, ``service/progressive_file.py``) whole, and what a client of it fetches
from the base to full detail (its header and JSON, the base's json form, the
split chunks; a static host sends ranges as they are, not gzipped); beside what
a client of the server fetches for the same way (the base's json form gzipped,
as the server's compression middleware sends it, plus version 4 packets of 8192
splits), and the full-detail mesh packed by ``gltfpack -cc`` at ``-vp 14`` and
gzipped (images dropped, ``bench/codec.py``'s ``gltfpack_bytes``). Also the
range requests a session of ``static/staticsource.js`` makes: the header and
JSON (one, two when the JSON is longer than 64 KiB), the base, then one per run
of chunks the stream asks for: at least one to full detail.

    PYTHONPATH=$PWD python bench/static_file.py [mesh ...]    # names of bench/codec_meshes.py
    PYTHONPATH=$PWD python bench/static_file.py --browser bunny_loop2

``--browser``: sessions in headless Chromium instead (software GL, viewport
1200x800), on each link of issue 25's table (``--links 20,5``: 20 Mbit/s with
50 ms latency, 5 Mbit/s with 150 ms; throttled through the DevTools protocol),
of (a) docs/three.md's example page opening the progressive file from a static
host with ``Range`` (``static_server.serve``), (b) the same page opening the same
mesh from a running ``lodserver serve`` (uploaded, built, opened as
``http://127.0.0.1:PORT/meshes/ID``; the page's origin allowed by
``LODSERVER_CORS_ORIGINS``) and (c) a page drawing the full-detail ``gltfpack
-cc`` GLB (14-bit positions, no images, as ``bench/codec.py`` packs it) with
three.js's GLTFLoader and MeshoptDecoder, served whole with ``Content-Encoding:
gzip`` as a CDN serves it. ``--repeats`` rounds per link of one session each,
each in a fresh browser context, the order rotated each round so that a drift
in the machine's load falls on every side: the requests, bytes (on the wire, as
the DevTools protocol counts them) and seconds to the first drawn frame, to the
1 px level of the view and then to full detail (``setLevel(fullLevel)``; the
GLB's first frame is all three); the medians and the medians of the paired
ratios (the sessions of one round) file / server, file / GLB, server / GLB.

    PYTHONPATH=$PWD python bench/static_file.py --browser --links 20,5 --repeats 3 stanford-bunny

gltfpack comes from bench/out/codec/npm (``npm i --no-save gltfpack`` there) or
the tests' tools (tests/tools/node_modules); three.js's meshopt decoder from
bench/out/static_file/npm (``npm i --no-save three@0.187.0`` there).
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import codec  # noqa: E402
from codec_meshes import SOURCES, progressive  # noqa: E402
from static_server import serve  # noqa: E402

from lodserver.packets.records_v4 import packet_between_v4  # noqa: E402
from lodserver.scene.asset import SceneAsset  # noqa: E402
from lodserver.service.levels import encode_level  # noqa: E402
from lodserver.service.progressive_file import progressive_glb, read_index  # noqa: E402

HEAD_BYTES = 65536          # staticsource.js's first read
REPO = Path(__file__).resolve().parents[1]
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run"]
# Issue 25's two links: Mbit/s -> latency in ms.
LINKS = {20: 50, 5: 150}


def throttle(mbit: float) -> dict:
    """``Network.emulateNetworkConditions``'s parameters for the link of ``mbit``."""
    rate = mbit * 1e6 / 8
    return {"offline": False, "latency": LINKS[mbit], "downloadThroughput": rate,
            "uploadThroughput": rate}


# docs/three.md's example, its URLs this bench's, the object left on window and
# window.drawn set once a frame has drawn a level of it.
EXAMPLE_URLS = {"https://cdn.jsdelivr.net/npm/three@0.187.0/": "/three/",
                "http://127.0.0.1:8000/viewer/lodserver-three.js": "/lodserver/lodserver-three.js",
                "scene.add(object);": "scene.add(object);\nwindow.object = object;",
                "renderer.render(scene, camera);": "renderer.render(scene, camera);\n"
                                                   "  window.drawn ||= object.level > 0;"}

# The -cc GLB as a three.js app draws one: docs/three.md's example (so lit and
# framed as it frames its object) with GLTFLoader and meshoptimizer's decoder
# in place of the module; window.drawn set once a frame has drawn it.
GLB_CHANGES = {
    "import { ProgressiveMeshLoader } from 'lodserver-three';":
        "import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';\n"
        "import { MeshoptDecoder } from '/meshopt/meshopt_decoder.module.js';",
    "const object = await new ProgressiveMeshLoader().load(":
        "const gltf = await new GLTFLoader().setMeshoptDecoder(MeshoptDecoder).loadAsync(",
    "const { center, radius } = object.boundingSphere;":
        "const object = gltf.scene;\nconst { center, radius } = new THREE.Box3()"
        ".setFromObject(object).getBoundingSphere(new THREE.Sphere());",
    "  object.update(camera, renderer);\n": "",
    "renderer.render(scene, camera);": "renderer.render(scene, camera);\n  window.drawn = true;"}
# meshoptimizer's decoder for three.js: three's own (examples/jsm/libs), which the
# vendored copy in static/ leaves out; ``npm i --no-save three@0.187.0`` here.
NPM = REPO / "bench" / "out" / "static_file" / "npm"
MESHOPT = NPM / "node_modules" / "three" / "examples" / "jsm" / "libs"


def example_page(file_url: str, glb: bool = False) -> str:
    """docs/three.md's example page, opening ``file_url`` (with ``glb``, a GLB
    drawn by GLTFLoader instead: GLB_CHANGES)."""
    text = (REPO / "docs" / "three.md").read_text()
    page = text.split("```html\n", 1)[1].split("```", 1)[0]
    changes = {**EXAMPLE_URLS, "http://127.0.0.1:8000/meshes/ID": file_url}
    if glb:
        changes.update(GLB_CHANGES)
    for old, new in changes.items():
        assert old in page, f"docs/three.md's example no longer has {old}"
        page = page.replace(old, new)
    return f"<!doctype html><html><body style=\"margin: 0\">{page}</body></html>"


# Resolves once the level is where update() sends it, twice in a row.
SETTLED_JS = """async () => {
  let last = null;
  for (;;) {
    await window.object.settled();
    await new Promise((resolve) => requestAnimationFrame(() => requestAnimationFrame(resolve)));
    const now = { level: window.object.level, target: window.object.target };
    if (now.target === now.level && last?.level === now.level) return now;
    last = now;
  }
}"""
TOOLS = Path(__file__).resolve().parents[1] / "tests" / "tools" / "node_modules" / ".bin"


def file_figures(pm) -> dict:
    """The file's size, what a client reads from it to full detail, its chunks."""
    began = time.perf_counter()
    data = progressive_glb(SceneAsset.of_mesh(pm))
    seconds = time.perf_counter() - began
    record, start = read_index(data)
    part = record["parts"][0]
    splits = sum(chunk[3] for chunk in part["splits"])
    collapses = sum(chunk[3] for chunk in part["collapses"])
    head = start                  # the header and the JSON chunk
    return {"file": len(data), "seconds": seconds, "head": head, "base": part["base"][2],
            "splits": splits, "collapses": collapses, "chunks": len(part["splits"]),
            "chunk_splits": part["chunkSplits"],
            "requests_to_full": (1 if head <= HEAD_BYTES else 2) + 2}


def server_bytes(pm) -> int:
    """The base's json form gzipped plus version 4 packets of 8192 splits to full."""
    n0, n = pm.base_vertices, pm.vertex_count
    total = codec.gz(encode_level(pm, n0, file_type="json"))
    for a in range(n0, n, codec.PACKET_SPLITS):
        total += len(packet_between_v4(pm, a, min(n, a + codec.PACKET_SPLITS)))
    return total


def upload_built(client, name: str, folder: Path, timeout_s: float) -> str:
    """Upload ``name``'s source (bunny_loop2 written as PLY) to the server behind
    ``client`` and wait until it is built; the mesh's id."""
    from codec_meshes import source_mesh
    from tests.server import upload, wait_ready
    path = SOURCES[name]
    if path is None:
        import trimesh
        mesh = source_mesh(name)
        path = folder / f"{name}.ply"
        path.write_bytes(trimesh.Trimesh(mesh.positions, mesh.faces, process=False)
                         .export(file_type="ply"))
    began = time.perf_counter()
    with open(path, "rb") as file:
        mesh_id = upload(client, path.name, file)
    wait_ready(client, mesh_id, timeout=timeout_s)
    print(f"server built {name} in {time.perf_counter() - began:.1f} s", file=sys.stderr)
    return mesh_id


def one_session(browser, page_url: str, prefix: str, mbit: float, timeout_s: float,
                log: list | None = None, log_path: str | None = None,
                progressive: bool = True) -> dict:
    """The page at ``page_url`` in a fresh context on the link of ``mbit``: its
    level, seconds from the page's load, requests (and CORS preflights) and bytes
    on the wire to the URLs under ``prefix``, at its first drawn frame, then (the
    example page, ``progressive``) at the 1 px level and at full detail. With
    ``log`` (the static host's), the file's ranges too."""
    context = browser.new_context(viewport={"width": 1200, "height": 800})
    page = context.new_page()
    cdp = context.new_cdp_session(page)
    fetched: dict = {}                      # requestId -> [url, method, bytes]

    def sent(event):
        request = event["request"]
        fetched.setdefault(event["requestId"], [request["url"], request["method"], 0])

    def finished(event):
        if event["requestId"] in fetched:
            fetched[event["requestId"]][2] = event["encodedDataLength"]

    cdp.on("Network.requestWillBeSent", sent)
    cdp.on("Network.loadingFinished", finished)
    cdp.send("Network.enable")
    cdp.send("Network.emulateNetworkConditions", throttle(mbit))
    page.set_default_timeout(timeout_s * 1000)
    first = len(log) if log is not None else 0
    began = time.perf_counter()
    page.goto(page_url)
    stops = {}
    for stop in ("first", "1 px", "full") if progressive else ("first",):
        if stop == "first":
            page.wait_for_function("() => window.drawn", polling="raf")
            seconds = time.perf_counter() - began
            level = page.evaluate("window.object?.level ?? null")
        else:
            if stop == "full":
                page.evaluate("window.object.setLevel(window.object.fullLevel)")
            level = page.evaluate(SETTLED_JS)["level"]
            seconds = time.perf_counter() - began
        mine = [f for f in list(fetched.values()) if f[0].startswith(prefix)]
        gets = [f for f in mine if f[1] != "OPTIONS"]
        stops[stop] = {"level": level, "seconds": seconds, "requests": len(gets),
                       "preflights": len(mine) - len(gets), "bytes": sum(f[2] for f in mine)}
        if log is not None:
            ranges = [e for e in log[first:] if e[0] == log_path]
            stops[stop]["ranges"] = [(e[1], e[2], e[3]) for e in ranges]
    if progressive:
        stops["full_level"] = page.evaluate("window.object.fullLevel")
    else:
        # the GLB is drawn at full detail at once
        stops["1 px"] = stops["full"] = stops["first"]
    context.close()
    return stops


SOURCES_OF_SESSIONS = ("file", "server", "glb")


def sessions(name: str, links: list, repeats: int, timeout_s: float = 1800) -> list:
    """``repeats`` rounds per link on ``name`` of a session of each source (see
    ``--browser``: the file, the server, the ``-cc`` GLB), the order rotated each
    round; one dict per session."""
    from playwright.sync_api import sync_playwright

    from tests.server import serve as lodserver
    pm = progressive(name)
    glb = codec.gltfpack_glb(pm, "-cc")
    if glb is None or not MESHOPT.is_dir():
        sys.exit("--browser needs gltfpack (bench/out/codec/npm) and three.js's meshopt decoder: "
                 f"cd {NPM} && npm i --no-save three@0.187.0")
    runs = []
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as playwright:
        folder = Path(tmp) / "static"
        folder.mkdir()
        (folder / "three").symlink_to(REPO / "static" / "vendor" / "three")
        (folder / "lodserver").symlink_to(REPO / "static")
        (folder / "meshopt").symlink_to(MESHOPT)
        (folder / f"{name}.glb").write_bytes(progressive_glb(SceneAsset.of_mesh(pm)))
        (folder / f"{name}-cc.glb").write_bytes(glb)
        browser = playwright.chromium.launch(executable_path=shutil.which("chromium"),
                                             args=CHROMIUM_ARGS)
        log: list = []
        # The static host first: its origin is the one the server must allow.
        with serve(folder, log, gzipped=(f"/{name}-cc.glb",)) as url, \
                lodserver(Path(tmp) / "data", warm_kernels=True, timeout=120,
                          env={"LODSERVER_CORS_ORIGINS": url}) as client:
            mesh_id = upload_built(client, name, Path(tmp), timeout_s)
            mesh_url = f"{client.base_url}".rstrip("/") + f"/meshes/{mesh_id}"
            pages = {"file": (f"{url}/{name}.glb", "file.html"),
                     "server": (mesh_url, "server.html"),
                     "glb": (f"{url}/{name}-cc.glb", "glb.html")}
            for source, (target, html) in pages.items():
                (folder / html).write_text(example_page(target, glb=source == "glb"))
            for mbit in links:
                for repeat in range(repeats):
                    shift = repeat % len(SOURCES_OF_SESSIONS)
                    order = SOURCES_OF_SESSIONS[shift:] + SOURCES_OF_SESSIONS[:shift]
                    for source in order:
                        target, html = pages[source]
                        stops = one_session(browser, f"{url}/{html}", target, mbit, timeout_s,
                                            log if source == "file" else None, f"/{name}.glb",
                                            progressive=source != "glb")
                        run = {"mesh": name, "link": mbit, "repeat": repeat,
                               "source": source, **stops}
                        print(run, file=sys.stderr)
                        runs.append(run)
        browser.close()
    return runs


def session_table(runs: list) -> None:
    """The medians per mesh, link and source, and the paired ratios (the sessions
    of one round) file / server, file / GLB and server / GLB."""
    print("| mesh | link | source | sessions | first frame: s | 1 px level | 1 px: s | requests "
          "| bytes | full level | full: s | requests | bytes |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    med = statistics.median
    kb = lambda x: f"{x / 1000:.1f} KB"       # noqa: E731
    keys = sorted({(r["mesh"], r["link"]) for r in runs}, key=lambda k: (k[0], -k[1]))
    for mesh, mbit in keys:
        link = f"{mbit:g} Mbit/s, {LINKS[mbit]} ms"
        mine = {s: sorted((r for r in runs if (r["mesh"], r["link"], r["source"])
                           == (mesh, mbit, s)), key=lambda r: r["repeat"])
                for s in SOURCES_OF_SESSIONS}
        for source, rs in mine.items():
            first, one, full = ([r[stop] for r in rs] for stop in ("first", "1 px", "full"))
            # (the GLB has no levels: it is the whole mesh)
            levels = lambda xs: "/".join(sorted({str(x["level"] or "whole") for x in xs}))  # noqa: E731,E501
            print(f"| {mesh} | {link} | {source} | {len(rs)} | "
                  f"{med(x['seconds'] for x in first):.2f} | {levels(one)} | "
                  f"{med(x['seconds'] for x in one):.2f} | {med(x['requests'] for x in one):g} | "
                  f"{kb(med(x['bytes'] for x in one))} | {levels(full)} | "
                  f"{med(x['seconds'] for x in full):.2f} | "
                  f"{med(x['requests'] for x in full):g} | {kb(med(x['bytes'] for x in full))} |")
        for a, b in (("file", "server"), ("file", "glb"), ("server", "glb")):
            pairs = list(zip(mine[a], mine[b]))
            ratio = {stop: med(x[stop]["seconds"] / y[stop]["seconds"] for x, y in pairs)
                     for stop in ("first", "1 px", "full")}
            nbytes = {stop: med(x[stop]["bytes"] / y[stop]["bytes"] for x, y in pairs)
                      for stop in ("1 px", "full")}
            print(f"| {mesh} | {link} | **{a} / {b}** (paired median) | {len(pairs)} pairs | "
                  f"**{ratio['first']:.2f}x** | | **{ratio['1 px']:.2f}x** | | "
                  f"{nbytes['1 px']:.2f}x | | **{ratio['full']:.2f}x** | | {nbytes['full']:.2f}x |")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", default=["spot", "stanford-bunny", "Duck"],
                        choices=list(SOURCES))
    parser.add_argument("--browser", action="store_true",
                        help="Chromium sessions, the file against the server, instead of "
                             "the byte counts")
    parser.add_argument("--links", default="20,5",
                        help="--browser's links, Mbit/s, comma-separated, of: "
                             + ", ".join(f"{m} ({ms} ms)" for m, ms in LINKS.items()))
    parser.add_argument("--repeats", type=int, default=3,
                        help="--browser's pairs (file, server) per mesh and link")
    args = parser.parse_args(argv)
    if not codec.GLTFPACK.exists() and (TOOLS / "gltfpack").exists():
        codec.GLTFPACK = TOOLS / "gltfpack"
    if args.browser:
        links = [float(x) for x in args.links.split(",")]
        links = [int(x) if x.is_integer() else x for x in links]
        unknown = [x for x in links if x not in LINKS]
        if unknown:
            parser.error(f"--links: no link of {unknown} Mbit/s (known: {list(LINKS)})")
        runs = []
        for name in args.meshes:
            runs += sessions(name, links, args.repeats)
        session_table(runs)
        return
    rows = []
    for name in args.meshes:
        pm = progressive(name)
        figures = file_figures(pm)
        client = figures["head"] + figures["base"] + figures["splits"]
        server = server_bytes(pm)
        packed = codec.gltfpack_bytes(pm, "-cc")
        rows.append((name, pm.vertex_count - pm.base_vertices, figures, client, server, packed))
        print(name, figures, client, server, packed, file=sys.stderr)
    print("| mesh | splits | file | chunks (splits each) | client reads to full: head + base + "
          "chunks | server: base gz + v4 packets | `-cc` gz | file read / server | file read / "
          "`-cc` | requests to full | write time |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, splits, f, client, server, packed in rows:
        kb = lambda x: f"{x / 1000:.1f} KB"   # noqa: E731
        ratio = f"{client / packed:.2f}x" if packed else "-"
        print(f"| {name} | {splits} | {kb(f['file'])} | {f['chunks']} ({f['chunk_splits']}) | "
              f"{kb(client)} ({kb(f['head'])} + {kb(f['base'])} + {kb(f['splits'])}) | "
              f"{kb(server)} | {kb(packed) if packed else '-'} | {client / server:.2f}x | "
              f"{ratio} | {f['requests_to_full']} | {f['seconds']:.1f} s |")


if __name__ == "__main__":
    main()
