"""Bytes from the base to full detail: version 3 and version 4 packets beside gltfpack.

For each mesh, at ``bits=14`` and at the mesh's default grid: the base level's json
form gzipped plus the packets of 8192 splits from the base to full detail (what a
streaming client fetches), in version 3 and in version 4 with each coding on and off
(``EDGE_POSITIONS``: the split edge and the place along it; ``MAGNITUDE_CONTEXTS``);
beside the full-detail mesh written as GLB without images (``Mesh.materials``
dropped, ``-kv`` keeps its normals and UVs) and packed by ``gltfpack -cc`` and
``-c`` at ``-vp 14``, gzipped (level 9); gltfpack writes 8-bit normals, so meshes
with normals also get version 4 with 8-bit normals (``v4 +edge n8``). Also the encode time of the whole
base -> full packet in each version (one call, after a warm-up).

    cd bench/out/codec/npm && npm i --no-save gltfpack && cd -   # gltfpack 1.3 (WASM)
    PYTHONPATH=$PWD python bench/codec.py [mesh ...]    # names of bench/codec_meshes.py

Meshes are built once into bench/out/codec/ (``bench/codec_meshes.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import gzip
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from codec_meshes import OUT, SOURCES, progressive  # noqa: E402

from lodserver.io.glb import encode_glb  # noqa: E402
from lodserver.packets import default_bits, encode_packet  # noqa: E402
from lodserver.packets.encode_v4 import encode_packet_v4  # noqa: E402
from lodserver.packets.format import EDGE_POSITIONS, MAGNITUDE_CONTEXTS  # noqa: E402
from lodserver.service.levels import encode_level  # noqa: E402

# gltfpack and glTF-Transform: bench/out/codec/npm's, else the tests' (tests/tools, npm ci)
TOOLS = [OUT / "npm" / "node_modules" / ".bin",
         OUT.parents[2] / "tests" / "tools" / "node_modules" / ".bin"]
GLTFPACK = next((d / "gltfpack" for d in TOOLS if (d / "gltfpack").exists()), TOOLS[0] / "gltfpack")
PACKET_SPLITS = 8192
VARIANTS = {
    "v4 plain": 0,
    "v4 +edge": EDGE_POSITIONS,
    "v4 +contexts": MAGNITUDE_CONTEXTS,
    "v4 both": EDGE_POSITIONS | MAGNITUDE_CONTEXTS,
}


def gz(data: bytes) -> int:
    return len(gzip.compress(bytes(data), 9))


def stream_bytes(pm, bits, encode) -> int:
    """Base json gzipped + the packets of PACKET_SPLITS splits from base to full."""
    n0, n = pm.base_vertices, pm.vertex_count
    total = gz(encode_level(pm, n0, file_type="json", bits=bits))
    for a in range(n0, n, PACKET_SPLITS):
        total += len(encode(pm, a, min(n, a + PACKET_SPLITS), bits=bits))
    return total


def gltfpack_bytes(pm, mode: str) -> int | None:
    """gltfpack ``mode`` (-cc or -c) of the full-detail mesh without images, gzipped."""
    if not GLTFPACK.exists():
        return None
    mesh = dataclasses.replace(pm.at(pm.vertex_count), materials=None, face_material=None)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.glb", Path(tmp) / "out.glb"
        src.write_bytes(encode_glb(mesh))
        subprocess.run([str(GLTFPACK), "-i", str(src), "-o", str(dst), mode, "-vp", "14", "-kv"],
                       check=True, capture_output=True, timeout=600)
        return gz(dst.read_bytes())


def timed(encode, pm, bits) -> float:
    n0, n = pm.base_vertices, pm.vertex_count
    encode(pm, n0, min(n, n0 + 64), bits=bits)          # compile / warm caches
    began = time.perf_counter()
    encode(pm, n0, n, bits=bits)
    return time.perf_counter() - began


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", default=list(SOURCES))
    args = parser.parse_args(argv)
    rows = []
    for name in args.meshes:
        pm = progressive(name)
        splits = pm.vertex_count - pm.base_vertices
        cc, c = gltfpack_bytes(pm, "-cc"), gltfpack_bytes(pm, "-c")
        for bits in sorted({14, default_bits(pm)}):
            row = {"mesh": name, "splits": splits, "bits": bits,
                   "v3": stream_bytes(pm, bits, encode_packet)}
            for label, flags in VARIANTS.items():
                row[label] = stream_bytes(pm, bits, lambda *a, f=flags, **k:
                                          encode_packet_v4(*a, flags=f, **k))
            # gltfpack writes 8-bit normals: the same precision on our side too
            # (the base json keeps its default normal grid: a few vertices)
            row["v4 +edge n8"] = None
            if any(name == "NORMAL" for name, _ in pm.attribute_layout or ()):
                row["v4 +edge n8"] = stream_bytes(pm, bits, lambda *a, **k: encode_packet_v4(
                    *a, attribute_bits={"NORMAL": 8}, **k))
            row["gltfpack -cc"], row["gltfpack -c"] = cc, c
            row["v3 s"] = timed(encode_packet, pm, bits)
            row["v4 s"] = timed(encode_packet_v4, pm, bits)
            rows.append(row)
            print(row, file=sys.stderr, flush=True)
    print(table(rows))


def table(rows) -> str:
    keys = ["v3", *VARIANTS, "v4 +edge n8", "gltfpack -cc", "gltfpack -c"]
    lines = ["| mesh | splits | bits | " + " | ".join(f"{k} KB" for k in keys)
             + " | best v4 / -cc | v3 / v4 encode s |",
             "|---" * (len(keys) + 5) + "|"]
    for r in rows:
        best = min(r[k] for k in [*VARIANTS, "v4 +edge n8"] if r[k] is not None)
        cells = [f"{r[k] / 1000:.1f}" if r[k] is not None else "-" for k in keys]
        ratio = f"{best / r['gltfpack -cc']:.2f}x" if r["gltfpack -cc"] else "-"
        lines.append(f"| {r['mesh']} | {r['splits']} | {r['bits']} | " + " | ".join(cells)
                     + f" | {ratio} | {r['v3 s']:.2f} / {r['v4 s']:.2f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
