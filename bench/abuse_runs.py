"""What the abuse benchmarks (``abuse_upload.py``, ``abuse_zip.py``,
``abuse_scenes.py``) share: a ``lodserver serve`` of the checkout under test,
a sampler of the peaks of what the server uses while a step runs, and the
labelled result file each writes, so that runs of two checkouts (``--repo``,
``--label``) sit side by side in ``bench/out/``."""

from __future__ import annotations

import contextlib
import json
import sys
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
from tests.server import server_process  # noqa: E402

OUT = ROOT / "bench" / "out"


def checkout_server(repo: Path, data: Path, log: Path, env: dict | None = None, **options):
    """``lodserver serve`` from ``repo`` (its own package first on sys.path, for
    the server and the processes it starts), storing in ``data``, its output in
    ``log``; a context manager yielding (base URL, process). ``options`` go to
    ``tests.server.server_process`` (``timeout`` 120 s unless given)."""
    options.setdefault("timeout", 120)
    return server_process(data, log=log, cwd=repo,
                          env={"PYTHONPATH": str(repo), **(env or {})}, **options)


@contextlib.contextmanager
def peaks(measure, every: float):
    """Call ``measure()`` (a tuple of numbers) at once and then every ``every``
    seconds, in a thread of its own, while the block runs; yields the list of
    each number's largest value so far, final once the block has ended."""
    peak, stop = [], threading.Event()

    def sample():
        while True:
            values = measure()
            peak[:] = [max(old, new) for old, new in zip(peak, values)] if peak else values
            if stop.wait(every):
                return

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        yield peak
    finally:
        stop.set()
        sampler.join()


def result_file(name: str, label: str) -> Path:
    """``bench/out/<name>-<label>.json`` (the folder made if missing)."""
    OUT.mkdir(parents=True, exist_ok=True)
    return OUT / f"{name}-{label}.json"


def report(name: str, label: str, result: dict) -> None:
    """Write ``result`` to :func:`result_file` as indented JSON and print it."""
    text = json.dumps(result, indent=2)
    result_file(name, label).write_text(text)
    print(text)
