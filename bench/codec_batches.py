"""Version 4 with the batch schedule of the ``batches`` branch: bytes base -> full.

The batched meshes were built by that branch's code (``BuildOptions.batched``) into
bench/out/codec/NAME-batched.pm with their batch ids beside (NAME-batched-ids.npy),
when this checkout's reader skipped the schedule block; a batched build now carries
its schedule (``split_batch``), which is used when the ids file is absent
(``bench/codec_levers.py`` measures the merged code's batched builds). Prints, per mesh at ``bits=14``: v3, v4 with one
batch per split, v4 with the schedule (whole packet base -> full), and the vertex
stream's bytes per split each way; then the streamed bytes as bench/codec.py counts
them.

    mkdir -p /tmp/batches-src && git archive batches lodserver | tar -x -C /tmp/batches-src
    PYTHONPATH=/tmp/batches-src python bench/codec_batches.py --build spot stanford-bunny Duck
    PYTHONPATH=$PWD python bench/codec_batches.py spot stanford-bunny Duck
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from codec_meshes import OUT  # noqa: E402



def build_batched(names):
    """Build ``names`` with the batches branch's ``batched`` option (run with that
    branch's lodserver/ on PYTHONPATH) and keep the .pm and the batch ids."""
    from codec_meshes import source_mesh

    from lodserver import build
    for name in names:
        pm = build(source_mesh(name), {"batched": True})
        pm.save(OUT / f"{name}-batched.pm")
        np.save(OUT / f"{name}-batched-ids.npy", pm.split_batch)


def main(names):
    """Bytes of each batched mesh's packets, with and without its schedule."""
    from codec import stream_bytes
    from codec_streams import breakdown

    from lodserver.packets import apply_packet, encode_packet, grid_of, quantized_level
    from lodserver.packets.decode_v4 import decode_packet_v4
    from lodserver.packets.encode_v4 import DEFAULT_FLAGS, encode_packet_v4
    from lodserver.progressive.mesh import ProgressiveMesh
    for name in names:
        pm = ProgressiveMesh.load(OUT / f"{name}-batched.pm")
        saved = OUT / f"{name}-batched-ids.npy"
        ids = np.load(saved) if saved.exists() else pm.split_batch
        n0, n = pm.base_vertices, pm.vertex_count
        splits = n - n0
        v3 = len(encode_packet(pm, n0, n, bits=14))
        one_each = np.arange(splits)
        plain = len(encode_packet_v4(pm, n0, n, bits=14, batch=one_each))
        data = encode_packet_v4(pm, n0, n, bits=14, batch=ids)
        state = apply_packet(quantized_level(pm, n0, grid_of(pm, bits=14)), decode_packet_v4(data))
        exact = np.array_equal(state.positions, quantized_level(pm, n, grid_of(pm, bits=14)).positions)
        one = breakdown(pm, n0, n, flags=DEFAULT_FLAGS, bits=14)
        runs = breakdown(pm, n0, n, flags=DEFAULT_FLAGS, batch=ids, bits=14)
        print(f"{name}: {splits} splits, {int(ids.max()) + 1} batches; v3 {v3} B, v4 {plain} B, "
              f"v4 batched {len(data)} B (exact: {exact}); vertex+batch "
              f"{(one['vertex'][1] + one['batch'][1]) / splits:.3f} -> "
              f"{(runs['vertex'][1] + runs['batch'][1]) / splits:.3f} B/split")
        streamed = [stream_bytes(pm, 14, encode) for encode in (
            encode_packet, lambda *a, **k: encode_packet_v4(*a, batch=one_each, **k),
            lambda *a, **k: encode_packet_v4(*a, batch=ids, **k))]
        print(f"  streamed (base json gz + packets of 8192): v3 {streamed[0]} B, v4 {streamed[1]} B, "
              f"v4 batched {streamed[2]} B")


if __name__ == "__main__":
    if sys.argv[1:2] == ["--build"]:
        build_batched(sys.argv[2:])
    else:
        main(sys.argv[1:])
