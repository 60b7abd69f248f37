"""Far levels judged by their look: lodserver's merged and baked levels against
gltfpack's aggressive simplification at the same triangle count (issue 28).

    python bench/hlod.py                                  # every asset, 10%, 2%, 0.5%
    python bench/hlod.py --assets office_chair --ratios 0.02 --size 256

For every asset (../shared/meshes: 2CylinderEngine, office_chair, Avocado,
Fox, and the textured bunny10k when present):

1. ``lodserver export IN -o OUT.glb --separate --lods 1,R1,R2,...`` once
   (wall time), every level a file; levels edge collapse cannot bring to their
   budget are merged and baked (``--reach merge``, the default).
2. For each level, ``gltfpack -i IN -o OUT.glb -si r -sa`` (simplify
   aggressively; the npm package's WASM build) with r tuned to lodserver's
   count: first r = count / input triangles, then twice more scaled by
   count / got; of the runs, the nearest at or above the count (else the nearest).
3. Headless Chromium (SwiftShader) draws the full-detail file and every
   candidate with three.js's GLTFLoader and **the files' own materials** under
   a hemisphere and a directional light (``bench/scenes/judge.html``,
   ``shading: "own"``), from four views framed on the input, and measures the
   RMS colour difference over the pixels both cover (0..1 units; x255 for
   8-bit levels) and the silhouette mismatch.

With ``--impostor``, the farthest ratio also gets an impostor row: that level
written by ``export --impostor`` (two triangles, one draw call), drawn by
static/impostor.js, its bake timed in-process (``scene.impostor_level``), its
colour ratio against gltfpack at the farthest ratio's count.

Per candidate: triangles and draw calls drawn (each mesh's triangles and
primitives once per node that places it; budgets are ratios of the input's), file bytes, colour error, silhouette mismatch; for lodserver
also the time one merge-and-bake of each merged level takes in-process
(``bake.level.merged_level``). Writes ``bench/out/hlod/results.json`` and
prints the markdown table (pasted into bench/README.md with the commit).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE / "scenes"))
sys.path.insert(0, str(HERE))
from glb import read_glb, triangle_count  # noqa: E402
from judge import CHROMIUM, CHROMIUM_ARGS, run  # noqa: E402
from static_server import serve  # noqa: E402

SHARED = ROOT.parent / "shared" / "meshes"
ASSETS = {"2CylinderEngine": SHARED / "2CylinderEngine.glb",
          "office_chair": SHARED / "office_chair.obj",
          "Avocado": SHARED / "Avocado" / "Avocado.gltf",
          "Fox": SHARED / "scenes" / "Fox.glb",
          "bunny10k_textured": SHARED / "bunny10k_textured" / "bunny10k_textured.obj"}
GLTFPACK = ROOT / "tests" / "tools" / "node_modules" / ".bin" / "gltfpack"
# front-right above, behind-left, above, below-front
VIEWS = [(0.8, 0.35, 1.0), (-1.0, 0.2, -0.6), (0.25, 1.0, 0.35), (0.3, -0.6, 1.0)]


def drawn(path: Path) -> tuple[int, int]:
    """(triangles, draw calls) drawn: each mesh's triangles and primitives once per
    node of the default scene (and its children) that places it."""
    document, _ = read_glb(path)
    nodes = document.get("nodes", [])
    roots = document.get("scenes", [{}])[document.get("scene", 0)].get("nodes", [])
    triangles, calls, stack = 0, 0, list(roots)
    while stack:
        node = nodes[stack.pop()]
        if "mesh" in node:
            mesh = document["meshes"][node["mesh"]]
            triangles += triangle_count({"meshes": [mesh], "accessors": document["accessors"]})
            calls += len(mesh["primitives"])
        stack.extend(node.get("children", ()))
    return triangles, calls


def gltfpack(gltfpack_bin: Path, source: Path, out: Path, target: int, base: int,
             timeout: float) -> dict:
    """gltfpack -si r -sa with r tuned to ``target`` triangles (see the module doc)."""
    runs, ratio = [], min(1.0, target / base)
    for attempt in range(3):
        path = out.with_name(f"{out.stem}_{attempt}.glb")
        seconds, _ = run([str(gltfpack_bin), "-i", str(source), "-o", str(path), "-si",
                          f"{ratio:.6f}", "-sa"], timeout)
        got = drawn(path)[0]
        runs.append({"path": path, "triangles": got, "ratio": ratio, "seconds": seconds})
        if abs(got - target) <= 0.02 * target or got == 0:
            break
        ratio = min(1.0, ratio * target / got)
    above = [r for r in runs if r["triangles"] >= target]
    best = min(above, key=lambda r: r["triangles"]) if above else max(
        runs, key=lambda r: r["triangles"])
    best["path"].replace(out)
    for r in runs:
        if r["path"].exists():
            r["path"].unlink()
    return {"path": out, "triangles": best["triangles"], "ratio": best["ratio"],
            "seconds": best["seconds"]}


def merged_levels(message: str) -> set[int]:
    """The levels (1-based, as the export numbers them) its message says clustering made."""
    import re

    found = re.search(r"; level ([0-9, ]+) by vertex clustering", message)
    return {int(i) for i in found.group(1).split(",")} if found else set()


def bake_seconds(source: Path, ratios, merged: set[int]) -> dict:
    """Seconds one ``merged_level`` takes for each level lodserver merged (in-process,
    on the full-detail mesh the export merged: a static scene's parts in world space,
    else a single mesh; a moving scene's parts are merged one by one, not timed here)."""
    from lodserver.bake.level import merged_level
    from lodserver.io import load_mesh
    from lodserver.io.scene import load_scene
    from lodserver.scene.merge import static_reason, world_mesh

    if not merged:
        return {}
    if source.suffix.lower() in (".glb", ".gltf"):
        scene = load_scene(source)
        if static_reason(scene) is not None:
            return {}
        full = world_mesh(scene)
    else:
        full, _ = load_mesh(source)
    times = {}
    for i, ratio in enumerate(ratios, start=1):
        if i in merged:
            started = time.perf_counter()
            merged_level(full, round(ratio * full.face_count))
            times[ratio] = time.perf_counter() - started
    return times


def impostor_candidate(source: Path, folder: Path, ratios, record: dict,
                       timeout: float) -> list:
    """The farthest ratio's level as an impostor (``export --impostor``), as a judge
    candidate: [(name, path)], or [] when the asset keeps its level (it moves).
    Fills ``record["levels"][ratio]["impostor"]`` and the bake's in-process seconds."""
    from lodserver.io import load_mesh
    from lodserver.io.scene import load_scene
    from lodserver.scene.impostor_level import baked_impostor, scene_full_mesh

    ratio = ratios[-1]
    _, message = run([sys.executable, "-m", "lodserver.cli", "export", str(source), "-o",
                      str(folder / "impostor.glb"), "--separate", "--lods", f"1,{ratio:g}",
                      "--impostor"], timeout)
    if "no impostor" in message:
        return []
    if source.suffix.lower() in (".glb", ".gltf"):
        full, _ = scene_full_mesh(load_scene(source))
    else:
        full, _ = load_mesh(source)
    _, seconds = baked_impostor(full, folder / "impostor.glb", 1)
    path = folder / "impostor_lod1.glb"
    count, calls = drawn(path)
    record["levels"][ratio]["impostor"] = {"triangles": count, "draw_calls": calls,
                                           "bytes": path.stat().st_size, "bake_seconds": seconds}
    return [(f"impostor {ratio:g}", path)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--assets", default=",".join(ASSETS))
    parser.add_argument("--ratios", default="0.1,0.02,0.005")
    parser.add_argument("--size", type=int, default=256, help="render size in pixels")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "hlod")
    parser.add_argument("--gltfpack", type=Path, default=GLTFPACK)
    parser.add_argument("--timeout", type=float, default=1800)
    parser.add_argument("--impostor", action="store_true",
                        help="also an impostor of the farthest level (static assets)")
    args = parser.parse_args(argv)
    if not args.gltfpack.exists():
        print(f"gltfpack not found at {args.gltfpack}: `npm i` in tests/tools", file=sys.stderr)
        return 2
    ratios = [float(r) for r in args.ratios.split(",")]
    from playwright.sync_api import sync_playwright

    records = []
    for key in args.assets.split(","):
        source = ASSETS[key]
        if not source.exists():
            print(f"{key}: {source} is absent, skipped", file=sys.stderr)
            continue
        folder = args.out / key
        folder.mkdir(parents=True, exist_ok=True)
        lods = ",".join(f"{r:g}" for r in [1.0, *ratios])
        seconds, message = run([sys.executable, "-m", "lodserver.cli", "export", str(source),
                                "-o", str(folder / "lodserver.glb"), "--separate", "--lods",
                                lods], args.timeout)
        reference = folder / "lodserver_lod0.glb"
        base = drawn(reference)[0]
        record = {"asset": key, "triangles": base, "export_seconds": seconds,
                  "message": message.strip().splitlines()[-1], "levels": {}}
        candidates = []
        for i, ratio in enumerate(ratios, start=1):
            ours = folder / f"lodserver_lod{i}.glb"
            count, calls = drawn(ours)
            theirs = gltfpack(args.gltfpack, source, folder / f"gltfpack_{ratio:g}.glb",
                              count, base, args.timeout)
            record["levels"][ratio] = {
                "budget": round(ratio * base),
                "lodserver": {"triangles": count, "draw_calls": calls,
                              "bytes": ours.stat().st_size},
                "gltfpack": {"triangles": theirs["triangles"],
                             "draw_calls": drawn(theirs["path"])[1],
                             "bytes": theirs["path"].stat().st_size, "ratio": theirs["ratio"]}}
            candidates += [(f"lodserver {ratio:g}", ours), (f"gltfpack {ratio:g}", theirs["path"])]
        record["bake_seconds"] = bake_seconds(source, ratios, merged_levels(record["message"]))
        if args.impostor:
            candidates += impostor_candidate(source, folder, ratios, record, args.timeout)
        with serve(ROOT) as served, sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                page = browser.new_page(viewport={"width": 400, "height": 400})
                page.goto(f"{served}/bench/scenes/judge.html")
                page.wait_for_function("window.judgeReady === true", timeout=120_000)
                page.set_default_timeout(args.timeout * 1000)
                url = lambda p: "/" + Path(p).resolve().relative_to(ROOT).as_posix()
                spec = {"input": url(reference), "views": VIEWS, "times": 1, "size": args.size,
                        "margin": 1.05, "shot_frame": 0, "shot": True, "shot_size": 200,
                        "shading": "own",
                        "candidates": [{"name": n, "url": url(p)} for n, p in candidates]}
                result = page.evaluate("(spec) => window.judge(spec)", spec)
            finally:
                browser.close()
        import base64
        (folder / "shot.png").write_bytes(base64.b64decode(result.pop("shot").split(",", 1)[1]))
        for item in result["results"]:
            method, ratio = item["name"].split(" ")
            level = record["levels"][float(ratio)][method]
            if "error" in item:
                level["error"] = item["error"]
                continue
            rms = [row["rms"] for row in item["rows"] if row["rms"] is not None]
            level["colour_rms"] = statistics.fmean(rms) if rms else None
            level["silhouette"] = statistics.fmean(row["silhouette"] for row in item["rows"])
        records.append(record)
        print(f"{key}: {record['message'][:200]}", file=sys.stderr, flush=True)
    (args.out / "results.json").write_text(json.dumps(records, indent=1, default=str))
    print(table(records))
    return 0


def table(records) -> str:
    lines = ["| asset | ratio | budget | lodserver tris | draws | bytes | colour | sil. | "
             "gltfpack -sa tris | draws | bytes | colour | sil. | colour ratio | bake s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for record in records:
        for ratio, level in record["levels"].items():
            ours, theirs = level["lodserver"], level["gltfpack"]
            colour = lambda c: f"{255 * c['colour_rms']:.1f}" if c.get("colour_rms") is not None \
                else c.get("error", "-")[:20]
            share = (f"{ours['colour_rms'] / theirs['colour_rms']:.2f}x"
                     if ours.get("colour_rms") and theirs.get("colour_rms") else "-")
            bake = record["bake_seconds"].get(ratio)
            lines.append(
                f"| {record['asset']} | {float(ratio):g} | {level['budget']} | "
                f"{ours['triangles']} | {ours['draw_calls']} | {ours['bytes']} | {colour(ours)} | "
                f"{ours.get('silhouette', 0):.3f} | {theirs['triangles']} | "
                f"{theirs['draw_calls']} | {theirs['bytes']} | {colour(theirs)} | "
                f"{theirs.get('silhouette', 0):.3f} | {share} | "
                f"{'-' if bake is None else f'{bake:.1f}'} |")
            if "impostor" in level:
                ours = level["impostor"]
                share = (f"{ours['colour_rms'] / theirs['colour_rms']:.2f}x"
                         if ours.get("colour_rms") and theirs.get("colour_rms") else "-")
                lines.append(
                    f"| {record['asset']} | {float(ratio):g} impostor | {level['budget']} | "
                    f"{ours['triangles']} | {ours['draw_calls']} | {ours['bytes']} | "
                    f"{colour(ours)} | {ours.get('silhouette', 0):.3f} | {theirs['triangles']} | "
                    f"{theirs['draw_calls']} | {theirs['bytes']} | {colour(theirs)} | "
                    f"{theirs.get('silhouette', 0):.3f} | {share} | {ours['bake_seconds']:.1f} |")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
