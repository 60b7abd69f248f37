"""Zip amplification benchmark: the disk one small zip makes a real server use.

Against one ``lodserver serve`` process on 127.0.0.1 (a checkout given by
``--repo``, so two trees can be compared): a zip of ``spot.obj`` (from
tests/data) and ``--entries`` entries of 1 MiB, each 11,000 random bytes then
zeros (about 80:1 deflated: within every ratio and size rule of the defaults),
is uploaded once and built. Meanwhile the data directory is walked every
50 ms; reported are the peak growth of the whole directory and of
``sources/`` over the state before the upload, the bytes the server and its
parse workers passed to ``write()`` (``wchar`` of ``/proc/<pid>/io``) during
the upload and build, and the seconds to the answer and to the build's end.
A first small upload starts the parse worker, so its start is not counted.

Bounded: every request has a timeout, the server is stopped and the data
directory removed whatever happens. Only 127.0.0.1 is contacted.

    python bench/abuse_zip.py                            # this checkout
    python bench/abuse_zip.py --repo /tmp/base --label before

Writes ``bench/out/abuse_zip-<label>.json`` and prints it.
"""

from __future__ import annotations

import argparse
import os
import random
import shutil
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import httpx

# abuse_runs puts the checkout on sys.path, for the tests.* imports after it
from abuse_runs import ROOT, peaks, report
from tests.server import server_process

SPOT = ROOT / "tests" / "data" / "spot.obj"
MIB = 2**20
RANDOM_BYTES = 11_000
TIMEOUT_S = 600


def make_zip(path: Path, entries: int) -> None:
    rng = random.Random(1)
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("spot.obj", SPOT.read_bytes())
        for at in range(entries):
            archive.writestr(f"junk/{at:04d}.bin", rng.randbytes(RANDOM_BYTES)
                             + bytes(MIB - RANDOM_BYTES))


def tree_bytes(root: Path) -> tuple[int, int]:
    """(bytes of every file under root, bytes under root/sources)."""
    total = sources = 0
    for folder, _, files in os.walk(root):
        for name in files:
            try:
                size = os.lstat(os.path.join(folder, name)).st_size
            except OSError:
                continue        # removed while walking
            total += size
            if Path(folder).name == "sources":
                sources += size
    return total, sources


def written(pid: int) -> int:
    """``wchar`` of the process and its children (the parse workers)."""
    pids = [pid]
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            pids += [int(child) for child in (task / "children").read_text().split()]
        except OSError:
            pass
    total = 0
    for each in pids:
        try:
            lines = Path(f"/proc/{each}/io").read_text().splitlines()
        except OSError:
            continue
        total += next(int(line.split()[1]) for line in lines if line.startswith("wchar"))
    return total


def wait_built(client: httpx.Client, mesh_id: str) -> str:
    deadline = time.monotonic() + TIMEOUT_S
    while (status := client.get(f"/meshes/{mesh_id}").json()["status"]) not in (
            "ready", "failed"):
        if time.monotonic() > deadline:
            raise RuntimeError(f"mesh {mesh_id} not built in {TIMEOUT_S} s")
        time.sleep(0.2)
    return status


def run(repo: Path, entries: int) -> dict:
    work = Path(tempfile.mkdtemp(prefix="abuse-zip-"))
    try:
        archive = work / "junk.zip"
        make_zip(archive, entries)
        data = work / "data"
        with server_process(data, log=work / "server.log", timeout=120, cwd=repo) as (
                base, process), httpx.Client(base_url=base, timeout=TIMEOUT_S) as client:
            first = client.post("/meshes", files={"file": ("spot.obj", SPOT.read_bytes())})
            wait_built(client, first.json()["id"])
            before, _ = tree_bytes(data)
            written_before = written(process.pid)
            with peaks(lambda: tree_bytes(data), every=0.05) as peak:
                started = time.monotonic()
                with open(archive, "rb") as file:
                    answer = client.post("/meshes", files={"file": ("junk.zip", file)})
                answered = time.monotonic() - started
                status = (wait_built(client, answer.json()["id"])
                          if answer.status_code == 202 else None)
                built = time.monotonic() - started
            return {"zip_bytes": archive.stat().st_size, "entries": entries + 1,
                    "unpacked_bytes": entries * MIB + SPOT.stat().st_size,
                    "answer": answer.status_code, "build": status,
                    "answered_s": round(answered, 2), "built_s": round(built, 2),
                    "peak_data_dir_growth_bytes": peak[0] - before,
                    "peak_sources_bytes": peak[1],
                    "written_bytes": written(process.pid) - written_before}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repo", type=Path, default=ROOT, help="checkout to serve")
    parser.add_argument("--label", default="head")
    parser.add_argument("--entries", type=int, default=1000, help="1 MiB entries (at most "
                        "1023 under the default entry limit)")
    args = parser.parse_args(argv)
    result = {"label": args.label, "repo": str(args.repo), **run(args.repo, args.entries)}
    report("abuse_zip", args.label, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
