"""Command line: ``lodserver build | extract | simplify | export | info | serve``.

Every failure ends with one sentence on stderr and a non-zero exit code:
1 for bad input or a failed operation, 2 for a malformed command line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .mesh import MeshError


def _progress_bar(total_hint: int):
    """A tqdm bar on a terminal, nothing otherwise (keeps logs clean)."""
    from tqdm import tqdm

    bar = tqdm(total=total_hint, unit="collapse", disable=None, dynamic_ncols=True,
               desc="decimating", file=sys.stderr)

    def update(done, expected):
        if not bar.total:
            bar.total = expected        # known once the mesh is loaded
        bar.update(done - bar.n)

    return bar, update


def _cmd_build(args) -> int:
    from .build import attribute_weights, build
    from .io import load_mesh

    mesh, report = load_mesh(args.mesh)
    locked = None
    if args.lock_border:
        from .topology import census
        locked = np.zeros(mesh.vertex_count, dtype=bool)
        locked[census(mesh.faces, mesh.vertex_count).on_boundary] = True
    bar, update = _progress_bar(mesh.vertex_count)
    start = time.perf_counter()
    try:
        pm = build(mesh, method=args.method, boundary_weight=args.boundary_weight,
                   locked=locked, min_vertices=args.min_vertices,
                   pair_threshold=args.pair_threshold, preserve_volume=not args.no_volume,
                   attributes=not args.no_attributes,
                   attribute_weights=attribute_weights(normal=args.normal_weight,
                                                       uv=args.uv_weight, color=args.color_weight),
                   progress=update)
    except ValueError as exc:
        raise MeshError(str(exc)) from exc
    finally:
        bar.close()
    pm.metadata["source"] = Path(args.mesh).name
    pm.metadata["load_report"] = report.as_dict()
    pm.save(args.output)
    print(f"{args.output}: {pm.vertex_count} vertices, {pm.face_count} faces, "
          f"{pm.split_count} splits down to a base of {pm.base_vertices} vertices / "
          f"{pm.faces_at_level(pm.base_vertices)} faces in {time.perf_counter() - start:.2f} s",
          file=sys.stderr)
    return 0


def _cmd_extract(args) -> int:
    from .io import save_mesh
    from .progressive import ProgressiveMesh

    pm = ProgressiveMesh.load(args.asset)
    criterion = {name: getattr(args, name) for name in ("vertices", "faces", "ratio", "error")
                 if getattr(args, name) is not None}
    try:
        level = pm.level_for(**criterion)
    except ValueError as exc:
        raise MeshError(str(exc)) from exc
    mesh = pm.at(level)
    save_mesh(mesh, args.output)
    print(f"{args.output}: level {level}, {mesh.vertex_count} vertices, {mesh.face_count} faces, "
          f"error {pm.error_at_level(level):.3g}", file=sys.stderr)
    return 0


def _cmd_simplify(args) -> int:
    from .io import load_mesh, save_mesh

    mesh, _ = load_mesh(args.mesh)
    target = args.faces if args.faces is not None else max(1, round(args.ratio * mesh.face_count))
    if target < 1 or (args.ratio is not None and not 0 < args.ratio <= 1):
        raise MeshError("the target must be a ratio in (0, 1] or at least one face")
    start = time.perf_counter()
    if args.method == "cluster":
        from .cluster import cluster
        lod = cluster(mesh, target_faces=target)
    else:
        from .build import build
        lod = build(mesh).at(faces=target)
    save_mesh(lod, args.output)
    print(f"{args.output}: {lod.vertex_count} vertices, {lod.face_count} faces (target {target}) "
          f"by {args.method} in {time.perf_counter() - start:.2f} s", file=sys.stderr)
    return 0


def _cmd_export(args) -> int:
    from .pipeline import export_lods, parse_lods

    ratios = parse_lods(args.lods)
    if Path(args.source).is_dir():
        if Path(args.output).suffix.lower() == ".glb":
            raise MeshError(f"{args.source} is a folder, so -o names the folder to write into, "
                            f"not a .glb file ({args.output})")
        return _export_folder(args, ratios)
    bar, update = _progress_bar(0)
    try:
        done = export_lods(args.source, args.output, lods=ratios, separate=args.separate,
                           reach=args.reach, progress=update)
    finally:
        bar.close()
    print(f"{', '.join(map(str, done.outputs))}: {_levels(done)}", file=sys.stderr)
    return 0


def _levels(done) -> str:
    faces = ", ".join(str(count) for count in done.faces)
    coverage = ", ".join(f"{c:.3g}" for c in done.coverage)
    text = (f"{len(done.faces)} levels of {faces} faces (screen coverage {coverage}) "
            f"in {done.seconds:.2f} s")
    if done.clustered:
        levels = ", ".join(str(i) for i in done.clustered)
        text += (f"; level {levels} by vertex clustering (edge collapse stops at "
                 f"{done.base_faces} faces), positions only")
    elif done.faces[-1] == done.base_faces and len(set(done.faces[-2:])) == 1:
        # the coarser ratios were out of reach: say so rather than ship copies quietly
        text += (f"; the mesh simplifies no further than {done.base_faces} faces "
                 f"(locked, non-manifold or separate parts; --reach cluster meets the budget)")
    return text


def _export_folder(args, ratios) -> int:
    """Every mesh file under ``args.source`` into the folder ``args.output``: a bar
    over the files on a terminal, a line per file, exit 1 if any failed."""
    from tqdm import tqdm

    from .pipeline import export_folder, find_sources

    bar = tqdm(total=len(find_sources(args.source)), unit="asset", disable=None,
               dynamic_ncols=True, desc="exporting", file=sys.stderr)

    def progress(relative, outcome):
        if isinstance(outcome, str) and outcome != "up to date":
            bar.write(f"{relative}: FAILED: {outcome}", file=sys.stderr)
        elif not isinstance(outcome, str):
            outputs = ", ".join(str(Path(p).relative_to(args.output)) for p in outcome.outputs)
            bar.write(f"{relative} -> {outputs}: {_levels(outcome)}", file=sys.stderr)
        bar.update(1)

    start = time.perf_counter()
    try:
        report = export_folder(args.source, args.output, lods=ratios, separate=args.separate,
                               reach=args.reach, jobs=args.jobs, force=args.force,
                               progress=progress)
    finally:
        bar.close()
    print(f"{args.output}: {report.total} assets in {time.perf_counter() - start:.2f} s: "
          f"{len(report.written)} written, {len(report.up_to_date)} up to date, "
          f"{len(report.failed)} failed", file=sys.stderr)
    if report.failed:
        reasons = "; ".join(f"{path}: {reason}" for path, reason in report.failed.items())
        raise MeshError(f"{len(report.failed)} of {report.total} assets failed: {reasons}")
    return 0


def _cmd_info(args) -> int:
    from .progressive import ProgressiveMesh

    pm = ProgressiveMesh.load(args.asset)
    print(json.dumps(pm.summary(), indent=2))
    return 0


def _cmd_serve(args) -> int:
    import os

    import uvicorn

    # The app reads its settings from LODSERVER_* variables; the flag is one of them.
    if args.data is not None:
        os.environ["LODSERVER_DATA_DIR"] = str(args.data)
    uvicorn.run("lodserver.api.main:create_app", factory=True, host=args.host, port=args.port,
                log_level=args.log_level)
    return 0


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lodserver", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("build", help="build the progressive mesh of a mesh file")
    p.add_argument("mesh", help="OBJ, PLY, STL, OFF, glTF or GLB file")
    p.add_argument("-o", "--output", required=True, help="the .pm artefact to write")
    p.add_argument("--boundary-weight", type=float, default=1.0,
                   help="weight of the planes that keep open borders in place (default 1)")
    p.add_argument("--lock-border", action="store_true",
                   help="never move or remove border vertices (tiles and parts keep stitching)")
    p.add_argument("--min-vertices", type=int, default=0,
                   help="stop decimating at this many vertices (default: as far as possible)")
    p.add_argument("--pair-threshold", default="0", metavar="T",
                   help="also contract vertices closer than T that share no edge, joining "
                        "parts: mesh units, or a percentage of the bounding-box diagonal "
                        "like 1%% (default 0: edges only)")
    p.add_argument("--method", choices=("qem", "cluster"), default="qem",
                   help="qem: quadric edge collapse (best quality; keeps topology and "
                        "attributes); cluster: octree vertex clustering recorded as splits "
                        "(joins parts; geometry only)")
    p.add_argument("--no-volume", action="store_true",
                   help="do not keep the enclosed volume when placing collapses")
    p.add_argument("--no-attributes", action="store_true",
                   help="ignore normals, UVs, colours and materials (positions only)")
    for kind, default in (("normal", "0.003"), ("uv", "0.3"), ("color", "0.3")):
        p.add_argument(f"--{kind}-weight", type=float, metavar="W",
                       help=f"weight of {kind} error against geometric error (default {default})")
    p.set_defaults(run=_cmd_build)

    p = sub.add_parser("extract", help="write one level of a .pm artefact as a mesh file")
    p.add_argument("asset", help="the .pm artefact")
    group = p.add_mutually_exclusive_group(required=True)
    group.add_argument("--vertices", type=int, help="at most this many vertices")
    group.add_argument("--faces", type=int, help="at most this many faces")
    group.add_argument("--ratio", type=float, help="this fraction of the faces, in (0, 1]")
    group.add_argument("--error", type=float, help="coarsest level with at most this error (mesh units)")
    p.add_argument("-o", "--output", required=True, help="PLY, OBJ, GLB, OFF or STL file to write")
    p.set_defaults(run=_cmd_extract)

    p = sub.add_parser("simplify", help="write one simplified copy of a mesh file (no .pm)")
    p.add_argument("mesh", help="OBJ, PLY, STL, OFF, glTF or GLB file")
    group = p.add_mutually_exclusive_group(required=True)
    group.add_argument("--faces", type=int, help="at most this many faces")
    group.add_argument("--ratio", type=float, help="this fraction of the faces, in (0, 1]")
    p.add_argument("--method", choices=("qem", "cluster"), default="qem",
                   help="qem: edge collapse (best quality); cluster: vertex clustering "
                        "(fastest; may merge parts and change topology)")
    p.add_argument("-o", "--output", required=True, help="PLY, OBJ, GLB, OFF or STL file to write")
    p.set_defaults(run=_cmd_simplify)

    p = sub.add_parser("export",
                       help="write levels of detail as one GLB (MSFT_lod) or one GLB each, "
                            "for a file or for every mesh file under a folder")
    p.add_argument("source", help="a .pm artefact or a mesh file to build one from; or a "
                   "folder: every mesh file under it, its layout mirrored in OUTPUT")
    p.add_argument("--lods", default="1,0.5,0.2,0.05", metavar="R1,R2,...",
                   help="face ratios of the levels, finest first, each in (0, 1] "
                        "(default 1,0.5,0.2,0.05); level i's screen coverage hint is "
                        "0.5*sqrt(R(i+1)/R1), the last level's 0")
    p.add_argument("-o", "--output", required=True,
                   help="the .glb file to write; for a folder source, the folder to write into")
    p.add_argument("--separate", action="store_true",
                   help="write OUT_lod0.glb, OUT_lod1.glb, ... instead of one file with MSFT_lod")
    p.add_argument("--reach", choices=("none", "cluster"), default="none",
                   help="levels edge collapse cannot bring down to their budget (locked, "
                        "non-manifold or separate parts): keep the coarsest it reaches (none, "
                        "default) or make them by vertex clustering, which joins parts but "
                        "keeps positions only (cluster)")
    p.add_argument("--jobs", type=int, default=1,
                   help="folder source: meshes built at once (default 1; each holds its mesh "
                        "in memory)")
    p.add_argument("--force", action="store_true",
                   help="folder source: rebuild every mesh, even those whose file and options "
                        "match the last run (lodserver-export.json in OUTPUT)")
    p.set_defaults(run=_cmd_export)

    p = sub.add_parser("info", help="print counts and the error curve of a .pm artefact as JSON")
    p.add_argument("asset")
    p.set_defaults(run=_cmd_info)

    p = sub.add_parser("serve", help="run the HTTP API (settings: LODSERVER_* variables)")
    p.add_argument("--data", type=Path, help="data directory (default: $LODSERVER_DATA_DIR or "
                   "./lodserver-data)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument("--log-level", default="info",
                   choices=["critical", "error", "warning", "info", "debug"])
    p.set_defaults(run=_cmd_serve)
    return parser


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        return args.run(args)
    except MeshError as exc:
        print(f"lodserver {args.command}: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"lodserver {args.command}: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": "),
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
