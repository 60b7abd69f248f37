"""Where a build's time goes: each phase of ``lodserver.build`` timed, beside
meshoptimizer's one-shot ``simplify`` to 10% of the same mesh, in one process.

    python bench/profile_build.py                         # the 1.1M bunny (bench/out/bunny_loop2.npz)
    python bench/profile_build.py --mesh ../shared/meshes/fertility.off --repeats 3
    NUMBA_NUM_THREADS=1 python bench/profile_build.py     # single thread

Phases are timed by wrapping the functions ``build`` calls (the wrappers only
read the clock), so the build measured is the one users get. A warm-up build
of a small tube comes first (compile time is not counted). Builds and
meshoptimizer calls alternate, and the medians are reported with their ratio:
timings from a loaded machine are only comparable side by side, and each
build is also paired with the meshoptimizer call right after it
(``paired_ratio_median``).

Prints one JSON document (also written to ``--out`` if given).
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import sys
import time
from collections import defaultdict
from pathlib import Path

import numba
import numpy as np

BENCH = Path(__file__).resolve().parent
sys.path.insert(0, str(BENCH))

from methods import meshoptimizer_simplify  # noqa: E402
from worker import warmup_mesh  # noqa: E402

import importlib  # noqa: E402
import lodserver.simplify.collapse as collapse  # noqa: E402
from lodserver import Mesh  # noqa: E402
from lodserver.progressive import encode_progressive  # noqa: E402

# the module, not the function ``lodserver.build`` that shadows it
build_module = importlib.import_module("lodserver.build")

# (module, function name, phase name): what each phase of a build is
PHASES = (
    (collapse, "memory_order", "memory order"),
    (collapse, "census", "topology"),
    (collapse, "classify_vertices", "classify"),
    (collapse, "vertex_quadrics", "quadrics"),
    (collapse, "wedge_inputs", "wedges"),
    (collapse, "_new_topology", "kernel topology"),
    (collapse, "partition", "partition"),
    (collapse, "_run_kernels", "kernels (all)"),
    (collapse, "merge_phases", "merge logs"),
    (collapse, "extract", "copy parts (all threads)"),
    (collapse, "write_back", "write back (all threads)"),
    (build_module, "decimate", "decimate (all)"),
    (build_module, "from_collapse_log", "renumber"),
)


def _timed(function, name, totals):
    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            totals[name] += time.perf_counter() - start
    return wrapper


def install_timers():
    """Wrap every phase's function; returns the dict the wrappers add seconds to."""
    totals = defaultdict(float)
    for module, attr, name in PHASES:
        if hasattr(module, attr):       # an older tree may lack a phase
            setattr(module, attr, _timed(getattr(module, attr), name, totals))
    return totals


def load(path: Path) -> Mesh:
    """The mesh at ``path``: an ``.npz`` of positions and faces, or any file ``load_mesh`` reads."""
    if path.suffix == ".npz":
        with np.load(path) as data:
            return Mesh(data["positions"], data["faces"])
    from lodserver.io import load_mesh
    return load_mesh(path)[0]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", type=Path, default=BENCH / "out" / "bunny_loop2.npz")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--ratio", type=float, default=0.1, help="meshoptimizer's target")
    parser.add_argument("--no-peer", action="store_true", help="skip meshoptimizer")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)

    totals = install_timers()
    build_module.build(Mesh(*warmup_mesh()))        # compile / load kernels
    collapse.decimate(Mesh(*warmup_mesh()), collapse.DecimateOptions(parts=2))  # and the partitioned path's
    start = time.perf_counter()
    mesh = load(args.mesh)
    load_s = time.perf_counter() - start
    target = round(args.ratio * mesh.face_count)
    meshoptimizer_simplify(mesh.positions, mesh.faces, target)     # warm the library

    runs, peer = [], []
    for _ in range(args.repeats):
        totals.clear()
        cpu = time.process_time()
        start = time.perf_counter()
        pm = build_module.build(mesh)
        total = time.perf_counter() - start
        cpu = time.process_time() - cpu
        start = time.perf_counter()
        artefact = encode_progressive(pm)
        encode_s = time.perf_counter() - start
        runs.append({**totals, "build": total, "build_cpu": cpu, "encode": encode_s})
        if not args.no_peer:
            start = time.perf_counter()
            meshoptimizer_simplify(mesh.positions, mesh.faces, target)
            peer.append(time.perf_counter() - start)

    median = {key: statistics.median(run[key] for run in runs) for key in runs[0]}
    decimation = pm.metadata["decimation"]
    report = {
        "mesh": str(args.mesh), "faces": mesh.face_count, "vertices": mesh.vertex_count,
        "numba_threads": numba.get_num_threads(),
        "load_s": load_s, "repeats": args.repeats,
        "median_s": median, "runs_s": runs,
        "collapses": pm.split_count, "passes": decimation["passes"],
        "rejected": decimation["rejected"], "artefact_bytes": len(artefact),
    }
    if peer:
        report["meshoptimizer_s"] = statistics.median(peer)
        report["meshoptimizer_runs_s"] = peer
        report["build_over_meshoptimizer"] = median["build"] / report["meshoptimizer_s"]
        # each build over the meshoptimizer call right after it: on a machine
        # whose speed drifts, the pairs see the same drift
        paired = [run["build"] / t for run, t in zip(runs, peer)]
        report["paired_ratios"] = paired
        report["paired_ratio_median"] = statistics.median(paired)
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
