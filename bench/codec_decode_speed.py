"""How fast version 4's symbol layer decodes when compiled: a stand-in for the
browser decoder's speed target (2M splits/s), measured on a real packet.

A numba transcription of ``rans.SymbolReader`` (the same arithmetic and model
schedule, a lookup table per context, 32-bit-safe state) decodes every coded
stream of the base -> full packet of a mesh, with each symbol's context taken
from the encoder (the contexts' rules cost a few operations more per symbol in a
real decoder). Prints symbols per second and splits per second for the symbol
layer alone; applying the records (connectivity, positions, wedges) comes on top.

    PYTHONPATH=$PWD python bench/codec_decode_speed.py stanford-bunny bunny_loop2
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).resolve().parent))

from codec_meshes import progressive  # noqa: E402

from lodserver.packets import encode, grid_of  # noqa: E402
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


if __name__ == "__main__":
    main(sys.argv[1:])
