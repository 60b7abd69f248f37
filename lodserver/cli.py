"""Command line: lodserver build | extract | simplify | export | info | serve | worker.

Every failure ends with one sentence on stderr and a non-zero exit code:
1 for bad input or a failed operation, 2 for a malformed command line. Every
command creates the folder of its output when it does not exist. The build
options of build, export and simplify are generated from ``options.BuildOptions``,
so their names, defaults and help are the ones the Python API and the HTTP form
use.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from . import __version__
from .io import SUPPORTED_OUTPUT
from .io.glb import COMPRESSIONS, DEFAULT_COMPRESS, LOD_NAMINGS
from .mesh import MeshError
from .options import METHODS, BuildOptions, Flag, describe_error, field_default_text
from .chains import REACH_METHODS       # the --reach choices, one list for the CLI and the library

DEFAULT_LODS_TEXT = "1,0.5,0.2,0.05"      # chains.DEFAULT_LODS, without importing it

EXAMPLES = """\
examples:
  lodserver build tests/data/spot.obj -o spot.pm
  lodserver extract spot.pm --ratio 0.1 -o spot_10.glb

'lodserver COMMAND --help' describes one command and its options."""


class _Progress:
    """A tqdm bar over collapses on a terminal, nothing otherwise (keeps logs clean).

    The bar appears with the first collapse, not before: while numba compiles
    the kernels the count stays at 0 for tens of seconds, and a bar frozen at
    0% looks hung (``_announce_compile`` says what is going on instead). With
    the kernels run as Python (``first_run``) nothing compiles: the bar comes
    at once and its clock is redrawn at every call, as the kernel reports its
    count only every so many collapses.
    """

    def __init__(self, desc: str = "decimating"):
        from .build import CompileTicker

        self.desc = desc
        self.bar = None
        self.compiling = CompileTicker()    # a moving line while kernels compile

    def __call__(self, done: int, expected: int) -> None:
        from numba.core import config

        if self.bar is None:
            if done == 0 and not config.DISABLE_JIT:
                return
            from tqdm import tqdm
            self.bar = tqdm(total=expected, unit="collapse", disable=None, dynamic_ncols=True,
                            desc=self.desc, file=sys.stderr)
        if done == self.bar.n and config.DISABLE_JIT:
            self.bar.refresh()      # the count waits, the seconds move
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        self.compiling.stop()
        if self.bar is not None:
            self.bar.close()


def _announce_compile(method: str = "qem") -> None:
    """Say so when this run will compile the kernels (an empty numba cache)."""
    from .build import COLD_COMPILE_SECONDS, kernels_cold

    if kernels_cold(method):
        print(f"compiling kernels (first run only, ~{COLD_COMPILE_SECONDS} s)", file=sys.stderr,
              flush=True)


def _input_file(path) -> Path:
    """``path`` as an input file: a folder is refused with what to do instead."""
    path = Path(path)
    if path.is_dir():
        raise MeshError(f"{path} is a folder; pass a mesh file (or use "
                        f"`lodserver export FOLDER/ -o OUT/`)")
    return path


def _output_file(path) -> Path:
    """``path`` as an output file: its folder is created if missing (every command alike)."""
    path = Path(path)
    if path.is_dir():
        raise MeshError(f"{path} is a folder; name the file to write")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


# --- build options as flags ------------------------------------------------------------

def _flag(name: str) -> tuple[str, Flag]:
    field = BuildOptions.model_fields[name]
    spelling = next((m for m in field.metadata if isinstance(m, Flag)), Flag())
    return spelling.name or "--" + name.replace("_", "-"), spelling


def add_option_flags(parser: argparse.ArgumentParser, *, exclude=()) -> None:
    """One flag per ``BuildOptions`` field (but ``exclude``), its help the field's description.

    A boolean that defaults to False is a switch that turns it on; one that
    defaults to True a switch that turns it off (``--no-volume``). The parsed
    value lands in ``args.<field name>``; ``options_from(args)`` validates.
    """
    group = parser.add_argument_group("build options")
    names = [name for name in BuildOptions.model_fields if name not in exclude]
    parser.set_defaults(option_names=names)    # what options_from reads back
    for name in names:
        field = BuildOptions.model_fields[name]
        flag, spelling = _flag(name)
        help_text = field.description.replace("%", "%%")
        if field.annotation is bool:
            # the help says what the option does and which way the switch turns it
            state = "on by default; this turns it off" if field.default else "off by default"
            group.add_argument(flag, dest=name, action="store_false" if field.default else
                               "store_true", default=field.default,
                               help=f"{help_text} ({state})")
            continue
        choices = getattr(field.annotation, "__args__", None)
        kind = {int: int, float: float}.get(field.annotation, str)
        group.add_argument(flag, dest=name, type=kind, default=field.default,
                           choices=choices, metavar=spelling.metavar or (None if choices else "X"),
                           help=f"{help_text} (default {field_default_text(name)})")


def options_from(args) -> BuildOptions:
    """The ``BuildOptions`` of parsed ``args``; a bad value is one sentence naming its flag."""
    from pydantic import ValidationError

    values = {name: getattr(args, name) for name in getattr(args, "option_names", ())}
    try:
        return BuildOptions.model_validate(values)
    except ValidationError as exc:
        raise MeshError(describe_error(exc, label=lambda name: _flag(name)[0])) from None


# --- commands ------------------------------------------------------------------------

def _cmd_build(args) -> int:
    from .build import build

    options = options_from(args)
    source, output = _input_file(args.mesh), Path(args.output)
    from .first_run import run_as_python, should_run_as_python, wait_for_background_compile
    if should_run_as_python(source, options.method):
        return run_as_python(args.argv)
    wait_for_background_compile(stream=sys.stderr)      # its kernels, loaded, not compiled again
    _announce_compile(options.method)
    progress = _Progress()
    start = time.perf_counter()
    try:
        pm = build(source, options, progress=progress, untrusted=args.untrusted)
    except ValueError as exc:       # argument checks deep in the kernel's wrapper
        raise MeshError(str(exc)) from exc
    finally:
        progress.close()
    pm.save(_output_file(output))
    print(f"{output}: {pm.vertex_count} vertices, {pm.face_count} faces, "
          f"{pm.split_count} splits down to a base of {pm.base_vertices} vertices / "
          f"{pm.faces_at_level(pm.base_vertices)} faces in {time.perf_counter() - start:.2f} s",
          file=sys.stderr)
    return 0


def _cmd_extract(args) -> int:
    from .io import save_mesh
    from .progressive.mesh import ProgressiveMesh

    pm = ProgressiveMesh.load(_input_file(args.asset))
    criterion = {name: getattr(args, name) for name in ("vertices", "faces", "ratio", "error")
                 if getattr(args, name) is not None}
    try:
        level = pm.level_for(**criterion)
    except ValueError as exc:
        raise MeshError(str(exc)) from exc
    mesh = pm.at(level)
    begun = time.perf_counter()
    save_mesh(mesh, _output_file(args.output), compress=args.compress)
    if args.report is not None:
        from .scene.report import extract_entry
        _write_report(args.report, "extract", [extract_entry(
            pm, level, Path(args.output), time.perf_counter() - begun)], begun)
    print(f"{args.output}: level {level}, {mesh.vertex_count} vertices, {mesh.face_count} faces, "
          f"error {pm.error_at_level(level):.3g}", file=sys.stderr)
    return 0


def _cmd_simplify(args) -> int:
    from .io import load_mesh, save_mesh

    options = options_from(args)        # checked before the load: a bad flag fails at once
    source = _input_file(args.mesh)
    mesh, _ = load_mesh(source, root=source.parent if args.untrusted else None)
    target = args.faces if args.faces is not None else max(1, round(args.ratio * mesh.face_count))
    if target < 1 or (args.ratio is not None and not 0 < args.ratio <= 1):
        raise MeshError("the target must be a ratio in (0, 1] or at least one face")
    start = time.perf_counter()
    if args.method == "cluster":
        from .simplify.cluster import cluster
        lod = cluster(mesh, target_faces=target)
    else:
        from .build import build
        _announce_compile()
        progress = _Progress()
        try:
            lod = build(mesh, options, progress=progress).at(faces=target)
        except ValueError as exc:
            raise MeshError(str(exc)) from exc
        finally:
            progress.close()
    save_mesh(lod, _output_file(args.output))
    print(f"{args.output}: {lod.vertex_count} vertices, {lod.face_count} faces (target {target}) "
          f"by {args.method} in {time.perf_counter() - start:.2f} s", file=sys.stderr)
    return 0


REPORT_HELP = ("write a JSON report of what was written: per asset and level its "
               "triangles, vertices, error (mesh units and fraction of the diagonal), coverage "
               "hints, bytes of geometry and images, seconds and warnings (docs/pipeline.md, "
               "'The report'); - writes it to stdout")


def _write_report(target: str, command: str, entries: list, begun: float) -> None:
    from .scene.report import report_document, write_report
    write_report(report_document(command, entries, time.perf_counter() - begun), target)


def _texture_scale(text: str):
    """argparse's type of --texture-scale (a usage error when malformed)."""
    from .scene.textures import parse_texture_scale
    try:
        return parse_texture_scale(text)
    except MeshError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _export_usage(args) -> str | None:
    """What is wrong with how ``export``'s level flags are combined (a usage error,
    exit code 2), or None."""
    if args.lods is not None and args.errors is not None:
        return "give --lods or --error, not both"
    if args.errors is not None and args.per_mesh:
        return "--per-mesh applies to --lods; levels by --error are per mesh already"
    if args.errors is not None and args.reach not in (None, "none"):
        return "--reach meets face budgets, and levels by --error have none"
    if args.impostor and (args.errors is not None or not args.separate):
        return ("--impostor writes the farthest of the --lods levels as a file of its own: "
                "give it with --lods and --separate")
    if args.errors is not None:
        try:
            values = [float(part) for part in args.errors.split(",")]
        except ValueError:
            return f"--error takes comma-separated numbers like 0.001,0.01, got {args.errors!r}"
        if not all(value >= 0 for value in values):     # NaN too
            return (f"--error values are fractions of the bounding-box diagonal, each 0 or "
                    f"more, got {args.errors}")
    if args.bits is not None:
        from .packets.grids import check_bits
        if not args.progressive:
            return "--bits sets the grid of --progressive's file; LOD chains have --compress"
        try:
            check_bits(args.bits)
        except ValueError as exc:
            return f"--{exc}"
    return None


def _cmd_export(args) -> int:
    from .chains import ChainOptions, parse_errors, parse_lods
    from .pipeline import export_lods, is_url

    begun = time.perf_counter()
    problem = _export_usage(args)
    if problem is not None:
        print(f"lodserver export: {problem}", file=sys.stderr)
        return 2
    if args.errors is not None:
        ratios, errors = None, parse_errors(args.errors)
    else:
        ratios, errors = parse_lods(args.lods or DEFAULT_LODS_TEXT), None
    chain = ChainOptions(lods=ratios, errors=errors, per_mesh=args.per_mesh,
                         separate=args.separate, reach=args.reach, atlas=args.atlas_size,
                         compress=args.compress, naming=args.lod_naming,
                         texture_scale=args.texture_scale, impostor=args.impostor)
    options = options_from(args)
    if args.progressive:
        return _export_progressive(args, options)
    if is_url(args.source) or Path(args.source).is_dir():
        if Path(args.output).suffix.lower() == ".glb":
            raise MeshError(f"{args.source} is a folder, so -o names the folder to write into, "
                            f"not a .glb file ({args.output})")
        return _export_folder(args, chain, options, begun)
    if args.scheduler is not None:
        raise MeshError("--scheduler runs the assets of a folder: name a folder, "
                        f"not a file ({args.source})")
    if is_url(args.output):
        raise MeshError(f"a file's levels are written to a local .glb; object-store URLs "
                        f"such as {args.output} are for folders")
    if Path(args.source).suffix.lower() != ".pm":
        _announce_compile(options.method)
    progress = _Progress()
    try:
        done = export_lods(args.source, _output_file(args.output), chain, options=options,
                           untrusted=args.untrusted, progress=progress)
    finally:
        progress.close()
    print(f"{', '.join(map(str, done.outputs))}: {_levels(done)}", file=sys.stderr)
    if args.report is not None:
        from .scene.report import asset_entry
        _write_report(args.report, "export", [asset_entry(done, done.outputs)], begun)
    return 0


def _export_progressive(args, options) -> int:
    """``export --progressive``: the file ``GET /meshes/{id}/progressive`` serves,
    built as the server builds an upload (a glTF scene kept whole)."""
    from .build import build
    from .io import load_mesh
    from .io.files import write_atomic
    from .pipeline import is_url
    from .progressive.mesh import ProgressiveMesh
    from .scene.asset import SceneAsset
    from .scene.build import build_asset
    from .scene.load import read_scene_upload
    from .service.progressive_file import progressive_glb

    chain_flags = [flag for flag, given in (
        ("--lods", args.lods is not None), ("--error", args.errors is not None),
        ("--separate", args.separate), ("--per-mesh", args.per_mesh),
        ("--reach", args.reach not in (None, "none")), ("--atlas-size", args.atlas_size),
        ("--texture-scale", args.texture_scale), ("--report", args.report),
        ("--jobs", args.jobs != 1), ("--scheduler", args.scheduler is not None),
        ("--force", args.force), ("--impostor", args.impostor)) if given]
    if chain_flags:
        print(f"lodserver export: --progressive writes every level in one file; "
              f"{', '.join(chain_flags)} apply to LOD chains", file=sys.stderr)
        return 2
    source, output = Path(args.source), Path(args.output)
    if output.suffix.lower() != ".glb" or is_url(args.source) or source.is_dir():
        raise MeshError("--progressive writes one mesh file's progressive file: SOURCE a "
                        f"mesh file or .pm artefact, -o a .glb file (got {source.name} -> "
                        f"{output.name})")
    start = time.perf_counter()
    if source.suffix.lower() == ".pm":
        asset = SceneAsset.of_mesh(ProgressiveMesh.load(source))
    else:
        _announce_compile(options.method)
        root = source.parent if args.untrusted else None
        found = read_scene_upload(source, root=root, limits=None, max_triangles=sys.maxsize)
        values = options.model_dump()
        lock_border = bool(values.pop("lock_border", False))
        progress = _Progress()
        try:
            asset = build_asset(found[0] if found else load_mesh(source, root=root)[0],
                                build=build, options=values, lock_border=lock_border,
                                progress=progress)
        finally:
            progress.close()
    data = progressive_glb(asset, name=source.stem, bits=args.bits)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(output, data)
    print(f"{output}: {len(data)} bytes, {len(asset.parts)} part(s), "
          f"{sum(p.pm.vertex_count for p in asset.parts)} vertices at full detail, in "
          f"{time.perf_counter() - start:.2f} s", file=sys.stderr)
    return 0


def _levels(done) -> str:
    faces = ", ".join(str(count) for count in done.faces)
    coverage = ", ".join(f"{c:.3g}" for c in done.coverage)
    text = (f"{len(done.faces)} levels of {faces} faces (screen coverage {coverage}) "
            f"in {done.seconds:.2f} s")
    if done.drawn:      # a scene: what is drawn, each mesh once per instance
        drawn = ", ".join(str(count) for count in done.drawn)
        errors = ", ".join("-" if e is None else f"{e:.3g}" for e in done.errors)
        text += f"; {drawn} triangles drawn, worst world error {errors}"
    if done.clustered:
        levels = ", ".join(str(i) for i in done.clustered)
        text += (f"; level {levels} by vertex clustering (edge collapse stops at "
                 f"{done.base_faces} faces)")
    elif done.faces[-1] == done.base_faces and len(set(done.faces[-2:])) == 1:
        # the coarser ratios were out of reach: say so rather than ship copies quietly
        text += (f"; the mesh simplifies no further than {done.base_faces} faces "
                 f"(locked, non-manifold or separate parts; --reach merge meets the budget)")
    for note in done.notes:     # what a glTF scene's export kept without levels
        text += f"; {note}"
    return text


def _export_folder(args, chain, options, begun: float) -> int:
    """Every mesh file under ``args.source`` into the folder ``args.output``: a bar
    over the files on a terminal, a line per file, exit 1 if any failed (the same
    on a Dask cluster, ``--scheduler``)."""
    from tqdm import tqdm

    from .pipeline import export_folder, find_sources, is_url
    from .schedulers import check_scheduler

    check_scheduler(args.scheduler)
    sources = find_sources(args.source)
    # kernels compile where the builds run: here, or in workers on this machine
    if args.scheduler in (None, "local") and any(path.suffix.lower() != ".pm"
                                                 for path in sources):
        _announce_compile(options.method)
    root = str(args.output).rstrip("/")

    def name(path) -> str:
        # outputs as the user named the folder: a path under it, or a key under the URL
        if is_url(args.output):
            return str(path)[len(root) + 1:]
        return str(Path(path).relative_to(args.output))

    bar = tqdm(total=len(sources), unit="asset", disable=None,
               dynamic_ncols=True, desc="exporting", file=sys.stderr)

    def progress(relative, outcome):
        if isinstance(outcome, str) and outcome != "up to date":
            bar.write(f"{relative}: FAILED: {outcome}", file=sys.stderr)
        elif not isinstance(outcome, str):
            outputs = ", ".join(name(p) for p in outcome.outputs)
            bar.write(f"{relative} -> {outputs}: {_levels(outcome)}", file=sys.stderr)
        bar.update(1)

    start = time.perf_counter()
    try:
        report = export_folder(args.source, args.output, chain, jobs=args.jobs,
                               force=args.force, options=options, untrusted=args.untrusted,
                               scheduler=args.scheduler, progress=progress)
    finally:
        bar.close()
    print(f"{args.output}: {report.total} assets in {time.perf_counter() - start:.2f} s: "
          f"{len(report.written)} written, {len(report.up_to_date)} up to date, "
          f"{len(report.failed)} failed", file=sys.stderr)
    if args.report is not None:
        from .scene.report import folder_entries
        _write_report(args.report, "export",
                      folder_entries(report, args.source, local=not is_url(args.output)),
                      begun)
    if report.failed:
        reasons = "; ".join(f"{path}: {reason}" for path, reason in report.failed.items())
        raise MeshError(f"{len(report.failed)} of {report.total} assets failed: {reasons}")
    return 0


def _cmd_info(args) -> int:
    from .progressive.mesh import ProgressiveMesh

    pm = ProgressiveMesh.load(_input_file(args.asset))
    print(json.dumps(pm.summary(), indent=2))
    sys.stdout.flush()      # here, where a closed pipe is caught, not at interpreter exit
    return 0


def _cmd_serve(args) -> int:
    from .api.run import serve

    return serve(data=args.data, host=args.host, port=args.port, log_level=args.log_level)


def _cmd_worker(args) -> int:
    from .api.run import work

    return work(data=args.data, workers=args.workers, log_level=args.log_level)


# --- the parser ----------------------------------------------------------------------

MESH_HELP = "OBJ, PLY, STL, OFF, glTF or GLB file"
OUTPUT_HELP = (f"{', '.join(name.upper() for name in SUPPORTED_OUTPUT[:-1])} or "
               f"{SUPPORTED_OUTPUT[-1].upper()} file to write (its folder is created)")
UNTRUSTED_HELP = ("the file comes from someone else: every file it names (glTF buffers and "
                  "images, mtllib, texture maps) must lie inside its folder, with no absolute "
                  "path, '..', symbolic link or URL, and the server's size limits apply")


def _input_flags(p: argparse.ArgumentParser, exclude=()) -> None:
    """The flags of a command that reads and builds a mesh file: --untrusted and
    the build options."""
    p.add_argument("--untrusted", action="store_true", help=UNTRUSTED_HELP)
    add_option_flags(p, exclude=set(exclude))


def _command(sub, name: str, help_text: str, example: str) -> argparse.ArgumentParser:
    return sub.add_parser(name, help=help_text, description=help_text[0].upper() + help_text[1:]
                          + ".", epilog=f"example:\n  {example}",
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lodserver", description="Decimate once, serve every level of detail: build a "
        "progressive mesh of a mesh file, write its levels, or serve them over HTTP.",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"lodserver {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", title="commands")

    p = _command(sub, "build", "build the progressive mesh of a mesh file",
                 "lodserver build tests/data/spot.obj -o spot.pm --pair-threshold 1%")
    p.add_argument("mesh", help=MESH_HELP)
    p.add_argument("-o", "--output", required=True,
                   help="the .pm artefact to write (its folder is created)")
    _input_flags(p)
    p.set_defaults(run=_cmd_build)

    p = _command(sub, "extract", "write one level of a .pm artefact as a mesh file",
                 "lodserver extract spot.pm --faces 500 -o lods/spot_500.obj")
    p.add_argument("asset", help="the .pm artefact")
    group = p.add_mutually_exclusive_group(required=True)
    group.add_argument("--vertices", type=int, help="at most this many vertices")
    group.add_argument("--faces", type=int, help="at most this many faces")
    group.add_argument("--ratio", type=float, help="this fraction of the faces, in (0, 1]")
    group.add_argument("--error", type=float, help="coarsest level with at most this error (mesh units)")
    p.add_argument("-o", "--output", required=True, help=OUTPUT_HELP)
    p.add_argument("--report", metavar="FILE.json|-", help=REPORT_HELP)
    p.add_argument("--compress", choices=COMPRESSIONS, default="none",
                   help="a .glb output's storage, as for export: none (float32, the "
                        "progressive mesh's order; default, and the only one for other "
                        "formats), quantize or meshopt (both in vertex cache and fetch order)")
    p.set_defaults(run=_cmd_extract)

    p = _command(sub, "simplify", "write one simplified copy of a mesh file (no .pm)",
                 "lodserver simplify tests/data/spot.obj --ratio 0.1 -o spot_10.obj")
    p.add_argument("mesh", help=MESH_HELP)
    group = p.add_mutually_exclusive_group(required=True)
    group.add_argument("--faces", type=int, help="at most this many faces")
    group.add_argument("--ratio", type=float, help="this fraction of the faces, in (0, 1]")
    p.add_argument("--method", choices=METHODS, default="qem",
                   help="qem: edge collapse (best quality; the build options apply); cluster: "
                        "vertex clustering (fastest; may merge parts and change topology)")
    p.add_argument("-o", "--output", required=True, help=OUTPUT_HELP)
    _input_flags(p, exclude={"method"})
    p.set_defaults(run=_cmd_simplify)

    p = _command(sub, "export", "write levels of detail as one GLB (MSFT_lod) or one GLB "
                 "each, for a file or for every mesh file under a folder",
                 "lodserver export assets/ -o lods/ --lods 1,0.25,0.05 --jobs 2")
    p.add_argument("source", help="a .pm artefact or a mesh file to build one from; or a "
                   "folder: every mesh file under it, its layout mirrored in OUTPUT (a "
                   "folder may be an object-store URL, s3://bucket/prefix, for SOURCE and "
                   "OUTPUT alike; endpoint and credentials from the AWS_* variables)")
    p.add_argument("--lods", metavar="R1,R2,...",
                   help=f"face ratios of the levels, finest first, each in (0, 1] "
                        f"(default {DEFAULT_LODS_TEXT}); for a glTF scene, of the whole "
                        f"scene's triangles (each mesh once per instance), one budget whose "
                        f"worst world error is as low as it allows; a single mesh's level "
                        f"i's screen coverage hint is 0.5*sqrt(R(i+1)/R1), the last level's 0")
    p.add_argument("--per-mesh", action="store_true",
                   help="a glTF scene's --lods are each mesh's own face ratios, not the "
                        "scene's")
    p.add_argument("--error", dest="errors", metavar="E1,E2,...",
                   help="instead of --lods: error bounds of the levels, finest first, "
                        "increasing, as fractions of the bounding-box diagonal (a scene's "
                        "world box), each mesh at its coarsest level within the bound; "
                        "screen coverage hints from the levels' errors (under a pixel at "
                        "1080p)")
    p.add_argument("-o", "--output", required=True,
                   help="the .glb file to write; for a folder source, the folder to write "
                        "into (created either way)")
    p.add_argument("--separate", action="store_true",
                   help="write OUT_lod0.glb, OUT_lod1.glb, ... (their nodes named OUT_LOD0, "
                        "OUT_LOD1, ...) instead of one file")
    p.add_argument("--lod-naming", choices=LOD_NAMINGS, default="msft",
                   help="how one file's levels are told apart: msft (the MSFT_lod extension, "
                        "read by Babylon.js; default), suffix (nodes OUT_LOD0, OUT_LOD1, ... "
                        "under a root OUT, all in the scene: the convention Unity and Unreal "
                        "import LOD groups by) or both (MSFT_lod, nodes named OUT_LODn); a "
                        "glTF scene's levels are linked by MSFT_lod only")
    p.add_argument("--compress", choices=COMPRESSIONS, default=DEFAULT_COMPRESS,
                   help=f"how the GLB files store the levels: none (float32, what any glTF "
                        f"reader opens), quantize (KHR_mesh_quantization: 14-bit positions, "
                        f"8-bit normals, 16-bit UVs; read by three.js, Babylon.js, Unity's "
                        f"glTFast, Godot and Blender) or meshopt (also EXT_meshopt_compression, "
                        f"gltfpack -cc's form; the viewer needs a decoder such as three.js's "
                        f"MeshoptDecoder); both in vertex cache and fetch order (default "
                        f"{DEFAULT_COMPRESS})")
    p.add_argument("--report", metavar="FILE.json|-", help=REPORT_HELP)
    p.add_argument("--texture-scale", metavar="auto|S1,S2,...", type=_texture_scale,
                   help="texture levels: auto scales each level's images to its screen size "
                        "(sides by the square root of its share of the finest level's faces, "
                        "a power of two, at least 64 px), or give one scale in (0, 1] per "
                        "level; PNG, JPEG and WebP stay in their format, KTX2 is kept as it "
                        "is (default: every level keeps the full-size images)")
    p.add_argument("--reach", choices=REACH_METHODS, default=None,
                   help="levels edge collapse cannot bring down to their budget (locked, "
                        "non-manifold or separate parts): remesh the whole surface by vertex "
                        "clustering to within 10%% of the budget, joining parts (merge, the "
                        "default with --lods), keep the coarsest edge collapse reaches (none, "
                        "the default with --error) or cluster keeping positions only (cluster)")
    p.add_argument("--atlas-size", type=int, default=None, metavar="TEXELS",
                   help="the side of a merged level's baked atlas (--reach merge; default: "
                        "from the level's screen coverage, 64 to 2048)")
    p.add_argument("--impostor", action="store_true",
                   help="the farthest level of a static asset as an octahedral impostor: "
                        "views of the full-detail asset baked to one colour and one normal "
                        "atlas on a quad, drawn by static/impostor.js (with --separate and two "
                        "or more --lods; an animated or skinned scene keeps its level)")
    p.add_argument("--jobs", type=int, default=1,
                   help="folder source: meshes built at once (default 1; each holds its mesh "
                        "in memory); with --scheduler local, the worker processes")
    p.add_argument("--scheduler", metavar="tcp://HOST:PORT|local",
                   help="folder source: run each mesh as a task on the Dask cluster whose "
                        "scheduler is at that address, or on a LocalCluster of --jobs "
                        "processes started for the run (needs pip install "
                        "'lodserver[distributed]'; default: threads in this process; local "
                        "folders must be seen by every worker at the same path)")
    p.add_argument("--force", action="store_true",
                   help="folder source: rebuild every mesh, even those whose file and options "
                        "match the last run (lodserver-export.json in OUTPUT)")
    p.add_argument("--progressive", action="store_true",
                   help="write the progressive file instead of levels: one GLB whose base "
                        "level any glTF viewer draws, with every split record in chunks "
                        "behind the LODSERVER_progressive extension, for streaming from any "
                        "static host with range requests (docs/packets.md); the bytes "
                        "GET /meshes/{id}/progressive serves")
    p.add_argument("--bits", type=int, metavar="K",
                   help="--progressive: the grid of the file's base level and records, bits "
                        "per axis (default: by mesh size, as the server's /lod?format=json)")
    _input_flags(p)
    p.set_defaults(run=_cmd_export)

    p = _command(sub, "info", "print counts and the error curve of a .pm artefact as JSON",
                 "lodserver info spot.pm | head -5")
    p.add_argument("asset", help="the .pm artefact")
    p.set_defaults(run=_cmd_info)

    p = _command(sub, "serve", "run the HTTP API and the viewer (settings: LODSERVER_* "
                 "variables)", "lodserver serve --data ./lodserver-data --port 8000")
    p.add_argument("--data", type=Path, help="data directory (default: $LODSERVER_DATA_DIR or "
                   "./lodserver-data)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.add_argument("--log-level", default="info",
                   choices=["critical", "error", "warning", "info", "debug"])
    p.set_defaults(run=_cmd_serve)

    p = _command(sub, "worker", "build meshes from the shared build queue without serving "
                 "HTTP (settings: LODSERVER_* variables, as for serve)",
                 "LODSERVER_CATALOG_URL=postgresql://db/lods LODSERVER_STORE_URL=s3://bucket/lods "
                 "lodserver worker --data ./worker-data")
    p.add_argument("--data", type=Path, help="this worker's own data directory, for scratch "
                   "files and cached artefacts (default: $LODSERVER_DATA_DIR or ./lodserver-data)")
    p.add_argument("--workers", type=int, help="builds at a time (default: $LODSERVER_WORKERS "
                   "or 1)")
    p.add_argument("--log-level", default="info",
                   choices=["critical", "error", "warning", "info", "debug"])
    p.set_defaults(run=_cmd_worker)
    return parser


def _error_text(exc: OSError, args) -> str:
    """An OSError as one sentence naming the user's file, never a temporary sibling of it."""
    name = exc.filename
    output = getattr(args, "output", None)
    if name is not None and output is not None:
        # io.write_atomic writes ".NAME.<hex>.tmp" beside the output first
        if Path(name).name.startswith(f".{Path(output).name}.") and str(name).endswith(".tmp"):
            name = output
    return f"{exc.strerror or exc}: {name}" if name else str(exc.strerror or exc)


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    args.argv = sys.argv[1:] if argv is None else list(argv)     # for a run in a child process
    if args.command is None:
        parser.print_help(sys.stderr)
        print("\nlodserver: name a command, such as 'lodserver build MESH -o ASSET.pm'.",
              file=sys.stderr)
        return 2
    try:
        return args.run(args)
    except BrokenPipeError:
        # `lodserver info x.pm | head -1`: the reader left; nothing more to say. Point
        # stdout at devnull so the interpreter's final flush does not complain either.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141      # what a shell reports for a command ended by SIGPIPE
    except MeshError as exc:
        print(f"lodserver {args.command}: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"lodserver {args.command}: {_error_text(exc, args)}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
