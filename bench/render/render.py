"""Renders to judge LODs by eye: each textured model, original and levels of
detail side by side, in one PNG per model.

    python bench/render/render.py                       # lodserver at 50/10/2%
    python bench/render/render.py --peers               # + meshoptimizer, pymeshlab
    python bench/render/render.py --meshes Duck --ratios 0.1,0.02 --size 360

For every model: the original (``lodserver.io.load_mesh``) and
``build(mesh).at(level)`` at the level whose face count is nearest each ratio
of the triangles (with ``--peers`` also the appearance benchmark's
meshoptimizer ``simplify_with_attributes`` and pymeshlab texture-aware
decimation at the same targets), each written as GLB with
``lodserver.io.encode_mesh(mesh, "glb")`` (textures travel inside; a mesh
without attributes is drawn untextured in grey) to
``bench/out/render/<model>/``. A loopback HTTP server on an ephemeral port
serves the repository; headless Chromium (Playwright) opens
``bench/render/index.html``, which draws every panel with the vendored
three.js and GLTFLoader under one camera fitted to the original's bounding
sphere (one row per view direction), labels each with its method and
triangle count, and the page is saved as ``bench/out/render/<model>.png``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE.parent))  # bench/, for appearance.py

from appearance import (  # noqa: E402
    MESH_DIR,
    MESHES,
    TEXTURE_FILES,
    meshoptimizer_with_attributes,
    nearest_level,
    pymeshlab_with_texture,
)
from lodserver.build import build  # noqa: E402
from lodserver.io import encode_mesh, load_mesh  # noqa: E402
from lodserver.mesh import Materials, Mesh  # noqa: E402
from static_server import serve  # noqa: E402

OUT = ROOT / "bench" / "out" / "render"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
RATIOS = (0.5, 0.1, 0.02)
# View directions (from the model's centre towards the camera), in the file's
# frame; all four models are Y-up. One row of panels per view.
VIEWS = {
    "Duck": [(0.8, 0.35, 1.0), (-0.9, 0.3, -0.6)],
    "Avocado": [(1.0, 0.25, 0.8), (-1.0, 0.2, -0.7)],
    "spot": [(1.0, 0.3, 0.9), (-0.9, 0.3, -0.8)],
    "bunny10k_textured": [(0.6, 0.3, 1.0), (-0.8, 0.3, -0.8)],
}
UP = (0.0, 1.0, 0.0)
UNTEXTURED_COLOR = "#b8b8b8"


def with_texture_file(key: str, mesh: Mesh, mesh_dir: Path) -> Mesh:
    """spot.obj names no material, so its texture is attached here as a glTF
    material, for the renders only."""
    if key not in TEXTURE_FILES or mesh.materials is not None or mesh.attributes is None:
        return mesh
    path = mesh_dir / TEXTURE_FILES[key]
    materials = Materials(
        gltf={"materials": [{"name": path.stem, "pbrMetallicRoughness": {
                  "baseColorTexture": {"index": 0}, "metallicFactor": 0.0}}],
              "textures": [{"source": 0}], "samplers": [],
              "images": [{"mimeType": "image/png", "name": path.name}]},
        images=(path.read_bytes(),))
    return Mesh(mesh.positions, mesh.faces, mesh.attributes,
                np.zeros(mesh.face_count, np.int32), materials)


def with_materials_of(source: Mesh, lod: Mesh) -> Mesh:
    """A peer's output (which has no materials) with the source's single
    material on every face, so it renders textured like the source."""
    if source.materials is None or source.materials.count != 1 or lod.materials is not None:
        return lod
    return Mesh(lod.positions, lod.faces, lod.attributes,
                np.zeros(lod.face_count, np.int32), source.materials)


def panels_for(key: str, mesh: Mesh, ratios, peers: bool):
    """{method: [(slug, label, detail, Mesh) per ratio]} for one model, the
    original under "original"."""
    rows = {"original": [("original", "original", f"{mesh.face_count:,} triangles", mesh)]}
    pm = build(mesh)
    calls = {"lodserver": lambda target: pm.at(nearest_level(pm, target))}
    if peers and mesh.attributes is not None:
        calls["meshoptimizer"] = lambda target: meshoptimizer_with_attributes(mesh, target)
        calls["pymeshlab"] = lambda target: pymeshlab_with_texture(mesh, target)
    for method, call in calls.items():
        rows[method] = []
        for ratio in ratios:
            target = max(1, round(ratio * mesh.face_count))
            try:
                lod = with_materials_of(mesh, call(target))
            except Exception as exc:  # shown in the log; the cell stays empty
                print(f"  {method} at {ratio:g} failed: {exc}", file=sys.stderr)
                rows[method].append(None)
                continue
            detail = f"{lod.face_count:,} triangles"
            if abs(lod.face_count - target) > 0.05 * target:
                detail += f" (asked {target:,})"
            rows[method].append((f"{method}-{ratio:g}", f"{method} {100 * ratio:g}%", detail, lod))
    return rows


def bounding_sphere(mesh: Mesh):
    used = mesh.positions[np.unique(mesh.faces)]
    lo, hi = used.min(axis=0), used.max(axis=0)
    centre = (lo + hi) / 2
    return centre, float(np.linalg.norm(used - centre, axis=1).max())


def write_model(key: str, mesh: Mesh, rows: dict, size: int) -> Path:
    """The GLBs and the page's manifest for one model. Layout: one row per
    method and view; column 0 the original (repeated on every row, as the
    reference beside each method), then one column per ratio."""
    folder = OUT / key
    folder.mkdir(parents=True, exist_ok=True)
    for old in folder.glob("*.glb"):
        old.unlink()
    centre, radius = bounding_sphere(mesh)
    panels, index = [], {}
    for method, cells in rows.items():
        for cell in cells:
            if cell is None:
                continue
            slug, label, detail, lod = cell
            path = folder / f"{slug}.glb"
            path.write_bytes(encode_mesh(lod, "glb"))
            textured = lod.attributes is not None and lod.materials is not None
            index[slug] = len(panels)
            panels.append({"url": "/" + path.relative_to(ROOT).as_posix(), "method": label,
                           "detail": detail + ("" if textured else ", untextured")})
    views = VIEWS.get(key, [(1.0, 0.3, 1.0)])
    methods = [m for m in rows if m != "original"]
    layout, row = [], 0
    for method in methods:
        for view in range(len(views)):
            layout.append({"panel": index["original"], "view": view, "row": row, "column": 0})
            for column, cell in enumerate(rows[method], start=1):
                if cell is not None:
                    layout.append({"panel": index[cell[0]], "view": view, "row": row,
                                   "column": column})
            row += 1
    manifest = {"title": f"{key}: the original and levels of detail; one camera per view "
                         f"({len(views)} views), the same in every column",
                "panels": panels, "cells": layout, "rows": row,
                "columns": 1 + max(len(rows[m]) for m in methods),
                "panel_size": size, "center": centre.tolist(), "radius": radius,
                "up": list(UP), "views": [list(v) for v in views],
                "untextured_color": UNTEXTURED_COLOR}
    path = folder / "manifest.json"
    path.write_text(json.dumps(manifest, indent=1))
    return path


def render(manifests: dict, timeout_s: float) -> dict:
    """Screenshot the page for every manifest; {key: PNG path}."""
    from playwright.sync_api import sync_playwright

    written = {}
    with serve(ROOT) as base, sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            for key, manifest in manifests.items():
                page = browser.new_page(viewport={"width": 800, "height": 600})
                messages = []
                page.on("console", lambda m: messages.append(f"{m.type}: {m.text}"))
                page.on("pageerror", lambda e: messages.append(f"pageerror: {e}"))
                url = (f"{base}/bench/render/index.html?manifest="
                       f"/{manifest.relative_to(ROOT).as_posix()}")
                page.goto(url)
                try:
                    page.wait_for_function("window.renderDone || window.renderError",
                                           timeout=timeout_s * 1000)
                except Exception:
                    raise RuntimeError(f"{key}: the page did not finish: {messages}") from None
                error = page.evaluate("window.renderError")
                if error:
                    raise RuntimeError(f"{key}: {error}\n{messages}")
                png = OUT / f"{key}.png"
                page.locator("#sheet").screenshot(path=str(png))
                written[key] = png
                page.close()
        finally:
            browser.close()
    return written


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", default=",".join(MESHES), help="comma-separated names")
    parser.add_argument("--ratios", default=",".join(f"{r:g}" for r in RATIOS))
    parser.add_argument("--peers", action="store_true",
                        help="also render meshoptimizer and pymeshlab at the same targets")
    parser.add_argument("--size", type=int, default=340, help="cell size in pixels")
    parser.add_argument("--mesh-dir", type=Path, default=MESH_DIR)
    parser.add_argument("--timeout", type=float, default=120, help="seconds per page")
    args = parser.parse_args(argv)
    ratios = [float(r) for r in args.ratios.split(",") if r]
    manifests = {}
    for key in [k for k in args.meshes.split(",") if k]:
        mesh, _ = load_mesh(args.mesh_dir / MESHES[key])
        mesh = with_texture_file(key, mesh, args.mesh_dir)
        rows = panels_for(key, mesh, ratios, args.peers)
        manifests[key] = write_model(key, mesh, rows, args.size)
        print(f"{key}: {', '.join(rows)}", file=sys.stderr, flush=True)
    for key, png in render(manifests, args.timeout).items():
        print(png)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
