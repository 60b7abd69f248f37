"""What a caller chooses of the edge-collapse kernel: ``DecimateOptions``.

``collapse.decimate`` and ``collapse.check_collapse`` take one
``DecimateOptions``, in the kernel's units: distances in mesh units, weights
as plain numbers, no percentages and no method choice. ``options.BuildOptions``
is the user's side (text from a form or a flag, ``"2%"``, ``method``); its
``decimate_options(mesh)`` makes this object for one mesh, so the copying of
option after option happens once.

The per-vertex inputs (``locked``, ``poses``) and the callbacks
(``progress``, ``cancel``) are not options: they are passed beside the mesh.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from .rules import DEFAULT_FLIP_COS

__all__ = ["DecimateOptions"]


@dataclass(frozen=True)
class DecimateOptions:
    """The options of one decimation, each with its default.

    Attributes
    ----------
    boundary_weight : float
        Weight of the border constraint planes; 0 lets borders shrink.
    seam_weight : float
        Weight of the constraint planes along attribute seams (as
        ``boundary_weight`` for borders).
    attribute_weights : mapping of str to float, optional
        Weight of each attribute's squared error (by glTF name, e.g.
        ``{"NORMAL": 0.25, "TEXCOORD_0": 1}``) against squared distance in the
        unit box; missing names take ``wedges.DEFAULT_ATTRIBUTE_WEIGHTS``. Only
        used when the mesh has attributes.
    flip_cos : float
        A collapse that turns a surviving face's normal by more than
        ``arccos(flip_cos)`` is refused.
    pair_threshold : float
        Also contract vertex pairs that share no edge but lie at most this far
        apart, in mesh units (Garland & Heckbert's close pairs); 0 contracts
        edges only. A pair is contracted only if the two vertices share no
        neighbour and are still that close; the joined vertex then has two
        fans, and the link condition keeps every later collapse from making a
        non-manifold edge.
    preserve_volume : bool
        Place every interior collapse on the plane that keeps the enclosed
        volume, so thin parts do not shrink away.
    min_vertices : int
        Stop when this few vertices remain; 0 runs until no legal collapse is
        left. ``check_collapse`` ignores it.
    max_collapses : int, optional
        Stop after this many collapses; None: no limit. ``check_collapse``
        ignores it.
    parts : int, optional
        Decimate in phases of this many parts first, as many at once as numba
        has threads (a power of two, ``simplify.parts``); 1 decimates the whole
        mesh in one thread; None: ``parts.default_parts`` (one part per
        ``PART_VERTICES`` vertices from ``PARALLEL_MIN_VERTICES`` on, else 1).
        Taken as 1 with close pairs or ``max_collapses``, whose order is that
        of the whole mesh. ``check_collapse`` ignores it.
    """

    boundary_weight: float = 1.0
    seam_weight: float = 1.0
    attribute_weights: Mapping[str, float] | None = None
    flip_cos: float = DEFAULT_FLIP_COS
    pair_threshold: float = 0.0
    preserve_volume: bool = True
    min_vertices: int = 0
    max_collapses: int | None = None
    parts: int | None = None
