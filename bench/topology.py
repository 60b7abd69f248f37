"""Topology simplification side by side: close pairs and vertex clustering.

For the multi-part meshes (``2CylinderEngine.glb``, ``office_chair.obj``) at
2% and 0.5% of the triangles: faces reached, connected components, RMS and
Hausdorff (the same judge as ``simplify.py``) for

- lodserver edge collapse, edges only and with close pairs (``--pair-threshold``);
- lodserver vertex clustering (``cluster``);
- meshoptimizer ``simplify`` and ``simplify_sloppy``;
- pymeshlab's clustering decimation, its cell size searched to the target.

On the Loop-subdivided bunny (1.1M triangles, made by ``simplify.py``):
clustering wall time against ``simplify_sloppy`` (median of repeats, numpy in
to numpy out), and clustering error against lodserver QEM at the same count.

Every method runs in a child process, so a crash (pymeshlab) is a recorded
failure, not the end of the run.

    python bench/topology.py [--samples 100000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path
from queue import Empty

import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))
from methods import meshoptimizer_simplify, meshoptimizer_sloppy  # noqa: E402

MESHES = ("2CylinderEngine.glb", "office_chair.obj")
RATIOS = (0.02, 0.005)
PAIR_THRESHOLD = "2%"


def components(faces, n) -> int:
    """Connected components among the vertices faces use."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    if len(faces) == 0:
        return 0
    rows = np.concatenate([faces[:, 0], faces[:, 1]])
    cols = np.concatenate([faces[:, 1], faces[:, 2]])
    labels = connected_components(coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)),
                                  directed=False)[1]
    return int(len(np.unique(labels[np.unique(faces)])))


def pymeshlab_clustering(positions, faces, target):
    """MeshLab's vertex clustering; the cell size (a percentage of the
    diagonal) is searched so the result has at most ``target`` faces."""
    import pymeshlab
    lo, hi, best = 0.01, 50.0, None
    for _ in range(14):
        cell = (lo * hi) ** 0.5
        ms = pymeshlab.MeshSet()
        ms.add_mesh(pymeshlab.Mesh(positions, faces.astype(np.int32)))
        ms.meshing_decimation_clustering(threshold=pymeshlab.PercentageValue(cell))
        m = ms.current_mesh()
        count = m.face_number()
        if count <= target:
            best = (m.vertex_matrix().copy(), m.face_matrix().astype(np.int64).copy())
            hi = cell
            if count >= 0.95 * target:
                break
        else:
            lo = cell
    if best is None:
        raise RuntimeError("no cell size reached the target")
    return best


def lodserver_cluster(positions, faces, target):
    from lodserver.simplify.cluster import cluster
    from lodserver.mesh import Mesh
    lod = cluster(Mesh(positions, faces), target_faces=target)
    return lod.positions, lod.faces


def _child(method, positions, faces, target, repeats, queue):
    try:
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            result = method(positions, faces, target)
            times.append(time.perf_counter() - start)
        queue.put(("ok", result, float(np.median(times))))
    except Exception as exc:  # a peer's failure is data for the table
        queue.put(("error", f"{type(exc).__name__}: {exc}", None))


def run_isolated(method, positions, faces, target, repeats=1, timeout=600):
    """(positions, faces, seconds) from ``method`` in a child process, or a failure string."""
    context = mp.get_context("spawn")  # fork is unsafe once numba has started OpenMP threads
    queue = context.Queue()
    child = context.Process(target=_child,
                                           args=(method, positions, faces, target, repeats, queue))
    child.start()
    # Read before joining: a child blocks on putting a large result until the
    # parent takes it, so joining first would deadlock.
    try:
        status, payload, seconds = queue.get(timeout=timeout)
    except Empty:
        child.kill()
        child.join()
        return (f"crashed (exit code {child.exitcode})" if child.exitcode not in (0, None, -9)
                else f"timed out after {timeout} s")
    child.join()
    return payload if status == "error" else (*payload, seconds)


def judge(reference, positions, faces, samples):
    from lodserver.mesh import Mesh
    from lodserver.metrics import surface_distance
    used = np.unique(faces)
    remap = np.full(len(positions), -1)
    remap[used] = np.arange(len(used))
    candidate = Mesh(np.asarray(positions, float)[used], remap[faces])
    d = surface_distance(reference, candidate, samples=samples)
    return {"faces": int(len(faces)), "components": components(candidate.faces, len(used)),
            "rms": d["rms"], "hausdorff": d["hausdorff"]}


def multipart_rows(mesh_dir: Path, samples: int):
    from lodserver import build
    from lodserver.io import load_mesh
    from lodserver.mesh import Mesh
    rows = []
    for name in MESHES:
        mesh, _ = load_mesh(mesh_dir / name)
        mesh = Mesh(mesh.positions, mesh.faces)     # geometry only, as the peers get it
        plain = build(mesh)
        paired = build(mesh, pair_threshold=PAIR_THRESHOLD)
        octree = build(mesh, method="cluster")
        rows.append({"mesh": name, "ratio": 1.0, "method": "input", "target": mesh.face_count,
                     "faces": mesh.face_count,
                     "components": components(mesh.faces, mesh.vertex_count),
                     "rms": 0.0, "hausdorff": 0.0})
        for ratio in RATIOS:
            target = max(1, round(ratio * mesh.face_count))
            results = {
                "lodserver-qem": (lambda t=target: plain.at(faces=t))(),
                f"lodserver-qem-pairs-{PAIR_THRESHOLD}": (lambda t=target: paired.at(faces=t))(),
                "lodserver-octree": (lambda t=target: octree.at(faces=t))(),
            }
            for key, value in list(results.items()):
                results[key] = (value.positions, value.faces)
            for key, method in (("lodserver-cluster", lodserver_cluster),
                                ("meshoptimizer", meshoptimizer_simplify),
                                ("meshoptimizer-sloppy", meshoptimizer_sloppy),
                                ("pymeshlab-clustering", pymeshlab_clustering)):
                outcome = run_isolated(method, mesh.positions, mesh.faces, target)
                results[key] = outcome if isinstance(outcome, str) else outcome[:2]
            for key, outcome in results.items():
                row = {"mesh": name, "ratio": ratio, "method": key, "target": target}
                if isinstance(outcome, str):
                    row["failure"] = outcome
                elif len(outcome[1]) == 0:
                    row.update(faces=0, failure="no faces left")
                else:
                    row.update(judge(mesh, outcome[0], outcome[1], samples))
                rows.append(row)
                print(_line(row), flush=True)
    return rows


def large_rows(npz: Path, samples: int, repeats: int):
    """Clustering against simplify_sloppy on the 1.1M-triangle mesh, and against QEM."""
    from lodserver import build
    from lodserver.io import clean_mesh
    data = np.load(npz)
    mesh, _ = clean_mesh(data["v"] if "v" in data else data["positions"],
                         data["f"] if "f" in data else data["faces"])
    pm = build(mesh)
    rows = []
    for ratio in (0.1, 0.02):
        target = round(ratio * mesh.face_count)
        row = {"mesh": npz.stem, "ratio": ratio, "target": target}
        ours = run_isolated(lodserver_cluster, mesh.positions, mesh.faces, target, repeats)
        sloppy = run_isolated(meshoptimizer_sloppy, mesh.positions, mesh.faces, target, repeats)
        qem = pm.at(faces=target)
        row["qem"] = judge(mesh, qem.positions, qem.faces, samples)
        for key, outcome in (("cluster", ours), ("sloppy", sloppy)):
            if isinstance(outcome, str):
                row[key] = {"failure": outcome}
            else:
                row[key] = {**judge(mesh, outcome[0], outcome[1], samples), "seconds": outcome[2]}
        if "seconds" in row["cluster"] and "seconds" in row["sloppy"]:
            row["cluster_time_over_sloppy"] = row["cluster"]["seconds"] / row["sloppy"]["seconds"]
            row["cluster_rms_over_qem"] = row["cluster"]["rms"] / row["qem"]["rms"]
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def _line(row) -> str:
    if "failure" in row:
        return f"{row['mesh']:20s} {row['ratio']:<6} {row['method']:28s} FAILED: {row['failure']}"
    return (f"{row['mesh']:20s} {row['ratio']:<6} {row['method']:28s} faces {row['faces']:6d} "
            f"(target {row['target']:6d})  components {row['components']:4d}  "
            f"rms {row['rms']:.3g}  hausdorff {row['hausdorff']:.3g}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh-dir", type=Path, default=BENCH.parents[1] / "shared" / "meshes")
    parser.add_argument("--large", type=Path, default=BENCH / "out" / "bunny_loop2.npz")
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=BENCH / "out" / "topology.json")
    args = parser.parse_args(argv)
    result = {"date": time.strftime("%Y-%m-%d %H:%M"), "pair_threshold": PAIR_THRESHOLD,
              "multipart": multipart_rows(args.mesh_dir, args.samples)}
    if args.large.exists():
        result["large"] = large_rows(args.large, args.samples, args.repeats)
    else:
        print(f"{args.large} not found: run bench/simplify.py first for the 1.1M-triangle mesh")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
