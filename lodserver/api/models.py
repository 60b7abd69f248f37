"""Request and response bodies: what a client sends (``MeshCreate``) and sees (``MeshPublic``)."""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from ..build import attribute_weights
from ..store import MeshRecord, Status


class MeshCreate(BaseModel):
    """The form fields of ``POST /meshes`` beside the file; build options of ``build.build``."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(None, min_length=1, max_length=200,
                             description="A label; defaults to the uploaded file's name.")
    boundary_weight: float = Field(1.0, ge=0, le=1e6, allow_inf_nan=False,
                                   description="Weight of the planes keeping open borders in "
                                   "place; 0 lets borders shrink.")
    min_vertices: int = Field(0, ge=0, le=2**31 - 1,
                              description="Stop decimating at this many vertices.")
    lock_border: bool = Field(False, description="Never move or remove border vertices.")
    pair_threshold: str = Field("0", pattern=r"^(\d+\.?\d*|\.\d+)(e[-+]?\d+)?%?$",
                                description="Also contract vertices closer than this that share "
                                "no edge (joins parts): mesh units, or a percentage of the "
                                "bounding-box diagonal such as '1%'. 0: edges only.")

    method: Literal["qem", "cluster"] = Field(
        "qem", description="qem: quadric edge collapse (best quality, keeps topology and "
        "attributes); cluster: octree vertex clustering (faster, joins parts, geometry only).")
    preserve_volume: bool = Field(True, description="Place collapses so the enclosed volume "
                                  "is kept (thin parts do not shrink away).")
    attributes: bool = Field(True, description="Simplify normals, UVs and colours with the "
                             "geometry (wedges, seams kept); false: positions only.")
    normal_weight: float | None = Field(None, gt=0, le=1e6, allow_inf_nan=False,
                                        description="Weight of normal error (default 0.003).")
    uv_weight: float | None = Field(None, gt=0, le=1e6, allow_inf_nan=False,
                                    description="Weight of UV error (default 0.3).")
    color_weight: float | None = Field(None, gt=0, le=1e6, allow_inf_nan=False,
                                       description="Weight of vertex colour error (default 0.3).")

    def build_options(self) -> dict:
        options = self.model_dump(exclude={"name", "normal_weight", "uv_weight", "color_weight"})
        options["attribute_weights"] = attribute_weights(
            normal=self.normal_weight, uv=self.uv_weight, color=self.color_weight)
        return options


class MeshCreated(BaseModel):
    id: str
    status: Status
    href: str = Field(description="Where to poll the build.")


class ErrorPoint(BaseModel):
    ratio: float
    vertices: int
    faces: int
    error: float = Field(description="Largest collapse error to reach this level, mesh units.")


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
    load_report: dict | None = None
    failure: str | None = Field(None, description="Why the build failed.")
    created: datetime
    updated: datetime

    @classmethod
    def from_record(cls, record: MeshRecord) -> MeshPublic:
        summary = record.summary
        return cls(
            id=record.id, name=record.name, status=record.status, progress=record.progress,
            file_type=record.file_type, source_bytes=record.source_bytes, options=record.options,
            vertices=summary.get("vertices"), faces=summary.get("faces"),
            base_vertices=summary.get("base_vertices"), base_faces=summary.get("base_faces"),
            splits=summary.get("splits"), max_error=summary.get("max_error"),
            error_curve=summary.get("error_curve", []),
            load_report=summary.get("metadata", {}).get("load_report"),
            failure=record.failure,
            created=datetime.fromtimestamp(record.created, timezone.utc),
            updated=datetime.fromtimestamp(record.updated, timezone.utc))


class MeshList(BaseModel):
    meshes: list[MeshPublic]


class Message(BaseModel):
    """Every error response: a sentence saying what went wrong."""

    message: str
