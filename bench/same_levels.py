"""Same levels before and after: a refactor of the simplifier must not change a bit.

Builds every shared mesh (the ones ``bench/simplify.py`` uses) with a few
option sets, once with this tree and once with a pristine ``git worktree`` of
HEAD (or any other tree, ``--base``), each in a child process with
``PYTHONPATH`` pointing at its tree and a numba cache of its own, and compares
the SHA-256 of the ``.pm`` bytes and of the levels extracted at a few ratios
(positions, faces and, where there are any, wedge values and corners).

    python bench/same_levels.py                      # every mesh, every option set
    python bench/same_levels.py --meshes spot,Duck --options default,pairs
    python bench/same_levels.py --timing 2           # + bunny_loop2 build times, interleaved

``--timing K`` then times the 1.1M-face Loop-subdivided bunny (``bunny_loop2``,
made as ``bench/simplify.py`` makes it) K times per tree, interleaved (base,
new, base, new, ...), each build in a fresh child after a warm-up build that
loads the compiled kernels, so both trees see the same machine load. Compare
times only within one run: other work on the machine moves them all.

Exit code 1 if any artefact or level differs.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BENCH = Path(__file__).resolve().parent
ROOT = BENCH.parent
MESH_DIR = ROOT.parent / "shared" / "meshes"
RATIOS = (1.0, 0.5, 0.1, 0.02)
# name -> build options (JSON-able; "lock_border" becomes locked= the border mask)
OPTION_SETS = {
    "default": {},
    "no_attributes": {"attributes": False},
    "cluster": {"method": "cluster"},
    "pairs": {"pair_threshold": "2%"},
    "lock_border": {"lock_border": True},
}
LARGE = "bunny_loop2"


def shared_meshes() -> dict:
    """``bench/simplify.py``'s SHARED_MESHES, read without importing it (it
    imports lodserver, and this parent process must not)."""
    tree = ast.parse((BENCH / "simplify.py").read_text())
    for node in tree.body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "SHARED_MESHES":
            return ast.literal_eval(node.value)
    raise SystemExit("bench/simplify.py has no SHARED_MESHES")


# ---------------------------------------------------------------------------
# Child: runs with PYTHONPATH=<tree>
# ---------------------------------------------------------------------------

def _digest(*arrays) -> str:
    import numpy as np
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def _build(mesh, options):
    from lodserver import build
    try:
        from lodserver.simplify.topology import census
    except ImportError:                 # a tree from before the package went by stage
        from lodserver.topology import census
    options = dict(options)
    if options.pop("lock_border", False):
        options["locked"] = census(mesh.faces, mesh.vertex_count).on_boundary.copy()
    if options.get("method") == "cluster":
        options.pop("attributes", None)
    return build(mesh, **options)


def child_levels(paths: list[str], options: dict) -> dict:
    """{mesh path: {"pm": sha, "levels": {ratio: sha}, "build_s": s}} for one tree."""
    from lodserver.io import load_mesh
    _build(load_mesh(ROOT / "tests" / "data" / "spot.obj")[0], options)   # compile or load kernels
    out = {}
    for path in paths:
        mesh, _ = load_mesh(path)
        start = time.perf_counter()
        try:
            pm = _build(mesh, options)
        except Exception as exc:    # a refusal is a result too: both trees must agree
            out[path] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        seconds = time.perf_counter() - start
        with tempfile.TemporaryDirectory() as tmp:
            pm.save(Path(tmp) / "x.pm")
            data = (Path(tmp) / "x.pm").read_bytes()
        levels = {}
        for ratio in RATIOS:
            level = pm.at(ratio=ratio) if ratio < 1 else pm.at(pm.vertex_count)
            parts = [level.positions, level.faces]
            if level.attributes is not None:
                parts += [level.attributes.values, level.attributes.corners]
            levels[str(ratio)] = _digest(*parts)
        out[path] = {"pm": hashlib.sha256(data).hexdigest()[:16], "levels": levels,
                     "build_s": round(seconds, 3), "splits": int(pm.split_count)}
    return out


def child_time(npz: str) -> float:
    """Seconds of one ``build`` of the mesh in ``npz`` (after a warm-up build)."""
    import numpy as np

    from lodserver import build
    from lodserver.io import clean_mesh, load_mesh
    build(load_mesh(ROOT / "tests" / "data" / "spot.obj")[0])     # loads the kernels
    data = np.load(npz)
    mesh, _ = clean_mesh(data["positions"], data["faces"])
    start = time.perf_counter()
    build(mesh)
    return time.perf_counter() - start


# ---------------------------------------------------------------------------
# Parent
# ---------------------------------------------------------------------------

def run_child(tree: Path, cache: Path, args: list[str], timeout: float):
    env = {**os.environ, "PYTHONPATH": str(tree), "NUMBA_CACHE_DIR": str(cache)}
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", *args],
                          capture_output=True, text=True, env=env, timeout=timeout, cwd=tree)
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-5:]
        raise RuntimeError(f"child in {tree} failed: " + " | ".join(tail))
    return json.loads(proc.stdout.strip().splitlines()[-1])


def levels_of(tree: Path, cache: Path, options: dict, paths: list[str], timeout: float) -> dict:
    """``child_levels`` of every path in one child; if that child dies, one
    child per path, so a crash is recorded against its mesh."""
    try:
        return run_child(tree, cache, ["levels", json.dumps(options), json.dumps(paths)], timeout)
    except RuntimeError:
        out = {}
        for path in paths:
            try:
                out.update(run_child(tree, cache, ["levels", json.dumps(options),
                                                   json.dumps([path])], timeout))
            except RuntimeError as exc:
                out[path] = {"error": f"crashed: {str(exc).split(': ', 1)[-1]}"}
        return out


def large_input() -> Path:
    """bench/out/bunny_loop2.npz, made as bench/simplify.py makes it."""
    path = BENCH / "out" / f"{LARGE}.npz"
    if not path.exists():
        code = ("import sys; sys.path.insert(0, %r); import simplify; "
                "simplify.prepare_input(%r, simplify.Path(%r), simplify.Path(%r))"
                % (str(BENCH), LARGE, str(MESH_DIR), str(path.parent)))
        path.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)
    return path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--base", type=Path, help="the tree to compare against "
                        "(default: a fresh git worktree of HEAD, removed afterwards)")
    parser.add_argument("--new", type=Path, default=ROOT, help="the tree under test (this one)")
    parser.add_argument("--meshes", help="comma-separated keys of SHARED_MESHES (default: all)")
    parser.add_argument("--options", default=",".join(OPTION_SETS),
                        help=f"comma-separated, from: {', '.join(OPTION_SETS)}")
    parser.add_argument("--timing", type=int, default=0, metavar="K",
                        help=f"also time K builds of {LARGE} per tree, interleaved")
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("--child", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)

    if args.child:
        kind, *rest = args.child
        if kind == "levels":
            print(json.dumps(child_levels(json.loads(rest[1]), json.loads(rest[0]))))
        else:
            print(json.dumps(child_time(rest[0])))
        return 0

    meshes = shared_meshes()
    keys = args.meshes.split(",") if args.meshes else list(meshes)
    paths = [str(MESH_DIR / meshes[k]) for k in keys]
    worktree = None
    base = args.base
    if base is None:
        worktree = Path(tempfile.mkdtemp(prefix="same-levels-base-"))
        subprocess.run(["git", "worktree", "add", "--detach", str(worktree), "HEAD"], cwd=ROOT,
                       check=True, capture_output=True)
        base = worktree
    trees = {"base": base.resolve(), "new": args.new.resolve()}
    caches = {name: Path(tempfile.gettempdir()) / f"same-levels-numba-{name}-"
              f"{hashlib.sha256(str(tree).encode()).hexdigest()[:8]}"
              for name, tree in trees.items()}
    differ = 0
    try:
        for option_name in args.options.split(","):
            options = OPTION_SETS[option_name]
            results = {name: levels_of(tree, caches[name], options, paths, args.timeout)
                       for name, tree in trees.items()}
            for key, path in zip(keys, paths):
                a, b = results["base"][path], results["new"][path]
                same = {k: v for k, v in a.items() if k != "build_s"} == \
                       {k: v for k, v in b.items() if k != "build_s"}
                differ += not same
                note = a.get("error") or f"pm {a['pm']} splits {a['splits']}"
                times = "" if "error" in a else f" build {a['build_s']:.2f}s -> {b['build_s']:.2f}s"
                print(f"{'same ' if same else 'DIFFERS'} {option_name:14s} {key:20s} {note}{times}",
                      flush=True)
                if not same:
                    print(f"    base {a}\n    new  {b}", flush=True)
        if args.timing:
            npz = str(large_input())
            times = {"base": [], "new": []}
            for _ in range(args.timing):
                for name in ("base", "new"):
                    seconds = run_child(trees[name], caches[name], ["time", npz], args.timeout)
                    times[name].append(seconds)
                    print(f"{LARGE} {name}: {seconds:.2f} s", flush=True)
            print(json.dumps({"timing_s": times, "load_average": os.getloadavg()}))
    finally:
        if worktree is not None:
            subprocess.run(["git", "worktree", "remove", "--force", str(worktree)], cwd=ROOT,
                           capture_output=True)
    print(f"{differ} differ" if differ else "all the same")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
