"""Bytes per exported level: lodserver raw / quantized / meshopt against gltfpack.

For each asset, one progressive mesh is built (``lodserver.build``) and its levels
at ``--lods`` are written by lodserver three ways (``encode_glb(level, compress)``:
none, quantize, meshopt); the raw level file is then given to gltfpack
(``tests/tools``: ``npm ci --prefix tests/tools``) with ``-c`` and ``-cc``, so
both tools compress the very same triangles. Bytes are geometry only: each
file's size less its images' bytes (the images are copied as they are by both).
``gz`` is the meshopt file and the ``-cc`` file without their images, gzipped
(level 6), as a CDN serves them.

    python bench/gltf_io.py                       # Duck, 2CylinderEngine, Avocado, spot, stanford-bunny
    python bench/gltf_io.py --meshes Duck.glb --lods 1,0.1

Texture levels (``--part textures``): each textured shared asset exported by
``export_lods`` as ``--separate --compress meshopt`` files, with and without
``--texture-scale auto``; per level the bytes of geometry and images from the
report (``scene.report.asset_entry``) and the report's seconds of the level's
file, against ``gltfpack -i SOURCE -si RATIO -cc`` run once per level (its
wall time, process start included; gltfpack resizes textures only when it
also re-encodes them, -tc/-tu/-tw, so its images are the source's).

Prints Markdown tables and writes ``bench/out/gltf_io.json``.
"""

from __future__ import annotations

import argparse
import gzip
import json
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lodserver.build import build  # noqa: E402
from lodserver.io import load_mesh  # noqa: E402
from lodserver.io.glb import encode_glb  # noqa: E402
from lodserver.pipeline import export_lods  # noqa: E402
from lodserver.scene.report import asset_entry  # noqa: E402

MESHES = ["Duck.glb", "2CylinderEngine.glb", "Avocado/Avocado.gltf", "spot/spot.obj",
          "stanford-bunny.obj"]
TEXTURED = ["Duck.glb", "Avocado/Avocado.gltf", "bunny10k_textured/bunny10k_textured.obj"]
GLTFPACK = REPO / "tests" / "tools" / "node_modules" / ".bin" / "gltfpack"


def image_bytes(data: bytes) -> int:
    """Bytes of the images a GLB holds in bufferViews."""
    length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + length])
    views = document.get("bufferViews", [])
    return sum(views[image["bufferView"]]["byteLength"]
               for image in document.get("images", ()) if "bufferView" in image)


def gltfpack(data: bytes, flag: str) -> bytes:
    """``data`` (a GLB) through ``gltfpack FLAG``."""
    with tempfile.TemporaryDirectory() as folder:
        source, output = Path(folder) / "in.glb", Path(folder) / "out.glb"
        source.write_bytes(data)
        subprocess.run([str(GLTFPACK), "-i", str(source), "-o", str(output), flag],
                       check=True, capture_output=True, timeout=600)
        return output.read_bytes()


def geometry(data: bytes) -> int:
    return len(data) - image_bytes(data)


def without_images(data: bytes) -> bytes:
    """A GLB's bytes with its images' byte ranges cut out (for sizes only)."""
    length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + length])
    binary = data[20 + length + 8:]
    views = document.get("bufferViews", [])
    cut = sorted((views[i["bufferView"]].get("byteOffset", 0),
                  views[i["bufferView"]]["byteLength"])
                 for i in document.get("images", ()) if "bufferView" in i)
    kept, at = [data[:20 + length + 8]], 0
    for start, size in cut:
        kept.append(binary[at:start])
        at = max(at, start + size)
    kept.append(binary[at:])
    return b"".join(kept)


def texture_rows(names: list[str], mesh_dir: Path, ratios: list[float]) -> list[dict]:
    """Per asset and level: lodserver's bytes without and with texture levels, the
    report's seconds, and gltfpack -cc's bytes and seconds for the same ratio."""
    rows = []
    with tempfile.TemporaryDirectory() as folder:     # kernels loaded before any timing
        export_lods(mesh_dir / names[0], Path(folder) / "warm.glb", lods=ratios)
    print("| asset | level | triangles | geometry | images (full) | images (auto) "
          "| level bytes auto / full | level s (report) | gltfpack -cc level s "
          "| gltfpack -cc bytes |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        source = mesh_dir / name
        entries, totals = {}, {}
        with tempfile.TemporaryDirectory() as folder:
            for scale in (None, "auto"):
                start = time.perf_counter()
                done = export_lods(source, Path(folder) / f"{scale}.glb", lods=ratios,
                                   separate=True, compress="meshopt", texture_scale=scale)
                totals[scale] = time.perf_counter() - start
                entries[scale] = asset_entry(done, done.outputs)["levels"]
            packed = []
            for ratio in ratios:
                output = Path(folder) / f"gltfpack_{ratio}.glb"
                start = time.perf_counter()
                subprocess.run([str(GLTFPACK), "-i", str(source), "-o", str(output), "-si",
                                str(ratio), "-cc"], check=True, capture_output=True, timeout=600)
                packed.append((time.perf_counter() - start, output.stat().st_size))
        for k, (full, auto) in enumerate(zip(entries[None], entries["auto"])):
            whole = full["bytes"]["geometry"] + full["bytes"]["images"]
            scaled = auto["bytes"]["geometry"] + auto["bytes"]["images"]
            row = {"asset": name, "level": k, "ratio": ratios[k], "triangles": full["triangles"],
                   "geometry": full["bytes"]["geometry"], "images full": full["bytes"]["images"],
                   "images auto": auto["bytes"]["images"], "auto / full": scaled / whole,
                   "level seconds": auto["seconds"], "gltfpack seconds": packed[k][0],
                   "gltfpack bytes": packed[k][1]}
            rows.append(row)
            print(f"| {name} | {k} | {row['triangles']} | {row['geometry']} "
                  f"| {row['images full']} | {row['images auto']} | {row['auto / full']:.2f} "
                  f"| {row['level seconds']:.3f} | {row['gltfpack seconds']:.3f} "
                  f"| {row['gltfpack bytes']} |", flush=True)
        gltfpack_total = sum(seconds for seconds, _ in packed)
        rows.append({"asset": name, "export seconds": totals, "gltfpack seconds": gltfpack_total})
        print(f"| {name} | all | | | | | | export {totals[None]:.2f} s, with texture levels "
              f"{totals['auto']:.2f} s | {gltfpack_total:.2f} s "
              f"(x{totals['auto'] / gltfpack_total:.2f}) | |", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default=",".join(MESHES))
    parser.add_argument("--lods", default="1,0.5,0.2,0.05")
    parser.add_argument("--mesh-dir", default=str(REPO.parent / "shared" / "meshes"))
    parser.add_argument("--out", default=str(REPO / "bench" / "out" / "gltf_io.json"))
    parser.add_argument("--part", choices=("levels", "textures", "all"), default="all",
                        help="bytes per level against gltfpack, texture levels, or both")
    args = parser.parse_args()
    if not GLTFPACK.exists():
        sys.exit("gltfpack is not installed: npm ci --prefix tests/tools")
    ratios = [float(r) for r in args.lods.split(",")]
    textures = []
    if args.part in ("textures", "all"):
        textures = texture_rows(TEXTURED, Path(args.mesh_dir), ratios)
    rows = []
    if args.part == "textures":
        args.meshes = ""
    print("| asset | ratio | triangles | raw | quantize | meshopt | gltfpack -c | gltfpack -cc "
          "| meshopt / -cc | meshopt gz | -cc gz | encode s (meshopt) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in filter(None, args.meshes.split(",")):
        mesh, _ = load_mesh(Path(args.mesh_dir) / name)
        pm = build(mesh)
        for ratio in ratios:
            level = pm.at(ratio=ratio)
            raw = encode_glb(level, "none")
            quantized = encode_glb(level, "quantize")
            start = time.perf_counter()
            meshopt = encode_glb(level, "meshopt")
            seconds = time.perf_counter() - start
            packed_c, packed_cc = gltfpack(raw, "-c"), gltfpack(raw, "-cc")
            row = {"asset": name, "ratio": ratio, "triangles": level.face_count,
                   "raw": geometry(raw), "quantize": geometry(quantized),
                   "meshopt": geometry(meshopt), "gltfpack -c": geometry(packed_c),
                   "gltfpack -cc": geometry(packed_cc),
                   "meshopt gz": len(gzip.compress(without_images(meshopt), 6)),
                   "-cc gz": len(gzip.compress(without_images(packed_cc), 6)),
                   "encode seconds": seconds}
            rows.append(row)
            print(f"| {name} | {ratio} | {row['triangles']} | {row['raw']} | {row['quantize']} "
                  f"| {row['meshopt']} | {row['gltfpack -c']} | {row['gltfpack -cc']} "
                  f"| {row['meshopt'] / row['gltfpack -cc']:.2f} | {row['meshopt gz']} "
                  f"| {row['-cc gz']} | {seconds:.3f} |", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"lods": ratios, "rows": rows, "textures": textures}, indent=1))


if __name__ == "__main__":
    main()
