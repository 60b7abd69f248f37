"""Level latency of a server sharing an object store: cold (artefact fetched from
S3), warm (from its local artefact cache), hot (in memory), against the embedded
default (SQLite and files in one data directory).

What it does, all on loopback, in one run so the figures compare side by side:

1. starts moto's S3 server (or uses ``LODSERVER_TEST_S3_ENDPOINT``) and a bucket;
2. server A (``LODSERVER_STORE_URL=s3://...``, a shared catalogue: SQLite file
   both servers open, or ``--catalog postgresql://...``) builds the meshes; an
   embedded server E (defaults) builds the same meshes in its own directory;
3. per round, for each mesh, three requests of levels not asked before (so no
   body cache answers; ``format=glb``, ``vertices=`` a fresh count each time):
   - ``B cold``: a second server B on a fresh data directory, first level of the
     mesh: catalogue row, artefact fetched from S3 into B's cache, decoded, encoded;
   - ``B hot``: another level from B right after (the mesh is in memory);
   - ``B warm``: B restarted on the same directory, first level: the artefact
     read from B's local cache (no S3 request), decoded, encoded;
   - ``E first`` / ``E hot``: E restarted, its first level (artefact read from
     its data directory, decoded, encoded), then another;
   every server start first asks for a level of two small meshes (the textured
   sample, fandisk), so that loading the compiled kernels is not counted against
   the mesh timed;
4. the blob layer alone: ``get_file`` of each artefact from S3, and a hit of the
   local cache (``ArtefactCache.path``), timed in this process.

Times are medians over ``--rounds`` (wall clock of one request, httpx on
loopback, the 2 cores shared with the servers and moto).

    python bench/shared_latency.py              # stanford-bunny and its Loop subdivision (~8 min)
    python bench/shared_latency.py --quick      # stanford-bunny only, 3 rounds

Writes ``bench/out/shared_latency.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
import uuid
from contextlib import ExitStack
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.server import server_process, upload_and_wait  # noqa: E402
from tests.services.s3 import CREDENTIALS, s3_environment, start_moto, stop_moto  # noqa: E402

MESH_DIR = ROOT.parent / "shared" / "meshes"
# asked for first at every server start: the encoder's and decoder's compiled
# kernels (textured and plain signatures) are loaded then, not on the mesh timed
WARM_UP = {"spot": ROOT / "tests" / "data" / "spot.obj", "fandisk": None}
OUT = ROOT / "bench" / "out"


def mesh_files(work: Path, quick: bool) -> dict[str, Path]:
    """name -> file to upload: stanford-bunny (69k faces), and unless ``quick`` the
    bunny Loop-subdivided once (277k faces) as a binary PLY."""
    bunny = MESH_DIR / "stanford-bunny.obj"
    if not bunny.is_file():
        sys.exit(f"this benchmark needs {bunny} (the shared meshes)")
    files = {"stanford-bunny": bunny}
    if not quick:
        import trimesh

        from lodserver.io import clean_mesh, load_mesh, save_mesh

        mesh, _ = load_mesh(bunny)
        positions, faces = trimesh.remesh.subdivide_loop(mesh.positions, mesh.faces,
                                                         iterations=1)
        mesh, _ = clean_mesh(positions, faces)
        files["bunny_loop1"] = work / "bunny_loop1.ply"
        save_mesh(mesh, files["bunny_loop1"], file_type="ply")
    return files


class Levels:
    """Fresh vertex counts per mesh: every request asks for a level never asked before."""

    def __init__(self, meshes: dict[str, dict]):
        self.next = {name: body["vertices"] - 1 for name, body in meshes.items()}

    def take(self, name: str) -> int:
        self.next[name] -= 7
        return self.next[name]


def timed_level(base: str, mesh_id: str, vertices: int) -> float:
    """Seconds for one glb level (a new connection: what a CDN miss costs)."""
    start = time.perf_counter()
    response = httpx.get(f"{base}/meshes/{mesh_id}/lod",
                         params={"vertices": vertices, "format": "glb"}, timeout=300)
    elapsed = time.perf_counter() - start
    if response.status_code != 200:
        raise RuntimeError(f"level {vertices} of {mesh_id}: {response.status_code} "
                           f"{response.text[:300]}")
    return elapsed


def warm_up(base: str, ids: dict, levels: Levels) -> None:
    for name in WARM_UP:
        timed_level(base, ids[name], levels.take(name))


def run(args) -> dict:
    work = Path(tempfile.mkdtemp(prefix="shared-latency-"))
    results: dict = {"rounds": args.rounds, "meshes": {}, "catalog": None}
    with ExitStack() as stack:
        stack.callback(shutil.rmtree, work, ignore_errors=True)
        endpoint = os.environ.get("LODSERVER_TEST_S3_ENDPOINT")
        if not endpoint:
            process, endpoint = start_moto()
            stack.callback(stop_moto, process)
        import boto3

        bucket = f"lodserver-bench-{uuid.uuid4().hex[:12]}"
        boto3.client("s3", endpoint_url=endpoint, aws_access_key_id="testing",
                     aws_secret_access_key="testing",
                     region_name=CREDENTIALS["AWS_DEFAULT_REGION"]).create_bucket(Bucket=bucket)
        catalog = args.catalog or f"sqlite:///{work / 'shared-catalogue.sqlite3'}"
        results["catalog"] = catalog.split(":", 1)[0]
        shared = {**s3_environment(endpoint), "LODSERVER_STORE_URL": f"s3://{bucket}/lods",
                  "LODSERVER_CATALOG_URL": catalog}
        files = mesh_files(work, args.quick)

        # A builds into the shared store; E builds the same into its own directory
        ids = {"shared": {}, "embedded": {}}
        bodies = {}
        for kind, env in (("shared", shared), ("embedded", {})):
            with server_process(work / f"{kind}-builder", env=env, timeout=120) as (base, _), \
                    httpx.Client(base_url=base, timeout=300) as client:
                for name, path in WARM_UP.items():
                    body = upload_and_wait(client, path or MESH_DIR / f"{name}.obj")
                    ids[kind][name], bodies[name] = body["id"], body
                for name, path in files.items():
                    body = upload_and_wait(client, path)
                    ids[kind][name], bodies[name] = body["id"], body
        embedded_dir = work / "embedded-builder"
        levels = Levels(bodies)
        samples = {name: {key: [] for key in ("B cold", "B hot", "B warm", "E first", "E hot")}
                   for name in files}

        for round_ in range(args.rounds):
            data = work / f"b-{round_}"
            with server_process(data, env=shared, timeout=120) as (base, _):
                warm_up(base, ids["shared"], levels)
                for name in files:
                    mesh_id = ids["shared"][name]
                    samples[name]["B cold"].append(timed_level(base, mesh_id, levels.take(name)))
                    samples[name]["B hot"].append(timed_level(base, mesh_id, levels.take(name)))
            with server_process(data, env=shared, timeout=120) as (base, _):
                warm_up(base, ids["shared"], levels)
                for name in files:
                    samples[name]["B warm"].append(timed_level(base, ids["shared"][name],
                                                               levels.take(name)))
            with server_process(embedded_dir, timeout=120) as (base, _):
                warm_up(base, ids["embedded"], levels)
                for name in files:
                    mesh_id = ids["embedded"][name]
                    samples[name]["E first"].append(timed_level(base, mesh_id,
                                                                levels.take(name)))
                    samples[name]["E hot"].append(timed_level(base, mesh_id, levels.take(name)))
            print(f"round {round_ + 1}/{args.rounds} done", flush=True)

        results["blob_layer"] = blob_layer(endpoint, bucket, shared, work, args.rounds)
        for name in files:
            results["meshes"][name] = {
                "faces": bodies[name]["faces"],
                "median_ms": {key: round(1000 * statistics.median(values), 1)
                              for key, values in samples[name].items()},
                "all_ms": {key: [round(1000 * v, 1) for v in values]
                           for key, values in samples[name].items()}}
    return results


def blob_layer(endpoint: str, bucket: str, shared: dict, work: Path, rounds: int) -> dict:
    """Medians (ms) of fetching each artefact from S3 and of a cache hit, in-process."""
    os.environ.update({key: value for key, value in shared.items() if value})
    from lodserver.service.blobs import open_blobs
    from lodserver.service.cache import ArtefactCache

    blobs = open_blobs(shared["LODSERVER_STORE_URL"])
    out = {}
    for key in blobs.keys("artefacts"):
        size = blobs.size(key)
        fetches, hits = [], []

        def fetch(dest, key=key):
            blobs.get_file(key, dest)

        for round_ in range(max(rounds, 3)):
            cache = ArtefactCache(work / f"cache-{round_}", 2**32)
            start = time.perf_counter()
            cache.path(key, fetch)
            fetches.append(time.perf_counter() - start)
            start = time.perf_counter()
            cache.path(key, fetch)
            hits.append(time.perf_counter() - start)
        out[f"{size / 2**20:.1f} MiB"] = {
            "s3_fetch_ms": round(1000 * statistics.median(fetches), 1),
            "cache_hit_ms": round(1000 * statistics.median(hits), 3)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="stanford-bunny only, 3 rounds")
    parser.add_argument("--rounds", type=int, default=None, help="rounds (default 5; quick 3)")
    parser.add_argument("--catalog", help="a postgresql:// catalogue URL to share instead of "
                        "a SQLite file")
    args = parser.parse_args()
    args.rounds = args.rounds or (3 if args.quick else 5)
    results = run(args)
    OUT.mkdir(parents=True, exist_ok=True)
    out = OUT / "shared_latency.json"
    out.write_text(json.dumps(results, indent=2) + "\n")
    keys = ("B cold", "B warm", "B hot", "E first", "E hot")
    print(f"\nmedian ms over {args.rounds} rounds (one glb level, fresh each time; "
          f"catalogue: {results['catalog']})")
    print(f"{'mesh':<16}{'faces':>9}" + "".join(f"{key:>10}" for key in keys))
    for name, row in results["meshes"].items():
        print(f"{name:<16}{row['faces']:>9}" + "".join(f"{row['median_ms'][key]:>10}"
                                                        for key in keys))
    print("\nblob layer alone (in-process):")
    for size, row in results["blob_layer"].items():
        print(f"  artefact {size:>9}: S3 fetch {row['s3_fetch_ms']} ms, "
              f"cache hit {row['cache_hit_ms']} ms")
    print(f"\nwritten to {out}")


if __name__ == "__main__":
    main()
