"""The object store unreachable for a minute under load (issue 23, 7d), counted.

One ``lodserver serve`` on a PostgreSQL cluster of its own and moto's S3
behind a TCP gate (``tests/services/gate.py``); uploads of the textured sample
and level requests over two ready meshes (read from the store each time: one
loaded mesh, no artefact cache) run in a loop while the gate resets every
connection to the store for ``--outage`` seconds. The loop is the one of
``tests/api/test_store_outage.py`` (:class:`StoreLoad`).

Prints the answers by kind and status (``reset`` for a failed connection),
then, once every accepted upload is settled: how many ended ready or failed,
the builds' claims (a build stopped by the outage went back to the queue and
was claimed again), and the orphan check (each bucket key has a row, each
ready row its object).

    python bench/chaos_store.py              # a 60 s outage
    python bench/chaos_store.py --outage 10
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
import uuid
from collections import Counter
from pathlib import Path
from urllib.parse import urlsplit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lodserver.service.catalog import open_catalog  # noqa: E402
from tests.api.test_store_outage import (READS_FROM_STORE, run_outage,  # noqa: E402
                                         upload_readable, wait_all_ready)
from tests.server import serve  # noqa: E402
from tests.service.test_chaos import _check_no_orphans, _env, _keys  # noqa: E402
from tests.services.gate import Gate  # noqa: E402
from tests.services.postgres import _start_cluster  # noqa: E402
from tests.services.s3 import (_boto_credentials, _remove_bucket, start_moto,  # noqa: E402
                               stop_moto)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--outage", type=float, default=60.0,
                        help="seconds the store is cut off (default 60)")
    args = parser.parse_args()

    import boto3

    folder = Path(tempfile.mkdtemp(prefix="lodserver-chaos-store-"))
    pg_folder = Path(tempfile.mkdtemp(prefix="lodserver-pg-"))
    moto, endpoint = start_moto()
    stop_pg = None
    try:
        url, stop_pg, _ = _start_cluster(pg_folder)
        where = urlsplit(endpoint)
        gate = Gate((where.hostname, where.port))
        s3 = boto3.client("s3", endpoint_url=endpoint, **_boto_credentials())
        bucket = f"lodserver-chaos-{uuid.uuid4().hex[:12]}"
        s3.create_bucket(Bucket=bucket)
        env = _env(url, f"s3://{bucket}/prefix", gate.endpoint, **READS_FROM_STORE)
        with serve(folder / "a", env=env, timeout=120, log=folder / "server.log") as client:
            readable = upload_readable(client)
            wait_all_ready(client, readable)
            started = time.monotonic()
            load = run_outage(client, gate, outage=args.outage, readable=readable)
            took = time.monotonic() - started
            settled_at = time.monotonic()
            bodies = wait_all_ready(client, load.accepted)
            settled = time.monotonic() - settled_at
        print(f"store cut off for {args.outage:g} s, load ran {took:.0f} s "
              f"(gate refused {gate.refused} connections)")
        for (kind, status), count in sorted(load.counts.items(), key=str):
            print(f"  {kind:6} {status!s:8} {count}")
        if load.problems:
            print("  problems:", *load.problems, sep="\n    ")
        ends = Counter(body["status"] for body in bodies.values())
        print(f"accepted uploads: {len(load.accepted)}, settled {settled:.0f} s after the "
              f"load stopped: {dict(ends)}")
        catalog = open_catalog(url, data_dir=folder)
        try:
            rows, _ = catalog._run("SELECT attempt FROM meshes")
            print(f"claims per build: {dict(sorted(Counter(row[0] for row in rows).items()))}")
            try:
                _check_no_orphans(catalog, _keys(s3, bucket))
                print("orphan check: passed (each object has its row, each ready row its "
                      "object)")
            except AssertionError as exc:
                print(f"orphan check: FAILED: {exc}")
        finally:
            catalog.close()
        gate.close()
        _remove_bucket(s3, bucket)
    finally:
        if stop_pg is not None:
            subprocess.run(stop_pg, capture_output=True)
        stop_moto(moto)
        shutil.rmtree(pg_folder, ignore_errors=True)
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
