"""The rules of edge collapse as data: vertex kinds, which kind may collapse
onto which, and the named reasons a candidate collapse is refused.

Every rule keeps one promise: a collapse, reversed, is a vertex split of
Hoppe's "Progressive Meshes" (SIGGRAPH 1996), so the mesh stays a manifold
with the same topology (Dey et al., "Topology preserving edge contraction",
1999), and no triangle folds over (Garland & Heckbert 1997, section 3.3).
"""

from __future__ import annotations

import numpy as np
from numba import njit

# --------------------------------------------------------------------------
# Vertex kinds (as meshoptimizer's simplifier classifies them)
# --------------------------------------------------------------------------

INTERIOR = 0    # every edge at it has two faces, one fan
BORDER = 1      # on an edge used by one face
LOCKED = 2      # on a non-manifold edge, a bow tie (two or more fans), or locked by the caller
KIND_NAMES = ("interior", "border", "locked")

# CAN_COLLAPSE[kind of the removed vertex, kind of the survivor]: may a vertex
# of the first kind vanish into one of the second? Rule of thumb: a vertex may
# only go where it keeps the features it is on. An interior vertex may go
# anywhere; a border vertex only along the border (onto a border or locked
# vertex: the border's constraint planes then keep the survivor on it); a
# locked vertex never goes (a bow tie or a non-manifold edge cannot be undone
# by one vertex split, and a caller's lock means exactly that).
#
#                removed \ survivor:  INTERIOR  BORDER  LOCKED
CAN_COLLAPSE = np.array([[True,     True,   True],     # INTERIOR
                         [False,    True,   True],     # BORDER
                         [False,    False,  False]])   # LOCKED

# KEEPS_POSITION[kind of the survivor]: the survivor stays where it is instead
# of moving to the quadric-optimal point. A locked vertex never moves.
KEEPS_POSITION = np.array([False, False, True])

# The compiled kernels read these tables as bit masks (bit ``3 * removed +
# survivor`` of CAN_COLLAPSE_BITS, bit ``kind`` of the others): a module-level
# integer is a compile-time constant, while indexing a global array is a memory
# read each time, and every candidate's ranking reads these tables.
# ON_BORDER[kind]: counts as a border vertex for the edge rule (an edge with
# one face may join two border vertices; an edge with two faces may not, see
# REJECT_PINCH). A locked vertex may sit on a border, so it counts.
ON_BORDER = np.array([False, True, True])

CAN_COLLAPSE_BITS = sum(1 << (3 * r + s) for r in range(3) for s in range(3) if CAN_COLLAPSE[r, s])
KEEPS_POSITION_BITS = sum(1 << k for k in range(3) if KEEPS_POSITION[k])
ON_BORDER_BITS = sum(1 << k for k in range(3) if ON_BORDER[k])


@njit(cache=True, nogil=True, inline="always")
def can_collapse(removed, survivor):
    """CAN_COLLAPSE[removed, survivor] from the bit mask (compiled kernels inline it)."""
    return (CAN_COLLAPSE_BITS >> (3 * removed + survivor)) & 1 != 0


@njit(cache=True, nogil=True, inline="always")
def keeps_position(kind):
    """KEEPS_POSITION[kind] from the bit mask."""
    return (KEEPS_POSITION_BITS >> kind) & 1 != 0


@njit(cache=True, nogil=True, inline="always")
def on_border(kind):
    """ON_BORDER[kind] from the bit mask."""
    return (ON_BORDER_BITS >> kind) & 1 != 0


# --------------------------------------------------------------------------
# Why a candidate collapse is refused
# --------------------------------------------------------------------------

# One row per reason: (name, the counter of ``CollapseLog.rejected`` it adds
# to, why the rule exists). The first twelve names are the counters the
# artefact has always recorded, in that order; the last two are finer
# reasons that ``check_collapse`` reports and the counters fold into an
# older name, so progressive meshes stay byte-identical.
_REASONS = (
    ("stale", "stale",
     "an endpoint changed since the entry was queued (the queue re-ranks lazily)"),
    ("not_an_edge", "not_an_edge",
     "the two vertices share no face and close pairs are off"),
    ("non_manifold_edge", "non_manifold_edge",
     "more than two faces on the edge: no vertex split makes that"),
    ("pinch", "pinch",
     "an edge with two faces between two border vertices: the survivor would "
     "have two fans (a bow tie); or a border edge with an interior endpoint"),
    ("link", "link",
     "the endpoints share a neighbour that is not opposite the edge: the "
     "collapse would pinch a handle or glue two sheets (Dey et al.'s link condition)"),
    ("tetrahedron", "tetrahedron",
     "both endpoints have a face on the two opposite vertices: the collapse "
     "would make two faces on the same three vertices (squashing a tetrahedron)"),
    ("last_face", "last_face",
     "a vertex (the survivor or one opposite the edge) would be left without faces"),
    ("flip", "flip",
     "a surviving face's normal would turn by more than arccos(flip_cos)"),
    ("pair_too_far", "pair_too_far",
     "a close pair (no shared edge) whose vertices have drifted apart"),
    ("pair_shares_neighbours", "pair_shares_neighbours",
     "a close pair with a common neighbour: joining it would make a "
     "duplicate face or a pinch"),
    ("seam", "seam",
     "the collapse would merge two wedges of one vertex (drag an attribute "
     "seam across the surface)"),
    ("deferred_by_volume", "deferred_by_volume",
     "placed on its volume-preserving plane, the collapse cost more than the "
     "next one in the queue: it goes back in at its true cost"),
    ("degenerate", "flip",
     "a surviving face would have (almost) no area: no normal left to keep"),
    ("locked", "seam",
     "neither endpoint may collapse onto the other (CAN_COLLAPSE): both locked"),
)

REASON_NAMES = tuple(name for name, _, _ in _REASONS)
REASON_WHY = {name: why for name, _, why in _REASONS}
# The counters of ``CollapseLog.rejected``, in the artefact's order.
REJECT_REASONS = tuple(dict.fromkeys(counted for _, counted, _ in _REASONS))
# COUNTED_AS[reason] = index into REJECT_REASONS
COUNTED_AS = np.array([REJECT_REASONS.index(counted) for _, counted, _ in _REASONS], np.int64)
REASON_COUNT = len(REASON_NAMES)

LEGAL = -1      # no rule refuses the collapse
(REJECT_STALE, REJECT_NOT_AN_EDGE, REJECT_NON_MANIFOLD_EDGE, REJECT_PINCH, REJECT_LINK,
 REJECT_TETRAHEDRON, REJECT_LAST_FACE, REJECT_FLIP, REJECT_PAIR_TOO_FAR,
 REJECT_PAIR_SHARES_NEIGHBOURS, REJECT_SEAM, REJECT_DEFERRED_BY_VOLUME, REJECT_DEGENERATE,
 REJECT_LOCKED) = range(REASON_COUNT)
assert REASON_NAMES[REJECT_LOCKED] == "locked" and REASON_NAMES[REJECT_LINK] == "link"


def rejected_counts(counts) -> dict:
    """``{name: count}`` over REJECT_REASONS from the kernel's (REASON_COUNT,) counters."""
    out = dict.fromkeys(REJECT_REASONS, 0)
    for reason, count in enumerate(counts):
        out[REJECT_REASONS[COUNTED_AS[reason]]] += int(count)
    return out


# --------------------------------------------------------------------------
# Tolerances
# --------------------------------------------------------------------------

# A collapse is refused if it turns any surviving triangle's normal by more
# than arccos(DEFAULT_FLIP_COS) (about 78 degrees): larger turns are fold-overs
# in the making, and a strict 90 degree test lets slivers through.
DEFAULT_FLIP_COS = 0.2
# New triangles with squared twice-area below this (in the unit-box frame) are degenerate.
DEGENERATE_AREA = 1e-20
