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

``--browser``: a session in headless Chromium instead (software GL, the link
throttled to 20 Mbit/s and 50 ms as in issue 25's table), docs/three.md's
example page opening the file from a static host with ``Range``
(``static_server.serve``): the requests, bytes and seconds to the 1 px level of
its view (1200x800) and then to full detail (``setLevel``).

gltfpack comes from bench/out/codec/npm (``npm i --no-save gltfpack`` there) or
the tests' tools (tests/tools/node_modules).
"""

from __future__ import annotations

import argparse
import shutil
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
THROTTLE = {"offline": False, "latency": 50, "downloadThroughput": 20e6 / 8,
            "uploadThroughput": 20e6 / 8}
# docs/three.md's example, its URLs this bench's, the object left on window.
EXAMPLE_URLS = {"https://cdn.jsdelivr.net/npm/three@0.187.0/": "/three/",
                "http://127.0.0.1:8000/viewer/lodserver-three.js": "/lodserver/lodserver-three.js",
                "scene.add(object);": "scene.add(object);\nwindow.object = object;"}


def example_page(file_url: str) -> str:
    """docs/three.md's example page, opening ``file_url``."""
    text = (REPO / "docs" / "three.md").read_text()
    page = text.split("```html\n", 1)[1].split("```", 1)[0]
    for old, new in {**EXAMPLE_URLS, "http://127.0.0.1:8000/meshes/ID": file_url}.items():
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


def session(name: str, timeout_s: float = 1800) -> dict:
    """A browser session on ``name``'s progressive file (see ``--browser``)."""
    from playwright.sync_api import sync_playwright
    pm = progressive(name)
    log: list = []
    with tempfile.TemporaryDirectory() as tmp, sync_playwright() as playwright:
        folder = Path(tmp)
        (folder / "three").symlink_to(REPO / "static" / "vendor" / "three")
        (folder / "lodserver").symlink_to(REPO / "static")
        (folder / f"{name}.glb").write_bytes(progressive_glb(SceneAsset.of_mesh(pm)))
        browser = playwright.chromium.launch(executable_path=shutil.which("chromium"),
                                             args=CHROMIUM_ARGS)
        with serve(folder, log) as url:
            (folder / "index.html").write_text(example_page(f"{url}/{name}.glb"))
            context = browser.new_context(viewport={"width": 1200, "height": 800})
            page = context.new_page()
            cdp = context.new_cdp_session(page)
            cdp.send("Network.enable")
            cdp.send("Network.emulateNetworkConditions", THROTTLE)
            page.set_default_timeout(timeout_s * 1000)
            began = time.perf_counter()
            page.goto(f"{url}/index.html")
            page.wait_for_function("() => window.object?.target != null")
            stops = {}
            full = f"window.object.setLevel({pm.vertex_count})"
            for stop, script in (("1 px", None), ("full", full)):
                if script:
                    page.evaluate(script)
                level = page.evaluate(SETTLED_JS)["level"]
                files = [entry for entry in log if entry[0] == f"/{name}.glb"]
                stops[stop] = {"level": level, "seconds": time.perf_counter() - began,
                               "requests": len(files), "bytes": sum(e[3] for e in files),
                               "log": [(e[1], e[2], e[3]) for e in files]}
            context.close()
        browser.close()
    return {"mesh": name, "vertices": pm.vertex_count, **stops}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", default=["spot", "stanford-bunny", "Duck"],
                        choices=list(SOURCES))
    parser.add_argument("--browser", action="store_true",
                        help="a Chromium session per mesh instead of the byte counts")
    args = parser.parse_args(argv)
    if args.browser:
        for name in args.meshes:
            print(session(name))
        return
    if not codec.GLTFPACK.exists() and (TOOLS / "gltfpack").exists():
        codec.GLTFPACK = TOOLS / "gltfpack"
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
