"""The asset pipeline: mesh files in, chains of levels of detail (GLB) out.

``export_lods`` writes one source's levels, picked by face ratio, as one GLB
whose nodes are linked by ``MSFT_lod`` (with ``MSFT_screencoverage`` hints), or
as one GLB per level. The source is a ``.pm`` artefact or a mesh file, built
on the way.

``export_folder`` does that for every mesh file under a folder, mirroring the
folder's layout (``ASSETS/props/chair.obj`` -> ``LODS/props/chair.glb``), with
several builds at once if asked. One bad file fails alone, with its reason,
and never leaves a partial output. A manifest beside the outputs
(``lodserver-export.json``) records each source's SHA-256 and the options used,
so a second run rebuilds only what changed. Only the named file is hashed:
after editing a texture or a ``.bin`` beside a ``.gltf``, pass ``force``.
"""

from __future__ import annotations

import hashlib
import json
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

from .io.glb import coverage_from_ratios, encode_lod_chain
from .io import SUPPORTED_INPUT, encode_mesh, write_atomic
from .mesh import Mesh, MeshError
from .options import BuildOptions
from .progressive.mesh import ProgressiveMesh

DEFAULT_LODS = (1.0, 0.5, 0.2, 0.05)
SOURCE_SUFFIXES = tuple(f".{kind}" for kind in SUPPORTED_INPUT) + (".pm",)
MANIFEST = "lodserver-export.json"
_MANIFEST_VERSION = 1


def parse_lods(text: str) -> tuple[float, ...]:
    """Face ratios from ``"1,0.5,0.2"``: finest first, each in (0, 1], decreasing."""
    try:
        ratios = tuple(float(part) for part in text.split(","))
    except ValueError:
        raise MeshError(f"LOD ratios must be comma-separated numbers like 1,0.5,0.2, "
                        f"got {text!r}") from None
    return check_lods(ratios)


def check_lods(ratios) -> tuple[float, ...]:
    ratios = tuple(float(r) for r in ratios)
    if not all(0 < ratio <= 1 for ratio in ratios):
        raise MeshError(f"every LOD ratio must be in (0, 1], got {list(ratios)}")
    coverage_from_ratios(ratios)        # and strictly decreasing
    return ratios


@dataclass
class Exported:
    """One source's levels of detail, as written."""

    source: Path
    outputs: list[Path]
    faces: list[int]            # per level, finest first
    coverage: list[float]       # MSFT_screencoverage per level
    seconds: float
    base_faces: int = 0         # the coarsest edge collapse reaches: ratios below it stop there
    clustered: list[int] = field(default_factory=list)   # levels made by clustering (reach)


# A level whose edge-collapse mesh overshoots its face budget by more than this is
# out of reach of edge collapse (locked, non-manifold or separate parts).
REACH_SLACK = 1.1
REACH_METHODS = ("none", "cluster")


def check_reach(reach: str) -> str:
    if reach not in REACH_METHODS:
        raise MeshError(f"reach must be one of {', '.join(REACH_METHODS)}, got {reach!r}")
    return reach


def lod_chain(pm: ProgressiveMesh, lods=DEFAULT_LODS, *, reach: str = "none"):
    """The levels of ``pm`` at face ratios ``lods`` (finest first).

    Returns ``(meshes, coverage, clustered)``: the meshes, their screen coverage
    hints (:func:`gltf.coverage_from_ratios`) and the indices of the levels made
    by clustering (``reach``, as for :func:`export_lods`). Raises
    :class:`MeshError` on bad ratios or ``reach``.
    """
    ratios = check_lods(lods)
    check_reach(reach)
    meshes, clustered, full = [], [], None
    for ratio in ratios:
        mesh = pm.at(pm.level_for(ratio=ratio))
        budget = max(1, round(ratio * pm.face_count))
        if reach == "cluster" and mesh.face_count > REACH_SLACK * budget:
            from .simplify.cluster import cluster
            if full is None:
                full = pm.at(pm.vertex_count)
                full = Mesh(full.positions, full.faces)
            joined = cluster(full, target_faces=budget)
            if joined.face_count < mesh.face_count:
                mesh = joined
                clustered.append(len(meshes))
        meshes.append(mesh)
    return meshes, coverage_from_ratios(ratios), clustered


def export_lods(source, output, *, lods=DEFAULT_LODS, separate: bool = False,
                reach: str = "none", options: BuildOptions | None = None,
                untrusted: bool = False,
                progress=None) -> Exported:
    """Write the levels of detail of ``source`` to ``output`` (a ``.glb`` path).

    Parameters
    ----------
    source : path
        A ``.pm`` artefact, or a mesh file (built with ``options``).
    lods : sequence of float
        Face ratios of the levels, finest first, strictly decreasing, in (0, 1].
    separate : bool
        Write ``OUT_lod0.glb``, ``OUT_lod1.glb``, ... instead of one file.
    reach : str
        ``"none"``: a level edge collapse cannot bring down to its budget stays
        at the coarsest it reaches. ``"cluster"``: such a level is made by vertex
        clustering of the full mesh instead (``cluster.cluster``), which joins
        parts and meets the budget but keeps positions only (no UVs, normals or
        materials: a textured asset's far level is drawn untextured).
    options : BuildOptions, optional
        How a mesh file is built (``options.BuildOptions``; None: the defaults).
        A ``.pm`` source was built already and ignores them.
    untrusted : bool
        Load a mesh file as the server loads an upload (``build.build``).
    progress : callable, optional
        ``progress(done, expected)`` during a build, as for ``build``.

    Raises
    ------
    MeshError
        On a bad source, bad ratios or an output that is not ``.glb``. Nothing is
        written then; each file written is complete (``io.write_atomic``).
    """
    check_lods(lods)        # before a build, not after
    check_reach(reach)
    options = BuildOptions.check(options)
    source, output = Path(source), Path(output)
    if output.suffix.lower() != ".glb":
        raise MeshError(f"levels of detail are written as GLB, so the output must end in .glb, "
                        f"got {output.name}")
    start = time.perf_counter()
    if source.suffix.lower() == ".pm":
        pm = ProgressiveMesh.load(source)
    else:
        from .build import build
        try:
            pm = build(source, options, progress=progress, untrusted=untrusted)
        except ValueError as exc:       # argument checks deep in the build
            raise MeshError(str(exc)) from exc
    meshes, coverage, clustered = lod_chain(pm, lods, reach=reach)
    if separate:
        outputs = [output.with_name(f"{output.stem}_lod{i}{output.suffix}")
                   for i in range(len(meshes))]
        blobs = [encode_mesh(mesh, "glb") for mesh in meshes]
    else:
        outputs, blobs = [output], [encode_lod_chain(meshes, coverage)]
    output.parent.mkdir(parents=True, exist_ok=True)
    for path, blob in zip(outputs, blobs):
        write_atomic(path, blob)
    return Exported(source, outputs, [mesh.face_count for mesh in meshes], coverage,
                    time.perf_counter() - start, pm.faces_at_level(pm.base_vertices),
                    clustered)


@dataclass
class FolderReport:
    """What ``export_folder`` did with each source (paths relative to the source folder)."""

    written: list[Exported] = field(default_factory=list)
    up_to_date: list[Path] = field(default_factory=list)
    failed: dict[Path, str] = field(default_factory=dict)

    @property
    def total(self) -> int:
        return len(self.written) + len(self.up_to_date) + len(self.failed)


def find_sources(folder) -> list[Path]:
    """Mesh files (and ``.pm`` artefacts) under ``folder``, sorted, as relative paths.

    Hidden files and folders (a leading dot) are left out, as are files inside a
    folder holding an export manifest: an output folder inside the source is
    not read back as input.
    """
    folder = Path(folder)
    outputs = {path.parent for path in folder.rglob(MANIFEST)}
    found = []
    for path in sorted(folder.rglob("*")):
        relative = path.relative_to(folder)
        if (not path.is_file() or path.suffix.lower() not in SOURCE_SUFFIXES
                or any(part.startswith(".") for part in relative.parts)
                or any(out == path.parent or out in path.parents for out in outputs)):
            continue
        found.append(relative)
    return found


def export_folder(source, output, *, lods=DEFAULT_LODS, separate: bool = False,
                  reach: str = "none", jobs: int = 1, force: bool = False,
                  options: BuildOptions | None = None, untrusted: bool = False,
                  progress=None) -> FolderReport:
    """Export every mesh file under ``source`` into ``output`` (see the module docstring).

    Parameters
    ----------
    source, output : path
        Folders; ``output`` is created. ``source/a/b.obj`` goes to ``output/a/b.glb``.
    lods, separate, reach, options
        As for :func:`export_lods`; the manifest records them all, so changing
        one rebuilds.
    jobs : int
        Sources built at once (threads: the compiled kernels release the GIL).
        Each holds its mesh in memory.
    force : bool
        Rebuild sources the manifest says are up to date.
    progress : callable, optional
        ``progress(relative_path, outcome)`` as each source ends, ``outcome`` an
        :class:`Exported`, the string ``"up to date"``, or a failure's reason.

    Returns
    -------
    FolderReport
        A failed source does not stop the others; the caller decides what a
        failure means (the CLI exits with 1).

    Raises
    ------
    MeshError
        If ``source`` is not a folder, holds no mesh file, or the options are bad.
    """
    ratios = check_lods(lods)
    check_reach(reach)
    options = BuildOptions.check(options)
    source, output = Path(source), Path(output)
    if not source.is_dir():
        raise MeshError(f"{source} is not a folder")
    sources = find_sources(source)
    if not sources:
        raise MeshError(f"{source} holds no mesh file ({', '.join(SOURCE_SUFFIXES)})")
    if jobs < 1:
        raise MeshError(f"jobs must be at least 1, got {jobs}")
    output.mkdir(parents=True, exist_ok=True)
    recorded = {"lods": list(ratios), "separate": separate, "reach": reach,
                "build": options.model_dump()}
    manifest_path = output / MANIFEST
    manifest = _read_manifest(manifest_path)
    report = FolderReport()

    def finish(relative, outcome):
        if progress is not None:
            progress(relative, outcome)

    # Two sources that differ only in their suffix would write the same file.
    targets: dict[Path, list[Path]] = {}
    for relative in sources:
        targets.setdefault(relative.with_suffix(".glb"), []).append(relative)
    todo = []
    for target, group in targets.items():
        if len(group) > 1:
            names = " and ".join(str(r) for r in group)
            for relative in group:
                report.failed[relative] = (f"{names} would both be written to {target}; "
                                           f"rename one")
                finish(relative, report.failed[relative])
            continue
        relative = group[0]
        try:
            digest = _sha256(source / relative)
        except OSError as exc:
            report.failed[relative] = f"cannot read it: {exc.strerror or exc}"
            finish(relative, report.failed[relative])
            continue
        entry = manifest.get(str(relative))
        if (not force and entry is not None and entry.get("sha256") == digest
                and entry.get("options") == recorded
                and all((output / path).is_file() for path in entry.get("outputs", ()))):
            report.up_to_date.append(relative)
            finish(relative, "up to date")
            continue
        todo.append((relative, digest))

    def one(relative):
        return export_lods(source / relative, output / relative.with_suffix(".glb"),
                           lods=ratios, separate=separate, reach=reach, options=options,
                           untrusted=untrusted)

    try:
        with ThreadPoolExecutor(max_workers=jobs) as pool:
            running = {pool.submit(one, relative): (relative, digest) for relative, digest in todo}
            for done in as_completed(running):
                relative, digest = running[done]
                try:
                    exported = done.result()
                except (MeshError, OSError) as exc:
                    reason = str(exc)
                except Exception as exc:  # a bug on one asset must not stop the others
                    reason = f"internal error: {type(exc).__name__}: {exc}"
                else:
                    manifest[str(relative)] = {
                        "sha256": digest, "options": recorded,
                        "outputs": [str(p.relative_to(output)) for p in exported.outputs]}
                    report.written.append(exported)
                    finish(relative, exported)
                    continue
                manifest.pop(str(relative), None)
                report.failed[relative] = reason
                finish(relative, reason)
    finally:
        # what finished is remembered even if the run is cut short; sources that are
        # gone are forgotten (their outputs are left alone)
        present = {str(relative) for relative in sources}
        kept = {name: entry for name, entry in manifest.items() if name in present}
        document = {"version": _MANIFEST_VERSION, "sources": dict(sorted(kept.items()))}
        write_atomic(manifest_path, (json.dumps(document, indent=1) + "\n").encode())
    report.written.sort(key=lambda e: e.source)
    return report


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _read_manifest(path: Path) -> dict:
    """The sources recorded by an earlier run; empty when there is none or it is unreadable
    (then everything is rebuilt, which is always safe)."""
    try:
        document = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(document, dict) or document.get("version") != _MANIFEST_VERSION:
        return {}
    sources = document.get("sources")
    return dict(sources) if isinstance(sources, dict) else {}
