"""Abusive reads against one real ``lodserver serve``: peak memory and liveness.

Against a server holding ``bunny_loop2`` (the Stanford bunny Loop-subdivided
twice, 1.1M triangles, uploaded as ``bench/load.py`` does), three bursts, each
request sent once on its own connection (``bench/load.py``'s ``LoopbackClient``):

a. 8 concurrent 16-level chains (``GET /chain``, 162 MiB each), all distinct, so
   no request can share another's body;
b. the same with 16;
c. 16 concurrent cold ``format=json`` levels (distinct random levels).

Meanwhile a thread asks ``/healthz`` every 20 ms and reads the server's VmRSS
(``/proc/<pid>/status``; VmHWM, reset before each burst through
``/proc/<pid>/clear_refs`` where allowed, gives the peak between samples). It
reports per burst: statuses (only 200 and 503 are allowed), peak RSS growth over
the RSS before the burst, RSS after, and ``/healthz`` latency p50/p99/max.
Targets: growth under 1 GB, ``/healthz`` p99 under 100 ms.

Bounded: loopback only, a fixed number of requests, a timeout per request and a
deadline for the run; the server is stopped at the end whatever happens.

    python bench/abuse_reads.py            # ~3-6 min on 2 cores

Writes ``bench/out/abuse_reads.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
from load import LARGE, LoopbackClient, upload, upload_file  # noqa: E402
from machine import machine_info, process_memory_kib, reset_memory_peak  # noqa: E402
from tests.server import server_process  # noqa: E402

OUT = ROOT / "bench" / "out"
GB = 1e9
PACKAGES = ("lodserver", "numpy", "numba", "fastapi", "uvicorn")



class Monitor(threading.Thread):
    """/healthz latency and the server's RSS, sampled every ``period`` seconds."""

    def __init__(self, base: str, pid: int, period: float = 0.02):
        super().__init__(daemon=True)
        self.base, self.pid, self.period = base, pid, period
        self.stop = threading.Event()
        self.latencies, self.rss, self.failures = [], [], Counter()

    def run(self):
        with httpx.Client(base_url=self.base, timeout=10) as client:
            while not self.stop.is_set():
                began = time.perf_counter()
                try:
                    response = client.get("/healthz")
                    self.latencies.append(time.perf_counter() - began)
                    if response.status_code != 200:
                        self.failures[response.status_code] += 1
                except httpx.HTTPError as exc:
                    self.failures[type(exc).__name__] += 1
                self.rss.append(process_memory_kib(self.pid)["VmRSS"])
                self.stop.wait(max(0.0, self.period - (time.perf_counter() - began)))


async def burst(base: str, requests: list[tuple[str, dict]], timeout: float) -> dict:
    """Send every request at once, one connection each: statuses and latencies."""

    async def one(path, params):
        client = LoopbackClient(base)
        began = time.perf_counter()
        try:
            status, size, _ = await asyncio.wait_for(client.get(path, params), timeout)
            return status, size, time.perf_counter() - began
        except (OSError, asyncio.TimeoutError, ValueError, KeyError) as exc:
            return type(exc).__name__, 0, time.perf_counter() - began
        finally:
            client.close()

    results = await asyncio.gather(*(one(path, params) for path, params in requests))
    statuses = Counter(str(status) for status, _, _ in results)
    ok = [seconds for status, _, seconds in results if status == 200]
    return {"statuses": dict(statuses),
            "ok_seconds_max": round(max(ok), 2) if ok else None,
            "ok_bytes": sum(size for status, size, _ in results if status == 200)}


def chain_requests(mesh_id: str, count: int) -> list[tuple[str, dict]]:
    """``count`` distinct 16-level chains (1, 15/16, ..., 1/16, each shifted a little)."""
    out = []
    for k in range(count):
        ratios = [1.0] + [round(1 - i / 16 - k * 1e-3, 6) for i in range(1, 16)]
        out.append((f"/meshes/{mesh_id}/chain", {"lods": ",".join(map(str, ratios))}))
    return out


def level_requests(mesh_id: str, record: dict, count: int, rng) -> list[tuple[str, dict]]:
    """``count`` distinct json levels in the upper half of the mesh's levels."""
    n0, n = record["base_vertices"], record["vertices"]
    levels = rng.sample(range((n0 + n) // 2, n + 1), count)
    return [(f"/meshes/{mesh_id}/lod", {"vertices": v, "format": "json"}) for v in levels]


def measure(base: str, pid: int, name: str, requests, timeout: float) -> dict:
    time.sleep(1.0)         # let the previous burst's threads finish and memory settle
    before = process_memory_kib(pid)["VmRSS"]
    peak_reset = reset_memory_peak(pid)
    monitor = Monitor(base, pid)
    monitor.start()
    time.sleep(0.2)
    began = time.perf_counter()
    result = asyncio.run(burst(base, requests, timeout))
    wall = time.perf_counter() - began
    time.sleep(0.5)
    monitor.stop.set()
    monitor.join()
    status = process_memory_kib(pid)
    peak = max(max(monitor.rss, default=before), status["VmHWM"] if peak_reset else 0)
    ms = np.array(monitor.latencies) * 1000
    result.update(
        case=name, requests=len(requests), wall_s=round(wall, 2),
        rss_before_mb=round(before * 1024 / 1e6), rss_peak_mb=round(peak * 1024 / 1e6),
        rss_after_mb=round(status["VmRSS"] * 1024 / 1e6),
        peak_growth_gb=round((peak - before) * 1024 / GB, 3), peak_from_vmhwm=peak_reset,
        healthz_samples=len(ms), healthz_failures=dict(monitor.failures),
        healthz_p50_ms=round(float(np.percentile(ms, 50)), 1) if len(ms) else None,
        healthz_p99_ms=round(float(np.percentile(ms, 99)), 1) if len(ms) else None,
        healthz_max_ms=round(float(ms.max()), 1) if len(ms) else None)
    result["only_200_or_503"] = set(result["statuses"]) <= {"200", "503"}
    print(f"  {name}: {result['statuses']}, peak growth {result['peak_growth_gb']} GB, "
          f"/healthz p99 {result['healthz_p99_ms']} ms", file=sys.stderr)
    return result


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--request-timeout", type=float, default=180)
    parser.add_argument("--build-timeout", type=float, default=600)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT / "abuse_reads.json")
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    rng = random.Random(args.seed)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    settings = {name: os.environ.get(f"LODSERVER_{name.upper()}") for name in
                ("heavy_requests", "heavy_slot_bytes", "heavy_wait_seconds", "body_file_bytes",
                 "body_cache_bytes", "loaded_meshes", "loaded_bytes")}
    document = {"machine": machine_info(PACKAGES), "server_settings_env": settings,
                "results": []}
    with tempfile.TemporaryDirectory(prefix="lodserver-abuse-") as folder:
        work = Path(folder)
        path, _ = upload_file(LARGE, work)
        with server_process(work / "data", log=work / "server.log", warm_kernels=True,
                            timeout=120) as (base, process):
            with httpx.Client(base_url=base) as client:
                mesh_id, record, seconds = upload(client, path, timeout=args.build_timeout)
                print(f"{LARGE}: {record['faces']:,} triangles, ready in {seconds:.1f} s",
                      file=sys.stderr)
                # load the mesh and its records as a client would, outside the bursts
                client.get(f"/meshes/{mesh_id}/lod", params={"vertices": record["base_vertices"]},
                           timeout=args.request_timeout).raise_for_status()
            document["mesh"] = {"id": mesh_id, **{k: record[k] for k in (
                "vertices", "faces", "base_vertices")}}
            cases = [("a: 8 chains", chain_requests(mesh_id, 8)),
                     ("b: 16 chains", chain_requests(mesh_id, 24)[8:]),   # none of a's
                     ("c: 16 json levels", level_requests(mesh_id, record, 16, rng))]
            for name, requests in cases:
                document["results"].append(measure(base, process.pid, name, requests,
                                                   args.request_timeout))
                args.out.write_text(json.dumps(document, indent=2))
            document["bodies_dir_bytes"] = sum(p.stat().st_size for p in
                                               (work / "data" / "bodies").iterdir())
            document["server_exit_code"] = process.poll()
    args.out.write_text(json.dumps(document, indent=2))
    print("| case | statuses | wall s | RSS before MB | peak growth GB | RSS after MB | "
          "/healthz p50 ms | p99 ms | max ms |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in document["results"]:
        print(f"| {r['case']} | {r['statuses']} | {r['wall_s']} | {r['rss_before_mb']} | "
              f"{r['peak_growth_gb']} | {r['rss_after_mb']} | {r['healthz_p50_ms']} | "
              f"{r['healthz_p99_ms']} | {r['healthz_max_ms']} |")
    met = all(r["peak_growth_gb"] < 1 and (r["healthz_p99_ms"] or 1e9) < 100 and
              r["only_200_or_503"] for r in document["results"])
    print(f"\ntargets (growth < 1 GB, /healthz p99 < 100 ms, only 200/503): "
          f"{'met' if met else 'NOT met'}\nwritten {args.out}")
    return 0 if all(r["only_200_or_503"] for r in document["results"]) else 1


if __name__ == "__main__":
    sys.exit(main())
