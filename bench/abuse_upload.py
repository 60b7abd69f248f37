"""Upload abuse benchmark: what big and many uploads do to a real server.

Against one ``lodserver serve`` process on 127.0.0.1 (a checkout given by
``--repo``, so HEAD and the working tree can be compared), two phases:

1. ``big``: one binary STL of ``--big-mb`` MB (a generated grid, 50 bytes a
   triangle) streamed in by a chunked POST while a second client asks
   ``/healthz`` every 20 ms. Latencies are split by phase: ``idle`` (5 s
   before the upload: the machine's own noise), ``transfer`` (until the last
   body byte is handed to the connection) and ``parse`` (from then until the
   answer: the server finishes receiving, then parses and checks the file
   before it answers 202); the five worst, with when they happened. The mesh
   is then deleted, which stops its build.
2. ``many``: ``--concurrent`` clients upload ``stanford-bunny.obj`` (2.4 MB,
   from ../shared/meshes) at once; a client answered 503 waits its
   Retry-After (at most 5 s) and tries again, up to 10 times. The server's
   resident memory (its process plus its children: the parse workers) is
   sampled every 20 ms; the peak is reported. The meshes are deleted after.

Bounded: every request has a timeout, the run has a deadline, the server is
stopped (and the generated file removed) whatever happens. Only 127.0.0.1 is
contacted.

    python bench/abuse_upload.py                         # this checkout
    python bench/abuse_upload.py --repo /tmp/base --label before

Writes ``bench/out/abuse_upload-<label>.json`` and prints a summary.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from abuse_runs import ROOT, checkout_server, peaks, report

BUNNY = ROOT.parent / "shared" / "meshes" / "stanford-bunny.obj"
BOUNDARY = "abuse-upload-boundary"
DEADLINE_S = 900
IDLE_S = 5


def grid_stl(path: Path, megabytes: float) -> int:
    """A binary STL of a wavy grid, about ``megabytes`` MB; its triangle count."""
    triangles = int(megabytes * 1e6 - 84) // 50
    n = int(np.sqrt(triangles / 2)) + 1
    x, y = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    z = 0.05 * np.sin(9 * x) * np.cos(7 * y)
    grid = np.stack([x, y, z], -1).astype(np.float32)
    a, b, c, d = grid[:-1, :-1], grid[:-1, 1:], grid[1:, 1:], grid[1:, :-1]
    corners = np.concatenate([np.stack([a, b, c], -2).reshape(-1, 3, 3),
                              np.stack([a, c, d], -2).reshape(-1, 3, 3)])[:triangles]
    record = np.zeros(len(corners), dtype=[("normal", "<f4", 3), ("corners", "<f4", (3, 3)),
                                           ("attribute", "<u2")])
    record["corners"] = corners
    with open(path, "wb") as out:
        out.write(b"\0" * 80 + np.uint32(len(record)).tobytes())
        out.write(record.tobytes())
    return len(record)


def multipart_stream(path: Path, marks: dict, chunk=1 << 20):
    """A multipart body read from ``path`` a chunk at a time; ``marks['sent']`` is
    set when the last byte is handed to the connection."""
    yield (f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"file\"; "
           f"filename=\"{path.name}\"\r\n\r\n").encode()
    with open(path, "rb") as file:
        while block := file.read(chunk):
            yield block
    yield f"\r\n--{BOUNDARY}--\r\n".encode()
    marks["sent"] = time.monotonic()


def poll_health(base: str, stop: threading.Event, samples: list) -> None:
    with httpx.Client(base_url=base, timeout=30) as client:
        while not stop.is_set():
            started = time.monotonic()
            try:
                status = client.get("/healthz").status_code
            except httpx.HTTPError:
                status = -1
            samples.append((started, time.monotonic() - started, status))
            time.sleep(max(0.0, 0.02 - (time.monotonic() - started)))


def tree_rss(pid: int) -> tuple[int, int]:
    """Resident bytes of ``pid`` and of it plus all its descendants."""
    def rss(p):
        try:
            for line in open(f"/proc/{p}/status"):
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
        except OSError:
            pass
        return 0

    def children(p):
        found = []
        try:
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    found += [int(c) for c in f.read().split()]
        except OSError:
            pass
        return found

    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        total += rss(p)
        todo += children(p)
    return rss(pid), total


def stats_ms(values) -> dict:
    values = sorted(values)
    if not values:
        return {"n": 0}
    pick = lambda q: values[min(len(values) - 1, int(q * len(values)))]  # noqa: E731
    return {"n": len(values), "p50_ms": round(1e3 * statistics.median(values), 1),
            "p99_ms": round(1e3 * pick(0.99), 1), "max_ms": round(1e3 * values[-1], 1)}


def big_upload(base: str, path: Path) -> dict:
    samples, stop, marks = [], threading.Event(), {}
    poller = threading.Thread(target=poll_health, args=(base, stop, samples))
    poller.start()
    time.sleep(IDLE_S)      # the machine's own noise: latencies with nothing uploading
    started = time.monotonic()
    try:
        with httpx.Client(base_url=base, timeout=600) as client:
            response = client.post("/meshes", content=multipart_stream(path, marks), headers={
                "content-type": f"multipart/form-data; boundary={BOUNDARY}"})
            answered = time.monotonic()
            if response.status_code == 202:
                client.delete(f"/meshes/{response.json()['id']}")
    finally:
        time.sleep(0.3)
        stop.set()
        poller.join()
    sent = marks.get("sent", answered)
    idle = [lat for t, lat, _ in samples if t < started]
    transfer = [lat for t, lat, _ in samples if started <= t < sent]
    worst = sorted((lat, t) for t, lat, _ in samples if started <= t < answered)[-5:]
    parse = [lat for t, lat, _ in samples if sent <= t < answered]
    return {"status": response.status_code, "body": response.text[:200],
            "upload_bytes": path.stat().st_size,
            "transfer_s": round(sent - started, 2), "parse_s": round(answered - sent, 2),
            "healthz_idle": stats_ms(idle),
            "healthz_transfer": stats_ms(transfer), "healthz_parse": stats_ms(parse),
            "healthz_worst": [{"ms": round(1e3 * lat, 1), "at_s": round(t - started, 2)}
                              for lat, t in reversed(worst)],
            "healthz_all": stats_ms(transfer + parse),
            "healthz_not_200": sum(1 for t, _, s in samples if started <= t < answered
                                   and s != 200)}


def many_uploads(base: str, pid: int, clients: int, mesh: Path) -> dict:
    content = mesh.read_bytes()
    results, ids, lock = [], [], threading.Lock()
    start = threading.Barrier(clients)

    def one():
        tries, refused, started = 0, 0, time.monotonic()
        with httpx.Client(base_url=base, timeout=300) as client:
            start.wait()
            while tries < 10:
                tries += 1
                response = client.post("/meshes", files={"file": (mesh.name, content)})
                if response.status_code != 503:
                    break
                refused += 1
                time.sleep(min(5.0, float(response.headers.get("retry-after", "1"))))
        with lock:
            results.append({"status": response.status_code, "refused": refused,
                            "seconds": time.monotonic() - started})
            if response.status_code == 202:
                ids.append(response.json()["id"])

    with peaks(lambda: tree_rss(pid), every=0.02) as peak:
        baseline = tree_rss(pid)
        threads = [threading.Thread(target=one) for _ in range(clients)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
    with httpx.Client(base_url=base, timeout=60) as client:
        for mesh_id in ids:
            client.delete(f"/meshes/{mesh_id}")
    statuses = {}
    for result in results:
        statuses[result["status"]] = statuses.get(result["status"], 0) + 1
    return {"clients": clients, "mesh": mesh.name, "mesh_bytes": len(content),
            "statuses": statuses, "refused_503": sum(r["refused"] for r in results),
            "slowest_client_s": round(max(r["seconds"] for r in results), 2),
            "rss_before_mb": round(baseline[1] / 2**20, 1),
            "peak_rss_server_mb": round(peak[0] / 2**20, 1),
            "peak_rss_with_workers_mb": round(peak[1] / 2**20, 1)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repo", type=Path, default=ROOT, help="checkout whose server to run")
    parser.add_argument("--label", default="after")
    parser.add_argument("--big-mb", type=float, default=250)
    parser.add_argument("--concurrent", type=int, default=20)
    parser.add_argument("--skip-big", action="store_true")
    parser.add_argument("--skip-many", action="store_true")
    args = parser.parse_args()
    if not BUNNY.is_file():
        print(f"needs {BUNNY}", file=sys.stderr)
        return 1
    work = Path(tempfile.mkdtemp(prefix="abuse-upload-"))
    result = {"repo": str(args.repo), "label": args.label}
    timer = threading.Timer(DEADLINE_S, lambda: os._exit(3))   # the run stops by itself
    timer.daemon = True
    timer.start()
    try:
        env = {"LODSERVER_MAX_UPLOAD_BYTES": str(400 * 2**20),
               "LODSERVER_MAX_TRIANGLES": "20000000"}
        if not args.skip_big:
            stl = work / "grid.stl"
            result["big_triangles"] = grid_stl(stl, args.big_mb)
            with checkout_server(args.repo, work / "data-big", work / "big.log",
                                 env) as (base, _):
                result["big"] = big_upload(base, stl)
            stl.unlink()
        if not args.skip_many:
            with checkout_server(args.repo, work / "data-many", work / "many.log",
                                 env) as (base, process):
                result["many"] = many_uploads(base, process.pid, args.concurrent, BUNNY)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    report("abuse_upload", args.label, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
