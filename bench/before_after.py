"""Fidelity before and after a change, in one run: the RMS surface error of
the levels two lodserver trees build of the same mesh, judged alike.

``same_levels.py`` proves that a change leaves small meshes' artefacts bit for
bit the same; a change that is meant to alter the result (the partitioned run
of large meshes, say) needs the error itself compared instead. Each tree
builds the mesh in a child process (``PYTHONPATH`` at the tree, a numba cache
of its own), extracts the levels at ``--ratios`` of the faces as
``simplify.py`` does (``pm.arrays_at(pm.level_for(faces=N))``), and this
process judges every level with ``simplify.py``'s judge
(``lodserver.metrics.surface_distance``, 200k samples a side, seed 0).

    python bench/before_after.py --base /tmp/head                 # the 1.1M bunny
    python bench/before_after.py --base /tmp/head --mesh bench/out/bunny_loop3.npz

``--base`` is a tree of the old sources (``git worktree add /tmp/head HEAD``);
``--mesh`` an ``.npz`` of welded ``positions`` and ``faces`` (default
``bench/out/bunny_loop2.npz``, which ``simplify.py`` makes). Prints one row a
ratio: RMS before, after, and after over before.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
RATIOS = (0.5, 0.1, 0.02, 0.005)

# Run in each tree's child: build, then the levels at each ratio into an .npz.
_CHILD = r"""
import sys
import numpy as np
from lodserver import Mesh, build
mesh_path, out, ratios = sys.argv[1], sys.argv[2], [float(r) for r in sys.argv[3].split(",")]
with np.load(mesh_path) as data:
    mesh = Mesh(data["positions"], data["faces"])
pm = build(mesh)
levels = {}
for ratio in ratios:
    positions, faces = pm.arrays_at(pm.level_for(faces=max(1, round(ratio * mesh.face_count))))[:2]
    levels[f"positions_{ratio}"], levels[f"faces_{ratio}"] = positions, faces
np.savez(out, **levels)
"""


def levels_of(tree: Path, mesh: Path, ratios, work: Path, name: str) -> dict:
    """The levels ``tree``'s lodserver builds of ``mesh``, by ratio."""
    out = work / f"{name}.npz"
    env = dict(os.environ, PYTHONPATH=str(tree), NUMBA_CACHE_DIR=str(work / f"numba-{name}"))
    subprocess.run([sys.executable, "-c", _CHILD, str(mesh), str(out),
                    ",".join(map(str, ratios))], env=env, check=True, cwd=work)
    with np.load(out) as data:
        return {r: (data[f"positions_{r}"], data[f"faces_{r}"]) for r in ratios}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--base", type=Path, required=True, help="a tree of the old sources")
    parser.add_argument("--new", type=Path, default=ROOT, help="the new tree (this one)")
    parser.add_argument("--mesh", type=Path, default=BENCH / "out" / "bunny_loop2.npz")
    parser.add_argument("--ratios", default=",".join(map(str, RATIOS)))
    parser.add_argument("--samples", type=int, default=200_000)
    args = parser.parse_args(argv)
    ratios = [float(r) for r in args.ratios.split(",")]

    from lodserver.metrics import surface_distance

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        before = levels_of(args.base.resolve(), args.mesh.resolve(), ratios, work, "before")
        after = levels_of(args.new.resolve(), args.mesh.resolve(), ratios, work, "after")
    with np.load(args.mesh) as data:
        reference = (data["positions"], data["faces"])
    print(f"mesh {args.mesh.name}, base {args.base}, new {args.new}")
    print("| ratio | faces before | faces after | RMS before | RMS after | after / before |")
    print("|---|---|---|---|---|---|")
    for ratio in ratios:
        rms = [surface_distance(reference, levels[ratio], samples=args.samples, seed=0)["rms"]
               for levels in (before, after)]
        print(f"| {ratio} | {len(before[ratio][1])} | {len(after[ratio][1])} | {rms[0]:.5g} | "
              f"{rms[1]:.5g} | {rms[1] / rms[0]:.4f} |")


if __name__ == "__main__":
    main()
