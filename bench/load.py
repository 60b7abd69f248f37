"""Load benchmark: one real ``lodserver serve`` process on loopback, many concurrent
LOD and packet requests, and the size of the packets against the raw arrays.

What it does, per mesh (``stanford-bunny``; ``bunny_loop2``, the bunny
Loop-subdivided twice, 1.1M triangles):

1. uploads the mesh (the OBJ as shipped; ``bunny_loop2`` as a binary PLY of the
   welded arrays) to a fresh server and waits until it is ready;
2. ``first``: one LOD request right after the build (the artefact is loaded from
   disk, the numba kernels of the encoder from their cache);
3. for each kind (``json`` and ``glb`` LODs, ``packet`` = vsplit packets between two
   random levels): ``cold``, distinct random targets the server has not seen, so
   every response is encoded; then ``cached``, many requests over a small hot set
   of those targets, answered from the server's in-memory body cache (the hot
   set's bytes are in the JSON: past the cache's 128 MiB it would not all stay);
   ``cold`` and ``cached`` keep ``--concurrency`` requests in flight, so their
   latencies include queueing; ``cached-serial`` sends the hot set one at a time;
4. the packets base -> full and back: bytes per record, what each stream costs,
   against the raw arrays (float32 positions + int32 indices) and the LOD formats.

The phases' requests go through ``LoopbackClient``, a minimal keep-alive HTTP/1.1
reader, one connection per request in flight: the client shares the cores with
the server, and httpx's own cost of reading big bodies was 4x the server's.

Everything is bounded: a fixed number of requests per phase, a per-request
timeout and a deadline for the whole run after which no new request starts; the
server is stopped at the end whatever happens. Only 127.0.0.1 is contacted.

    python bench/load.py                   # both meshes (~5-10 min on 2 cores)
    python bench/load.py --quick           # stanford-bunny only, fewer requests (~1 min)

Writes ``bench/out/load.json`` (``load-quick.json`` for ``--quick``) and prints tables.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import socket
import sys
import tempfile
import time
import zlib
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from codec_meshes import bunny_loop2  # noqa: E402
from machine import machine_info  # noqa: E402
from tests.server import server_process  # noqa: E402

PACKAGES = ("lodserver", "numpy", "numba", "fastapi", "uvicorn", "httptools", "uvloop", "httpx")

MESH_DIR = ROOT.parent / "shared" / "meshes"
OUT = ROOT / "bench" / "out"
HOST = "127.0.0.1"           # loopback only
LARGE = "bunny_loop2"
MESHES = {"stanford-bunny": "stanford-bunny.obj", LARGE: None}
KINDS = ("json", "glb", "packet")
CACHE_BYTES = 128 * 2**20    # lodserver.api.caching.CACHE_BYTES
BITS_SWEEP = (10, 12)
STREAMS = ("vertex", "count", "pattern", "other", "fan", "mask", "position")


# ---- the server ----------------------------------------------------------------
def _process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU time of a process, from /proc (None where unavailable)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


# ---- the meshes ----------------------------------------------------------------
def upload_file(key: str, work: Path) -> tuple[Path, dict]:
    """The file to upload for ``key`` and the welded mesh's counts (computed here,
    for the raw-array comparison)."""
    from lodserver.io import load_mesh, save_mesh

    if key == LARGE:
        mesh = bunny_loop2(MESH_DIR, OUT)     # the same arrays as bench/simplify.py uses
        path = work / f"{LARGE}.ply"
        save_mesh(mesh, path, file_type="ply")
    else:
        path = MESH_DIR / MESHES[key]
        mesh, _ = load_mesh(path)
    raw = (np.ascontiguousarray(mesh.positions, dtype="<f4").tobytes()
           + np.ascontiguousarray(mesh.faces, dtype="<i4").tobytes())
    return path, {"vertices": mesh.vertex_count, "faces": mesh.face_count,
                  "raw_bytes": len(raw), "raw_zlib_bytes": len(zlib.compress(raw, 9))}


def upload(client: httpx.Client, path: Path, timeout: float) -> tuple[str, dict, float]:
    """POST the file, wait until the mesh is ready: (id, its record, seconds)."""
    began = time.perf_counter()
    with open(path, "rb") as file:
        created = client.post("/meshes", files={"file": (path.name, file)},
                              data={"name": path.stem}, timeout=timeout)
    if created.status_code != 202:
        raise RuntimeError(f"upload of {path.name} answered {created.status_code}: "
                           f"{created.text[:300]}")
    mesh_id = created.json()["id"]
    deadline = time.monotonic() + timeout
    while True:
        record = client.get(f"/meshes/{mesh_id}").json()
        if record["status"] == "ready":
            return mesh_id, record, time.perf_counter() - began
        if record["status"] == "failed" or time.monotonic() > deadline:
            raise RuntimeError(f"the build of {path.name} did not finish: {record}")
        time.sleep(0.25)


# ---- requests ------------------------------------------------------------------
def request_for(mesh_id: str, kind: str, target) -> tuple[str, dict]:
    if kind == "packet":
        return f"/meshes/{mesh_id}/splits", {"from": target[0], "to": target[1]}
    return f"/meshes/{mesh_id}/lod", {"vertices": target, "format": kind}


class LoopbackClient:
    """One keep-alive HTTP/1.1 connection for GETs, reading bodies into a scratch buffer.

    The load generator shares the two cores with the server. httpx spent about 4x
    the server's CPU reading megabyte bodies (2.9 s against 0.7 s for 120 levels
    of the 1.1M-face bunny), which inflated every latency it measured; reading
    with ``recv_into`` costs a tenth of that. Only the status and the size of a
    body are kept (its first bytes too on an error). Responses must carry a
    Content-Length, as the server's do.
    """

    def __init__(self, base: str):
        host, port = base.split("//", 1)[1].rsplit(":", 1)
        self.host, self.port = host, int(port)
        self.sock = None
        self.scratch = memoryview(bytearray(1 << 20))

    async def get(self, path: str, params: dict) -> tuple[int, int, bytes]:
        """(status, body length, the body's first 200 bytes)."""
        loop = asyncio.get_running_loop()
        if self.sock is None:
            self.sock = socket.create_connection((self.host, self.port))
            self.sock.setblocking(False)
        query = "&".join(f"{k}={v}" for k, v in params.items())
        request = f"GET {path}?{query} HTTP/1.1\r\nHost: {self.host}\r\n\r\n"
        await loop.sock_sendall(self.sock, request.encode())
        head = b""
        while b"\r\n\r\n" not in head:
            got = await loop.sock_recv_into(self.sock, self.scratch)
            if not got:
                raise ConnectionError("the server closed the connection")
            head += bytes(self.scratch[:got])
        head, body = head.split(b"\r\n\r\n", 1)
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        fields = dict(line.split(":", 1) for line in lines[1:])
        fields = {k.strip().lower(): v.strip() for k, v in fields.items()}
        length = int(fields["content-length"])
        first, seen = body[:200], len(body)
        while seen < length:
            got = await loop.sock_recv_into(self.sock, self.scratch[:min(len(self.scratch),
                                                                         length - seen)])
            if not got:
                raise ConnectionError("the server closed the connection mid-body")
            if len(first) < 200:
                first += bytes(self.scratch[:min(got, 200 - len(first))])
            seen += got
        return status, length, first

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None


async def run_phase(base: str, mesh_id: str, kind: str, targets: list, concurrency: int,
                    deadline: float, timeout: float) -> dict:
    """Send one request per target, ``concurrency`` at a time (one connection each);
    stop starting new ones at ``deadline``. Latency is send to last body byte, on
    the client."""
    latencies, sizes, errors = [], [], []
    queue = list(reversed(targets))

    async def worker():
        client = LoopbackClient(base)
        try:
            while queue and time.monotonic() < deadline:
                path, params = request_for(mesh_id, kind, queue.pop())
                began = time.perf_counter()
                try:
                    status, size, first = await asyncio.wait_for(client.get(path, params),
                                                                  timeout)
                except (OSError, asyncio.TimeoutError, ValueError, KeyError) as exc:
                    errors.append(f"{type(exc).__name__}: {exc}")
                    client.close()          # a fresh connection for the next one
                    continue
                elapsed = time.perf_counter() - began
                if status != 200:
                    errors.append(f"{status}: {first.decode(errors='replace')}")
                    continue
                latencies.append(elapsed)
                sizes.append(size)
        finally:
            client.close()

    began = time.perf_counter()
    await asyncio.gather(*(worker() for _ in range(concurrency)))
    wall = time.perf_counter() - began
    return summarize(latencies, sizes, errors, wall, asked=len(targets))


def summarize(latencies, sizes, errors, wall, asked) -> dict:
    ms = np.array(latencies) * 1000
    pct = (lambda q: round(float(np.percentile(ms, q)), 2)) if len(ms) else (lambda q: None)
    return {"asked": asked, "ok": len(latencies), "errors": len(errors),
            "error_samples": errors[:5], "wall_s": round(wall, 3),
            "throughput_rps": round(len(latencies) / wall, 2) if wall > 0 else None,
            "p50_ms": pct(50), "p90_ms": pct(90), "p99_ms": pct(99),
            "max_ms": round(float(ms.max()), 2) if len(ms) else None,
            "mean_bytes": int(np.mean(sizes)) if sizes else None}


def pick_targets(kind: str, n0: int, n: int, count: int, rng: random.Random,
                 taken: set) -> list:
    """``count`` distinct random targets of ``kind`` not in ``taken`` (and added to it)."""
    out = []
    levels = n - n0 + 1
    space = levels if kind != "packet" else levels * (levels - 1)
    count = min(count, space - len([t for t in taken if t[0] == kind]))
    while len(out) < count:
        if kind == "packet":
            a, b = rng.randint(n0, n), rng.randint(n0, n)
            if a == b:
                continue
            target = (a, b)
        else:
            target = rng.randint(n0, n)
        if (kind, target) not in taken:
            taken.add((kind, target))
            out.append(target)
    return out


# ---- packet sizes ----------------------------------------------------------------
def packet_sizes(client: httpx.Client, mesh_id: str, record: dict, counts: dict,
                 timeout: float) -> dict:
    """Bytes of the packets base -> full and back, per record and per stream,
    against the raw arrays and the full level's json and glb."""
    from lodserver.packets import decode_packet

    n0, n = record["base_vertices"], record["vertices"]
    splits = n - n0
    out = {"splits": splits, "vertices": n, "faces": record["faces"]}
    for name, (a, b) in (("forward", (n0, n)), ("backward", (n, n0))):
        began = time.perf_counter()
        response = client.get(f"/meshes/{mesh_id}/splits", params={"from": a, "to": b},
                              timeout=timeout)
        response.raise_for_status()
        seconds = time.perf_counter() - began
        packet = decode_packet(response.content)
        # each stream deflated alone: an attribution of the bytes (the packet
        # deflates them together, which is what "total" is)
        streams = {label: round(len(zlib.compress(stream, 9)) / splits, 3) if stream else 0.0
                   for label, stream in zip(STREAMS, packet.streams)}
        out[name] = {"bytes": len(response.content),
                     "bytes_per_split": round(len(response.content) / splits, 3),
                     "inflated_bytes_per_split": round(sum(map(len, packet.streams)) / splits, 3),
                     "stream_bytes_per_split": streams,
                     "bits": packet.grid.bits, "first_request_s": round(seconds, 3)}
    # coarser grids, which a client may ask for (``bits``): fewer bytes, larger rounding
    out["forward_bytes_per_split_by_bits"] = {}
    for bits in BITS_SWEEP:
        response = client.get(f"/meshes/{mesh_id}/splits",
                              params={"from": n0, "to": n, "bits": bits}, timeout=timeout)
        response.raise_for_status()
        out["forward_bytes_per_split_by_bits"][bits] = round(len(response.content) / splits, 3)
    for kind in ("json", "glb"):
        response = client.get(f"/meshes/{mesh_id}/lod", params={"vertices": n, "format": kind},
                              timeout=timeout)
        response.raise_for_status()
        out[f"{kind}_full_bytes_per_vertex"] = round(len(response.content) / n, 3)
    out["raw_bytes_per_vertex"] = round(counts["raw_bytes"] / counts["vertices"], 3)
    out["raw_zlib_bytes_per_vertex"] = round(counts["raw_zlib_bytes"] / counts["vertices"], 3)
    # dominant stream of the forward packet
    forward = out["forward"]["stream_bytes_per_split"]
    out["dominant_forward_stream"] = max(forward, key=forward.get)
    return out


def check_packets(client: httpx.Client, mesh_id: str, n0: int, n: int, rng: random.Random,
                  timeout: float, checks: int = 3) -> int:
    """A few short packets applied with the reference decoder land exactly on the
    LOD endpoint's json (so the numbers above are for right answers)."""
    from lodserver.packets import apply_packet, state_from_json

    top = min(n, n0 + 20_000)     # keep the json states small
    done = 0
    for _ in range(checks):
        a = rng.randint(n0, top)
        b = min(max(a + rng.randint(-2000, 2000), n0), n)
        def lod(v):
            return state_from_json(client.get(f"/meshes/{mesh_id}/lod", params={"vertices": v},
                                              timeout=timeout).json())
        data = client.get(f"/meshes/{mesh_id}/splits", params={"from": a, "to": b},
                          timeout=timeout).content
        state, expected = apply_packet(lod(a), data), lod(b)
        if not (np.array_equal(state.positions, expected.positions)
                and np.array_equal(state.faces, expected.faces)):
            raise RuntimeError(f"packet {a} -> {b} does not land on the LOD endpoint's level {b}")
        done += 1
    return done


# ---- the run -------------------------------------------------------------------
def bench_mesh(key: str, base: str, work: Path, args, deadline: float, rng: random.Random,
               server_pid: int) -> dict:
    path, counts = upload_file(key, work)
    result = {"mesh": key, "upload_bytes": path.stat().st_size, "input": counts}
    with httpx.Client(base_url=base) as client:
        mesh_id, record, seconds = upload(client, path, timeout=args.build_timeout)
        n0, n = record["base_vertices"], record["vertices"]
        result.update(id=mesh_id, upload_to_ready_s=round(seconds, 2),
                      record={k: record.get(k) for k in ("vertices", "faces", "base_vertices",
                                                         "base_faces")})
        print(f"{key}: {record['faces']:,} triangles, ready in {seconds:.1f} s", file=sys.stderr)
        taken: set = set()
        phases = {}
        # the very first request: artefact load + encoder kernels from the numba cache
        first = pick_targets("json", n0, n, 1, rng, taken)
        phases["first/json"] = asyncio.run(run_phase(base, mesh_id, "json", first, 1, deadline,
                                                     args.request_timeout))
        large = record["faces"] >= 500_000
        cold_n = args.cold_large if large else args.cold
        cached_n = args.cached_large if large else args.cached
        for kind in KINDS:
            cold = pick_targets(kind, n0, n, cold_n, rng, taken)
            cpu = _process_cpu_seconds(server_pid)
            stats = asyncio.run(run_phase(base, mesh_id, kind, cold, args.concurrency, deadline,
                                          args.request_timeout))
            after = _process_cpu_seconds(server_pid)
            stats["server_cpu_s"] = round(after - cpu, 2) if cpu is not None else None
            phases[f"cold/{kind}"] = stats
            # the most recent cold targets: the least likely to have left the LRU cache
            hot = cold[-args.hot:] if args.hot else []
            hot_requests = [rng.choice(hot) for _ in range(cached_n)] if hot else []
            cached = asyncio.run(run_phase(base, mesh_id, kind, hot_requests, args.concurrency,
                                           deadline, args.request_timeout))
            cached["hot_set"] = len(hot)
            cached["hot_set_bytes_est"] = (cached["mean_bytes"] or 0) * len(hot)
            cached["hot_set_fits_cache"] = cached["hot_set_bytes_est"] <= CACHE_BYTES
            phases[f"cached/{kind}"] = cached
            # one at a time: the latency of a cached answer without queueing behind others
            serial = asyncio.run(run_phase(base, mesh_id, kind, hot_requests[:args.serial], 1,
                                           deadline, args.request_timeout))
            phases[f"cached-serial/{kind}"] = serial
            print(f"  {kind}: cold p99 {stats['p99_ms']} ms, cached p99 {cached['p99_ms']} ms",
                  file=sys.stderr)
        result["phases"] = phases
        if time.monotonic() < deadline:
            result["packet_sizes"] = packet_sizes(client, mesh_id, record, counts,
                                                  args.request_timeout)
            result["packets_checked_exact"] = check_packets(client, mesh_id, n0, n, rng,
                                                            args.request_timeout)
    return result


def tables(results: list[dict]) -> str:
    lines = ["| mesh | phase | kind | ok/asked | req/s | p50 ms | p99 ms | max ms | KiB/resp |",
             "|---|---|---|---|---|---|---|---|---|"]
    for mesh in results:
        for name, s in mesh.get("phases", {}).items():
            phase, kind = name.split("/")
            kib = f"{s['mean_bytes'] / 1024:,.0f}" if s["mean_bytes"] is not None else "-"
            lines.append(f"| {mesh['mesh']} | {phase} | {kind} | {s['ok']}/{s['asked']} | "
                         f"{s['throughput_rps']} | {s['p50_ms']} | {s['p99_ms']} | {s['max_ms']} | "
                         f"{kib} |")
    lines += ["", ("| mesh | splits | bits | forward B/split | backward B/split | "
                   "position | vertex | pattern+other | count | fan+mask | raw f32+i32 B/vertex | "
                   "raw zlib | json full | glb full |"),
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for mesh in results:
        p = mesh.get("packet_sizes")
        if not p:
            continue
        f = p["forward"]["stream_bytes_per_split"]
        lines.append(
            f"| {mesh['mesh']} | {p['splits']:,} | {p['forward']['bits']} | "
            f"{p['forward']['bytes_per_split']} | {p['backward']['bytes_per_split']} | "
            f"{f['position']} | {f['vertex']} | {round(f['pattern'] + f['other'], 3)} | "
            f"{f['count']} | {round(f['fan'] + f['mask'], 3)} | {p['raw_bytes_per_vertex']} | "
            f"{p['raw_zlib_bytes_per_vertex']} | {p['json_full_bytes_per_vertex']} | "
            f"{p['glb_full_bytes_per_vertex']} |")
    sweep = [m for m in results if m.get("packet_sizes")]
    if sweep:
        lines += ["", "| mesh | forward B/split at bits: " + " | ".join(
            f"{b}" for b in (*BITS_SWEEP, "default")) + " |",
            "|---|" + "---|" * (len(BITS_SWEEP) + 1)]
        for mesh in sweep:
            p = mesh["packet_sizes"]
            values = [p["forward_bytes_per_split_by_bits"][b] for b in BITS_SWEEP]
            values.append(f"{p['forward']['bytes_per_split']} ({p['forward']['bits']})")
            lines.append(f"| {mesh['mesh']} | " + " | ".join(map(str, values)) + " |")
    return "\n".join(lines)


def verdicts(results: list[dict]) -> dict:
    """The issue's targets, checked against what was measured."""
    out = {}
    for mesh in results:
        phases = mesh.get("phases", {})
        if mesh["record"]["faces"] >= 1_000_000:
            for phase in ("cold", "cached", "cached-serial"):
                worst = max((phases[f"{phase}/{k}"]["p99_ms"] or float("inf"))
                            for k in ("json", "glb") if f"{phase}/{k}" in phases)
                out[f"{mesh['mesh']}: LOD p99 < 100 ms ({phase})"] = {
                    "p99_ms": worst, "met": worst < 100}
        p = mesh.get("packet_sizes")
        if p:
            value = p["forward"]["bytes_per_split"]
            out[f"{mesh['mesh']}: packets < 8 B/split (geometry only)"] = {
                "bytes_per_split": value, "met": value < 8}
    return out


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", default=",".join(MESHES),
                        help=f"comma-separated, of {', '.join(MESHES)}")
    parser.add_argument("--quick", action="store_true",
                        help="stanford-bunny only, fewer requests")
    parser.add_argument("--concurrency", type=int, default=8)
    parser.add_argument("--cold", type=int, default=40,
                        help="distinct first-time targets per kind (meshes under 500k faces)")
    parser.add_argument("--cached", type=int, default=400,
                        help="requests over the hot set per kind (meshes under 500k faces)")
    parser.add_argument("--cold-large", type=int, default=12)
    parser.add_argument("--cached-large", type=int, default=200)
    parser.add_argument("--hot", type=int, default=4, help="targets in the hot set")
    parser.add_argument("--serial", type=int, default=50,
                        help="cached requests sent one at a time, per kind")
    parser.add_argument("--request-timeout", type=float, default=180)
    parser.add_argument("--build-timeout", type=float, default=600)
    parser.add_argument("--max-seconds", type=float, default=1200,
                        help="no request starts after this many seconds")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.meshes, args.cold, args.cached = "stanford-bunny", 16, 160
    args.meshes = [m for m in args.meshes.split(",") if m]
    unknown = [m for m in args.meshes if m not in MESHES]
    if unknown:
        parser.error(f"unknown meshes: {', '.join(unknown)}")
    if args.out is None:
        args.out = OUT / ("load-quick.json" if args.quick else "load.json")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    rng = random.Random(args.seed)
    deadline = time.monotonic() + args.max_seconds
    args.out.parent.mkdir(parents=True, exist_ok=True)
    document = {"machine": machine_info(PACKAGES), "settings": {
        k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "results": []}
    with tempfile.TemporaryDirectory(prefix="lodserver-load-") as folder:
        work = Path(folder)
        with server_process(work / "data", log=work / "server.log", warm_kernels=True,
                            timeout=120) as (base, process):
            for key in args.meshes:
                if time.monotonic() > deadline:
                    print(f"{key}: skipped, the run's deadline has passed", file=sys.stderr)
                    break
                try:
                    result = bench_mesh(key, base, work, args, deadline, rng, process.pid)
                except Exception as exc:  # noqa: BLE001 (one mesh failing still writes the others)
                    result = {"mesh": key, "failed": f"{type(exc).__name__}: {exc}"}
                    print(f"{key}: failed: {exc}", file=sys.stderr)
                document["results"].append(result)
                document["machine"]["load_average_at_end"] = os.getloadavg()
                document["verdicts"] = verdicts([r for r in document["results"]
                                                 if "failed" not in r])
                args.out.write_text(json.dumps(document, indent=2))
            if process.poll() is not None:
                document["server_exit_code"] = process.returncode
    print(tables([r for r in document["results"] if "failed" not in r]))
    print()
    for name, verdict in document.get("verdicts", {}).items():
        print(f"{'met ' if verdict['met'] else 'NOT met'}  {name}: "
              f"{verdict.get('p99_ms', verdict.get('bytes_per_split'))}")
    print(f"\nwritten {args.out}")
    return 0 if all("failed" not in r for r in document["results"]) else 1


if __name__ == "__main__":
    sys.exit(main())
