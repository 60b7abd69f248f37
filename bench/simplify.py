"""Simplification benchmark: lodserver against meshoptimizer, pymeshlab and
fast-simplification, side by side, judged by one metric.

For every mesh and every ratio r, each method is asked for N = round(r * faces)
triangles of the same welded input (``lodserver.io.load_mesh``). lodserver
builds its progressive mesh once per mesh and extracts every N from it; each
peer runs once per N. Every measurement runs in a child process
(``worker.py``), so a crash or a hang is recorded as a failure and the run
goes on. Every result is judged by ``lodserver.metrics.surface_distance``
against the welded input, with the same seed.

    python bench/simplify.py                     # everything (15-20 min on 2 cores)
    python bench/simplify.py --quick             # a smoke run (~2 min)
    python bench/simplify.py --meshes fandisk,Duck --ratios 0.1 --repeats 5

See bench/README.md for what each column means.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
WORKER = BENCH / "worker.py"
# A compile cache of our own: it starts empty, so the compile time measured
# below is real, and lodserver/__pycache__ is left to whoever edits the kernel.
# Set before lodserver (and so numba) is imported.
NUMBA_CACHE = BENCH / "out" / "numba-cache"
os.environ["NUMBA_CACHE_DIR"] = str(NUMBA_CACHE)

from lodserver.io import clean_mesh, load_mesh  # noqa: E402
from lodserver.metrics import surface_distance  # noqa: E402
from machine import cpu_busy, machine_info  # noqa: E402
from methods import PEER_SETTINGS, PEERS  # noqa: E402

PACKAGES = ("lodserver", "numpy", "numba", "scipy", "trimesh", "meshoptimizer", "pymeshlab",
            "fast-simplification")

SHARED_MESHES = {
    "stanford-bunny": "stanford-bunny.obj",
    "fandisk": "fandisk.obj",
    "spot": "spot/spot.obj",
    "decimated-max": "decimated-max.obj",
    "fertility": "fertility.off",
    "camelhead": "camelhead.off",
    "Laurana50k": "Laurana50k.ply",
    "bunny10k_textured": "bunny10k_textured/bunny10k_textured.obj",
    "Duck": "Duck.glb",
    "Avocado": "Avocado/Avocado.gltf",
    "2CylinderEngine": "2CylinderEngine.glb",
    "office_chair": "office_chair.obj",
    "mountain": "mountain.obj",
    "non_manif_hole": "non_manif_hole.ply",
    "conrod": "conrod.stl",
    "soup": "soup.stl",
    "joined_tetrahedra": "joined_tetrahedra.obj",
    "brain": "brain.ply",
}
# stanford-bunny Loop-subdivided twice (1.11M triangles), made on first use.
LARGE = "bunny_loop2"
ALL_MESHES = [*SHARED_MESHES, LARGE]
QUICK_MESHES = ["fertility", "Duck", "soup", "joined_tetrahedra"]
RATIOS = (0.5, 0.1, 0.02, 0.005)
SEED = 0  # one judge seed for every result
HIT_TOLERANCE = 0.05  # a result "hits" N if its face count is within 5% of N
LARGE_FACES = 500_000  # meshes this big use --repeats-large


# ---------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------


def prepare_input(key: str, mesh_dir: Path, out: Path):
    """The welded mesh for ``key``, its load report, and an .npz of it for workers."""
    if key == LARGE:
        path = out / f"{LARGE}.npz"
        if path.exists():
            data = np.load(path)
            mesh, report = clean_mesh(data["positions"], data["faces"])
        else:
            import trimesh

            bunny, _ = load_mesh(mesh_dir / SHARED_MESHES["stanford-bunny"])
            positions, faces = trimesh.remesh.subdivide_loop(
                bunny.positions, bunny.faces, iterations=2
            )
            mesh, report = clean_mesh(positions, faces)
            np.savez(path, positions=mesh.positions, faces=mesh.faces)
        return mesh, report.as_dict(), path
    mesh, report = load_mesh(mesh_dir / SHARED_MESHES[key])
    path = out / "inputs" / f"{key}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, positions=mesh.positions, faces=mesh.faces)
    return mesh, report.as_dict(), path


# ---------------------------------------------------------------------------
# Running workers
# ---------------------------------------------------------------------------


class WorkerFailed(Exception):
    """A child process crashed, raised, or ran out of time; the message says which."""


def run_worker(args: list[str], output: Path, timeout: float):
    """Run ``worker.py *args`` (which writes ``output``); (report, arrays).

    Raises WorkerFailed on a timeout, a signal or a non-zero exit.
    """
    try:
        proc = subprocess.run([sys.executable, str(WORKER), *args], capture_output=True,
                              text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise WorkerFailed(f"timeout after {timeout:g} s") from None
    if proc.returncode < 0:
        try:
            name = signal.Signals(-proc.returncode).name
        except ValueError:
            name = f"signal {-proc.returncode}"
        raise WorkerFailed(f"crashed ({name})")
    if proc.returncode > 0:
        lines = proc.stderr.strip().splitlines()
        raise WorkerFailed(f"error: {lines[-1] if lines else f'exit code {proc.returncode}'}")
    with np.load(output) as data:
        arrays = {name: data[name] for name in data.files if name != "report"}
        report = json.loads(str(data["report"]))
    output.unlink()
    return report, arrays


def measure_compile_time(work: Path, timeout: float) -> dict:
    """First lodserver build in a process with an empty numba cache (compile)
    and with a filled one (cache load), both on the warm-up tube."""
    shutil.rmtree(NUMBA_CACHE, ignore_errors=True)
    output = work / "warmup.npz"
    try:
        cold, _ = run_worker(["warmup", str(output)], output, timeout)
        cached, _ = run_worker(["warmup", str(output)], output, timeout)
    except WorkerFailed as exc:
        return {"failed": str(exc)}
    return {
        "cold_first_build_s": cold["first_build_s"],
        "cached_first_build_s": cached["first_build_s"],
        "steady_build_s": cached["steady_build_s"],
        "compile_s": cold["first_build_s"] - cached["steady_build_s"],
        "source_digest": cold["source_digest"],
    }


# ---------------------------------------------------------------------------
# Judging
# ---------------------------------------------------------------------------


def nonmanifold_edges(faces: np.ndarray) -> int:
    """Edges shared by more than two faces (edges of degenerate faces excluded)."""
    if len(faces) == 0:
        return 0
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    keys = edges[:, 0] * (int(faces.max()) + 1) + edges[:, 1]
    _, counts = np.unique(keys, return_counts=True)
    return int((counts > 2).sum())


def judge(reference, positions, faces, target: int, samples: int) -> dict:
    """Face count, target hit, non-manifold edges and the surface distance."""
    faces = np.asarray(faces, dtype=np.int64)
    result = {
        "faces": len(faces),
        "vertices": int(np.unique(faces).size),
        "hit_target": abs(len(faces) - target) <= HIT_TOLERANCE * target,
        "nonmanifold_edges": nonmanifold_edges(faces),
    }
    try:
        result.update(surface_distance(reference, (positions, faces), samples=samples,
                                       seed=SEED))
    except ValueError as exc:  # no faces, or zero area: nothing to measure
        result["note"] = f"not judged: {exc}"
    return result


# ---------------------------------------------------------------------------
# One mesh, every method
# ---------------------------------------------------------------------------


def bench_mesh(key, mesh, input_path, ratios, repeats, samples, timeout, work):
    """Rows (one per method and ratio) and lodserver's build facts for one mesh."""
    targets = [max(1, round(ratio * mesh.face_count)) for ratio in ratios]
    base = {"mesh": key, "input_faces": mesh.face_count}
    rows, build = [], None

    output = work / f"{key}-lodserver.npz"
    try:
        report, arrays = run_worker(
            ["lodserver", str(input_path), str(output), "--targets",
             ",".join(map(str, targets)), "--repeats", str(repeats)], output, timeout)
    except WorkerFailed as exc:
        rows += [{**base, "ratio": ratio, "target": target, "method": "lodserver",
                  "status": "failed", "reason": str(exc)}
                 for ratio, target in zip(ratios, targets)]
    else:
        build = {name: report[name] for name in
                 ("build_times_s", "build_cpu_times_s", "build_peaks_mib", "base_faces",
                  "splits", "passes", "source_digest")}
        build["build_s"] = statistics.median(report["build_times_s"])
        for i, (ratio, run) in enumerate(zip(ratios, report["runs"])):
            rows.append({
                **base, "ratio": ratio, "target": run["target"], "method": "lodserver",
                "status": "ok", "time_s": build["build_s"],
                "times_s": report["build_times_s"],
                "cpu_times_s": report["build_cpu_times_s"],
                "peak_mib": _largest_peak(report["build_peaks_mib"]),
                "extract_s": statistics.median(run["extract_times_s"]),
                "extract_times_s": run["extract_times_s"], "level": run["level"],
                **judge(mesh, arrays[f"positions_{i}"], arrays[f"faces_{i}"],
                        run["target"], samples),
            })

    for method in PEERS:
        for i, (ratio, target) in enumerate(zip(ratios, targets)):
            row = {**base, "ratio": ratio, "target": target, "method": method}
            output = work / f"{key}-{method}-{i}.npz"
            try:
                report, arrays = run_worker(
                    ["peer", method, str(input_path), str(output), "--targets", str(target),
                     "--repeats", str(repeats)], output, timeout)
            except WorkerFailed as exc:
                rows.append({**row, "status": "failed", "reason": str(exc)})
                continue
            run = report["runs"][0]
            rows.append({
                **row, "status": "ok", "time_s": statistics.median(run["times_s"]),
                "times_s": run["times_s"], "cpu_times_s": run["cpu_times_s"],
                "peak_mib": _largest_peak(run["peaks_mib"]),
                **judge(mesh, arrays["positions_0"], arrays["faces_0"], target, samples),
            })
    return rows, build


def _largest_peak(values):
    """Largest peak over repeats: a library may keep its buffers between calls,
    so only the first call shows what it allocates."""
    known = [v for v in values if v is not None]
    return max(known) if known else None


# ---------------------------------------------------------------------------
# lodserver against the best peer
# ---------------------------------------------------------------------------


def compare(rows) -> list[dict]:
    """Per mesh and ratio: lodserver's RMS and Hausdorff over the best peer's,
    and its build time over each peer's single call.

    The best peer has the lowest RMS among peers that hit the target; if none
    did, among all judged peers (``best_peer_hit_target`` is then False).
    Error ratios are left out where lodserver itself missed the target: a
    result of another size is not comparable.
    """
    out = []
    for lod in (r for r in rows if r["method"] == "lodserver" and r.get("rms") is not None):
        peers = [r for r in rows if r["mesh"] == lod["mesh"] and r["ratio"] == lod["ratio"]
                 and r["method"] != "lodserver" and r.get("rms") is not None]
        entry = {"mesh": lod["mesh"], "ratio": lod["ratio"], "lodserver_faces": lod["faces"],
                 "lodserver_hit_target": lod["hit_target"],
                 "build_over_peer_time": {p["method"]: lod["time_s"] / p["time_s"]
                                          for p in peers}}
        candidates = [p for p in peers if p["hit_target"]] or peers
        if candidates:
            best = min(candidates, key=lambda p: p["rms"])
            entry.update(best_peer=best["method"], best_peer_hit_target=best["hit_target"],
                         best_peer_rms=best["rms"])
            if lod["hit_target"]:
                entry.update(rms_over_best=lod["rms"] / best["rms"],
                             hausdorff_over_best=lod["hausdorff"] / best["hausdorff"])
        out.append(entry)
    return out


# ---------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------


def _g(value, digits=3):
    return "-" if value is None else f"{value:.{digits}g}"


def markdown_table(header, lines) -> str:
    """A pipe table, columns padded so it also reads as plain text."""
    widths = [max(len(str(c)) for c in column) for column in zip(header, *lines)]

    def render(cells):
        return "| " + " | ".join(str(c).ljust(w) for c, w in zip(cells, widths)) + " |"

    return "\n".join([render(header), render(["---"] * len(widths)), *map(render, lines)])


def inputs_table(meshes) -> str:
    header = ["mesh", "faces", "vertices", "nm edges", "dropped on load", "repeats",
              "lodserver build s", "coarsest faces", "lodserver digest"]
    lines = []
    for key, m in meshes.items():
        load, build = m["load_report"], m["lodserver_build"] or {}
        dropped = ", ".join(f"{load[k]} {k.replace('_', ' ')}" for k in
                            ("welded_vertices", "unreferenced_vertices", "degenerate_faces",
                             "duplicate_faces") if load[k]) or "-"
        lines.append([key, m["faces"], m["vertices"], m["nonmanifold_edges"], dropped,
                      m["repeats"], _g(build.get("build_s")), build.get("base_faces", "-"),
                      build.get("source_digest", "-")])
    return markdown_table(header, lines)


def results_table(rows) -> str:
    header = ["mesh", "ratio", "method", "target", "faces", "hit", "rms e-4",
              "hausdorff e-4", "time s", "extract s", "peak MiB", "nm edges"]
    lines = []
    for r in rows:
        head = [r["mesh"], r["ratio"], r["method"], r["target"]]
        if r["status"] != "ok":
            lines.append(head + [f"FAILED: {r['reason']}"] + [""] * 7)
            continue
        judged = r.get("rms") is not None  # not when the result is empty
        lines.append(head + [
            r["faces"], "yes" if r["hit_target"] else "NO",
            _g(r["rms"] * 1e4) if judged else "-",
            _g(r["hausdorff"] * 1e4) if judged else "-",
            _g(r["time_s"]), _g(r.get("extract_s")), _g(r["peak_mib"]),
            r["nonmanifold_edges"],
        ])
    return markdown_table(header, lines)


def comparison_table(comparison) -> str:
    header = ["mesh", "ratio", "best peer", "rms / best", "hausdorff / best",
              *(f"build / {p}" for p in PEERS)]
    lines = []
    for c in comparison:
        best = c.get("best_peer", "-")
        if best != "-" and not c["best_peer_hit_target"]:
            best += " (missed target)"
        if not c["lodserver_hit_target"]:
            best += f"; lodserver missed target ({c['lodserver_faces']} faces)"
        lines.append([c["mesh"], c["ratio"], best, _g(c.get("rms_over_best")),
                      _g(c.get("hausdorff_over_best")),
                      *(_g(c["build_over_peer_time"].get(p)) for p in PEERS)])
    return markdown_table(header, lines)


# ---------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------


def _log(*parts):
    """Progress, on stderr, so stdout holds only the final tables."""
    print(*parts, file=sys.stderr, flush=True)


def add_io_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    """``--mesh-dir`` (the shared meshes) and ``--out`` (the folder of the inputs
    made once and of the results, :func:`results_file`), for a benchmark writing
    ``<name>.json``."""
    parser.add_argument("--mesh-dir", type=Path, default=ROOT.parent / "shared" / "meshes")
    parser.add_argument("--out", type=Path, default=BENCH / "out",
                        help=f"output directory ({name}.json, or {name}-quick.json)")


def results_file(args, name: str) -> Path:
    """Where a run of ``args`` writes its results: ``<name>.json`` in ``args.out``
    (made if missing), ``<name>-quick.json`` for a --quick run."""
    args.out.mkdir(parents=True, exist_ok=True)
    return args.out / (f"{name}-quick.json" if args.quick else f"{name}.json")


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--meshes", help=f"comma-separated, from: {', '.join(ALL_MESHES)}")
    parser.add_argument("--ratios", default=",".join(map(str, RATIOS)),
                        help="comma-separated fractions of the input triangle count")
    parser.add_argument("--repeats", type=int, help="timed calls per measurement (median); 3")
    parser.add_argument("--repeats-large", type=int,
                        help=f"repeats for meshes over {LARGE_FACES:,} faces (default: --repeats)")
    parser.add_argument("--samples", type=int, help="judge samples per surface; 200000")
    parser.add_argument("--timeout", type=float, default=300.0,
                        help="seconds per child process before it counts as failed")
    parser.add_argument("--quick", action="store_true",
                        help=f"smoke run: {', '.join(QUICK_MESHES)}; 1 repeat; 20000 samples")
    add_io_arguments(parser, "simplify")
    args = parser.parse_args(argv)
    # --quick only changes what was not given explicitly
    if args.meshes is None:
        args.meshes = ",".join(QUICK_MESHES if args.quick else ALL_MESHES)
    args.repeats = args.repeats or (1 if args.quick else 3)
    args.repeats_large = args.repeats_large or args.repeats
    args.samples = args.samples or (20_000 if args.quick else 200_000)
    args.ratios = [float(r) for r in args.ratios.split(",")]
    by_name = {name.lower(): name for name in ALL_MESHES}
    try:
        args.meshes = [by_name[m.strip().lower()] for m in args.meshes.split(",")]
    except KeyError as exc:
        parser.error(f"unknown mesh {exc}; choose from {', '.join(ALL_MESHES)}")
    return args


def main(argv=None):
    args = parse_args(argv)
    result_path = results_file(args, "simplify")
    work = Path(tempfile.mkdtemp(prefix="work-", dir=args.out))

    _log("measuring lodserver compile time (empty numba cache) ...")
    results = {
        "machine": {**machine_info(PACKAGES), "cpu_busy_before": cpu_busy()},
        "settings": {"ratios": args.ratios, "repeats": args.repeats,
                     "repeats_large": args.repeats_large, "large_faces": LARGE_FACES,
                     "samples": args.samples, "seed": SEED, "timeout_s": args.timeout,
                     "hit_tolerance": HIT_TOLERANCE, "peers": PEER_SETTINGS},
        "lodserver_compile": measure_compile_time(work, args.timeout),
        "meshes": {}, "results": [], "comparison": [],
    }
    _log(f"  {results['lodserver_compile']}")
    for key in args.meshes:
        mesh, load_report, input_path = prepare_input(key, args.mesh_dir, args.out)
        repeats = args.repeats_large if mesh.face_count > LARGE_FACES else args.repeats
        _log(f"{key}: {mesh.face_count:,} faces, {repeats} repeats ...")
        rows, build = bench_mesh(key, mesh, input_path, args.ratios, repeats,
                                 args.samples, args.timeout, work)
        results["meshes"][key] = {"faces": mesh.face_count, "vertices": mesh.vertex_count,
                                  "nonmanifold_edges": nonmanifold_edges(mesh.faces),
                                  "repeats": repeats, "load_report": load_report,
                                  "lodserver_build": build}
        results["results"] += rows
        results["comparison"] = compare(results["results"])
        # rewritten after every mesh, so an interrupted run keeps what it measured
        result_path.write_text(json.dumps(results, indent=1))
        _log(results_table(rows))
    shutil.rmtree(work, ignore_errors=True)
    results["machine"]["cpu_busy_after"] = cpu_busy()
    result_path.write_text(json.dumps(results, indent=1))

    compile_facts = results["lodserver_compile"]
    print(f"lodserver compile: {_g(compile_facts.get('compile_s'))} s with an empty numba "
          f"cache; first build from the cache {_g(compile_facts.get('cached_first_build_s'))} s"
          f" (steady {_g(compile_facts.get('steady_build_s'))} s on the 1,240-face warm-up tube)\n")
    print(inputs_table(results["meshes"]), "\n")
    print(results_table(results["results"]), "\n")
    print(comparison_table(results["comparison"]))
    _log(f"\nwrote {result_path}")


if __name__ == "__main__":
    main()
