"""How fast packets decode: the browser decoder in node against another build's,
and version 4's symbol layer compiled, on real packets.

``--node``: the base -> full packet of each mesh (one packet, all splits), version 3
and version 4 at their default flags, read (``LodState.readPacket``) and applied
(``LodState.apply``) by this checkout's ``static/`` and by the ``static/`` of git ref
``--against`` (``git archive``, default ``main``), in node, CPU time, the builds
alternating round by round (``codec_decode_node.mjs``); every build must reach the
same state from both packets. Prints the medians of read, apply and read + apply
(the first round, JIT warm-up, dropped) in ms and M splits/s, and each build's
paired ratio to this one (median over rounds). Headless Chromium, the same packets
(wall time): ``codec_browser.py --against DIR``.

    PYTHONPATH=$PWD python bench/codec_decode_speed.py --node bunny_loop2 --bits 14
    PYTHONPATH=$PWD python bench/codec_decode_speed.py --node stanford-bunny --rounds 21

Without ``--node``: a numba transcription of ``rans.SymbolReader`` (the same arithmetic and model
schedule, a lookup table per context, 32-bit-safe state) decodes every coded
stream of the base -> full packet of a mesh, with each symbol's context taken
from the encoder (the contexts' rules cost a few operations more per symbol in a
real decoder). Prints symbols per second and splits per second for the symbol
layer alone; applying the records (connectivity, positions, wedges) comes on top.

    PYTHONPATH=$PWD python bench/codec_decode_speed.py stanford-bunny bunny_loop2
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parent))

from codec_meshes import progressive  # noqa: E402

from codec_browser import document_of  # noqa: E402

from lodserver.packets import encode, encode_packet, grid_of, quantized_level  # noqa: E402
from lodserver.packets import encode_v4 as v4  # noqa: E402
from lodserver.packets.format import stream_names  # noqa: E402
from lodserver.packets.rans import (  # noqa: E402
    ALPHABET,
    INCREMENT,
    PROB_BITS,
    PROB_SCALE,
    RAW_CHUNK,
    STATE_LOW,
    encode_symbols,
    frequencies,
    new_models,
    next_rebuild,
)
from lodserver.packets.format import Reader  # noqa: E402


# Find a slot's bucket by binary search over the starts instead of a lookup table:
# the table must be refilled (4096 entries) at every rebuild of its context.
SEARCH = True


@njit(cache=True)
def _decode(data, contexts, n_contexts, out):
    counts, freq, start, coded, rebuild = new_models(n_contexts)
    lookup = np.empty((n_contexts, PROB_SCALE), dtype=np.uint8)
    for c in range(n_contexts):
        for b in range(ALPHABET):
            lookup[c, start[c, b]:start[c, b] + freq[c, b]] = b
    x = data[0] | (data[1] << 8) | (data[2] << 16) | (np.int64(data[3]) << 24)
    at = 4
    for i in range(out.shape[0]):
        c = contexts[i]
        slot = x & (PROB_SCALE - 1)
        if SEARCH:                     # the bucket by binary search over the starts
            lo, hi = 0, ALPHABET - 1
            while lo < hi:
                mid = (lo + hi + 1) >> 1
                if start[c, mid] <= slot:
                    lo = mid
                else:
                    hi = mid - 1
            b = lo
        else:
            b = lookup[c, slot]
        x = freq[c, b] * (x >> PROB_BITS) + slot - start[c, b]
        while x < STATE_LOW:
            x = (x << 8) | data[at]
            at += 1
        counts[c, b] += INCREMENT
        coded[c] += 1
        if coded[c] == rebuild[c]:
            rebuild[c] = next_rebuild(coded[c])
            frequencies(counts[c], freq[c])
            s = 0
            for k in range(ALPHABET):
                start[c, k] = s
                if not SEARCH:
                    for j in range(freq[c, k]):
                        lookup[c, s + j] = k
                s += freq[c, k]
        if b < 32:
            out[i] = b
            continue
        n = (b - 32) // 2 + 6
        extra = 0
        k = 0
        while k < n - 2:
            size = min(RAW_CHUNK, n - 2 - k)
            extra |= (x & ((1 << size) - 1)) << k
            x >>= size
            while x < STATE_LOW:
                x = (x << 8) | data[at]
                at += 1
            k += size
        out[i] = (1 << (n - 1)) | (((b - 32) & 1) << (n - 2)) | extra
    return x


def main(names):
    for name in names:
        pm = progressive(name)
        n0, n = pm.base_vertices, pm.vertex_count
        grid, grids = grid_of(pm, bits=14), encode.attribute_grids_of(pm)
        records = n - n0
        marks = np.zeros((len(stream_names(grids, pm.face_material is not None)), records + 1),
                         dtype=np.int64)
        streams = encode.encode_streams(pm, n0, n, grid, grids, marks)
        layout = v4.shapes(grids, pm.face_material is not None, True, v4.DEFAULT_FLAGS)
        jobs = []
        for r0, r1 in v4.segment_cuts(0, records):
            fields = [v4._integers(s[m[r0]:m[r1]], k in v4.BYTE_STREAMS)
                      for k, (s, m) in enumerate(zip(streams, marks))]
            symbols, ctx = v4._segment_symbols(fields, n0 + r0, None, v4.DEFAULT_FLAGS, layout)
            for values, c, shape in zip(symbols, ctx, layout):
                if len(values):
                    out = bytearray()
                    encode_symbols(out, values, c, shape.contexts)
                    reader = Reader(bytes(out), "s")
                    count = reader.varint()
                    data = np.frombuffer(reader.take(reader.varint()), dtype=np.uint8)
                    jobs.append((data.astype(np.int64), np.asarray(c, dtype=np.int64),
                                 shape.contexts, np.asarray(values, dtype=np.int64), count))
        for data, c, k, values, count in jobs[:1]:
            _decode(data, c, k, np.empty(count, dtype=np.int64))       # compile
        best = None
        for _ in range(3):
            began = time.perf_counter()
            for data, c, k, values, count in jobs:
                got = np.empty(count, dtype=np.int64)
                final = _decode(data, c, k, got)
                assert final == STATE_LOW and np.array_equal(got, values)
            took = time.perf_counter() - began
            best = took if best is None else min(best, took)
        symbols = sum(job[4] for job in jobs)
        print(f"{name}: {symbols} symbols of {records} splits in {best:.3f} s: "
              f"{symbols / best / 1e6:.1f} M symbols/s, {records / best / 1e6:.2f} M splits/s")


HERE = Path(__file__).resolve().parent
REPO = HERE.parent


def static_of(ref: str, into: Path) -> Path:
    """The ``static/`` folder of git ref ``ref``, extracted under ``into``."""
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref, "static"],
                             check=True, capture_output=True).stdout
    folder = into / ref.replace("/", "_")
    folder.mkdir()
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    return folder / "static"


def node_rounds(name: str, bits: int | None, rounds: int, against: list[str]) -> None:
    """Times this checkout's browser decoder against the refs' in node (see the module
    docstring); prints the table rows of one mesh."""
    node = shutil.which("node")
    if node is None:
        raise SystemExit("no node on PATH")
    pm = progressive(name)
    n0, n = pm.base_vertices, pm.vertex_count
    grid = grid_of(pm, bits=bits)
    full = quantized_level(pm, n, grid)
    packets = {"v3": encode_packet(pm, n0, n, bits=bits),
               "v4": v4.encode_packet_v4(pm, n0, n, bits=bits)}
    with tempfile.TemporaryDirectory() as scratch:
        folder = Path(scratch)
        (folder / "level.json").write_text(json.dumps({
            "document": document_of(quantized_level(pm, n0, grid),
                                    0 if full.wedges is None else len(full.wedges)),
            "capacity": {"vertexCapacity": n, "faceCapacity": int(pm.face_counts[-1])}}))
        for version, data in packets.items():
            (folder / version).write_bytes(data)
        (folder / "packets.json").write_text(json.dumps(list(packets)))
        builds = {"this": REPO / "static"}
        for ref in against:
            builds[ref] = static_of(ref, folder)
        labels = {str(path): label for label, path in builds.items()}
        out = subprocess.run([node, str(HERE / "codec_decode_node.mjs"), str(folder),
                              str(rounds), *map(str, builds.values())],
                             check=True, capture_output=True, text=True).stdout
    times = {label: {v: [] for v in packets} for label in builds}
    for line in out.splitlines():
        row = json.loads(line)
        label = labels[row["build"]]
        for version, (read, apply) in row["times"].items():
            times[label][version].append((read, apply))
        ends = row["ends"]
        assert ends["v3"] == ends["v4"], f"{label}: v3 and v4 end on different states: {ends}"
        assert ends["v3"][:2] == [n, int(pm.face_counts[-1])], ends
    splits = n - n0
    print(f"{name}: {splits} splits, bits {grid.bits}, {rounds} rounds (first dropped), "
          "node, CPU ms, medians")
    for label in builds:
        for version in packets:
            kept = times[label][version][1:]
            read = statistics.median(r for r, _ in kept)
            apply = statistics.median(a for _, a in kept)
            both = statistics.median(r + a for r, a in kept)
            rate = [splits / ms / 1e3 for ms in (read, apply, both)]
            print(f"  {label:8s} {version}: read {read:7.1f}  apply {apply:7.1f}  read+apply "
                  f"{both:7.1f} ms = M splits/s {rate[0]:.2f} / {rate[1]:.2f} / {rate[2]:.2f}")
    for label in list(builds)[1:]:
        for version in packets:
            pairs = list(zip(times[label][version][1:], times["this"][version][1:]))
            ratio = [statistics.median(o[k] / t[k] for o, t in pairs) for k in (0, 1)]
            total = statistics.median(sum(o) / sum(t) for o, t in pairs)
            print(f"  {label}/this {version}: read x{ratio[0]:.2f}  apply x{ratio[1]:.2f}  "
                  f"read+apply x{total:.2f} (paired)")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("meshes", nargs="*", default=["bunny_loop2"])
    parser.add_argument("--node", action="store_true", help="time the browser decoder in node")
    parser.add_argument("--bits", type=int, default=None)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--against", action="append", default=None,
                        help="git ref whose static/ is timed too (default: main)")
    args = parser.parse_args()
    if args.node:
        for mesh in args.meshes:
            node_rounds(mesh, args.bits, args.rounds, args.against or ["main"])
    else:
        main(args.meshes)
