"""Each size lever of version 4 alone and together: bytes base -> full per mesh.

Levers: **turned faces** (``progressive/face_rotation.py``: every new face starts at
its split vertex, so its pattern need not say where it starts), **batches**
(``BuildOptions.batched``: splits in batches of independent ones, ``vs`` coded as
gaps within a batch) and **the ring** (``RING_POSITIONS``, ``packets/ring_v4.py``:
the split edge coded less its prediction from the two rings; columns ``+ring``,
on the turned build and on both). Without the unturned folder its columns are ``-``. The meshes without turned faces are built by the code before
the turn (commit ``2ce85ce``) into a folder of their own; the turned ones are
bench/codec_meshes.py's. For every mesh at ``bits=14``: the base json gzipped plus
the version 4 packets of 8192 splits (as bench/codec.py counts them), each mesh
of at most 100,000 splits decoded back exactly, and gltfpack ``-cc`` of the full-detail mesh (bench/codec.py);
gltfpack writes 8-bit normals, so meshes with normals also get ``both`` with 8-bit
normals (``both n8``; the base json keeps its default normal grid, as bench/codec.py).

    mkdir -p /tmp/unturned && git archive 2ce85ce lodserver | tar -x -C /tmp/unturned
    PYTHONPATH=/tmp/unturned python bench/codec_levers.py --build bench/out/codec-unturned
    PYTHONPATH=$PWD python bench/codec_levers.py --build bench/out/codec
    PYTHONPATH=$PWD python bench/codec_levers.py --unturned bench/out/codec-unturned [mesh ...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from codec_meshes import OUT, SOURCES, source_mesh  # noqa: E402

BITS = 14


def build_all(folder: Path, names) -> None:
    """``NAME.pm`` and ``NAME-batched.pm`` of every mesh into ``folder``, by the
    lodserver on the path."""
    from lodserver import build
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        for suffix, options in (("", {}), ("-batched", {"batched": True})):
            path = folder / f"{name}{suffix}.pm"
            if not path.exists():
                build(source_mesh(name), options).save(path)
                print(f"built {path}", file=sys.stderr, flush=True)


# The reference decoder is plain Python: meshes past this many splits are not decoded back.
CHECKED_SPLITS = 100_000


def streamed(pm, attribute_bits=None, flags=None) -> tuple[int, int]:
    """(base json gzipped, packets) bytes base -> full; decoded back onto full detail
    exactly when the mesh has at most :data:`CHECKED_SPLITS` splits."""
    from codec import PACKET_SPLITS, gz

    from lodserver.packets import apply_packet, grid_of, quantized_level
    from lodserver.packets.decode_v4 import decode_packet_v4
    from lodserver.packets.encode_v4 import encode_packet_v4
    from lodserver.service.levels import encode_level
    n0, n = pm.base_vertices, pm.vertex_count
    grid = grid_of(pm, bits=BITS)
    check = n - n0 <= CHECKED_SPLITS and attribute_bits is None
    state = quantized_level(pm, n0, grid) if check else None
    packets = 0
    for a in range(n0, n, PACKET_SPLITS):
        data = encode_packet_v4(pm, a, min(n, a + PACKET_SPLITS), bits=BITS,
                                attribute_bits=attribute_bits, flags=flags)
        if check:
            state = apply_packet(state, decode_packet_v4(data))
        packets += len(data)
    full = quantized_level(pm, n, grid) if check else None
    if check and not (np.array_equal(state.positions, full.positions)
                      and np.array_equal(state.faces, full.faces)):
        raise AssertionError("the packets did not land on full detail")
    return gz(encode_level(pm, n0, file_type="json", bits=BITS)), packets


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("meshes", nargs="*", default=list(SOURCES))
    parser.add_argument("--build", type=Path, help="build the meshes into this folder and stop")
    parser.add_argument("--unturned", type=Path, default=OUT.parent / "codec-unturned")
    args = parser.parse_args(argv)
    if args.build:
        build_all(args.build, args.meshes)
        return
    from codec import gltfpack_bytes

    from lodserver.packets.format import EDGE_POSITIONS, RING_POSITIONS
    from lodserver.progressive.mesh import ProgressiveMesh
    edge, ring = EDGE_POSITIONS, EDGE_POSITIONS | RING_POSITIONS
    columns = {"baseline": (args.unturned, "", edge), "turned": (OUT, "", edge),
               "batches": (args.unturned, "-batched", edge), "both": (OUT, "-batched", edge),
               "turned +ring": (OUT, "", ring), "both +ring": (OUT, "-batched", ring)}
    lines = ["| mesh | splits | " + " | ".join(f"{c} KB (B/split)" for c in columns)
             + " | both +ring n8 KB | gltfpack -cc KB | best / -cc |",
             "|---" * (len(columns) + 5) + "|"]
    for name in args.meshes:
        cells, cc = [], None
        for label, (folder, suffix, flags) in columns.items():
            if not (folder / f"{name}{suffix}.pm").exists():
                cells.append("-")
                continue
            pm = ProgressiveMesh.load(folder / f"{name}{suffix}.pm")
            splits = pm.vertex_count - pm.base_vertices
            base, packets = streamed(pm, flags=flags)
            cells.append(f"{(base + packets) / 1000:.1f} ({packets / splits:.2f})")
            print(name, label, base, packets, file=sys.stderr, flush=True)
            if cc is None:
                cc = gltfpack_bytes(pm, "-cc")
        best = float(cells[-1].split()[0]) * 1000
        n8 = "-"
        if any(a == "NORMAL" for a, _ in pm.attribute_layout or ()):
            base, packets = streamed(pm, {"NORMAL": 8}, flags=ring)
            n8 = f"{(base + packets) / 1000:.1f} ({packets / splits:.2f})"
            best = min(best, base + packets)
        ratio = f"{best / cc:.2f}x" if cc else "-"
        lines.append(f"| {name} | {splits} | " + " | ".join(cells)
                     + f" | {n8} | {cc / 1000 if cc else 0:.1f} | {ratio} |")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
