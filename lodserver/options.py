"""Build options, each spelled out once: name, default, range and a one-line doc.

``BuildOptions`` is what ``build.build`` consumes; the command line generates
its ``build`` / ``export`` / ``simplify`` flags from these fields
(``cli.add_option_flags``), and the HTTP form of ``POST /meshes`` is this model
plus a ``name`` (``api.models.MeshCreate``). So a default or a range changes in
one place, and the three faces cannot disagree (``tests/test_options.py``).

A field's description is its help text everywhere: one plain sentence, no
markup. ``Flag`` metadata gives a field a command-line spelling other than
``--field-name`` (``--no-volume`` for ``preserve_volume``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from pydantic_core import PydanticCustomError

from .simplify.collapse import DEFAULT_ATTRIBUTE_WEIGHTS, DEFAULT_FLIP_COS
from .simplify.options import DecimateOptions
from .mesh import Mesh, MeshError

METHODS = ("qem", "cluster")
# A distance in mesh units, or a percentage of the bounding-box diagonal: "0.01", "2%", "1e-3".
DISTANCE_PATTERN = r"^(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?%?$"
# Weights above this are a typo, not a wish: they drown every other term of the cost.
MAX_WEIGHT = 1e6
# The weight field of each glTF attribute ``decimate`` weighs (both UV sets share one).
_WEIGHT_FIELDS = {"NORMAL": "normal_weight", "TEXCOORD_0": "uv_weight",
                  "TEXCOORD_1": "uv_weight", "COLOR_0": "color_weight"}


@dataclass(frozen=True)
class Flag:
    """How a field is spelled on the command line when ``--field-name`` will not do.

    ``name`` is the flag; for a boolean whose default is True it is the flag
    that turns it off (``--no-volume``). ``metavar`` names the value in help.
    """

    name: str | None = None
    metavar: str | None = None


def _weight(description: str, default: float, *, positive: bool = False):
    bound = {"gt": 0} if positive else {"ge": 0}
    return Annotated[float, Field(default, le=MAX_WEIGHT, allow_inf_nan=False,
                                  description=description, **bound), Flag(metavar="W")]


# Options added after artefacts, manifests and catalogue rows were first written,
# with the default at which they are left out of those records (BuildOptions.recorded).
LATE_OPTIONS = {"batched": False}


class BuildOptions(BaseModel):
    """Every option of ``build.build`` but the per-vertex ``locked`` mask and the callbacks.

    Construct with keywords (``BuildOptions(boundary_weight=2)``) or validate a
    mapping of strings, as a form sends (``BuildOptions.model_validate(fields)``);
    bad values raise ``pydantic.ValidationError``, which ``describe_error``
    turns into one sentence. ``check`` does both and raises ``MeshError``.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    method: Annotated[Literal[METHODS], Field(
        "qem", description="qem: quadric edge collapse (best quality; keeps topology and "
        "attributes); cluster: octree vertex clustering recorded as splits (faster; joins "
        "parts; geometry only: the other options but attributes do not apply).")]
    boundary_weight: _weight("Weight of the planes that keep open borders in place; 0 lets "
                             "borders shrink.", 1.0)
    lock_border: Annotated[bool, Field(
        False, description="Never move or remove border vertices, so separately simplified "
        "tiles and parts keep stitching.")]
    min_vertices: Annotated[int, Field(
        0, ge=0, le=2**31 - 1, description="Stop decimating at this many vertices; 0 goes "
        "as far as possible."), Flag(metavar="N")]
    pair_threshold: Annotated[str, Field(
        "0", json_schema_extra={"pattern": DISTANCE_PATTERN},
        description="Also contract vertices closer than this that share no edge, joining "
        "parts: mesh units, or a percentage of the bounding-box diagonal such as 1%; 0: "
        "edges only."), Flag(metavar="T")]
    preserve_volume: Annotated[bool, Field(
        True, description="Place collapses so the enclosed volume is kept (thin parts do "
        "not shrink away)."), Flag("--no-volume")]
    attributes: Annotated[bool, Field(
        True, description="Simplify normals, UVs and colours with the geometry, seams kept; "
        "off: positions only, materials dropped."), Flag("--no-attributes")]
    normal_weight: _weight("Weight of normal error against geometric error.",
                           DEFAULT_ATTRIBUTE_WEIGHTS["NORMAL"], positive=True)
    uv_weight: _weight("Weight of texture-coordinate error against geometric error.",
                       DEFAULT_ATTRIBUTE_WEIGHTS["TEXCOORD_0"], positive=True)
    color_weight: _weight("Weight of vertex-colour error against geometric error.",
                          DEFAULT_ATTRIBUTE_WEIGHTS["COLOR_0"], positive=True)
    seam_weight: _weight("Weight of the planes that keep UV and colour seams in place, as the "
                         "boundary weight does for borders.", 1.0)
    batched: Annotated[bool, Field(
        False, description="Re-order the splits into batches of independent ones (a codec "
        "then codes one mark per vertex per batch); the full and base meshes stay, the "
        "levels between change slightly.")]
    flip_cos: Annotated[float, Field(
        DEFAULT_FLIP_COS, ge=-1, le=1, allow_inf_nan=False,
        description="Refuse a collapse that turns a surviving face's normal by more than "
        "the angle of this cosine (0.2: about 78 degrees)."), Flag(metavar="C")]

    @field_validator("pair_threshold", mode="before")
    @classmethod
    def _distance_text(cls, value):
        # Python callers pass a number; a form and the command line pass text.
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            value = repr(float(value)) if math.isfinite(value) else str(value)
        if not isinstance(value, str) or not re.match(DISTANCE_PATTERN, value.strip()):
            raise PydanticCustomError(
                "distance", "must be a non-negative number or a percentage like 1%, "
                "got {value}", {"value": repr(value)})
        return value.strip()

    def attribute_weights(self) -> dict:
        """``decimate``'s attribute_weights: weight by glTF attribute name."""
        return {name: getattr(self, field) for name, field in _WEIGHT_FIELDS.items()}

    def recorded(self) -> dict:
        """The options by name as artefacts, manifests and the catalogue keep them.
        An option added after records were first written (:data:`LATE_OPTIONS`) is
        left out at its default, so that what earlier versions wrote stays the same
        bytes and an export folder is not rebuilt for an option nobody set."""
        values = self.model_dump()
        for name, default in LATE_OPTIONS.items():
            if values.get(name) == default:
                del values[name]
        return values

    def decimate_options(self, mesh: Mesh) -> DecimateOptions:
        """These options as the edge-collapse kernel takes them for ``mesh``
        (``simplify.options.DecimateOptions``): the pair threshold in mesh
        units (a percentage is of ``mesh``'s bounding-box diagonal), the
        weights by attribute name. ``method``, ``attributes`` and
        ``lock_border`` are the builder's to apply; they are not here.

        Raises
        ------
        MeshError
            The pair threshold is not a finite distance.
        """
        return DecimateOptions(
            boundary_weight=self.boundary_weight, seam_weight=self.seam_weight,
            attribute_weights=self.attribute_weights(), flip_cos=self.flip_cos,
            pair_threshold=distance_from(self.pair_threshold, mesh),
            preserve_volume=self.preserve_volume, min_vertices=self.min_vertices)

    @classmethod
    def check(cls, options: BuildOptions | dict | None = None, **overrides) -> BuildOptions:
        """``options`` (a model, a mapping or None for the defaults) with ``overrides`` applied.

        Also takes the older ``attribute_weights={"NORMAL": w, "TEXCOORD_0": w, ...}``
        keyword (so options stored by earlier versions still build).

        Raises
        ------
        MeshError
            A value is out of range or malformed; one sentence naming the option.
        TypeError
            A name is not a build option (as for any unexpected keyword).
        """
        if isinstance(options, BuildOptions):
            values = options.model_dump()
        else:
            values = dict(options or {})
        values.update(overrides)
        weights = values.pop("attribute_weights", None) or {}
        for name, field in _WEIGHT_FIELDS.items():
            if name in weights:
                values.setdefault(field, weights[name])
        unknown = set(weights) - set(DEFAULT_ATTRIBUTE_WEIGHTS)
        if unknown:
            raise MeshError(f"no attribute named {', '.join(sorted(unknown))}; known are "
                            f"{', '.join(DEFAULT_ATTRIBUTE_WEIGHTS)}")
        unexpected = sorted(set(values) - set(cls.model_fields))
        if unexpected:
            raise TypeError(f"{unexpected[0]!r} is not a build option; they are "
                            f"{', '.join(cls.model_fields)}")
        try:
            return cls.model_validate(values)
        except ValidationError as exc:
            raise MeshError(describe_error(exc)) from None


# pydantic's wording where it is longer than the point
_PLAIN = {"int_parsing": "must be an integer", "int_type": "must be an integer",
          "int_from_float": "must be an integer", "float_parsing": "must be a number",
          "float_type": "must be a number", "bool_parsing": "must be true or false",
          "bool_type": "must be true or false"}


def describe_error(exc: ValidationError, label=None) -> str:
    """One sentence from a pydantic ``ValidationError`` of build options.

    ``label(field_name) -> str`` names a field the way the caller's user knows
    it (a flag, a form field); the default is the field name.
    """
    label = label or (lambda name: name)
    parts = []
    for error in exc.errors(include_url=False):
        name = ".".join(str(part) for part in error["loc"]) or "options"
        kind = error["type"]
        if kind == "extra_forbidden":
            parts.append(f"{label(name)} is not a build option")
            continue
        message = _PLAIN.get(kind) or error["msg"][0].lower() + error["msg"][1:]
        if kind == "greater_than" and error.get("ctx", {}).get("gt") == 0:
            message = "must be a positive number"
        if kind != "distance" and "input" in error:
            message += f", got {error['input']!r}"
        parts.append(f"{label(name)} {message}".replace("input should be", "must be"))
    return "; ".join(parts)


def field_default_text(name: str) -> str:
    """A field's default as help text shows it (``1``, ``0.003``, ``qem``)."""
    default = BuildOptions.model_fields[name].default
    if isinstance(default, float) and default.is_integer():
        return str(int(default))
    return str(default)


def distance_from(value, mesh: Mesh) -> float:
    """A distance in mesh units from a number, or from ``"P%"`` of the bounding-box diagonal."""
    text = str(value).strip()
    try:
        if text.endswith("%"):
            distance = float(text[:-1]) / 100.0 * mesh.bounding_box_diagonal
        else:
            distance = float(text)
    except ValueError:
        raise MeshError(f"a distance must be a number or a percentage like '1%', got {value!r}") from None
    if not distance >= 0 or distance == float("inf"):
        raise MeshError(f"a distance must be finite and non-negative, got {value!r}")
    return distance
