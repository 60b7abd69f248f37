"""Request and response bodies: what a client sends (``MeshCreate``) and sees (``MeshPublic``)."""

from __future__ import annotations

from datetime import datetime, timezone

from pydantic import BaseModel, Field, field_validator

from ..io.fileset import MAX_NAME_BYTES, check_name, load_warnings
from ..options import BuildOptions
from ..service.store import MeshRecord, Status
from ..packets.served import SERVED_VERSIONS
from .caching import version_of, versioned_urls


class MeshCreate(BuildOptions):
    """The form fields of ``POST /meshes`` beside the file: the build options
    (``options.BuildOptions``, the same names, defaults and ranges as the
    command line's) and a name."""

    name: str | None = Field(None, min_length=1, description="A label; defaults to the "
                             f"uploaded file's name. At most {MAX_NAME_BYTES} bytes in "
                             "UTF-8, no control characters.")

    @field_validator("name")
    @classmethod
    def _kept_as_given(cls, value):
        # io.fileset.check_name: the one rule for names, the same on every catalogue
        return value if value is None else check_name(value, what="the name")

    def build_options(self) -> dict:
        """The options to store with the mesh and pass to ``build.build``, by name."""
        options = self.recorded()
        del options["name"]
        return options


class MeshCreated(BaseModel):
    id: str
    status: Status
    href: str = Field(description="Where to poll the build.")
    main: str | None = Field(None, description="The file built (of a set: the mesh file).")
    files: list[str] = Field(default_factory=list, description="The files of the upload.")
    warnings: list[str] = Field(default_factory=list, description="What the load left out "
                                "(files the mesh names that were not uploaded, data not kept).")


class ErrorPoint(BaseModel):
    ratio: float
    vertices: int
    faces: int
    error: float = Field(description="Largest collapse error to reach this level, mesh units.")


class PartPublic(BaseModel):
    """One part of a mesh: a glTF mesh of a scene with its own levels (a single mesh
    is a scene of one part, index 0, whose endpoints answer as the mesh's own)."""

    index: int
    name: str
    mesh: int | None = Field(None, description="The glTF mesh index in the uploaded "
                             "document; null for a single mesh.")
    nodes: list[int] = Field(default_factory=list, description="The glTF nodes placing it.")
    vertices: int
    faces: int
    base_vertices: int
    base_faces: int
    splits: int | None = None
    max_error: float | None = None
    error_curve: list[ErrorPoint] = Field(default_factory=list)
    bounds: dict[str, list[float]] | None = Field(
        None, description="Full-detail bounding box in the part's own (mesh) space.")
    urls: dict[str, str] = Field(description="The part's lod and splits URLs at the mesh's "
                                 "version (append the route's parameters).")
    packet_versions: list[int] = Field(default_factory=lambda: list(SERVED_VERSIONS),
                                       description="The packet versions its splits route "
                                       "writes (version=K); a client asks for the newest it reads.")


class MeshPublic(BaseModel):
    """A mesh as clients see it; counts and the error curve appear once it is ready."""

    id: str
    name: str
    status: Status
    progress: float = Field(ge=0, le=1)
    file_type: str
    source_bytes: int
    options: dict
    vertices: int | None = None
    faces: int | None = None
    base_vertices: int | None = None
    base_faces: int | None = None
    splits: int | None = None
    max_error: float | None = None
    error_curve: list[ErrorPoint] = Field(default_factory=list)
    bounds: dict[str, list[float]] | None = Field(
        None, description="Full-detail bounding box: {min: [x, y, z], max: [x, y, z]}, mesh units "
                          "(absent for meshes built before it was recorded).")
    load_report: dict | None = None
    warnings: list[str] = Field(default_factory=list, description="What the load left out, "
                                "in sentences (from load_report), once ready.")
    queue_position: int | None = Field(None, description="While queued: how many uploads "
                                       "queued before this one wait to be built (0: next).")
    failure: str | None = Field(None, description="Why the build failed.")
    version: str | None = Field(None, description="Once ready: the artefact's version, the "
                                "v= of the URLs in urls.")
    urls: dict[str, str] | None = Field(None, description="Once ready: the lod, splits, chain "
                                        "and materials URLs at this version (append the "
                                        "route's parameters: &ratio=0.1), which any cache, a "
                                        "CDN too, may keep for a year. A scene has no "
                                        "splits of its own (its parts have).")
    scene: bool = Field(False, description="Once ready: whether the mesh is a glTF scene "
                        "kept with its node tree (several parts, skins, animations, cameras).")
    parts: list[PartPublic] = Field(default_factory=list, description="Once ready: its parts, "
                                    "one per glTF mesh of a scene, one for a single mesh. "
                                    "Empty in the list of meshes (GET /meshes), which gives "
                                    "part_count: a scene may have thousands.")
    part_count: int = Field(0, description="Once ready: how many parts it has.")
    packet_versions: list[int] = Field(default_factory=lambda: list(SERVED_VERSIONS),
                                       description="The packet versions the splits routes "
                                       "write (version=K; docs/packets.md); a client asks for "
                                       "the newest it reads.")
    created: datetime
    updated: datetime

    @classmethod
    def from_record(cls, record: MeshRecord, *, parts: bool = True) -> MeshPublic:
        """The record as a client sees it; ``parts=False`` (the list of meshes)
        leaves the parts out and says only how many there are, so that the list's
        size depends on the number of meshes, not on their parts."""
        summary = record.summary
        listed = _parts(record) if parts else []
        return cls(
            id=record.id, name=record.name, status=record.status, progress=record.progress,
            file_type=record.file_type, source_bytes=record.source_bytes, options=record.options,
            vertices=summary.get("vertices"), faces=summary.get("faces"),
            base_vertices=summary.get("base_vertices"), base_faces=summary.get("base_faces"),
            splits=summary.get("splits"), max_error=summary.get("max_error"),
            error_curve=summary.get("error_curve", []), bounds=summary.get("bounds"),
            load_report=summary.get("metadata", {}).get("load_report"),
            warnings=report_warnings(summary.get("metadata", {}).get("load_report")),
            failure=record.failure,
            version=version_of(record.digest) if record.status is Status.READY else None,
            urls=_urls(record), scene=bool(summary.get("scene")),
            parts=listed, part_count=_part_count(record),
            created=datetime.fromtimestamp(record.created, timezone.utc),
            updated=datetime.fromtimestamp(record.updated, timezone.utc))


def report_warnings(report: dict | None) -> list[str]:
    """``io.fileset.load_warnings`` of a load report, and a scene's notes (what
    ``io.scene`` keeps without levels, or leaves out)."""
    return load_warnings(report) + list((report or {}).get("notes") or ())


def _urls(record: MeshRecord) -> dict | None:
    if record.status is not Status.READY:
        return None
    urls = versioned_urls(record.id, record.digest)
    if urls is not None and record.summary.get("scene"):
        del urls["splits"]
    return urls


def _part_count(record: MeshRecord) -> int:
    """How many parts ``_parts`` lists, without making them."""
    summary = record.summary
    if record.status is not Status.READY or "vertices" not in summary:
        return 0
    return len(summary["parts"]) if summary.get("scene") else 1


def _parts(record: MeshRecord) -> list[PartPublic]:
    """The parts of a ready mesh from its row alone: a scene's summary lists them,
    a single mesh is its own part 0."""
    summary, version = record.summary, version_of(record.digest)
    if record.status is not Status.READY or "vertices" not in summary or version is None:
        return []
    listed = summary["parts"] if summary.get("scene") else [
        {**summary, "index": 0, "name": record.name, "mesh": None, "nodes": []}]
    base = f"/meshes/{record.id}/parts"
    return [PartPublic(index=part["index"], name=part["name"], mesh=part["mesh"],
                       nodes=part["nodes"], vertices=part["vertices"], faces=part["faces"],
                       base_vertices=part["base_vertices"], base_faces=part["base_faces"],
                       splits=part.get("splits"), max_error=part.get("max_error"),
                       error_curve=part.get("error_curve", []), bounds=part.get("bounds"),
                       urls={route: f"{base}/{part['index']}/{route}?v={version}"
                             for route in ("lod", "splits")})
            for part in listed]


class MeshList(BaseModel):
    meshes: list[MeshPublic]


class Message(BaseModel):
    """Every error response: a sentence saying what went wrong."""

    message: str
