"""One measurement in its own process, so a crash cannot take the benchmark down.

Usage (run by ``simplify.py``, not by hand)::

    worker.py peer METHOD INPUT.npz OUTPUT.npz --targets N --repeats R
    worker.py lodserver INPUT.npz OUTPUT.npz --targets N1,N2,... --repeats R [--levels K]
    worker.py warmup OUTPUT.npz

INPUT.npz holds the welded ``positions`` and ``faces``. OUTPUT.npz gets
``positions_i`` / ``faces_i`` for the i-th target and ``report``, a JSON
string with the timings. Each call is timed and memory-measured by
:func:`measure`; loading the input and saving the output are not. The report
also holds ``process_max_rss_mib``, the whole process's peak RSS (input,
imports and all; ``process_peak_mib``).
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import hashlib
import json
import resource
import time
from pathlib import Path

import numpy as np


def _status_kib(field: str) -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise KeyError(field)


def _release_free_memory() -> None:
    """Return freed heap pages to the OS (glibc), so a repeat's peak RSS is not
    hidden by memory the previous repeat freed but the allocator kept."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass  # not glibc: peaks of later repeats may read low


# the process's peak RSS before the last VmHWM reset (KiB): a reset also lowers
# what getrusage reports, so the whole process's peak is kept here
_process_peak_kib = 0


def process_peak_mib() -> float:
    """Peak RSS of this whole process so far (input, imports and all), MiB."""
    current = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    return max(_process_peak_kib, current) / 1024


def _reset_peak() -> bool:
    """Reset VmHWM to the current RSS (Linux); False where that is unsupported."""
    global _process_peak_kib
    try:
        _process_peak_kib = max(_process_peak_kib, _status_kib("VmHWM"))
    except (OSError, KeyError):
        pass
    try:
        with open("/proc/self/clear_refs", "w") as clear_refs:
            clear_refs.write("5")
        return True
    except OSError:
        return False


def measure(call):
    """Run ``call()`` once: (its result, wall seconds, CPU seconds, peak RSS
    increase in MiB).

    CPU seconds are this process's, all threads: well below the wall time on a
    single-threaded call means something else had the CPU. The peak is VmHWM
    after the call minus VmRSS before it, with VmHWM reset just before the
    call; it is None where /proc cannot be used.
    """
    _release_free_memory()
    can_measure = _reset_peak()
    baseline = _status_kib("VmRSS") if can_measure else 0
    cpu = time.process_time()
    start = time.perf_counter()
    result = call()
    elapsed = time.perf_counter() - start
    cpu = time.process_time() - cpu
    peak = (_status_kib("VmHWM") - baseline) / 1024 if can_measure else None
    return result, elapsed, cpu, peak


def warmup_mesh(rings=32, segments=20):
    """A bent open tube (a torus missing one ring of faces), as writable arrays,
    to load and compile code before timing: 2 * (rings - 1) * segments (1,240)
    triangles with both interior and border vertices, so border-only code is
    loaded too. Built with numpy alone, so a peer's process does not pay for
    importing trimesh."""
    u = np.linspace(0.0, 2 * np.pi, rings, endpoint=False)[:, None]
    v = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)[None, :]
    tube = 1.0 + 0.3 * np.cos(v)
    positions = np.stack(np.broadcast_arrays(tube * np.cos(u), tube * np.sin(u),
                                             0.3 * np.sin(v)), axis=-1).reshape(-1, 3)
    i, j = np.arange(rings - 1)[:, None], np.arange(segments)[None, :]
    a, b = i * segments + j, (i + 1) * segments + j
    c, d = (i + 1) * segments + (j + 1) % segments, i * segments + (j + 1) % segments
    faces = np.concatenate([np.stack([a, b, c], axis=-1).reshape(-1, 3),
                            np.stack([a, c, d], axis=-1).reshape(-1, 3)])
    return positions, faces


def lodserver_digest() -> str:
    """SHA-1 of the lodserver sources, to tell which kernel version was timed."""
    import lodserver

    digest = hashlib.sha1()
    for path in sorted(Path(lodserver.__file__).parent.rglob("*.py")):
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def run_peer(method, positions, faces, targets, repeats):
    """Time ``repeats`` calls of a peer per target; keep the last result."""
    from methods import PEERS

    simplify = PEERS[method]
    simplify(*warmup_mesh(), 100)  # loads the library's lazy parts
    arrays, runs = {}, []
    for i, target in enumerate(targets):
        times, cpu_times, peaks = [], [], []
        for _ in range(repeats):
            result = None  # free the previous result before the next call
            result, elapsed, cpu, peak = measure(lambda: simplify(positions, faces, target))
            times.append(elapsed)
            cpu_times.append(cpu)
            peaks.append(peak)
        arrays[f"positions_{i}"], arrays[f"faces_{i}"] = result
        runs.append({"target": target, "times_s": times, "cpu_times_s": cpu_times,
                     "peaks_mib": peaks})
    return arrays, {"runs": runs}


def _timed(call, *args):
    """(wall, thread CPU) seconds of ``call(*args)``, in the steady state of a
    process that keeps serving: unlike :func:`measure`, no collection and no
    heap returned to the OS first. CPU time tells the call apart from a busy
    machine (it excludes time spent waiting for a core)."""
    cpu = time.thread_time()
    start = time.perf_counter()
    call(*args)
    return time.perf_counter() - start, time.thread_time() - cpu


def run_lodserver(positions, faces, targets, repeats, levels=0):
    """Time ``build`` (once per repeat), per target ``arrays_at`` of its level,
    and ``arrays_at`` and ``at`` of ``levels`` random levels (seed 0), once each."""
    from lodserver import Mesh, build

    mesh = Mesh(positions, faces)
    digest = lodserver_digest()  # now: the sources just imported
    # Compiles (or loads from the numba cache) everything the timed calls use,
    # the partitioned path of a large mesh included (simplify.parts).
    warm = build(Mesh(*warmup_mesh()))
    warm.arrays_at(warm.level_for(ratio=0.5))
    _warm_parts()
    build_times, build_cpu_times, build_peaks, pm = [], [], [], None
    for _ in range(repeats):
        pm = None  # free the previous progressive mesh before the next build
        pm, elapsed, cpu, peak = measure(lambda: build(mesh))
        build_times.append(elapsed)
        build_cpu_times.append(cpu)
        build_peaks.append(peak)
    arrays, runs = {}, []
    for i, target in enumerate(targets):
        level = pm.level_for(faces=target)
        times = []
        for _ in range(repeats):
            extracted, elapsed, _, _ = measure(lambda: pm.arrays_at(level))
            times.append(elapsed)
        arrays[f"positions_{i}"], arrays[f"faces_{i}"] = extracted
        runs.append({"target": target, "level": level, "extract_times_s": times})
    drawn = np.random.default_rng(0).integers(pm.base_vertices, pm.vertex_count + 1, levels)
    arrays_at_times = [_timed(pm.arrays_at, level) for level in drawn]
    at_times = [_timed(pm.at, level) for level in drawn]
    report = {
        "build_times_s": build_times,
        "build_cpu_times_s": build_cpu_times,
        "build_peaks_mib": build_peaks,
        "base_faces": int(pm.face_counts[0]),
        "splits": pm.split_count,
        "passes": pm.metadata["decimation"]["passes"],
        "source_digest": digest,
        "runs": runs,
        "random_levels": {"levels": drawn.tolist(),
                          "arrays_at_s": [wall for wall, _ in arrays_at_times],
                          "arrays_at_cpu_s": [cpu for _, cpu in arrays_at_times],
                          "at_s": [wall for wall, _ in at_times],
                          "at_cpu_s": [cpu for _, cpu in at_times]},
    }
    return arrays, report


def _warm_parts():
    """Decimate the warm-up mesh in parts, as ``build`` does a mesh of
    ``PARALLEL_MIN_VERTICES`` or more: its kernels compile (or load) now."""
    from lodserver import Mesh
    from lodserver.simplify.collapse import DecimateOptions, decimate

    decimate(Mesh(*warmup_mesh()), DecimateOptions(parts=2))


def run_warmup():
    """Time the first build in this process (compile or cache load), the
    partitioned path's included, and a second one."""
    from lodserver import Mesh, build

    digest = lodserver_digest()
    mesh = Mesh(*warmup_mesh())
    _, first, _, _ = measure(lambda: (build(mesh), _warm_parts()))
    _, second, _, _ = measure(lambda: (build(mesh), _warm_parts()))
    return {}, {"first_build_s": first, "steady_build_s": second, "source_digest": digest}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    modes = parser.add_subparsers(dest="mode", required=True)
    peer = modes.add_parser("peer")
    peer.add_argument("method")
    lodserver = modes.add_parser("lodserver")
    for mode in (peer, lodserver):
        mode.add_argument("input")
        mode.add_argument("output")
        mode.add_argument("--targets", required=True, help="comma-separated face counts")
        mode.add_argument("--repeats", type=int, default=1)
    lodserver.add_argument("--levels", type=int, default=0,
                           help="random levels to extract, timed once each")
    modes.add_parser("warmup").add_argument("output")
    args = parser.parse_args(argv)

    if args.mode == "warmup":
        arrays, report = run_warmup()
    else:
        data = np.load(args.input)
        targets = [int(t) for t in args.targets.split(",")]
        if args.mode == "peer":
            arrays, report = run_peer(args.method, data["positions"], data["faces"],
                                      targets, args.repeats)
        else:
            arrays, report = run_lodserver(data["positions"], data["faces"], targets,
                                           args.repeats, args.levels)
    report["process_max_rss_mib"] = process_peak_mib()
    np.savez(args.output, report=np.array(json.dumps(report)), **arrays)


if __name__ == "__main__":
    main()
