"""Batches of independent vertex splits (``lodserver.progressive.batches``):
how many, how large against their level, what a split's location would cost
as one mark per vertex per batch against an index over the level, and what
the re-ordering does to fidelity at the levels ``bench/simplify.py`` judges.

    python bench/batches.py                                 # the five meshes below
    python bench/batches.py --meshes spot,Duck --windows 0.1,0.25

For each mesh the progressive mesh is built once with the default options
(``build``; a scene's mesh with its poses, as the server builds it; with
``--geometry`` or ``--meshes all-simplify`` of positions and faces only, as
``bench/simplify.py`` builds) and scheduled at each window (by default the
schedule's own: ``WINDOW``, ``ATTRIBUTE_WINDOW`` with attributes). Per window:

- batches; splits per batch over the level's vertex count (mean and median
  over batches);
- location bits per split: a batch of ``k`` splits in a level of ``N``
  vertices codes ``N`` marks, about ``log2(e N / k)`` bits a split (the
  issue's estimate), against ``log2`` of the level for an index (today's
  ``vs``), both averaged over splits;
- RMS surface distance (``metrics.surface_distance``, the bench's seed and
  samples, over the bounding-box diagonal) at the face counts of
  ``bench/simplify.py``'s ratios, batched over unbatched;
- the schedule's time (dependencies, batches, the re-laid arrays).

``--appearance`` instead judges the lodserver rows of ``bench/appearance.py``
(its meshes, ratios, level nearest N faces, texture and judge), batched over
unbatched: geometry RMS, UV and normal RMS and p99, texture RMS.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(BENCH))

from codec_meshes import bunny_loop2  # noqa: E402
from lodserver import build  # noqa: E402
from lodserver.io import load_mesh  # noqa: E402
from lodserver.mesh import Mesh  # noqa: E402
from lodserver.metrics import surface_distance  # noqa: E402
from lodserver.progressive.batches import (ATTRIBUTE_WINDOW, ERROR_RATIO, WINDOW,  # noqa: E402
                                           schedule)

RATIOS = (0.5, 0.1, 0.02, 0.005)  # bench/simplify.py's
SEED = 0
MESHES = {
    "spot": "spot/spot.obj",
    "stanford-bunny": "stanford-bunny.obj",
    "bunny_loop2": None,  # made as bench/simplify.py makes it
    "Duck": "Duck.glb",
    "Fox": "scenes/Fox.glb",
}
# every mesh of bench/simplify.py, for the fidelity check alone (--meshes all-simplify)
SIMPLIFY_MESHES = {
    "stanford-bunny": "stanford-bunny.obj", "fandisk": "fandisk.obj", "spot": "spot/spot.obj",
    "decimated-max": "decimated-max.obj", "fertility": "fertility.off",
    "camelhead": "camelhead.off", "Laurana50k": "Laurana50k.ply",
    "bunny10k_textured": "bunny10k_textured/bunny10k_textured.obj", "Duck": "Duck.glb",
    "Avocado": "Avocado/Avocado.gltf", "2CylinderEngine": "2CylinderEngine.glb",
    "office_chair": "office_chair.obj", "mountain": "mountain.obj",
    "non_manif_hole": "non_manif_hole.ply", "conrod": "conrod.stl", "soup": "soup.stl",
    "joined_tetrahedra": "joined_tetrahedra.obj", "brain": "brain.ply", "bunny_loop2": None,
}


def built(key: str, relative, mesh_dir: Path, out: Path, geometry: bool = False):
    """(reference mesh, progressive mesh) of one bench mesh; ``geometry``:
    positions and faces only, as bench/simplify.py builds."""
    if relative is None:
        mesh = bunny_loop2(mesh_dir, out)
        return mesh, build(mesh)
    path = mesh_dir / relative
    if path.parent.name == "scenes":
        from lodserver.io.scene import load_scene
        from lodserver.simplify.poses import scene_poses

        scene = load_scene(path)
        # the scene's largest mesh, built with its poses as the server builds it
        index, mesh = max(scene.meshes.items(), key=lambda item: item[1].face_count)
        return mesh, build(mesh, poses=scene_poses(scene, index, mesh))
    mesh, _ = load_mesh(path)
    if geometry:
        mesh = Mesh(mesh.positions, mesh.faces)
    return mesh, build(mesh)


def label(pm, window, error_ratio) -> str:
    """'window / error ratio', the window the schedule takes when given None."""
    if window is None:
        window = ATTRIBUTE_WINDOW if pm.has_attributes else WINDOW
    return f"{window} / {error_ratio}"


def batch_facts(pm, batch) -> dict:
    """Batch counts and location bits of one schedule."""
    k = pm.split_count
    if k == 0:
        return {"batches": 0}
    starts = np.concatenate([[0], np.flatnonzero(np.diff(batch)) + 1, [k]])
    sizes = np.diff(starts)
    levels = pm.base_vertices + starts[:-1]
    share = sizes / levels
    return {"batches": int(len(sizes)), "mean_share": float(share.mean()),
            "median_share": float(np.median(share)),
            "mark_bits": float(np.sum(sizes * np.log2(np.e * levels / sizes)) / k),
            "index_bits": float(np.mean(np.log2(pm.base_vertices + np.arange(k))))}


def rms_at(reference, pm, ratios, samples) -> list:
    out = []
    for ratio in ratios:
        target = max(1, round(ratio * reference.face_count))
        level = pm.level_for(faces=target)
        positions, faces = pm.arrays_at(level)
        try:
            out.append(surface_distance(reference, (positions, faces), samples=samples,
                                        seed=SEED)["rms"])
        except ValueError:  # no faces or no area: nothing to judge
            out.append(None)
    return out


def bench(key, relative, args) -> dict:
    reference, pm = built(key, relative, args.mesh_dir, args.out, args.geometry)
    row = {"mesh": key, "faces": reference.face_count, "splits": pm.split_count,
           "base_vertices": pm.base_vertices, "windows": {}}
    if not args.no_fidelity:
        row["rms"] = rms_at(reference, pm, args.ratios, args.samples)
    for window, error_ratio in ((w, r) for w in args.windows for r in args.error_ratios):
        start = time.perf_counter()
        result = schedule(pm, window, error_ratio)
        elapsed = time.perf_counter() - start
        facts = {**batch_facts(result.pm, result.batch), "schedule_s": elapsed}
        if not args.no_fidelity:
            facts["rms"] = rms_at(reference, result.pm, args.ratios, args.samples)
            facts["rms_over_unbatched"] = [None if a is None or b is None or b == 0 else a / b
                                           for a, b in zip(facts["rms"], row["rms"])]
        row["windows"][label(pm, window, error_ratio)] = facts
        print(f"{key} {label(pm, window, error_ratio)}: {json.dumps(facts)}", file=sys.stderr,
              flush=True)
    return row


def appearance_rows(windows, samples) -> list:
    """bench/appearance.py's lodserver rows, batched at each (window, error
    ratio) over unbatched."""
    import appearance as bench_appearance

    out = []
    for key, relative in bench_appearance.MESHES.items():
        mesh, _ = load_mesh(bench_appearance.MESH_DIR / relative)
        texture, _ = bench_appearance.base_colour_texture(key, mesh)
        from_file = mesh.attributes is not None and mesh.attributes.columns("NORMAL") is not None
        reference = mesh if from_file else bench_appearance.with_computed_normals(mesh)
        pm = build(mesh)
        versions = {"unbatched": pm, **{label(pm, w, r): schedule(pm, w, r).pm
                                        for w, r in windows}}
        for ratio in bench_appearance.RATIOS:
            target = max(1, round(ratio * mesh.face_count))
            judged = {}
            for name, version in versions.items():
                lod = version.at(bench_appearance.nearest_level(version, target))
                candidate = lod if from_file else bench_appearance.with_computed_normals(lod)
                report = bench_appearance.attribute_deviation(
                    reference, candidate, samples=samples, seed=bench_appearance.SEED,
                    texture=texture)
                judged[name] = {"rms": report["geometry"]["rms"],
                                **{f"{a} {s}": (report.get(a) or {}).get(s)
                                   for a in ("TEXCOORD_0", "NORMAL", "texture")
                                   for s in ("rms", "p99")}}
            for window in (label(pm, w, r) for w, r in windows):
                row = {"mesh": key, "ratio": ratio, "window": window}
                for figure, value in judged[window].items():
                    base = judged["unbatched"][figure]
                    row[figure] = None if value is None or not base else value / base
                out.append(row)
                print(json.dumps(row), file=sys.stderr, flush=True)
    return out


def appearance_table(rows) -> str:
    figures = [k for k in rows[0] if k not in ("mesh", "ratio", "window")] if rows else []
    lines = ["| mesh | ratio | window | " + " | ".join(f"{f} batched / unbatched"
                                                     for f in figures) + " |",
             "|" + "---|" * (3 + len(figures))]
    for row in rows:
        lines.append(f"| {row['mesh']} | {row['ratio']} | {row['window']} | " + " | ".join(
            "-" if row[f] is None else f"{row[f]:.3f}" for f in figures) + " |")
    return "\n".join(lines)


def table(rows, ratios) -> str:
    header = ["mesh", "splits", "window / error ratio", "batches", "mean k/N", "median k/N",
              "mark bits/split", "log2 level", "schedule s",
              *(f"rms ratio @{r}" for r in ratios)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for row in rows:
        for window, f in row["windows"].items():
            ratio = f.get("rms_over_unbatched") or [None] * len(ratios)
            lines.append("| " + " | ".join([
                row["mesh"], str(row["splits"]), window, str(f.get("batches")),
                f"{f.get('mean_share', 0):.3f}", f"{f.get('median_share', 0):.3f}",
                f"{f.get('mark_bits', 0):.2f}", f"{f.get('index_bits', 0):.2f}",
                f"{f['schedule_s']:.2f}",
                *("-" if x is None else f"{x:.3f}" for x in ratio)]) + " |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--meshes", default=",".join(MESHES),
                        help=f"comma-separated, from {', '.join(SIMPLIFY_MESHES)}, Fox; "
                        "all-simplify: every mesh of bench/simplify.py")
    parser.add_argument("--windows", default="default",
                        help="comma-separated windows; default: the schedule's own choice")
    parser.add_argument("--error-ratios", default=str(ERROR_RATIO),
                        help="comma-separated error ratios (each with each window)")
    parser.add_argument("--ratios", default=",".join(map(str, RATIOS)))
    parser.add_argument("--samples", type=int, default=200_000)
    parser.add_argument("--no-fidelity", action="store_true", help="skip the RMS judging")
    parser.add_argument("--geometry", action="store_true",
                        help="build positions and faces only, as bench/simplify.py does "
                        "(implied by all-simplify)")
    parser.add_argument("--appearance", action="store_true",
                        help="judge bench/appearance.py's lodserver rows instead")
    parser.add_argument("--mesh-dir", type=Path, default=ROOT.parent / "shared" / "meshes")
    parser.add_argument("--out", type=Path, default=BENCH / "out")
    args = parser.parse_args(argv)
    known = {**SIMPLIFY_MESHES, **MESHES}
    names = list(SIMPLIFY_MESHES) if args.meshes == "all-simplify" else args.meshes.split(",")
    args.geometry = args.geometry or args.meshes == "all-simplify"
    unknown = [n for n in names if n not in known]
    if unknown:
        parser.error(f"unknown mesh {unknown[0]}; choose from {', '.join(known)}")
    args.windows = [None if w == "default" else float(w) for w in args.windows.split(",")]
    args.error_ratios = [float(r) for r in args.error_ratios.split(",")]
    args.ratios = [float(r) for r in args.ratios.split(",")]
    if args.appearance:
        rows = appearance_rows([(w, r) for w in args.windows for r in args.error_ratios],
                               min(args.samples, 100_000))
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "batches-appearance.json").write_text(json.dumps(rows, indent=1))
        print(appearance_table(rows))
        return
    rows = [bench(name, known[name], args) for name in names]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "batches.json").write_text(json.dumps(rows, indent=1))
    print(table(rows, args.ratios))
    ratios = [x for row in rows for f in row["windows"].values()
              for x in f.get("rms_over_unbatched", []) if x is not None]
    if ratios:
        print(f"\nrms batched / unbatched over every mesh and ratio: median "
              f"{statistics.median(ratios):.3f}, worst {max(ratios):.3f}")


if __name__ == "__main__":
    main()
