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

``--table`` prints instead the issue's table, at ``bits=14`` only: version 3, version 4
at its default codings (``encode_v4.DEFAULT_FLAGS``) and with the split edge alone,
``gltfpack -c`` and ``-cc``, and Draco (``gltf-transform draco``, edgebreaker, positions
at 14 bits, normals 10, UVs and other attributes 12: our grids' defaults) of the same
full-detail GLB, all gzipped; by default for the eight meshes of the issue
(``TABLE_MESHES``). gltfpack and glTF-Transform are the tests' (``npm ci`` in tests/tools).

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

from lodserver.packets.encode_v4 import DEFAULT_FLAGS  # noqa: E402

from lodserver.io.glb import encode_glb  # noqa: E402
from lodserver.packets import default_bits, encode_packet  # noqa: E402
from lodserver.packets.encode_v4 import encode_packet_v4  # noqa: E402
from lodserver.packets.format import (  # noqa: E402
    EDGE_POSITIONS,
    MAGNITUDE_CONTEXTS,
    RING_POSITIONS,
)
from lodserver.service.levels import encode_level  # noqa: E402

# gltfpack and glTF-Transform: bench/out/codec/npm's, else the tests' (tests/tools, npm ci)
TOOLS = [OUT / "npm" / "node_modules" / ".bin",
         OUT.parents[2] / "tests" / "tools" / "node_modules" / ".bin"]
GLTFPACK = next((d / "gltfpack" for d in TOOLS if (d / "gltfpack").exists()), TOOLS[0] / "gltfpack")
GLTF_TRANSFORM = next((d / "gltf-transform" for d in TOOLS if (d / "gltf-transform").exists()),
                      TOOLS[0] / "gltf-transform")
# The issue's eight meshes (bunny_loop3 stands for a 4M-face scan).
TABLE_MESHES = ["stanford-bunny", "spot", "bunny_loop2", "bunny_loop3", "Duck", "Avocado", "Fox",
                "mountain"]
PACKET_SPLITS = 8192
VARIANTS = {
    "v4 plain": 0,
    "v4 +edge": EDGE_POSITIONS,
    "v4 +contexts": MAGNITUDE_CONTEXTS,
    "v4 both": EDGE_POSITIONS | MAGNITUDE_CONTEXTS,
    "v4 +edge +ring": EDGE_POSITIONS | RING_POSITIONS,
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


def gltfpack_glb(pm, mode: str) -> bytes | None:
    """gltfpack ``mode`` (-cc or -c) of the full-detail mesh without images, 14-bit
    positions: the GLB's bytes (None without gltfpack)."""
    if not GLTFPACK.exists():
        return None
    return _packed(pm, [str(GLTFPACK), "-i", "{src}", "-o", "{dst}", mode, "-vp", "14", "-kv"])


def gltfpack_bytes(pm, mode: str) -> int | None:
    """gltfpack ``mode`` (-cc or -c) of the full-detail mesh without images, gzipped."""
    glb = gltfpack_glb(pm, mode)
    return None if glb is None else gz(glb)


def draco_bytes(pm) -> int | None:
    """Draco (glTF-Transform, edgebreaker) of the full-detail mesh without images at
    14-bit positions and our default attribute bits, gzipped."""
    if not GLTF_TRANSFORM.exists():
        return None
    return gz(_packed(pm, [str(GLTF_TRANSFORM), "draco", "{src}", "{dst}",
                           "--quantize-position", "14", "--quantize-normal", "10",
                           "--quantize-texcoord", "12", "--quantize-generic", "12"]))


def _packed(pm, command: list) -> bytes:
    """The GLB ``command`` writes from the full-detail GLB without images."""
    mesh = dataclasses.replace(pm.at(pm.vertex_count), materials=None, face_material=None)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.glb", Path(tmp) / "out.glb"
        src.write_bytes(encode_glb(mesh))
        subprocess.run([a.format(src=src, dst=dst) for a in command], check=True,
                       capture_output=True, timeout=1800)
        return dst.read_bytes()


def timed(encode, pm, bits) -> float:
    n0, n = pm.base_vertices, pm.vertex_count
    encode(pm, n0, min(n, n0 + 64), bits=bits)          # compile / warm caches
    began = time.perf_counter()
    encode(pm, n0, n, bits=bits)
    return time.perf_counter() - began


def issue_table(names) -> str:
    """The issue's table: bytes base -> full at 14 bits beside the single-rate coders."""
    keys = ["v3", "v4", "v4 edge", "gltfpack -c", "gltfpack -cc", "draco"]
    lines = ["| mesh | faces | splits | " + " | ".join(f"{k} KB" for k in keys)
             + " | v4 / -cc | v4 / draco | v4 edge -> v4 |", "|---" * (len(keys) + 6) + "|"]
    for name in names:
        pm = progressive(name)
        splits = pm.vertex_count - pm.base_vertices
        row = {"v3": stream_bytes(pm, 14, encode_packet),
               "v4": stream_bytes(pm, 14, encode_packet_v4),
               "v4 edge": stream_bytes(pm, 14, lambda *a, **k: encode_packet_v4(
                   *a, flags=DEFAULT_FLAGS & ~RING_POSITIONS, **k)),
               "gltfpack -c": gltfpack_bytes(pm, "-c"), "gltfpack -cc": gltfpack_bytes(pm, "-cc"),
               "draco": draco_bytes(pm)}
        print(name, row, file=sys.stderr, flush=True)
        cells = [f"{row[k] / 1000:.1f}" if row[k] else "-" for k in keys]
        ratio = [f"{row['v4'] / row[k]:.2f}x" if row[k] else "-" for k in ("gltfpack -cc", "draco")]
        lines.append(f"| {name} | {int(pm.face_counts[-1])} | {splits} | " + " | ".join(cells)
                     + f" | {' | '.join(ratio)} | {row['v4'] / row['v4 edge'] - 1:+.1%} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*")
    parser.add_argument("--table", action="store_true", help="the issue's table (see above)")
    args = parser.parse_args(argv)
    if args.table:
        print(issue_table(args.meshes or TABLE_MESHES))
        return
    args.meshes = args.meshes or list(SOURCES)
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
