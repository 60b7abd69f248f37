"""Appearance benchmark: how well UVs, normals and the texture survive
simplification, lodserver against attribute-aware peers, judged by one metric.

For every textured mesh and every ratio r, each method is asked for
N = round(r * faces) triangles of the same input (``lodserver.io.load_mesh``,
with its wedges: per-corner normals and UVs):

- ``lodserver``: ``build(mesh)`` once (Hoppe 1999 attribute quadrics), then
  ``pm.at(level)`` at the level whose face count is nearest N.
- ``lodserver-geometry``: the same on ``Mesh(mesh.positions, mesh.faces)``,
  attributes stripped: the geometric error lodserver's attribute-aware build
  should stay within 10% of.
- ``meshoptimizer``: ``simplify_with_attributes`` on render vertices (one per
  wedge, so seams are split), normals and UVs as attributes.
- ``pymeshlab``: ``meshing_decimation_quadric_edge_collapse_with_texture`` on
  the welded mesh with wedge texture coordinates.

Every result, converted to a ``Mesh`` with wedges, is judged by
``lodserver.metrics.attribute_deviation`` against the input: two-sided surface
distance (RMS and Hausdorff over the bounding-box diagonal), UV distance,
normal angle, and the base-colour texture looked up at both points.

    python bench/appearance.py                   # 4 meshes x 3 ratios (~1 min)
    python bench/appearance.py --meshes Duck --ratios 0.1 --repeats 1

Writes bench/out/appearance.json and prints markdown tables; see
bench/README.md ("Appearance benchmark").
"""

from __future__ import annotations

import argparse
import ctypes
import json
import statistics
import struct
import sys
import time
import zlib
from pathlib import Path

import numba
import numpy as np

from machine import machine_info

from lodserver.build import build
from lodserver.io import load_mesh
from lodserver.mesh import Attributes, Mesh
from lodserver.metrics import attribute_deviation

PACKAGES = ("lodserver", "numpy", "numba", "meshoptimizer", "pymeshlab")

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
MESH_DIR = ROOT.parent / "shared" / "meshes"

MESHES = {
    "Duck": "Duck.glb",
    "Avocado": "Avocado/Avocado.gltf",
    "spot": "spot/spot.obj",
    "bunny10k_textured": "bunny10k_textured/bunny10k_textured.obj",
}
# spot.obj names no material library; its texture sits beside it.
TEXTURE_FILES = {"spot": "spot/spot_texture.png"}
RATIOS = (0.5, 0.1, 0.02)
HIT_TOLERANCE = 0.05  # a result "hits" N if its face count is within 5% of N
SAMPLES = 100_000
SEED = 0

# meshoptimizer: normals at the 0.5 its README's example uses, UVs at 1.0 (UVs
# span about [0, 1]; meshoptimizer scales positions to the unit box, so a UV
# error of 0.01 then weighs like a position error of 1% of the extent). The
# triangle count decides, not the error bound, as in bench/simplify.py.
MESHOPT_NORMAL_WEIGHT = 0.5
MESHOPT_UV_WEIGHT = 1.0
MESHOPT_TARGET_ERROR = 1.0
MESHOPT_OPTIONS = 0

# pymeshlab 2025.7: every parameter given (an omitted one keeps its value from
# the previous call), at the filter's defaults except preservenormal, as in
# bench/methods.py.
PYMESHLAB_SETTINGS = {
    "targetperc": 0.0,
    "qualitythr": 0.3,
    "extratcoordw": 1.0,
    "preserveboundary": False,
    "boundaryweight": 1.0,
    "optimalplacement": True,
    "preservenormal": True,
    "planarquadric": False,
    "selected": False,
}

METHODS = ("lodserver", "lodserver-geometry", "meshoptimizer", "pymeshlab")
PEERS = ("meshoptimizer", "pymeshlab")
SETTINGS = {
    "lodserver": {"call": "build(mesh)", "extract": "pm.at(level nearest N faces)"},
    "lodserver-geometry": {"call": "build(Mesh(mesh.positions, mesh.faces))",
                           "extract": "pm.at(level nearest N faces)"},
    "meshoptimizer": {
        "call": "simplify_with_attributes", "vertices": "one per wedge (seams split)",
        "attributes": "NORMAL (if the file has normals) + TEXCOORD_0",
        "attribute_weights": {"NORMAL": MESHOPT_NORMAL_WEIGHT, "TEXCOORD_0": MESHOPT_UV_WEIGHT},
        "target_index_count": "3N", "target_error": MESHOPT_TARGET_ERROR,
        "options": MESHOPT_OPTIONS,
    },
    "pymeshlab": {
        "call": "meshing_decimation_quadric_edge_collapse_with_texture",
        "input": "vertices split at seams with per-vertex UVs, "
                 "compute_texcoord_transfer_vertex_to_wedge, "
                 "meshing_remove_duplicate_vertices (welded again, UVs now per wedge)",
        "normals": "the output's vertex normals (MeshLab recomputes them)",
        "targetfacenum": "N", **PYMESHLAB_SETTINGS,
    },
}


# ---------------------------------------------------------------------------
# Textures: a small PNG reader (no imaging library in the environment)
# ---------------------------------------------------------------------------


@numba.njit(cache=True)
def _unfilter(raw, height, stride, bpp):
    """Undo PNG's per-row filters (spec section 9) on the inflated IDAT bytes."""
    out = np.zeros((height, stride), np.uint8)
    pos = 0
    for y in range(height):
        kind = raw[pos]
        pos += 1
        for x in range(stride):
            value = np.int32(raw[pos + x])
            left = np.int32(out[y, x - bpp]) if x >= bpp else np.int32(0)
            up = np.int32(out[y - 1, x]) if y > 0 else np.int32(0)
            corner = np.int32(out[y - 1, x - bpp]) if (x >= bpp and y > 0) else np.int32(0)
            if kind == 1:
                value += left
            elif kind == 2:
                value += up
            elif kind == 3:
                value += (left + up) // 2
            elif kind == 4:
                p = left + up - corner
                pa, pb, pc = abs(p - left), abs(p - up), abs(p - corner)
                if pa <= pb and pa <= pc:
                    value += left
                elif pb <= pc:
                    value += up
                else:
                    value += corner
            out[y, x] = value & 255
        pos += stride
    return out


def read_png(data: bytes) -> np.ndarray:
    """(h, w, c) uint8 pixels of an 8-bit, non-interlaced PNG (grey, RGB,
    palette, grey + alpha or RGBA). Raises ValueError on anything else."""
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG file")
    pos, idat, palette, header = 8, [], None, None
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        pos += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"PLTE":
            palette = np.frombuffer(body, np.uint8).reshape(-1, 3)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    width, height, depth, colour, _, _, interlace = header
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}[colour]
    if depth != 8 or interlace:
        raise ValueError(f"unsupported PNG: bit depth {depth}, interlace {interlace}")
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8)
    pixels = _unfilter(raw, height, width * channels, channels).reshape(height, width, channels)
    if colour == 3:
        pixels = palette[pixels[:, :, 0]]
    return pixels


def base_colour_texture(key: str, mesh: Mesh, mesh_dir: Path = MESH_DIR):
    """The base-colour image the mesh's UVs address, as (h, w, c) uint8, and
    where it came from; (None, reason) if there is none or it cannot be read."""
    try:
        if key in TEXTURE_FILES:
            path = mesh_dir / TEXTURE_FILES[key]
            return read_png(path.read_bytes()), path.name
        if mesh.materials is None:
            return None, "no material"
        gltf = mesh.materials.gltf
        used = mesh.face_material[mesh.face_material >= 0] if mesh.face_material is not None else []
        material = int(np.bincount(used).argmax()) if len(used) else 0
        info = gltf["materials"][material].get("pbrMetallicRoughness", {}).get("baseColorTexture")
        if info is None:
            return None, "no base colour texture"
        source = gltf["textures"][info["index"]]["source"]
        image = gltf["images"][source]
        return read_png(mesh.materials.images[source]), image.get("name", f"image {source}")
    except (ValueError, KeyError, IndexError, OSError) as exc:
        return None, f"unreadable ({exc})"


# ---------------------------------------------------------------------------
# Methods: each returns a Mesh (with wedges where the method keeps attributes)
# ---------------------------------------------------------------------------


def nearest_level(pm, target: int) -> int:
    """The level whose face count is nearest ``target`` (the finer on a tie)."""
    below = pm.level_for(faces=target)  # finest level with at most target faces
    if below < pm.vertex_count:
        above = below + 1
        if abs(pm.faces_at_level(above) - target) <= abs(pm.faces_at_level(below) - target):
            return above
    return below


def _declare_simplify_with_attributes():
    """The PyPI wrapper 0.2.30a0 calls meshopt_simplifyWithAttributes without
    declaring its C signature, so ctypes cannot pass the float target_error
    (ArgumentError on parameter 13). Declare it (meshoptimizer 0.22's header)."""
    from meshoptimizer._loader import lib

    function = lib.meshopt_simplifyWithAttributes
    if function.argtypes is None:
        uint_p = ctypes.POINTER(ctypes.c_uint)
        float_p = ctypes.POINTER(ctypes.c_float)
        size = ctypes.c_size_t
        function.argtypes = [uint_p, uint_p, size, float_p, size, size, float_p, size,
                             float_p, size, ctypes.POINTER(ctypes.c_ubyte), size,
                             ctypes.c_float, ctypes.c_uint, float_p]
        function.restype = size


def render_vertices(mesh: Mesh):
    """One render vertex per wedge: positions (w, 3), the layout kept, values
    (w, d) and indices (m, 3) into them (the wedge corners)."""
    a = mesh.attributes
    owner = mesh.wedge_vertices()
    return mesh.positions[owner], a.layout, a.values, a.corners


def meshoptimizer_with_attributes(mesh: Mesh, target: int) -> Mesh:
    import meshoptimizer

    _declare_simplify_with_attributes()
    positions, layout, values, corners = render_vertices(mesh)
    columns, weights = [], []
    for name, weight in (("NORMAL", MESHOPT_NORMAL_WEIGHT), ("TEXCOORD_0", MESHOPT_UV_WEIGHT)):
        cols = mesh.attributes.columns(name)
        if cols is not None:
            columns.append(values[:, cols])
            weights += [weight] * (cols.stop - cols.start)
    indices = np.ascontiguousarray(corners, dtype=np.uint32).ravel()
    destination = np.empty_like(indices)
    count = meshoptimizer.simplify_with_attributes(
        destination, indices, np.ascontiguousarray(positions, dtype=np.float32),
        np.ascontiguousarray(np.column_stack(columns), dtype=np.float32),
        np.asarray(weights, dtype=np.float32),
        target_index_count=3 * target, target_error=MESHOPT_TARGET_ERROR,
        options=MESHOPT_OPTIONS)
    kept = destination[:count].reshape(-1, 3).astype(np.int64)
    # meshoptimizer never moves a vertex: its output indexes the input render
    # vertices, i.e. our wedges, whose vertices are the welded input's
    owner = mesh.wedge_vertices()
    return Mesh(mesh.positions, owner[kept], Attributes(layout, values, kept))


def pymeshlab_with_texture(mesh: Mesh, target: int) -> Mesh:
    import pymeshlab

    positions, _, values, corners = render_vertices(mesh)
    uv_cols = mesh.attributes.columns("TEXCOORD_0")
    meshset = pymeshlab.MeshSet()
    # An array-built mesh with wedge UVs is refused ("some faces without
    # texture": no texture index). So: one vertex per wedge with per-vertex UVs,
    # MeshLab's own vertex-to-wedge transfer, then weld the split seams back.
    meshset.add_mesh(pymeshlab.Mesh(vertex_matrix=positions,
                                    face_matrix=corners.astype(np.int32),
                                    v_tex_coords_matrix=values[:, uv_cols]))
    meshset.compute_texcoord_transfer_vertex_to_wedge()
    meshset.meshing_remove_duplicate_vertices()
    meshset.meshing_decimation_quadric_edge_collapse_with_texture(
        targetfacenum=int(target), **PYMESHLAB_SETTINGS)
    result = meshset.current_mesh()
    out_positions = result.vertex_matrix()
    out_faces = result.face_matrix().astype(np.int64)
    uv = result.wedge_tex_coord_matrix().reshape(-1, 3, 2)
    layout = [("TEXCOORD_0", 2)]
    corner_values = uv
    if mesh.attributes.columns("NORMAL") is not None:
        normals = result.vertex_normal_matrix()[out_faces]
        layout = [("NORMAL", 3), ("TEXCOORD_0", 2)]
        corner_values = np.concatenate([normals, uv], axis=2)
    return mesh_from_corners(out_positions, out_faces, tuple(layout), corner_values)


def mesh_from_corners(positions, faces, layout, corner_values) -> Mesh:
    """A Mesh whose wedges are the distinct (vertex, attribute vector) pairs
    of the corners."""
    d = corner_values.shape[2]
    rows = np.column_stack([faces.reshape(-1, 1).astype(np.float64),
                            corner_values.reshape(-1, d)])
    unique, inverse = np.unique(rows, axis=0, return_inverse=True)
    return Mesh(positions, faces,
                Attributes(layout, unique[:, 1:], inverse.reshape(faces.shape)))


def with_computed_normals(mesh: Mesh) -> Mesh:
    """The mesh with smooth vertex normals (area-weighted face normals) as a
    NORMAL attribute, for judging shading when the file has no normals."""
    p, f = mesh.positions, mesh.faces
    face_normal = np.cross(p[f[:, 1]] - p[f[:, 0]], p[f[:, 2]] - p[f[:, 0]])
    normal = np.zeros_like(p)
    for k in range(3):
        np.add.at(normal, f[:, k], face_normal)
    if mesh.attributes is None:
        return Mesh(p, f, Attributes((("NORMAL", 3),), normal[f].reshape(-1, 3),
                                     np.arange(3 * len(f)).reshape(-1, 3)))
    a = mesh.attributes
    owner = mesh.wedge_vertices()
    values = np.column_stack([normal[np.maximum(owner, 0)], a.values])
    return Mesh(p, f, Attributes((("NORMAL", 3), *a.layout), values, a.corners),
                mesh.face_material, mesh.materials)


# ---------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------


def timed(call, repeats: int):
    """(result of the last call, median wall seconds, every call's (wall, CPU)
    seconds) over ``repeats`` calls after one untimed warm-up call. CPU time
    well below wall time means another process had the CPU."""
    result = call()  # loads libraries, compiles or loads numba code
    times = []
    for _ in range(repeats):
        cpu = time.process_time()
        start = time.perf_counter()
        result = call()
        times.append((time.perf_counter() - start, time.process_time() - cpu))
    return result, statistics.median(wall for wall, _ in times), times


def run_methods(mesh: Mesh, targets: list[int], repeats: int) -> dict:
    """{method: {target: (Mesh or None, seconds, extra dict)}}; a method that
    raises is recorded with its error."""
    out = {}
    for method in METHODS:
        rows = {}
        try:
            if method.startswith("lodserver"):
                source = mesh if method == "lodserver" else Mesh(mesh.positions, mesh.faces)
                pm, build_s, build_times = timed(lambda: build(source), repeats)
                for target in targets:
                    level = nearest_level(pm, target)
                    lod, extract_s, _ = timed(lambda: pm.at(level), repeats)
                    rows[target] = (lod, build_s, {"extract_s": extract_s, "level": level,
                                                   "build_wall_cpu_s": build_times,
                                                   "coarsest_faces": pm.faces_at_level(
                                                       pm.base_vertices)})
            elif mesh.attributes is None or mesh.attributes.columns("TEXCOORD_0") is None:
                for target in targets:
                    rows[target] = (None, None, {"error": "the input has no UVs"})
            else:
                call = meshoptimizer_with_attributes if method == "meshoptimizer" \
                    else pymeshlab_with_texture
                for target in targets:
                    lod, seconds, times = timed(lambda: call(mesh, target), repeats)
                    rows[target] = (lod, seconds, {"wall_cpu_s": times})
        except Exception as exc:  # recorded, the run goes on
            for target in targets:
                rows.setdefault(target, (None, None, {"error": f"{type(exc).__name__}: {exc}"}))
        out[method] = rows
    return out


def judge_all(mesh: Mesh, results: dict, texture, samples: int) -> dict:
    normals_from_file = mesh.attributes is not None and mesh.attributes.columns("NORMAL") is not None
    reference = mesh if normals_from_file else with_computed_normals(mesh)
    judged = {}
    for method, rows in results.items():
        for target, (lod, _, _) in rows.items():
            if lod is None:
                continue
            candidate = lod if normals_from_file else with_computed_normals(lod)
            judged[method, target] = attribute_deviation(reference, candidate, samples=samples,
                                                         seed=SEED, texture=texture)
    return judged, ("file" if normals_from_file else "computed")


def _median_cpu(extra: dict):
    times = extra.get("wall_cpu_s") or extra.get("build_wall_cpu_s")
    return statistics.median(cpu for _, cpu in times) if times else None


def _stat(report, name, key):
    if report is None or report.get(name) is None:
        return None
    return report[name][key]


def summarise(key, mesh, ratios, targets, results, judged, normal_source, texture_name):
    rows = []
    for ratio, target in zip(ratios, targets):
        for method in METHODS:
            lod, seconds, extra = results[method][target]
            report = judged.get((method, target))
            faces = lod.face_count if lod is not None else None
            rows.append({
                "mesh": key, "ratio": ratio, "method": method, "target": target,
                "faces": faces,
                "hit": faces is not None and abs(faces - target) <= HIT_TOLERANCE * target,
                "time_s": seconds, "cpu_s": _median_cpu(extra), **extra,
                "normal_source": normal_source, "texture": texture_name,
                "geometry_rms": _stat(report, "geometry", "rms"),
                "geometry_hausdorff": _stat(report, "geometry", "hausdorff"),
                "uv_rms": _stat(report, "TEXCOORD_0", "rms"),
                "uv_p50": _stat(report, "TEXCOORD_0", "p50"),
                "uv_p99": _stat(report, "TEXCOORD_0", "p99"),
                "uv_max": _stat(report, "TEXCOORD_0", "max"),
                "normal_rms_deg": _stat(report, "NORMAL", "rms"),
                "normal_p99_deg": _stat(report, "NORMAL", "p99"),
                "normal_max_deg": _stat(report, "NORMAL", "max"),
                "texture_rms": _stat(report, "texture", "rms"),
                "texture_p99": _stat(report, "texture", "p99"),
                "judge": report,
            })
    return rows


COMPARED = (("uv_rms", "UV RMS"), ("uv_p99", "UV p99"), ("normal_rms_deg", "normal RMS"),
            ("texture_rms", "texture RMS"))


def compare(rows) -> list[dict]:
    """Per mesh and ratio: lodserver's attribute errors over the best peer's
    (lowest value among peers that hit the target; among all judged if none
    did), and its geometric error over the geometry-only build's."""
    out = []
    keys = sorted({(r["mesh"], r["ratio"]) for r in rows}, key=lambda k: (k[0], -k[1]))
    for mesh, ratio in keys:
        by = {r["method"]: r for r in rows if r["mesh"] == mesh and r["ratio"] == ratio}
        ours, geo = by["lodserver"], by["lodserver-geometry"]
        entry = {"mesh": mesh, "ratio": ratio, "target": ours["target"],
                 "lodserver_faces": ours["faces"]}
        for field, _ in COMPARED:
            peers = [by[p] for p in PEERS if by[p][field] is not None]
            hit = [p for p in peers if p["hit"]]
            pool = hit or peers
            if ours[field] is None or not pool:
                entry[field] = None
                continue
            best = min(pool, key=lambda r: r[field])
            entry[field] = {"best_peer": best["method"], "peer_hit": bool(hit),
                            "peer_value": best[field], "lodserver": ours[field],
                            "ratio": ours[field] / best[field] if best[field] > 0 else None}
        for field in ("geometry_rms", "geometry_hausdorff"):
            if ours[field] is not None and geo[field]:
                entry[field + "_vs_geometry_only"] = ours[field] / geo[field]
        out.append(entry)
    return out


def fmt(value, scale=1.0, digits=3):
    if value is None:
        return "-"
    value = value * scale
    if value == 0:
        return "0"
    return f"{value:.{digits}g}"


def markdown(rows, comparison) -> str:
    lines = ["| mesh | ratio | method | target | faces | hit | rms e-4 | hausdorff e-4 "
             "| UV rms e-3 | UV p50 e-3 | UV p99 e-3 | normal rms ° | normal p99 ° | texture rms "
             "| texture p99 | wall s | cpu s |",
             "|" + "---|" * 17]
    for r in rows:
        lines.append("| " + " | ".join([
            r["mesh"], f"{r['ratio']:g}", r["method"], str(r["target"]),
            str(r["faces"]) if r["faces"] is not None else r.get("error", "-"),
            "yes" if r["hit"] else "no",
            fmt(r["geometry_rms"], 1e4), fmt(r["geometry_hausdorff"], 1e4),
            fmt(r["uv_rms"], 1e3), fmt(r["uv_p50"], 1e3), fmt(r["uv_p99"], 1e3),
            fmt(r["normal_rms_deg"]) + ("" if r["normal_rms_deg"] is None or
                                         r["normal_source"] == "file" else "ᶜ"),
            fmt(r["normal_p99_deg"]), fmt(r["texture_rms"]), fmt(r["texture_p99"]),
            fmt(r["time_s"]), fmt(r["cpu_s"]),
        ]) + " |")
    lines += ["", "| mesh | ratio | lodserver faces | UV rms / best peer | UV p99 / best peer "
              "| normal rms / best peer | texture rms / best peer | rms / geometry-only "
              "| hausdorff / geometry-only |", "|" + "---|" * 9]
    for c in comparison:
        cells = [c["mesh"], f"{c['ratio']:g}", f"{c['lodserver_faces']} of {c['target']}"]
        for field, _ in COMPARED:
            e = c[field]
            if e is None or e["ratio"] is None:
                cells.append("-")
            else:
                cells.append(f"{e['ratio']:.2f} ({e['best_peer']}"
                             + ("" if e["peer_hit"] else ", missed target") + ")")
        cells.append(fmt(c.get("geometry_rms_vs_geometry_only")))
        cells.append(fmt(c.get("geometry_hausdorff_vs_geometry_only")))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--meshes", default=",".join(MESHES), help="comma-separated names")
    parser.add_argument("--ratios", default=",".join(f"{r:g}" for r in RATIOS))
    parser.add_argument("--repeats", type=int, default=3, help="timed calls (median)")
    parser.add_argument("--samples", type=int, default=SAMPLES, help="judge points per surface")
    parser.add_argument("--mesh-dir", type=Path, default=MESH_DIR)
    parser.add_argument("--out", type=Path, default=BENCH / "out" / "appearance.json")
    args = parser.parse_args(argv)
    keys = [k for k in args.meshes.split(",") if k]
    ratios = [float(r) for r in args.ratios.split(",") if r]
    unknown = [k for k in keys if k not in MESHES]
    if unknown:
        parser.error(f"unknown meshes {unknown}; known: {', '.join(MESHES)}")

    document = {"machine": machine_info(PACKAGES), "settings": {
        "ratios": ratios, "repeats": args.repeats, "samples": args.samples, "seed": SEED,
        "hit_tolerance": HIT_TOLERANCE, "methods": SETTINGS}, "inputs": {}, "rows": []}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    for key in keys:
        mesh, report = load_mesh(args.mesh_dir / MESHES[key])
        texture, texture_name = base_colour_texture(key, mesh, args.mesh_dir)
        targets = [max(1, round(r * mesh.face_count)) for r in ratios]
        print(f"{key}: {mesh}, texture {texture_name}", file=sys.stderr, flush=True)
        results = run_methods(mesh, targets, args.repeats)
        judged, normal_source = judge_all(mesh, results, texture, args.samples)
        document["inputs"][key] = {
            "file": MESHES[key], "faces": mesh.face_count, "vertices": mesh.vertex_count,
            "wedges": None if mesh.attributes is None else mesh.attributes.wedge_count,
            "layout": None if mesh.attributes is None else [list(x) for x in mesh.attributes.layout],
            "texture": texture_name,
            "texture_shape": None if texture is None else list(texture.shape),
            "normal_source": normal_source, "load_report": report.as_dict()}
        document["rows"] += summarise(key, mesh, ratios, targets, results, judged,
                                      normal_source, texture_name if texture is not None else None)
        document["comparison"] = compare(document["rows"])
        document["elapsed_s"] = time.perf_counter() - started
        args.out.write_text(json.dumps(document, indent=1, default=float))
    table = markdown(document["rows"], document["comparison"])
    print(table)
    print(f"\nwritten {args.out} in {time.perf_counter() - started:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
