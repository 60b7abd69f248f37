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

gltfpack comes from bench/out/codec/npm (``npm i --no-save gltfpack`` there) or
the tests' tools (tests/tools/node_modules).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import codec  # noqa: E402
from codec_meshes import SOURCES, progressive  # noqa: E402

from lodserver.packets.records_v4 import packet_between_v4  # noqa: E402
from lodserver.scene.asset import SceneAsset  # noqa: E402
from lodserver.service.levels import encode_level  # noqa: E402
from lodserver.service.progressive_file import progressive_glb, read_index  # noqa: E402

HEAD_BYTES = 65536          # staticsource.js's first read
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", default=["spot", "stanford-bunny", "Duck"],
                        choices=list(SOURCES))
    args = parser.parse_args(argv)
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
