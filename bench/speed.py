"""Build speed and memory: lodserver's whole progressive mesh against one
simplification by each peer, at 1.1M, 4.4M and 9.4M triangles.

For every size, in one run and each in its own child process
(``worker.py``): lodserver ``build`` with ``NUMBA_NUM_THREADS=1`` and with
every core, then meshoptimizer ``simplify`` and ``simplify_sloppy``,
pymeshlab and fast-simplification (settings of ``methods.py``) asked for 10%
of the triangles. Each gets its wall and CPU time, its peak memory (the RSS
growth during the call, and the child's whole peak RSS) and the ratio of both
to meshoptimizer ``simplify``'s. lodserver's child also times ``arrays_at``
and ``at`` of 100 random levels (worst and median).

    python bench/speed.py                  # every size (about 25 min on 2 busy cores)
    python bench/speed.py --quick          # 1.1M only, 1 repeat (about 3 min)
    python bench/speed.py --sizes 1m,4m --methods lodserver,meshoptimizer --repeats 3
    python bench/speed.py --sizes 1m --no-methods --command --first-run --repeats 3

``--command`` adds the whole ``lodserver build FILE.ply -o OUT.pm`` (a child
process from start to exit: imports, the PLY load, the build and the save),
each run paired with meshoptimizer ``simplify`` run right after it, and the
ratio of each pair; ``--first-run`` the sample's build on an empty numba cache
(its kernels run as Python while a background process compiles them,
``lodserver.first_run``), when that process had filled the cache, and the
build again on the filled cache: wall and CPU seconds, the load average.

Inputs are Loop-subdivided scans from ``../shared/meshes``, made on first use
and cached in ``bench/out/`` (``bunny_loop2.npz`` is the same file
``simplify.py`` makes). See the "Speed benchmark" section of bench/README.md.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

# simplify.py sets NUMBA_CACHE_DIR to the benchmarks' own cache on import
from simplify import (
    NUMBA_CACHE,
    WorkerFailed,
    _g,
    _largest_peak,
    _log,
    add_io_arguments,
    markdown_table,
    results_file,
    run_worker,
)


# size key -> (cache name, shared mesh, Loop iterations): triangles x 4 per iteration
SIZES = {
    "1m": ("bunny_loop2", "stanford-bunny.obj", 2),   # 1,111,216 triangles
    "4m": ("bunny_loop3", "stanford-bunny.obj", 3),   # 4,444,864
    "10m": ("brain_loop4", "brain.ply", 4),           # 9,408,512 (the bunny's next is 17.8M)
}
# the slowest last, so a run cut short by a timeout has the rest
METHODS = ("lodserver", "meshoptimizer", "meshoptimizer-sloppy", "fast-simplification",
           "lodserver-1t", "pymeshlab")
REFERENCE = "meshoptimizer"   # ratios are to its time and memory
RATIO = 0.1                   # peers are asked for 10% of the triangles
LEVELS = 100                  # random levels extracted by lodserver's child
PACKAGES = ("lodserver", "numpy", "numba", "meshoptimizer", "pymeshlab", "fast-simplification",
            "trimesh")


def prepare_input(size: str, mesh_dir: Path, out: Path) -> tuple[Path, int]:
    """The cached .npz (welded ``positions``, ``faces``) of ``size`` and its face count,
    made by Loop subdivision of a shared scan the first time."""
    name, source, iterations = SIZES[size]
    path = out / f"{name}.npz"
    if not path.exists():
        import trimesh

        from lodserver.io import clean_mesh, load_mesh

        _log(f"making {name} ({iterations} Loop subdivisions of {source}) ...")
        mesh, _ = load_mesh(mesh_dir / source)
        positions, faces = trimesh.remesh.subdivide_loop(mesh.positions, mesh.faces,
                                                         iterations=iterations)
        mesh, _ = clean_mesh(positions, faces)
        partial = path.with_suffix(".partial.npz")
        np.savez(partial, positions=mesh.positions, faces=mesh.faces)
        os.replace(partial, path)   # an interrupted run leaves no truncated cache
    with np.load(path) as data:
        return path, len(data["faces"])


@contextlib.contextmanager
def environment(**values):
    """``os.environ`` with ``values`` set for the children started inside."""
    saved = {key: os.environ.get(key) for key in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def fresh_numba_cache() -> None:
    """Empty the benchmarks' numba cache if it was filled by other lodserver sources.

    numba only notices a change to a kernel's own file, not to one it calls in
    another module, so a cache from older sources could run stale code.
    """
    from worker import lodserver_digest

    stamp = NUMBA_CACHE / "lodserver-digest"
    digest = lodserver_digest()
    if not stamp.exists() or stamp.read_text() != digest:
        shutil.rmtree(NUMBA_CACHE, ignore_errors=True)
        NUMBA_CACHE.mkdir(parents=True)
        stamp.write_text(digest)


def run_method(method, input_path, faces, repeats, levels, timeout, work) -> dict:
    """One method on one input in a child process: its timings and peaks, or why it failed."""
    target = max(1, round(RATIO * faces))
    output = work / f"{method}.npz"
    if method.startswith("lodserver"):
        args = ["lodserver", str(input_path), str(output), "--targets", str(target),
                "--repeats", str(repeats), "--levels", str(levels)]
    else:
        args = ["peer", method, str(input_path), str(output), "--targets", str(target),
                "--repeats", str(repeats)]
    # one numba thread for the single-thread run; the others get numba's default (every core)
    threads = {"NUMBA_NUM_THREADS": "1"} if method == "lodserver-1t" else {}
    try:
        with environment(**threads):
            report, arrays = run_worker(args, output, timeout)
    except WorkerFailed as exc:
        # numba's errors are coloured: keep the text only
        return {"method": method, "status": "failed",
                "reason": re.sub(r"\x1b\[[0-9;]*m", "", str(exc))}
    row = {"method": method, "status": "ok", "target": target,
           "process_max_rss_mib": report["process_max_rss_mib"]}
    if method.startswith("lodserver"):
        row.update(times_s=report["build_times_s"], cpu_times_s=report["build_cpu_times_s"],
                   peak_mib=_largest_peak(report["build_peaks_mib"]),
                   faces=int(len(arrays["faces_0"])), splits=report["splits"],
                   source_digest=report["source_digest"])
        drawn = report["random_levels"]
        for key in ("arrays_at_s", "arrays_at_cpu_s", "at_s", "at_cpu_s"):
            if drawn[key]:
                row[f"{key[:-2]}_worst_s"] = max(drawn[key])
                row[f"{key[:-2]}_median_s"] = statistics.median(drawn[key])
        row["random_levels"] = drawn
    else:
        run = report["runs"][0]
        row.update(times_s=run["times_s"], cpu_times_s=run["cpu_times_s"],
                   peak_mib=_largest_peak(run["peaks_mib"]), faces=int(len(arrays["faces_0"])))
    row["time_s"] = statistics.median(row["times_s"])
    row["cpu_s"] = statistics.median(row["cpu_times_s"])
    return row


def with_ratios(rows) -> None:
    """Add each row's time and peak over the reference's (same size), in place."""
    reference = next((r for r in rows if r["method"] == REFERENCE and r["status"] == "ok"), None)
    for row in rows:
        if reference is None or row["status"] != "ok":
            continue
        row["time_over_reference"] = row["time_s"] / reference["time_s"]
        row["cpu_over_reference"] = row["cpu_s"] / reference["cpu_s"]
        if row["peak_mib"] and reference["peak_mib"]:
            row["peak_over_reference"] = row["peak_mib"] / reference["peak_mib"]


def speed_table(results) -> str:
    header = ["size", "faces", "method", "time s", "cpu s", f"time / {REFERENCE}",
              f"cpu / {REFERENCE}", "peak MiB", "B / face", f"peak / {REFERENCE}", "process MiB",
              "result faces"]
    lines = []
    for size, entry in results["sizes"].items():
        for r in entry["rows"]:
            head = [size, entry["faces"], r["method"]]
            if r["status"] != "ok":
                lines.append(head + [f"FAILED: {r['reason']}"] + [""] * 8)
                continue
            per_face = None if r["peak_mib"] is None else r["peak_mib"] * 2**20 / entry["faces"]
            lines.append(head + [_g(r["time_s"]), _g(r["cpu_s"]),
                                 _g(r.get("time_over_reference")),
                                 _g(r.get("cpu_over_reference")), _g(r["peak_mib"], 4),
                                 _g(per_face), _g(r.get("peak_over_reference")),
                                 _g(r["process_max_rss_mib"], 4), r["faces"]])
    return markdown_table(header, lines)


def scaling_table(results) -> str:
    """Time and peak memory per input face, and each relative to the smallest size."""
    sizes = results["sizes"]
    header = ["method", *(f"{size}: us / face" for size in sizes),
              *(f"{size}: cpu us / face" for size in sizes),
              *(f"{size}: B / face" for size in sizes), "time/face growth",
              "cpu/face growth", "memory/face growth"]
    lines = []
    for method in results["settings"]["methods"]:
        per_time, per_cpu, per_peak = [], [], []
        for entry in sizes.values():
            row = next((r for r in entry["rows"] if r["method"] == method), None)
            ok = row is not None and row["status"] == "ok"
            per_time.append(row["time_s"] * 1e6 / entry["faces"] if ok else None)
            per_cpu.append(row["cpu_s"] * 1e6 / entry["faces"] if ok else None)
            per_peak.append(row["peak_mib"] * 2**20 / entry["faces"]
                            if ok and row["peak_mib"] else None)

        def growth(values):
            """Last known size's value over the first's (1 = linear cost)."""
            known = [v for v in values if v is not None]
            return _g(known[-1] / known[0]) if len(known) > 1 else "-"

        lines.append([method, *map(_g, per_time), *map(_g, per_cpu), *map(_g, per_peak),
                      growth(per_time), growth(per_cpu), growth(per_peak)])
    return markdown_table(header, lines)


def levels_table(results) -> str:
    keys = ("arrays_at_worst_s", "arrays_at_median_s", "arrays_at_cpu_worst_s",
            "arrays_at_cpu_median_s", "at_worst_s", "at_median_s", "at_cpu_worst_s",
            "at_cpu_median_s")
    header = ["size", "faces", "method", "arrays_at worst ms", "median ms", "cpu worst ms",
              "cpu median ms", "at worst ms", "median ms", "cpu worst ms", "cpu median ms",
              "levels"]
    lines = []
    for size, entry in results["sizes"].items():
        for r in entry["rows"]:
            if r["method"].startswith("lodserver") and r["status"] == "ok" \
                    and "arrays_at_worst_s" in r:
                lines.append([size, entry["faces"], r["method"],
                              *(_g(r[k] * 1e3) for k in keys),
                              len(r["random_levels"]["levels"])])
    return markdown_table(header, lines)


# --- the whole command and the first run (issue 29) ----------------------------------

SAMPLE = Path(__file__).resolve().parents[1] / "tests" / "data" / "spot.obj"


def write_ply(npz: Path) -> Path:
    """``npz``'s welded mesh as a binary little-endian PLY beside it (float64
    coordinates, int32 indices), the file the whole command reads; made once."""
    path = npz.with_suffix(".ply")
    if path.exists():
        return path
    with np.load(npz) as data:
        positions, faces = data["positions"], data["faces"]
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(positions)}\n"
              "property double x\nproperty double y\nproperty double z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
              "end_header\n").encode()
    rows = np.empty(len(faces), dtype=[("count", "u1"), ("corners", "<i4", (3,))])
    rows["count"], rows["corners"] = 3, faces
    partial = path.with_suffix(".partial.ply")
    with open(partial, "wb") as out:
        out.write(header)
        out.write(np.ascontiguousarray(positions, dtype="<f8").tobytes())
        out.write(rows.tobytes())
    os.replace(partial, path)
    return path


# --source-cache: the command's children use numba's cache beside each tree's
# sources (filled by that tree's own runs) instead of the benchmarks' own
SOURCE_CACHE = False


def timed_command(command: list[str], timeout: float, env: dict | None = None,
                  tree: Path | None = None) -> float:
    """Wall seconds of ``command`` in a child process, from its start to its exit
    (interpreter start, imports, load and save included); WorkerFailed if it fails.
    ``tree``: the lodserver sources the child imports (default: this checkout's)."""
    return run_child(command, timeout, env, tree)[0]


def run_child(command: list[str], timeout: float, env: dict | None = None,
              tree: Path | None = None) -> tuple[float, float, str]:
    """``timed_command``'s (wall s, CPU s of the child and its threads, its stdout)."""
    import resource
    import subprocess
    import sys
    import time

    inherited = dict(os.environ)
    if SOURCE_CACHE:        # a cache the caller names (the first run's empty one) still holds
        inherited.pop("NUMBA_CACHE_DIR", None)
    env = {**inherited, **(env or {})}
    if tree is not None:
        env["PYTHONPATH"] = str(tree)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.perf_counter()
    try:
        done = subprocess.run([sys.executable, *command], capture_output=True, text=True,
                              timeout=timeout, env=env, cwd=tree)
    except subprocess.TimeoutExpired:
        raise WorkerFailed(f"timeout after {timeout:g} s") from None
    seconds = time.perf_counter() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode:
        lines = done.stderr.strip().splitlines()
        raise WorkerFailed(lines[-1] if lines else f"exit code {done.returncode}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return seconds, cpu, done.stdout


def whole_command(input_path: Path, faces: int, repeats: int, timeout: float,
                  work: Path, base: Path | None = None, levels: int = LEVELS) -> dict:
    """``lodserver build FILE.ply -o OUT.pm`` in a child process, each run paired
    with meshoptimizer's ``simplify`` to 10% in a child right after it (its
    load excluded, in its favour): the walls and CPU times (the child's, all
    its threads), the peer's call times and each pair's ratios. Then
    ``levels`` random ``pm.at()`` of the file written, each in a fresh child
    after ``load`` (``fresh_levels``).

    With ``base`` (another checkout's root), the same command with its
    sources runs beside each pair, first or second in turn, and each run's
    CPU time is divided by its base's: what a change bought, paired.
    """
    ply, work = write_ply(input_path).resolve(), work.resolve()   # a base's child runs in its tree
    trees = [None] if base is None else [None, base.resolve()]
    base = trees[-1] if base is not None else None
    outputs = {tree: work / f"command-{i}.pm" for i, tree in enumerate(trees)}

    def command(tree):
        return ["-m", "lodserver.cli", "build", str(ply), "-o", str(outputs[tree])]

    for tree in trees:      # untimed: fills each tree's numba cache, so no pair compiles
        run_child(command(tree), timeout, tree=tree)
    runs = {tree: {"wall_s": [], "cpu_s": []} for tree in trees}
    peers, peer_cpu = [], []
    for i in range(repeats):
        for tree in (trees if i % 2 == 0 else trees[::-1]):
            wall, cpu, _ = run_child(command(tree), timeout, tree=tree)
            runs[tree]["wall_s"].append(wall)
            runs[tree]["cpu_s"].append(cpu)
        row = run_method(REFERENCE, input_path, faces, 1, 0, timeout, work)
        if row["status"] != "ok":
            raise WorkerFailed(row["reason"])
        peers.append(row["time_s"])
        peer_cpu.append(row["cpu_s"])
    mine = runs[None]
    result = {"input": ply.name, "faces": faces, "command_s": mine["wall_s"],
              "command_cpu_s": mine["cpu_s"], f"{REFERENCE}_s": peers,
              f"{REFERENCE}_cpu_s": peer_cpu,
              "ratios": [c / p for c, p in zip(mine["wall_s"], peers)],
              "cpu_ratios": [c / p for c, p in zip(mine["cpu_s"], peer_cpu)]}
    result["median_ratio"] = statistics.median(result["ratios"])
    result["median_cpu_ratio"] = statistics.median(result["cpu_ratios"])
    if base is not None:
        result.update(base=str(base), base_command_s=runs[base]["wall_s"],
                      base_command_cpu_s=runs[base]["cpu_s"],
                      over_base=[c / b for c, b in zip(mine["cpu_s"], runs[base]["cpu_s"])])
        result["median_over_base"] = statistics.median(result["over_base"])
    if levels:
        result["fresh_levels"] = {("base" if tree else "this"): fresh_levels(
            outputs[tree], levels, repeats, timeout, tree) for tree in trees}
    return result


def fresh_levels(pm_path: Path, levels: int, repeats: int, timeout: float,
                 tree: Path | None = None) -> dict:
    """``levels`` random ``pm.at()`` (seed 0, base to full detail) in each of
    ``repeats`` fresh children, right after ``ProgressiveMesh.load`` (which
    pages in what the first level needs): the worst and median of each
    child's thread CPU and wall milliseconds."""
    children = []
    for _ in range(repeats):
        _, _, out = run_child([str(Path(__file__).resolve()), "--levels-of", str(pm_path),
                               "--levels", str(levels)], timeout, tree=tree)
        children.append(json.loads(out.strip().splitlines()[-1]))
    return {"children": children,
            "worst_cpu_ms": max(c["worst_cpu_ms"] for c in children),
            "worst_wall_ms": max(c["worst_wall_ms"] for c in children)}


def levels_of(pm_path: Path, levels: int) -> dict:
    """The child of ``fresh_levels``: load, then time each level once."""
    import time

    from lodserver import ProgressiveMesh

    started = time.perf_counter()
    pm = ProgressiveMesh.load(pm_path)
    load_s = time.perf_counter() - started
    drawn = np.random.default_rng(0).integers(pm.base_vertices, pm.vertex_count + 1, levels)
    cpu, wall = [], []
    for level in drawn:
        w, c = time.perf_counter(), time.thread_time()
        pm.at(int(level))
        cpu.append((time.thread_time() - c) * 1e3)
        wall.append((time.perf_counter() - w) * 1e3)
    return {"load_s": load_s, "worst_cpu_ms": max(cpu), "median_cpu_ms": statistics.median(cpu),
            "worst_wall_ms": max(wall), "median_wall_ms": statistics.median(wall),
            "first_cpu_ms": cpu[0]}


def first_run(repeats: int, timeout: float, work: Path) -> dict:
    """``lodserver build`` of the sample on an empty numba cache, then again on
    the cache it filled; each ``repeats`` times with a new empty cache. A small
    input's first build runs its kernels as Python while a background process
    compiles them (``lodserver.first_run``): the second build waits until that
    process lets go of its lock, and how long after the first build's start the
    cache was filled is recorded too. Wall and CPU seconds of each build (the
    child and its own children; the background compile not included) and the
    one-minute load average when it ended."""
    from lodserver.first_run import wait_for_background_compile

    runs = []
    for i in range(repeats):
        cache = work / f"empty-numba-cache-{i}"
        command = ["-m", "lodserver.cli", "build", str(SAMPLE), "-o", str(work / "sample.pm")]
        env = {"NUMBA_CACHE_DIR": str(cache)}
        started = time.perf_counter()
        cold = _wall_and_cpu(command, timeout, env)
        wait_for_background_compile(str(cache), timeout)
        filled = time.perf_counter() - started
        runs.append({"cold": cold, "filled_after_s": filled,
                     "warm": _wall_and_cpu(command, timeout, env)})
        shutil.rmtree(cache, ignore_errors=True)
    return {"sample": SAMPLE.name, "runs": runs}


def _wall_and_cpu(command: list[str], timeout: float, env: dict) -> dict:
    """``timed_command``'s wall seconds, with the CPU seconds of the processes it
    waited for (user + system) and the load average after."""
    before = os.times()
    wall = timed_command(command, timeout, env)
    after = os.times()
    cpu = (after.children_user - before.children_user
           + after.children_system - before.children_system)
    return {"wall_s": wall, "cpu_s": cpu, "load": os.getloadavg()[0]}


def command_table(results) -> str:
    header = ["size", "faces", "run", "lodserver build s", "cpu s", f"{REFERENCE} s", "cpu s",
              "ratio", "cpu ratio", "cpu / base"]
    lines = []
    for size, entry in results.get("command", {}).items():
        over_base = entry.get("over_base", [None] * len(entry["ratios"]))
        for i, row in enumerate(zip(entry["command_s"], entry["command_cpu_s"],
                                    entry[f"{REFERENCE}_s"], entry[f"{REFERENCE}_cpu_s"],
                                    entry["ratios"], entry["cpu_ratios"], over_base)):
            lines.append([size, entry["faces"], i + 1, *map(_g, row)])
        lines.append([size, entry["faces"], "median", "", "", "", "",
                      _g(entry["median_ratio"]), _g(entry["median_cpu_ratio"]),
                      _g(entry.get("median_over_base"))])
    return markdown_table(header, lines)


def fresh_levels_table(results) -> str:
    header = ["size", "sources", "child", "load s", "first cpu ms", "worst cpu ms",
              "median cpu ms", "worst wall ms", "median wall ms"]
    lines = []
    for size, entry in results.get("command", {}).items():
        for tree, levels in entry.get("fresh_levels", {}).items():
            for i, c in enumerate(levels["children"]):
                lines.append([size, tree, i + 1, _g(c["load_s"]), _g(c["first_cpu_ms"]),
                              _g(c["worst_cpu_ms"]), _g(c["median_cpu_ms"]),
                              _g(c["worst_wall_ms"]), _g(c["median_wall_ms"])])
    return markdown_table(header, lines)


def first_run_table(results) -> str:
    first = results["first_run"]
    lines = [[first["sample"], i + 1, _g(run["cold"]["wall_s"]), _g(run["cold"]["cpu_s"]),
              _g(run["cold"]["load"]), _g(run["filled_after_s"]), _g(run["warm"]["wall_s"]),
              _g(run["warm"]["cpu_s"]), _g(run["cold"]["wall_s"] / run["warm"]["wall_s"])]
             for i, run in enumerate(first["runs"])]
    return markdown_table(["sample", "run", "empty cache wall s", "CPU s", "load",
                           "cache filled after s", "filled cache wall s", "CPU s",
                           "empty / filled wall"], lines)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--sizes", help=f"comma-separated, from: {', '.join(SIZES)} (default: all)")
    parser.add_argument("--methods", default=",".join(METHODS),
                        help="comma-separated; lodserver-1t is the NUMBA_NUM_THREADS=1 build")
    parser.add_argument("--repeats", type=int, help="timed calls per method at 1m (median); 3")
    parser.add_argument("--repeats-large", type=int, default=1,
                        help="timed calls per method at the larger sizes; 1")
    parser.add_argument("--levels", type=int, default=LEVELS,
                        help=f"random levels extracted by lodserver; {LEVELS}")
    parser.add_argument("--timeout", type=float, default=900.0,
                        help="seconds per child process before it counts as failed; 900")
    parser.add_argument("--quick", action="store_true", help="1m only, 1 repeat")
    parser.add_argument("--command", action="store_true",
                        help="also the whole `lodserver build` of each size's PLY, paired "
                             f"with {REFERENCE} (--repeats pairs)")
    parser.add_argument("--first-run", action="store_true",
                        help="also `lodserver build` of the sample on an empty numba cache")
    parser.add_argument("--no-methods", action="store_true",
                        help="skip the per-method runs (with --command or --first-run)")
    parser.add_argument("--base", type=Path,
                        help="with --command: another checkout's root, whose same command "
                             "runs beside each pair (its CPU time the divisor)")
    parser.add_argument("--source-cache", action="store_true",
                        help="with --command: each tree's numba cache beside its sources, not "
                             "the benchmarks' own (no compiling a second tree from scratch)")
    parser.add_argument("--levels-of", type=Path, help=argparse.SUPPRESS)   # fresh_levels' child
    add_io_arguments(parser, "speed")
    args = parser.parse_args(argv)
    args.sizes = (args.sizes or ("1m" if args.quick else ",".join(SIZES))).split(",")
    args.methods = args.methods.split(",")
    for given, known, what in ((args.sizes, SIZES, "size"), (args.methods, METHODS, "method")):
        unknown = [x for x in given if x not in known]
        if unknown:
            parser.error(f"unknown {what} {unknown[0]!r}; choose from {', '.join(known)}")
    args.repeats = args.repeats or (1 if args.quick else 3)
    if args.repeats < 1 or args.repeats_large < 1 or args.levels < 0 or args.timeout <= 0:
        parser.error("repeats must be at least 1, levels at least 0 and the timeout positive")
    if not args.mesh_dir.is_dir():
        parser.error(f"no mesh folder at {args.mesh_dir}; give --mesh-dir")
    return args


def main(argv=None):
    args = parse_args(argv)
    global SOURCE_CACHE
    SOURCE_CACHE = args.source_cache
    if args.levels_of:
        print(json.dumps(levels_of(args.levels_of, args.levels)))
        return
    if args.base is not None and not (args.base / "lodserver").is_dir():
        raise SystemExit(f"--base {args.base}: no lodserver folder there")
    from machine import cpu_busy, machine_info

    result_path = results_file(args, "speed")
    fresh_numba_cache()
    results = {"machine": {**machine_info(PACKAGES), "cpu_busy_before": cpu_busy()},
               "settings": {"ratio": RATIO, "repeats": args.repeats,
                            "repeats_large": args.repeats_large, "levels": args.levels,
                            "timeout_s": args.timeout, "methods": args.methods,
                            "reference": REFERENCE},
               "sizes": {}}
    work = Path(tempfile.mkdtemp(prefix="speed-", dir=args.out))
    try:
        # the first run alone builds the sample only: no large input to make
        needed = args.command or not args.no_methods
        inputs = {size: prepare_input(size, args.mesh_dir, args.out)
                  for size in args.sizes if needed}
        for size, (input_path, faces) in inputs.items():
            results["sizes"][size] = {"input": input_path.name, "faces": faces, "rows": [],
                                      "repeats": args.repeats if size == "1m"
                                      else args.repeats_large}
        if args.first_run:
            _log("first run on an empty numba cache ...")
            results["first_run"] = first_run(args.repeats, args.timeout, work)
            result_path.write_text(json.dumps(results, indent=1))
        if args.command:
            results["command"] = {}
            for size, (input_path, faces) in inputs.items():
                _log(f"{size} ({faces:,} faces): the whole command ...")
                results["command"][size] = whole_command(input_path, faces, args.repeats,
                                                         args.timeout, work, args.base,
                                                         args.levels)
                result_path.write_text(json.dumps(results, indent=1))
        # method by method over the sizes, so a run cut short still has the first
        # methods (lodserver and meshoptimizer) at every size
        for method in ([] if args.no_methods else args.methods):
            for size, (input_path, faces) in inputs.items():
                entry = results["sizes"][size]
                _log(f"{size} ({faces:,} faces): {method} ...")
                row = run_method(method, input_path, faces, entry["repeats"], args.levels,
                                 args.timeout, work)
                _log(f"  {row.get('time_s', row.get('reason'))}")
                entry["rows"].append(row)
                with_ratios(entry["rows"])
                # rewritten after every child, so an interrupted run keeps what it measured
                result_path.write_text(json.dumps(results, indent=1))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    results["machine"]["cpu_busy_after"] = cpu_busy()
    result_path.write_text(json.dumps(results, indent=1))
    if "first_run" in results:
        print(first_run_table(results), "\n")
    if "command" in results:
        print(command_table(results), "\n")
        print(fresh_levels_table(results), "\n")
    if not args.no_methods:
        print(speed_table(results), "\n")
        print(scaling_table(results), "\n")
        print(levels_table(results))
    _log(f"\nwrote {result_path}")


if __name__ == "__main__":
    main()
