"""Asset throughput of ``lodserver export`` on this machine: local pool against Dask.

Makes a library of a few hundred assets: every file of ``../shared/meshes``
(with its textures and buffers) plus copies of its small self-contained meshes,
then exports it from scratch (``force``) with

- the local pool (threads in this process) with 1 and 2 jobs;
- a Dask cluster started here as a deployment would run one: ``dask scheduler``
  and 1 or 2 ``dask worker`` processes (one thread each) on loopback, their
  kernels loaded by a warm-up build before the clock starts.

and reports assets per second and seconds per asset. The scheduler's overhead
per asset is measured apart, on assets that cost next to nothing to build (a
4-face tetrahedron, copied): local pool and Dask with one worker each, the
difference per asset; and Dask's bare round trip (a no-op task, submitted and
gathered through ``as_completed`` as the pipeline does).

    python bench/throughput.py                   # ~10 min on 2 busy cores
    python bench/throughput.py --copies 40 --tiny 100 --rounds 1

Writes ``bench/out/throughput.json`` (every time, the load average around
each run, the machine). Compare figures within one run only: the machine is
shared and its load moves everything.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
sys.path[:0] = [str(ROOT), str(BENCH)]

from machine import machine_info  # noqa: E402

from lodserver.pipeline import export_folder, find_sources  # noqa: E402
from tests.services.dask import start_cluster, stop_cluster  # noqa: E402

MESH_DIR = ROOT.parent / "shared" / "meshes"
# self-contained (no sibling files) and small: what the copies are made of
COPIED = ("Duck.glb", "conrod.stl", "fertility.off", "non_manif_hole.ply",
          "office_chair.obj", "decimated-max.obj", "scenes/Fox.glb", "soup.stl")
TETRAHEDRON = b"""ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 4
property list uchar int vertex_indices
end_header
0 0 0
1 0 0
0 1 0
0 0 1
3 0 2 1
3 0 1 3
3 0 3 2
3 1 2 3
"""


def make_library(folder: Path, copies: int, mesh_dir: Path = MESH_DIR) -> int:
    """The shared meshes plus ``copies`` copies of the small ones; the asset count."""
    shutil.copytree(mesh_dir, folder / "shared")
    for index in range(copies):
        name = COPIED[index % len(COPIED)]
        target = folder / "copies" / f"{index // len(COPIED):03d}" / Path(name).name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(mesh_dir / name, target)
    return len(find_sources(folder))


def make_tiny(folder: Path, count: int) -> None:
    for index in range(count):
        path = folder / f"{index // 100:02d}" / f"t{index:04d}.ply"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(TETRAHEDRON)


def timed_export(source: Path, output: Path, **kwargs) -> dict:
    before = os.getloadavg()[0]
    start = time.perf_counter()
    report = export_folder(source, output, force=True, **kwargs)
    seconds = time.perf_counter() - start
    shutil.rmtree(output)
    return {"seconds": seconds, "written": len(report.written), "failed": len(report.failed),
            "assets_per_second": report.total / seconds,
            "seconds_per_asset": seconds / report.total,
            "load_before": before, "load_after": os.getloadavg()[0]}


def make_warm(folder: Path, mesh_dir: Path = MESH_DIR) -> None:
    """One asset of each kind the library holds (textured OBJ and glTF, GLB, STL,
    OFF, PLY): exporting it loads every kernel the timed runs use."""
    shutil.copytree(mesh_dir / "spot", folder / "spot")
    for name in ("Duck.glb", "conrod.stl", "fertility.off", "non_manif_hole.ply",
                 "office_chair.obj"):
        shutil.copyfile(mesh_dir / name, folder / name)


def _warm(folder: str) -> int:
    """Export ``folder`` in this process, into a folder thrown away (runs in every
    worker, by client.run: loads the compiled kernels and the imports there)."""
    import tempfile

    from lodserver.pipeline import export_folder

    with tempfile.TemporaryDirectory() as out:
        return len(export_folder(folder, out, force=True).written)


def noop(value):
    return value


def dask_round_trip(client, count: int) -> float:
    """Seconds per no-op task, submitted one by one and taken back as they finish."""
    import distributed

    start = time.perf_counter()
    futures = [client.submit(noop, index, pure=False) for index in range(count)]
    for future in distributed.as_completed(futures):
        future.result()
    return (time.perf_counter() - start) / count


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--copies", type=int, default=120,
                        help="copies of the small meshes (default 120)")
    parser.add_argument("--tiny", type=int, default=200,
                        help="tetrahedra for the overhead runs (default 200)")
    parser.add_argument("--rounds", type=int, default=2,
                        help="rounds of every configuration, interleaved (default 2)")
    parser.add_argument("--mesh-dir", type=Path, default=MESH_DIR,
                        help="the shared meshes (default ../shared/meshes)")
    parser.add_argument("--out", type=Path, default=BENCH / "out" / "throughput.json")
    args = parser.parse_args(argv)
    if not args.mesh_dir.is_dir():
        raise SystemExit(f"the shared meshes are not at {args.mesh_dir}")
    import distributed

    results = {"machine": machine_info(["dask", "distributed", "numba", "numpy"]),
               "runs": {}}
    runs = results["runs"]

    def record(name, value):
        runs.setdefault(name, []).append(value)
        print(f"{name}: {json.dumps(value)}", file=sys.stderr)

    clusters = []
    with tempfile.TemporaryDirectory(prefix="lodserver-throughput-") as scratch:
        scratch = Path(scratch)
        assets = make_library(scratch / "library", args.copies, args.mesh_dir)
        make_tiny(scratch / "tiny", args.tiny)
        make_warm(scratch / "warm", args.mesh_dir)
        results["assets"], results["tiny_assets"] = assets, args.tiny
        print(f"{assets} assets ({args.copies} copies), {args.tiny} tiny", file=sys.stderr)
        # compile (or load) every kernel and read every file once before a clock runs
        start = time.perf_counter()
        export_folder(scratch / "library", scratch / "first", jobs=2)
        shutil.rmtree(scratch / "first")
        results["first_run_seconds"] = time.perf_counter() - start
        try:
            # both clusters up for the whole run, so their runs interleave with the
            # local ones and all see the same machine load (idle workers cost ~nothing)
            clients = {}
            for workers in (1, 2):
                folder = scratch / f"dask{workers}"
                folder.mkdir()
                start = time.perf_counter()
                processes, address = start_cluster(folder, workers)
                clusters.append(processes)
                clients[workers] = distributed.Client(address)
                clients[workers].run(_warm, str(scratch / "warm"))
                # and one batch through the scheduler, untimed (its first tasks are slow)
                export_folder(scratch / "tiny", scratch / "out", scheduler=clients[workers])
                shutil.rmtree(scratch / "out")
                record(f"dask cluster start + warm-up, {workers} workers",
                       {"seconds": time.perf_counter() - start})
            library, tiny, out = scratch / "library", scratch / "tiny", scratch / "out"
            for _ in range(args.rounds):
                record("local pool, tiny", timed_export(tiny, out))
                record("dask, 1 worker, tiny", timed_export(tiny, out, scheduler=clients[1]))
                record("dask no-op task", {"seconds_per_task":
                                           dask_round_trip(clients[1], args.tiny)})
                for workers in (1, 2):
                    plural = "s" * (workers > 1)
                    record(f"local pool, {workers} job{plural}",
                           timed_export(library, out, jobs=workers))
                    record(f"dask, {workers} worker{plural}",
                           timed_export(library, out, scheduler=clients[workers]))
            for client in clients.values():
                client.close()
        finally:
            for processes in clusters:
                stop_cluster(processes)

    def mean(name, key="seconds_per_asset"):
        return sum(run[key] for run in runs[name]) / len(runs[name])

    results["overhead_per_asset_seconds"] = (mean("dask, 1 worker, tiny")
                                             - mean("local pool, tiny"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"\n{assets} assets, {args.rounds} rounds interleaved; load average at start "
          f"{results['machine']['load_average_at_start']}; first run (jobs 2, compiling "
          f"or loading kernels) {results['first_run_seconds']:.1f} s")
    print("| run | seconds (each round) | assets/s (mean) | s/asset (mean) | load 1-min |")
    print("|---|---|---|---|---|")
    for name, each in runs.items():
        if "seconds_per_asset" in each[0]:
            seconds = ", ".join(f"{run['seconds']:.1f}" for run in each)
            loads = ", ".join(f"{run['load_before']:.0f}" for run in each)
            print(f"| {name} | {seconds} | {mean(name, 'assets_per_second'):.2f} | "
                  f"{mean(name):.4f} | {loads} |")
    print(f"\nscheduler overhead per asset (dask - local, tiny): "
          f"{1000 * results['overhead_per_asset_seconds']:.1f} ms; bare no-op task: "
          f"{1000 * mean('dask no-op task', 'seconds_per_task'):.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
