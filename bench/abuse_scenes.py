"""Scene abuse benchmark: the hostile scenes of issue 23 against one real ``lodserver serve``.

Small uploads whose cost sits in data that triangle counts do not see, written by
``tests/hostile_files.py`` (the same generators the tests use):

a. ``instances``: a 162-triangle grid drawn by ``--instances`` (5M) translations of
   ``EXT_mesh_gpu_instancing`` (60 MB);
b. ``animation-aliases``: 60 animation outputs, accessors over one 12 MB bufferView
   (15 MB);
c. ``morph-aliases``: 255 morph targets naming one accessor, on a 10k-vertex grid
   (480 KB).

For each, against one server (a checkout given by ``--repo``, so a base and a merge
can be compared): the upload's status, then (when accepted) its build, then a burst
of concurrent distinct reads: 4 scene levels (``format=glb``), 8 json levels of
part 0 and one chain. Per case it reports the statuses, the serve process's peak
RSS growth over its RSS before the case (``VmHWM``, reset through
``/proc/<pid>/clear_refs`` before the upload and again before the burst), the
artefact's size over the upload's, and times. The parse workers are processes of
their own, under their own memory limit, and not counted.

Targets: peak growth under 512 MB per hostile file (or its 4xx), artefacts at most
20 times the upload.

Bounded: loopback only, one upload and a fixed number of requests per case, a
timeout per request and per build; each mesh is deleted after its case and the
server is stopped at the end whatever happens.

    python bench/abuse_scenes.py                            # this checkout
    python bench/abuse_scenes.py --repo /tmp/merged --label merged

Writes ``bench/out/abuse_scenes-<label>.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import httpx

# abuse_runs puts the checkout on sys.path, for the tests.* imports after it
from abuse_runs import ROOT, checkout_server, result_file
from machine import process_memory_kib, reset_memory_peak
from tests.hostile_files import aliased_animation_glb, aliased_morph_glb, instanced_glb

MB = 1e6
GROWTH_TARGET_MB = 512
ARTEFACT_TARGET = 20



class Peak:
    """The serve process's peak RSS from now on: VmHWM after a reset, else sampled."""

    def __init__(self, pid: int):
        self.pid = pid
        time.sleep(0.5)                         # let freed memory of the last step settle
        self.before = process_memory_kib(pid)["VmRSS"]
        self.reset = reset_memory_peak(pid)
        self.samples = [self.before]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._sample, daemon=True)
        self.thread.start()

    def _sample(self):
        while not self.stop.wait(0.05):
            try:
                self.samples.append(process_memory_kib(self.pid)["VmRSS"])
            except OSError:
                return

    def growth_mb(self) -> float:
        self.stop.set()
        self.thread.join()
        peak = max(self.samples)
        if self.reset:
            peak = max(peak, process_memory_kib(self.pid)["VmHWM"])
        return round((peak - self.before) * 1024 / MB, 1)


def wait_built(client: httpx.Client, mesh_id: str, timeout: float) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        body = client.get(f"/meshes/{mesh_id}").json()
        if body["status"] in ("ready", "failed") or time.monotonic() > deadline:
            return body
        time.sleep(0.5)


def burst(base: str, requests: list[tuple[str, dict]], timeout: float) -> dict:
    """Every request at once, each on its own connection: statuses, bytes, wall time."""
    results = [None] * len(requests)

    def one(i, path, params):
        try:
            with httpx.Client(base_url=base, timeout=timeout) as client:
                response = client.get(path, params=params)
                results[i] = (str(response.status_code), len(response.content))
        except httpx.HTTPError as exc:
            results[i] = (type(exc).__name__, 0)

    began = time.perf_counter()
    threads = [threading.Thread(target=one, args=(i, *request))
               for i, request in enumerate(requests)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout + 30)
    return {"statuses": dict(Counter(r[0] if r else "unfinished" for r in results)),
            "ok_bytes_max": max((r[1] for r in results if r and r[0] == "200"), default=0),
            "wall_s": round(time.perf_counter() - began, 2)}


def reads(mesh_id: str) -> list[tuple[str, dict]]:
    scene = [(f"/meshes/{mesh_id}/lod", {"ratio": r, "format": "glb"})
             for r in (1.0, 0.5, 0.25, 0.125)]
    parts = [(f"/meshes/{mesh_id}/parts/0/lod", {"ratio": r})
             for r in (1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3)]
    return scene + parts + [(f"/meshes/{mesh_id}/chain", {"lods": "1,0.5,0.25"})]


def run_case(base: str, pid: int, data: Path, name: str, content: bytes, args) -> dict:
    result = {"case": name, "upload_bytes": len(content)}
    print(f"{name}: uploading {len(content) / MB:.1f} MB", file=sys.stderr)
    peak = Peak(pid)
    began = time.perf_counter()
    with httpx.Client(base_url=base, timeout=args.request_timeout) as client:
        try:
            created = client.post("/meshes", files={"file": (f"{name}.glb", content)})
        except httpx.HTTPError as exc:
            result.update(upload_status=type(exc).__name__,
                          upload_growth_mb=peak.growth_mb())
            return result
        result["upload_status"] = created.status_code
        if created.status_code != 202:
            result.update(upload_message=created.json().get("message"),
                          upload_growth_mb=peak.growth_mb(),
                          upload_s=round(time.perf_counter() - began, 1))
            return result
        mesh_id = created.json()["id"]
        try:
            body = wait_built(client, mesh_id, args.build_timeout)
            result.update(build_status=body["status"], failure=body.get("failure"),
                          build_s=round(time.perf_counter() - began, 1),
                          upload_growth_mb=peak.growth_mb())
            if body["status"] == "ready":
                result["faces"] = body.get("faces")
                artefacts = list((data / "artefacts").glob(f"{mesh_id}.*.pm"))
                if artefacts:
                    size = artefacts[0].stat().st_size
                    result.update(artefact_bytes=size,
                                  artefact_ratio=round(size / len(content), 2))
                peak = Peak(pid)
                result["reads"] = burst(base, reads(mesh_id), args.request_timeout)
                result["reads_growth_mb"] = peak.growth_mb()
        finally:
            client.delete(f"/meshes/{mesh_id}")
    growths = [result.get(k) for k in ("upload_growth_mb", "reads_growth_mb")]
    result["met"] = (max(g for g in growths if g is not None) < GROWTH_TARGET_MB
                     and result.get("artefact_ratio", 0) <= ARTEFACT_TARGET)
    print(f"  {json.dumps(result)}", file=sys.stderr)
    return result


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repo", type=Path, default=ROOT, help="the checkout to serve")
    parser.add_argument("--label", default="current")
    parser.add_argument("--instances", type=int, default=5_000_000)
    parser.add_argument("--cases", default="instances,animation-aliases,morph-aliases")
    parser.add_argument("--request-timeout", type=float, default=300)
    parser.add_argument("--build-timeout", type=float, default=600)
    return parser.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    makers = {"instances": lambda: instanced_glb(args.instances),
              "animation-aliases": lambda: aliased_animation_glb(60, 12),
              "morph-aliases": lambda: aliased_morph_glb(255)}
    out = result_file("abuse_scenes", args.label)
    document = {"repo": str(args.repo), "results": []}
    with tempfile.TemporaryDirectory(prefix="lodserver-abuse-scenes-") as folder:
        work = Path(folder)
        with checkout_server(args.repo, work / "data", work / "server.log", warm_kernels=True,
                             timeout=180) as (base, process):
            for name in args.cases.split(","):
                document["results"].append(run_case(base, process.pid, work / "data", name,
                                                    makers[name](), args))
                out.write_text(json.dumps(document, indent=2))
            document["server_exit_code"] = process.poll()
    out.write_text(json.dumps(document, indent=2))
    print("| case | upload MB | upload | build | growth upload+build MB | artefact / upload | "
          "reads | growth reads MB | met |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in document["results"]:
        print(f"| {r['case']} | {r['upload_bytes'] / MB:.2f} | {r['upload_status']} | "
              f"{r.get('build_status', '-')} {r.get('build_s', '')} s | "
              f"{r.get('upload_growth_mb')} | {r.get('artefact_ratio', '-')} | "
              f"{(r.get('reads') or {}).get('statuses', '-')} | {r.get('reads_growth_mb', '-')} | "
              f"{r.get('met')} |")
    print(f"\ntargets: growth < {GROWTH_TARGET_MB} MB, artefact <= {ARTEFACT_TARGET}x upload; "
          f"written {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
