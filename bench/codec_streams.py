"""Where a version 4 packet's bytes go: per stream, its coded bytes and its empirical
entropy in its contexts (static, order 0 per context: what an ideal coder of these
symbols with these contexts would approach).

    PYTHONPATH=$PWD python bench/codec_streams.py spot stanford-bunny
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from codec_meshes import progressive  # noqa: E402

from lodserver.packets import encode, grid_of  # noqa: E402
from lodserver.packets import encode_v4 as v4  # noqa: E402
from lodserver.packets.format import stream_names  # noqa: E402
from lodserver.packets.rans import ALPHABET, bucket_of, encode_symbols, extra_bits  # noqa: E402
from lodserver.packets.streams_v4 import shapes, stream_names_v4  # noqa: E402


def breakdown(pm, start, stop, flags=v4.DEFAULT_FLAGS, batch=None, bits=None):
    """{stream: (bytes of an empty stream, coded bytes, entropy bytes)} of the packet
    start -> stop, summed over its segments."""
    grid = grid_of(pm, bits=bits)
    grids = encode.attribute_grids_of(pm)
    has_materials = pm.face_material is not None
    forward = stop > start
    records = abs(stop - start)
    n0, n = pm.base_vertices, pm.vertex_count
    marks = np.zeros((len(stream_names(grids, has_materials)), records + 1), dtype=np.int64)
    streams = encode.encode_streams(pm, start, stop, grid, grids, marks)
    first = start - n0 if forward else n - start
    layout = shapes(grids, has_materials, forward, flags)
    names = stream_names_v4(grids, has_materials)
    out = {name: np.zeros(3) for name in names}
    for r0, r1 in v4.segment_cuts(first, records):
        fields = [v4._integers(s[m[r0]:m[r1]], k in v4.BYTE_STREAMS)
                  for k, (s, m) in enumerate(zip(streams, marks))]
        ids = None if batch is None else batch[first + r0:first + r1]
        symbols, ctx = v4._segment_symbols(fields, start + r0 if forward else None, ids, flags,
                                           layout)
        for name, values, c, shape in zip(names, symbols, ctx, layout):
            whole = bytearray()
            encode_symbols(whole, values, c, shape.contexts)
            if not len(values):
                out[name] += (len(whole), 0, 0)
                continue
            buckets = np.array([bucket_of(int(v))[0] for v in values])
            counts = np.zeros((shape.contexts, ALPHABET))
            np.add.at(counts, (np.asarray(c), buckets), 1)
            p = counts / np.maximum(counts.sum(1, keepdims=True), 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                h = -(counts * np.where(counts > 0, np.log2(p), 0)).sum()
            raw = sum(extra_bits(b) * int(k) for b, k in enumerate(counts.sum(0)))
            out[name] += (0, len(whole), (h + raw) / 8)
    return out


def show(name, pm, start, stop, **kw):
    out = breakdown(pm, start, stop, **kw)
    records = abs(stop - start)
    total = sum(v[0] + v[1] for v in out.values())
    print(f"{name} {start}->{stop}: {total} B, {total / records:.2f} B/record")
    for stream, (tables, coded, entropy) in out.items():
        if tables + coded > 2:
            print(f"  {stream:18s} coded {coded:9.0f} ({coded / records:.3f} B/rec)  "
                  f"entropy {entropy:9.0f}")


if __name__ == "__main__":
    for mesh in sys.argv[1:]:
        pm = progressive(mesh)
        for flags in (0, v4.DEFAULT_FLAGS):
            print("flags", flags)
            show(mesh, pm, pm.base_vertices, pm.vertex_count, flags=flags)
