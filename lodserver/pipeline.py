"""The asset pipeline: mesh files in, chains of levels of detail (GLB) out.

``export_lods`` writes one source's levels, picked by face ratio or by error
bound, as one GLB whose nodes are linked by ``MSFT_lod`` (with
``MSFT_screencoverage`` hints), or as one GLB per level. The source is a ``.pm``
artefact or a mesh file, built on the way; a glTF scene keeps its document,
each of its meshes replaced by its own chain, the levels of all its meshes
chosen together: a ratio is of the whole scene's triangles (``budget``).

``export_folder`` does that for every mesh file under a folder, mirroring the
folder's layout (``ASSETS/props/chair.obj`` -> ``LODS/props/chair.glb``), with
several builds at once if asked. One bad file fails alone, with its reason,
and never leaves a partial output. A manifest beside the outputs
(``lodserver-export.json``) records each source's SHA-256 and the options used,
so a second run rebuilds only what changed. Only the named file is hashed:
after editing a texture or a ``.bin`` beside a ``.gltf``, pass ``force``.

Each asset is one task (:func:`export_asset`, given an :class:`AssetJob`) run
where ``scheduler`` says (:mod:`.schedulers`: threads here by default, or a Dask
cluster); this process alone hashes the sources, reads and writes the manifest
and reports, so the outcome does not depend on where the tasks ran. Either
folder may be an object-store URL (``s3://bucket/prefix``, through fsspec): a
task fetches its source and the files it names into a temporary folder, and
writes each output as one whole object.
"""

from __future__ import annotations

import json
import tempfile
import time
import uuid
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath

from .chains import ChainOptions, Exported, error_chain, lod_chain, shared_materials
from .folders import (MANIFEST, MANIFEST_VERSION, Folder, fetch_with_references, filesystem,
                      is_url, listing)
from .io.glb import encode_glb, encode_lod_chain, lod_name
from .io import SUPPORTED_INPUT, write_atomic
from .mesh import MeshError
from .options import BuildOptions
from .progressive.mesh import ProgressiveMesh
from .scene.budget import part_diagonal
from .scene.export import export_scene
from .scene.report import level_errors
from .scene.textures import chain_with_texture_levels

SOURCE_SUFFIXES = tuple(f".{kind}" for kind in SUPPORTED_INPUT) + (".pm",)


def export_lods(source, output, chain: ChainOptions | None = None, *,
                options: BuildOptions | None = None, untrusted: bool = False, progress=None,
                **chain_keywords) -> Exported:
    """Write the levels of detail of ``source`` to ``output`` (a ``.glb`` path).

    Parameters
    ----------
    source : path
        A ``.pm`` artefact, or a mesh file (built with ``options``). A glTF or
        GLB file keeps its scene (``io.scene``): each glTF mesh is built once
        and the output is the input document with every mesh replaced by its
        levels (``io.scene_glb``); skinned and morphed meshes are kept as they
        are, one level, and ``Exported.notes`` says so.
    chain : ChainOptions, optional
        Which levels, and how they are written (None: every default). Its
        fields may be given as keywords instead (``lods=(1, 0.5, 0.1)``,
        ``errors``, ``per_mesh``, ``separate``, ``reach``), not with it.
    options : BuildOptions, optional
        How a mesh file is built (``options.BuildOptions``; None: the defaults).
        A ``.pm`` source was built already and ignores them.
    untrusted : bool
        Load a mesh file as the server loads an upload (``build.build``).
    progress : callable, optional
        ``progress(done, expected)`` during a build, as for ``build``.

    The ``MSFT_screencoverage`` hints of a single mesh's ratios come from the
    ratios (``glb.coverage_from_ratios``); those of a scene, and of levels by
    error, from the levels' measured errors (``budget.coverage_from_errors``:
    the coverage below which the next level's error is under a pixel at 1080p).

    Raises
    ------
    MeshError
        On a bad source, bad ratios or errors, both given, or an output that is
        not ``.glb``. Nothing is written then; each file written is complete
        (``io.write_atomic``).
    TypeError
        A keyword that is not a field of ``ChainOptions``, or ``chain`` with keywords.
    """
    chain = ChainOptions.of(chain, chain_keywords)      # checked before a build
    options = BuildOptions.check(options)
    source, output = Path(source), Path(output)
    if output.suffix.lower() != ".glb":
        raise MeshError(f"levels of detail are written as GLB, so the output must end in .glb, "
                        f"got {output.name}")
    start = time.perf_counter()
    if source.suffix.lower() in (".gltf", ".glb"):
        from .io.scene import load_scene
        scene = load_scene(source, root=source.parent if untrusted else None)
        if chain.impostor:
            return _scene_with_impostor(scene, source, output, chain, options, progress, start)
        return export_scene(scene, source, output, chain, options, progress, start)
    if source.suffix.lower() == ".pm":
        pm = ProgressiveMesh.load(source)
    else:
        from .build import build
        try:
            pm = build(source, options, progress=progress, untrusted=untrusted)
        except ValueError as exc:       # argument checks deep in the build
            raise MeshError(str(exc)) from exc
    full_chain, impostor = chain, None
    if chain.impostor:     # baked before any level is written (scene.impostor_level)
        from .scene.impostor_level import baked_impostor, without_farthest
        impostor = baked_impostor(pm.at(pm.vertex_count), output, len(chain.lods) - 1)
        chain = without_farthest(chain)
    if chain.errors is not None:
        (meshes, coverage), clustered = error_chain(pm, chain.errors), []
    else:
        meshes, coverage, clustered = lod_chain(pm, chain.lods, reach=chain.reach,
                                                atlas=chain.atlas)
    outputs, notes, seconds = _write_chain(output, chain, meshes, coverage)
    done = Exported(source, outputs, [mesh.face_count for mesh in meshes], coverage,
                    time.perf_counter() - start, pm.faces_at_level(pm.base_vertices),
                    clustered, notes, errors=level_errors(pm, chain, clustered),
                    diagonal=part_diagonal(pm), level_seconds=seconds)
    if impostor is None:
        return done
    from .scene.impostor_level import with_impostor
    blob, seconds = impostor
    return with_impostor(done, output, blob, full_chain.lods, seconds, start)


def _scene_with_impostor(scene, source, output, chain, options, progress, start) -> Exported:
    """``export_scene`` with the farthest level an impostor (``scene.impostor_level``),
    or, for a scene that is not static, without one and a note saying why."""
    from .scene.impostor_level import (baked_impostor, scene_full_mesh, with_impostor,
                                       without_farthest)

    full, reason = scene_full_mesh(scene)
    if full is None:
        done = export_scene(scene, source, output, replace(chain, impostor=False), options,
                            progress, start)
        return replace(done, notes=[*done.notes, reason])
    blob, seconds = baked_impostor(full, output, len(chain.lods) - 1)
    done = export_scene(scene, source, output, without_farthest(chain), options, progress, start)
    return with_impostor(done, output, blob, chain.lods, seconds, start)


def _write_chain(output: Path, chain: ChainOptions, meshes, coverage):
    """The chain's files written: (their paths, notes on what was not scaled, the
    seconds each level's file took with ``separate``)."""
    meshes, notes = chain_with_texture_levels(meshes, chain.texture_scale,
                                              separate=chain.separate)
    output.parent.mkdir(parents=True, exist_ok=True)
    if not chain.separate:
        meshes = shared_materials(meshes)      # a baked level's material joins the rest
        write_atomic(output, encode_lod_chain(meshes, coverage, chain.compress,
                                              naming=chain.naming, name=output.stem))
        return [output], notes, []
    outputs = [output.with_name(f"{output.stem}_lod{i}{output.suffix}")
               for i in range(len(meshes))]
    blobs, seconds = [], []
    for i, mesh in enumerate(meshes):       # every level encoded before any is written
        begun = time.perf_counter()
        blobs.append(encode_glb(mesh, chain.compress, name=lod_name(output.stem, i)))
        seconds.append(time.perf_counter() - begun)
    for i, (path, blob) in enumerate(zip(outputs, blobs)):
        begun = time.perf_counter()
        write_atomic(path, blob)
        seconds[i] += time.perf_counter() - begun
    return outputs, notes, seconds


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
    not read back as input. ``folder`` may be an object-store URL (see
    :func:`export_folder`); the paths are then ``PurePosixPath``.
    """
    if is_url(folder):
        fs, root = filesystem(folder)
        return _keep_sources([PurePosixPath(key[len(root) + 1:]) for key in listing(fs, root)])
    folder = Path(folder)
    return _keep_sources([path.relative_to(folder) for path in sorted(folder.rglob("*"))
                          if path.is_file()])


def _keep_sources(relatives: list) -> list:
    outputs = {relative.parent for relative in relatives if relative.name == MANIFEST}
    return [relative for relative in sorted(relatives)
            if relative.suffix.lower() in SOURCE_SUFFIXES
            and not any(part.startswith(".") for part in relative.parts)
            and not any(out == relative.parent or out in relative.parents for out in outputs)]


def export_folder(source, output, chain: ChainOptions | None = None, *, jobs: int = 1,
                  force: bool = False, options: BuildOptions | None = None,
                  untrusted: bool = False, scheduler=None, progress=None,
                  **chain_keywords) -> FolderReport:
    """Export every mesh file under ``source`` into ``output`` (see the module docstring).

    Parameters
    ----------
    source, output : path or str
        Folders; ``output`` is created. ``source/a/b.obj`` goes to ``output/a/b.glb``.
        Either may be an object-store URL (``s3://bucket/prefix``; the endpoint and
        credentials come from the standard AWS variables, such as
        ``AWS_ENDPOINT_URL``): a task then fetches its source, with the files it
        names (a glTF's buffers and images, an OBJ's MTL and textures), into a
        temporary folder, and writes each output as one whole object.
    chain, options
        As for :func:`export_lods` (the chain's fields may be keywords here
        too); the manifest records them all, so changing one rebuilds
        (``per_mesh`` only for glTF sources, the only ones it changes;
        ``errors`` when given).
    jobs : int
        Sources built at once: threads of the local pool (the compiled kernels
        release the GIL), or worker processes of ``scheduler="local"``. Each holds
        its mesh in memory.
    force : bool
        Rebuild sources the manifest says are up to date.
    scheduler : None, str or distributed.Client
        Where the builds run (:mod:`.schedulers`): None, the local pool; ``"local"``,
        a Dask ``LocalCluster`` started for this call; a Dask address
        (``tcp://HOST:PORT``) or a ``Client``: that cluster, whose workers must
        see local folders at the same paths. The outputs and the manifest are the
        same byte for byte.
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
        If ``source`` is not a folder, holds no mesh file, or the options or the
        scheduler are bad (``schedulers.SchedulerError``).
    """
    from .schedulers import check_scheduler, open_scheduler

    chain = ChainOptions.of(chain, chain_keywords)
    options = BuildOptions.check(options)
    check_scheduler(scheduler)
    if jobs < 1:
        raise MeshError(f"jobs must be at least 1, got {jobs}")
    inputs, outputs = Folder(source), Folder(output)
    if not inputs.is_folder():
        raise MeshError(f"{source} is not a folder")
    sources = find_sources(source)
    if not sources:
        raise MeshError(f"{source} holds no mesh file ({', '.join(SOURCE_SUFFIXES)})")
    outputs.create()
    recorded = {"lods": list(chain.lods) if chain.lods is not None else None,
                "separate": chain.separate, "reach": chain.reach, "build": options.recorded()}
    if chain.errors is not None:
        recorded["errors"] = list(chain.errors)
    # (recorded when not the default, so the manifests of earlier runs stay as they were)
    if chain.compress != "none":
        recorded["compress"] = chain.compress
    if chain.atlas is not None:
        recorded["atlas"] = chain.atlas
    if chain.naming != "msft":
        recorded["naming"] = chain.naming
    if chain.impostor:
        recorded["impostor"] = True
    if chain.texture_scale is not None:
        recorded["texture_scale"] = (chain.texture_scale if chain.texture_scale == "auto"
                                     else list(chain.texture_scale))

    def recorded_for(relative) -> dict:
        # a glTF scene's levels depend on whether they share one budget; other
        # sources are one mesh either way, so their entries stay as they were
        if PurePosixPath(relative).suffix.lower() in (".gltf", ".glb"):
            return {**recorded, "levels": "per mesh" if chain.per_mesh else "scene"}
        return recorded

    manifest = outputs.read_manifest()
    existing = outputs.existing()
    report = FolderReport()

    def finish(relative, outcome):
        if progress is not None:
            progress(relative, outcome)

    def fail(relative, reason, *, built=False):
        if built:       # a build that failed forgets the last good one
            manifest.pop(_key(relative), None)
        report.failed[relative] = reason
        finish(relative, reason)

    # Two sources that differ only in their suffix would write the same file.
    targets: dict[Path, list[Path]] = {}
    for relative in sources:
        targets.setdefault(relative.with_suffix(".glb"), []).append(relative)
    digests = inputs.sha256_all([group[0] for group in targets.values() if len(group) == 1])
    todo = []
    for target, group in targets.items():
        if len(group) > 1:
            names = " and ".join(str(r) for r in group)
            for relative in group:
                fail(relative, f"{names} would both be written to {target}; rename one")
            continue
        relative = group[0]
        digest = digests[relative]
        if isinstance(digest, OSError):
            fail(relative, f"cannot read it: {digest.strerror or digest}")
            continue
        entry = manifest.get(_key(relative))
        if (not force and entry is not None and entry.get("sha256") == digest
                and entry.get("options") == recorded_for(relative)
                and all(path in existing for path in entry.get("outputs", ()))):
            report.up_to_date.append(relative)
            finish(relative, "up to date")
            continue
        todo.append((relative, digest))

    # the local pool's threads share this process's working folder; a cluster's
    # workers need absolute paths (or URLs)
    shared = scheduler is not None
    try:
        # nothing to build: no cluster started (a LocalCluster takes seconds)
        with (open_scheduler(scheduler, jobs=jobs) if todo else nullcontext()) as runner:
            running = {}
            for relative, digest in todo:
                job = AssetJob(inputs.shared(shared), outputs.shared(shared),
                               PurePosixPath(relative).as_posix(), chain, options, untrusted)
                key = f"lodserver-export-{_key(relative)}-{uuid.uuid4().hex[:12]}"
                running[runner.submit(export_asset, job, key)] = (relative, digest)
            for done in runner.completed(list(running)) if running else ():
                relative, digest = running.pop(done)
                outcome = runner.outcome(done)
                if isinstance(outcome, BaseException):   # the scheduler's, not the asset's
                    fail(relative, f"its task was lost: {type(outcome).__name__}: {outcome}",
                         built=True)
                elif isinstance(outcome, str):
                    fail(relative, outcome, built=True)
                else:
                    exported = replace(outcome, source=inputs.location(relative),
                                       outputs=[outputs.location(name)
                                                for name in outcome.outputs])
                    manifest[_key(relative)] = {
                        "sha256": digest, "options": recorded_for(relative),
                        "outputs": [str(name) for name in outcome.outputs]}
                    report.written.append(exported)
                    finish(relative, exported)
    finally:
        # what finished is remembered even if the run is cut short; sources that are
        # gone are forgotten (their outputs are left alone). Only this process writes
        # the manifest: a task retried on another worker cannot race it.
        present = {_key(relative) for relative in sources}
        kept = {name: entry for name, entry in manifest.items() if name in present}
        document = {"version": MANIFEST_VERSION, "sources": dict(sorted(kept.items()))}
        outputs.write(MANIFEST, (json.dumps(document, indent=1) + "\n").encode())
    report.written.sort(key=lambda e: PurePosixPath(str(e.source)))
    return report


def _key(relative) -> str:
    # the manifest's name of a source: its relative path as the OS writes it
    return str(relative)


@dataclass(frozen=True)
class AssetJob:
    """One asset of a folder export, as a task gets it (picklable; folders as strings:
    absolute local paths every worker sees, or object-store URLs)."""

    source: str
    output: str
    relative: str            # the source file under ``source``, '/'-separated
    chain: ChainOptions
    options: BuildOptions
    untrusted: bool


def export_asset(job: AssetJob):
    """Export one asset of a folder (the task a scheduler runs): :func:`export_lods`,
    fetching the source and writing the outputs through the object store when its
    folders are URLs.

    Returns the :class:`Exported`, with ``source`` and ``outputs`` relative
    (``PurePosixPath``) to the job's folders, or the reason it failed (str).
    Running it twice writes the same files (each whole): a worker lost
    mid-task costs only the rerun.
    """
    try:
        return _export_asset(job)
    except (MeshError, OSError) as exc:
        return str(exc)
    except Exception as exc:  # a bug on one asset must not stop the others
        return f"internal error: {type(exc).__name__}: {exc}"


def _export_asset(job: AssetJob) -> Exported:
    relative = PurePosixPath(job.relative)
    target = relative.with_suffix(".glb")
    with tempfile.TemporaryDirectory(prefix="lodserver-export-") as scratch:
        if is_url(job.source):
            fs, root = filesystem(job.source)
            source = fetch_with_references(fs, root, relative, Path(scratch, "in"))
        else:
            source = Path(job.source, *relative.parts)
        written_to = Path(scratch, "out") if is_url(job.output) else Path(job.output)
        exported = export_lods(source, written_to.joinpath(*target.parts), job.chain,
                               options=job.options, untrusted=job.untrusted)
        names = [PurePosixPath(path.relative_to(written_to).as_posix())
                 for path in exported.outputs]
        if is_url(job.output):
            fs, root = filesystem(job.output)
            for path, name in zip(exported.outputs, names):
                # one PUT of the whole object (or a multipart upload, completed at
                # once): a reader sees the old object or the new one
                fs.put_file(str(path), f"{root}/{name}")
    return replace(exported, source=relative, outputs=names)
