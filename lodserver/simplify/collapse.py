"""Greedy quadric-error edge collapse, recording every collapse.

Implements Garland & Heckbert, "Surface Simplification Using Quadric Error
Metrics" (SIGGRAPH 1997) with the topology rules of Hoppe, "Progressive
Meshes" (SIGGRAPH 1996) and Dey et al., "Topology preserving edge contraction"
(1999): a collapse is taken only when it keeps the mesh a manifold and flips
no triangle, so that every collapse, reversed, is a vertex split. Appearance
attributes follow Hoppe 1999 (``simplify.wedges``), volume preservation
Lindstrom & Turk 1998.

Pipeline, in the order of this file:

1. classify vertices (interior, border, locked; ``simplify.rules``);
2. build vertex quadrics (``quadrics.vertex_quadrics``) and wedge quadrics;
3. in compiled steps, in passes (``_decimate_kernel``):
   - *rank* every edge (G&H section 4: the summed quadric, minimised;
     ``simplify.rank``) into the queue (``simplify.queue``), and the close
     pairs when asked for;
   - *pop* the cheapest fresh candidate, re-place it on its volume plane;
   - *check* it against the rules, each refusal a named reason
     (``simplify.legality``, ``simplify.rules.REJECT_*``), counted;
   - *perform* it on the corner lists and *log* it (``simplify.perform``,
     ``simplify.log``);
   - *re-rank* the edges around the survivor (``simplify.rank``);
   until no legal collapse is left: a collapse refused now may become legal
   once its neighbourhood has moved, so each pass re-ranks all edges;
   on a large mesh, first in phases of parts at once, each part on its
   own dense copy, then on a dense copy of the whole mesh (``_run_kernels``,
   ``simplify.parts``, ``simplify.submesh``);
4. return the collapse log as parallel arrays, one row per collapse.

A large mesh is decimated with its vertices renumbered along a Morton curve,
so that a collapse's neighbours share cache lines (``parts.memory_order``,
``_in_memory_order``); the log is mapped back to the input's vertex ids.

Positions are rescaled to the unit box inside the kernel so its tolerances
are scale-free; logged positions are kept in mesh units alongside.
``check_collapse`` runs the kernel's own rank and check steps on one edge.
"""

from __future__ import annotations

import dataclasses
import threading
from collections import namedtuple
from concurrent.futures import ThreadPoolExecutor
from queue import SimpleQueue

import numba
import numpy as np
from numba import njit

from ..heap import give_back
from ..mesh import Mesh, MeshError, read_only, take_rows, to_unit_box, unit_box
from ..overlap import both
from .legality import check_legality
from .log import COLLAPSES, MOVED, CollapseLog, filled, new_log, with_room_for_moves
from .options import DecimateOptions
from .pairs import MAX_PAIRS_PER_VERTEX
from .parts import (
    PHASES,
    REORDER_MIN_VERTICES,
    concatenate_logs,
    default_parts,
    kernel_count,
    memory_order,
    merge_phases,
    partition,
    phase_parts,
    renumbered,
)
from .perform import perform_collapse
from .prefetch import prefetch, prefetch2
from .quadrics import add_edge_planes, vertex_quadrics
from .queue import (
    CAPACITY,
    EMPTY,
    HEAP,
    NEEDS_ROOM,
    RESERVOIR,
    clear_queue,
    new_queue,
    pair_key,
    pop_fresh_from,
    push,
    with_room,
)
from .rank import place_on_volume_plane, rank_all, rank_collapse, rank_geometry, rerank_around
from .rules import (
    BORDER,
    DEFAULT_FLIP_COS,
    INTERIOR,
    LEGAL,
    LOCKED,
    REASON_COUNT,
    REASON_NAMES,
    REJECT_DEFERRED_BY_VOLUME,
    REJECT_LOCKED,
    REJECT_REASONS,
    REJECT_STALE,
    rejected_counts,
)
from .state import NO_REFCOUNT, Options, Vertices, new_scratch, new_state, new_topology
from .submesh import extract, group_faces, map_log, write_back
from .topology import Census, census
from .wedges import (
    DEFAULT_ATTRIBUTE_WEIGHTS,
    attribute_scales,
    fill_fixed,
    texture_seams,
    wedge_inputs,
)

__all__ = ["decimate", "check_collapse", "classify_vertices", "CollapseLog", "DecimateOptions",
           "DEFAULT_FLIP_COS",
           "DEFAULT_ATTRIBUTE_WEIGHTS", "REJECT_REASONS", "INTERIOR", "BORDER", "LOCKED",
           "MAX_PAIRS_PER_VERTEX", "attribute_scales"]

# How often (in collapses) the kernel reports progress and checks for cancellation.
_PROGRESS_STRIDE = 1024

# With volume preservation, a collapse popped from the queue is re-placed on
# its volume plane, which can only raise its cost; if the cost rose past this
# factor times the next key in the queue, it goes back into the queue (lazy
# re-ranking keeps the order cheapest-first to within the factor).
VOLUME_SLACK = 1.1



# --------------------------------------------------------------------------
# 1. Vertex classification
# --------------------------------------------------------------------------

def classify_vertices(found: Census, n, locked=None):
    """Kind of every vertex: INTERIOR, BORDER or LOCKED (``simplify.rules``).

    Parameters
    ----------
    found : Census
        The mesh's connectivity facts (``topology.census``).
    n : int
        Vertex count.
    locked : (n,) bool, optional
        Vertices the caller wants kept exactly (e.g. tile borders).

    Returns
    -------
    kind : (n,) int8
    """
    kind = np.zeros(n, dtype=np.int8)
    kind[found.on_boundary] = BORDER
    # Non-manifold edges and bow-tie vertices (two or more fans) cannot be
    # collapsed and split back as a Hoppe vertex split: lock them.
    kind[found.on_nonmanifold_edge | (found.fans > 1)] = LOCKED
    if locked is not None:
        locked = np.asarray(locked, dtype=bool)
        if locked.shape != (n,):
            raise ValueError(f"locked must be a boolean mask of shape ({n},), got {locked.shape}")
        kind[locked] = LOCKED
    return kind


# --------------------------------------------------------------------------
# 2. The passes: rank all, then pop / check / perform / re-rank
#    (ranking in simplify.rank, the kernel's state in simplify.state, the
#    check step in simplify.legality, the perform step in simplify.perform)
# --------------------------------------------------------------------------

@njit(inline="always", **NO_REFCOUNT)
def _warm_candidate(e_ab, pos, quadrics, vhead):
    """Start loading the rows the next candidate (queue entry ``e_ab``) is
    ranked and checked on (``simplify.prefetch``): it lies anywhere in the
    mesh, and this collapse's work hides the wait."""
    for v in (e_ab >> 32, e_ab & 0xFFFFFFFF):
        prefetch(pos, v)
        prefetch(quadrics, v)
        prefetch2(quadrics, v, 8)
        prefetch(vhead, v)


@njit(cache=True, nogil=True)
def _decimate_kernel(verts, topo, wedges, scratch, options, label, me, progress):
    """Collapse the edges of part ``me`` (and close pairs, if
    ``options.pair_radius`` > 0) cheapest first until none is legal or a
    limit is hit (``options.min_vertices`` counts the part's vertices).

    A part is the vertices ``v`` with ``label[v] == me`` (n,) int32; a
    collapse is considered only if both ends are in it, so kernels on
    different parts of one mesh can run at once (``simplify.parts``); a
    whole-mesh run labels every vertex 0. ``verts`` (``Vertices``), ``topo``
    (``Topology``) and ``wedges`` (``simplify.wedges.Wedges``; its marks,
    stamp and merge scratch must be this call's own, as ``scratch`` is) are
    updated in place. ``progress[0]`` receives the collapse count as it
    goes; a non-zero ``progress[1]`` asks the kernel to stop early.

    Returns (the filled log, ``simplify.log.LogColumns``; the queue key (k,)
    each collapse was taken at; rejections (REASON_COUNT,) by reason;
    passes).
    """
    n = verts.pos.shape[0]
    vertex_alive = topo.vertex_alive
    room = 0
    for v in range(n):
        if vertex_alive[v] and label[v] == me:
            room += 1
    has_wedges = wedges.quadric.shape[0] > 0
    # a collapse kills at most two faces and merges at most two wedge pairs
    log = new_log(room, min(topo.faces.shape[0], 2 * room + 16), 2 * room if has_wedges else 0,
                  wedges.value.shape[1])
    keys = np.empty(room, np.float64)
    # The reservoir's capacity decides when it is compacted, and so the order
    # the refills see (``simplify.queue``): one and a half entries per face of
    # the part, the same rule as a whole-mesh run's.
    part_faces = 0
    faces, face_alive = topo.faces, topo.face_alive
    for f in range(faces.shape[0]):
        if (face_alive[f] and label[faces[f, 0]] == me and label[faces[f, 1]] == me
                and label[faces[f, 2]] == me):
            part_faces += 1
    queue = new_queue(3 * part_faces // 2 + 16)
    rejected = np.zeros(REASON_COUNT, np.int64)
    # fields read once: every read of a namedtuple field inside the loop
    # would take and drop a reference
    pos, quadrics, kind, version = verts.pos, verts.quadrics, verts.kind, verts.version
    face_count, vhead, cnext = topo.face_count, topo.vhead, topo.cnext
    q, p, pairs, plane = scratch.q, scratch.p, scratch.pairs, scratch.plane
    count = log.count           # the same array even when log's columns grow
    min_vertices, max_collapses = options.min_vertices, min(options.max_collapses, room)
    volume, pair_radius = options.volume, options.pair_radius
    size, tau = queue.size, queue.tau       # the same arrays for the whole run
    alive_count = room
    stamp = np.int64(0)     # not a literal 0: every step it reaches would compile twice
    passes = 0
    while True:
        passes += 1
        collapses_before = count[COLLAPSES]
        clear_queue(queue)
        queue, stamp = rank_all(verts, topo, wedges, scratch, queue, stamp, pair_radius, label,
                                 me)
        # the heap's and reservoir's arrays, read again whenever the queue grows
        hk, hab, hvs, rk = queue.heap_key, queue.heap_pair, queue.heap_version, queue.key
        moved_room = log.moved_corners.shape[0]
        stop = False
        while True:
            if (alive_count <= min_vertices or count[COLLAPSES] >= max_collapses
                    or progress[1] != 0):
                stop = True
                break
            a, b, entry_version = pop_fresh_from(hk, hab, hvs, size, queue, version, vertex_alive,
                                                 rejected, REJECT_STALE)
            if a == EMPTY:
                break
            if a == NEEDS_ROOM:     # the heap takes the whole reservoir at a refill
                queue = with_room(queue, size[RESERVOIR], np.int64(0))
                hk, hab, hvs, rk = queue.heap_key, queue.heap_pair, queue.heap_version, queue.key
                continue
            if size[HEAP] > 0:
                _warm_candidate(hab[0], pos, quadrics, vhead)
            if has_wedges:
                cost, s, n_pairs, seams_meet, reason = rank_collapse(a, b, pos, quadrics, kind, q,
                                                                     p, pairs, topo, wedges)
            else:
                cost, s = rank_geometry(a, b, pos, quadrics, kind, q, p)
                n_pairs, seams_meet, reason = 0, False, LEGAL if s >= 0 else REJECT_LOCKED
            if reason != LEGAL:
                rejected[reason] += 1
                continue
            if volume and kind[a] == INTERIOR and kind[b] == INTERIOR:
                placed = place_on_volume_plane(a, b, seams_meet, pos, faces, vhead, cnext,
                                               face_alive, q, p, plane)
                if placed >= 0.0:
                    cost = placed
                    if cost > VOLUME_SLACK * (hk[0] if size[HEAP] > 0 else tau[0]):
                        # dearer than what waits next: back into the queue at its true cost
                        rejected[REJECT_DEFERRED_BY_VOLUME] += 1
                        if size[HEAP] + 1 > hk.shape[0] or size[CAPACITY] + 1 > rk.shape[0]:
                            queue = with_room(queue, np.int64(1), np.int64(1))
                            hk, hab, hvs = queue.heap_key, queue.heap_pair, queue.heap_version
                            rk = queue.key
                        push(queue, cost, pair_key(a, b), entry_version, version, vertex_alive)
                        continue
            r = b if s == a else a
            if s != a:      # wedge pairs as (survivor's, removed's)
                for g in range(n_pairs):
                    pairs[g, 0], pairs[g, 1] = pairs[g, 1], pairs[g, 0]
            stamp += 1
            reason, o0, o1 = check_legality(s, r, p, options, verts, topo, scratch, stamp)
            if reason != LEGAL:
                rejected[reason] += 1
                continue
            # Room is made here, between steps: a step that returned grown
            # arrays would pay for it on every call (simplify.queue).
            if count[MOVED] + face_count[r] > moved_room:
                log = with_room_for_moves(log, face_count[r])
                moved_room = log.moved_corners.shape[0]
            keys[count[COLLAPSES]] = cost
            perform_collapse(s, r, n_pairs, o0, o1, verts, topo, wedges, scratch, log)
            alive_count -= 1
            if count[COLLAPSES] % _PROGRESS_STRIDE == 0:
                progress[0] = count[COLLAPSES]
            k = 2 * face_count[s]
            if not (size[HEAP] + k <= hk.shape[0] and size[CAPACITY] + k <= rk.shape[0]):
                queue = with_room(queue, k, k)      # has_room, on the arrays held
                hk, hab, hvs, rk = queue.heap_key, queue.heap_pair, queue.heap_version, queue.key
            stamp += 1
            rerank_around(s, verts, topo, wedges, scratch, queue, stamp, label, me)
        if stop or count[COLLAPSES] == collapses_before:
            break
    progress[0] = log.count[COLLAPSES]
    return filled(log), keys[:count[COLLAPSES]], rejected, passes


@njit(cache=True, nogil=True)
def _check_kernel(a, b, verts, faces, wedges, options):
    """Rank and check the one collapse (a, b) of the input mesh with the
    kernel's own steps. Returns (reason, survivor, cost, placement (3,))."""
    topo, scratch = new_state(faces, verts.pos.shape[0])
    fill_fixed(topo, wedges)
    cost, s, n_pairs, seams_meet, reason = rank_collapse(
        a, b, verts.pos, verts.quadrics, verts.kind, scratch.q, scratch.p, scratch.pairs, topo,
        wedges)
    if reason != LEGAL:
        return reason, s, cost, scratch.p.copy()
    if options.volume and verts.kind[a] == INTERIOR and verts.kind[b] == INTERIOR:
        placed = place_on_volume_plane(a, b, seams_meet, verts.pos, topo.faces, topo.vhead,
                                       topo.cnext, topo.face_alive, scratch.q, scratch.p,
                                       scratch.plane)
        if placed >= 0.0:
            cost = placed
    r = b if s == a else a
    reason = check_legality(s, r, scratch.p, options, verts, topo, scratch, np.int64(1))[0]
    return reason, s, cost, scratch.p.copy()


@njit(cache=True, nogil=True)
def _new_topology(faces, n, wedges):
    """The shared ``Topology`` of the input, with every vertex's fixed wedge quadrics."""
    topo = new_topology(faces, n)
    fill_fixed(topo, wedges)
    return topo


def _run_kernels(verts, faces, wedges, options, parts, states):
    """Run the decimation: the whole mesh in one kernel when ``parts`` is 1;
    else every phase of ``parts.PHASES`` (the parts of the live mesh, each
    on its own dense copy, ``simplify.submesh``, as many at once as there are
    threads), then the whole live mesh on a dense copy. ``states`` are the
    kernels' progress counters, one per kernel (``parts.kernel_count``).
    ``faces`` is (m, 3) int64 for a whole-mesh run, int32 for a partitioned one
    (its working copy, edited in place).
    Returns (the log, ``simplify.log.LogColumns``; rejections
    (REASON_COUNT,); passes)."""
    n = len(verts.pos)
    if parts == 1:
        topo = _new_topology(faces, n, wedges)
        columns, _, rejected, passes = _decimate_kernel(
            verts, topo, wedges, new_scratch(n), options, np.zeros(n, dtype=np.int32), 0,
            states[0])
        return columns, rejected, passes
    # the mesh as the phases leave it (and ``faces``); each phase copies its parts out of these
    face_alive = np.ones(len(faces), dtype=bool)
    vertex_alive = np.bincount(faces.ravel(), minlength=n) > 0
    counters = iter(states)
    phases, rejected, passes = [], np.zeros(REASON_COUNT, np.int64), 0

    def run(sub, stop, state):
        """Decimate a copy down to ``stop`` of its own vertices."""
        columns, keys, refused, runs = _decimate_kernel(
            sub.verts, sub.topo, sub.wedges, new_scratch(len(sub.vertex_ids)),
            options._replace(min_vertices=stop), sub.label, 0, state)
        return map_log(columns, sub), keys.copy(), refused, runs

    threads = min(parts, numba.get_num_threads())
    # one (n,) array of -1 per thread for ``extract``, which hands it back
    # clean: a fresh one per part would fill a mesh-sized array for every part
    spare = SimpleQueue()
    for _ in range(threads):
        spare.put(np.full(n, -1))
    with ThreadPoolExecutor(threads) as pool:
        for turned, fraction, divisor in PHASES:
            count = phase_parts(parts, divisor)
            live = faces[face_alive]
            label = partition(verts.pos, live, vertex_alive, count, turned)
            face_ids, offsets = group_faces(faces, face_alive, label, count)
            face_count = np.bincount(live.ravel(), minlength=n)
            del live        # a copy of the live faces, not needed while the parts run
            sizes = np.bincount(label[label >= 0], minlength=count)
            alive = int(np.count_nonzero(vertex_alive))

            def run_part(part, state):
                seen = spare.get()
                try:
                    sub = extract(verts, faces, face_alive, face_count, wedges, label, part,
                                  face_ids[offsets[part]:offsets[part + 1]], seen)
                finally:
                    spare.put(seen)
                stop = max(int(fraction * sizes[part]),
                           options.min_vertices * int(sizes[part]) // max(alive, 1))
                result = run(sub, stop, state)
                # the next phase copies its parts out of the mesh's arrays
                write_back(sub, verts, faces, face_alive, vertex_alive, wedges)
                del sub
                give_back()     # the copy and the kernel's queue and log, freed in this thread's arena
                return result

            results = list(pool.map(run_part, range(count), [next(counters) for _ in range(count)]))
            phases.append(([r[0] for r in results], [r[1] for r in results]))
            rejected += sum(r[2] for r in results)
            passes += sum(r[3] for r in results)
            del results

        def run_tail():
            """The rest of the hierarchy, on one dense copy of what is left
            (nothing reads the mesh's arrays after it: no write-back)."""
            sub = extract(verts, faces, face_alive, None, wedges, None, 0,
                          np.flatnonzero(face_alive), spare.get())
            return run(sub, options.min_vertices, next(counters))

        # the tail is one kernel: the phases' logs are merged on this thread
        # meanwhile, off its critical path
        pending = pool.submit(run_tail)
        logs = [merge_phases(phases)]       # which frees the parts' logs
        tail, _, refused, runs = pending.result()
        del pending
    logs.append(tail)
    del tail
    return concatenate_logs(logs), rejected + refused, passes + runs


# --------------------------------------------------------------------------
# 3. Public entry points
# --------------------------------------------------------------------------

def _prepare(mesh: Mesh, options: DecimateOptions, locked=None, poses=None):
    """The kernel's inputs for ``mesh`` decimated with ``options``, ``locked``
    (n,) bool and ``poses`` (P, n, 3, 4) as ``decimate`` takes them:
    (Vertices, faces, Wedges, the kernel's ``state.Options``, attribute
    scales, unit-box scale)."""
    positions = np.asarray(mesh.positions, dtype=np.float64)
    faces = read_only(mesh.faces, np.int64)
    n = len(positions)
    if 3 * len(faces) >= 2**31:
        # the kernel stores vertex and corner ids as int32
        raise MeshError(f"{len(faces)} faces is more than the 715 million decimation supports")
    # Work in the unit box: tolerances become scale-free and quadric
    # coefficients stay in a range where float64 cancellation is harmless.
    lo, scale = unit_box(positions)
    unit = to_unit_box(positions, lo, scale)
    # The census and the face quadrics read the same faces, write nothing in
    # common and release the GIL, so they run at once (``overlap``). The
    # planes are added in one fixed order (faces, borders, seams), so the
    # sums, and the artefact, are the same bits on every run.
    quadrics, found = both(lambda: vertex_quadrics(unit, faces, boundary_weight=0.0),
                           lambda: census(faces, n))
    kind = classify_vertices(found, n, locked)
    boundary_weight, seam_weight = options.boundary_weight, options.seam_weight
    if boundary_weight > 0:
        add_edge_planes(quadrics, unit, faces, found.boundary_edges, found.boundary_faces,
                        boundary_weight)
    attributes = mesh.attributes
    seams = texture_seams(mesh) if attributes is not None else None
    if seams is not None and seam_weight > 0:
        add_edge_planes(quadrics, unit, faces, *seams, seam_weight)
    if poses is not None:
        # Skinned or morphed: the surface is also measured in the poses it is seen in,
        # each posed plane pulled back through the vertex's own pose map to bind space
        # (simplify.poses); the mean over the bind pose and every pose keeps mesh units.
        from .poses import pose_quadrics, poses_to_unit_box
        posed = pose_quadrics(unit, faces, poses_to_unit_box(poses, lo, scale))
        quadrics = (quadrics + posed) / (1.0 + len(poses))
    wedges, scales = wedge_inputs(attributes, unit, faces, options.attribute_weights, n)

    pair_threshold = options.pair_threshold
    if not pair_threshold >= 0:
        raise ValueError(f"pair_threshold must be a non-negative distance, got {pair_threshold}")
    # cells of the pair search are this wide in the unit box; keep their count sane
    radius = max(float(pair_threshold) / scale, 1e-6) if pair_threshold > 0 else 0.0
    verts = Vertices(unit, positions.copy(), quadrics, kind, np.zeros(n, np.int64), lo,
                     float(scale))
    limit = options.max_collapses
    kernel_options = Options(int(options.min_vertices), n if limit is None else int(limit),
                             float(options.flip_cos), radius, bool(options.preserve_volume))
    return verts, faces, wedges, kernel_options, scales, scale


def _in_memory_order(mesh: Mesh, locked, poses):
    """``mesh`` with its vertices renumbered along a Morton curve when it has
    ``parts.REORDER_MIN_VERTICES`` or more (``parts.memory_order``; faces keep
    their rows, so face, corner and wedge ids are unchanged), with ``locked``
    (n,) and ``poses`` (P, n, 3, 4) permuted to match. Returns (mesh, order,
    locked, poses); ``order`` (n,) maps the new ids back (``order[new] =
    old``), None when the mesh is left as it is. Arguments of the wrong shape
    are passed on untouched, for ``_prepare`` to report."""
    n = len(mesh.positions)
    order = memory_order(mesh.positions) if n >= REORDER_MIN_VERTICES else None
    if order is None:
        return mesh, None, locked, poses
    inverse = np.empty(n, dtype=np.int64)
    inverse[order] = np.arange(n)
    mesh = dataclasses.replace(mesh, positions=take_rows(mesh.positions, order),
                               faces=renumbered(np.ascontiguousarray(mesh.faces), inverse))
    if locked is not None and np.shape(locked) == (n,):
        locked = np.asarray(locked)[order]
    if poses is not None and np.ndim(poses) >= 2 and np.shape(poses)[1] == n:
        poses = np.asarray(poses)[:, order]
    return mesh, order, locked, poses


def decimate(mesh: Mesh, options: DecimateOptions = DecimateOptions(), *, locked=None,
             poses=None, progress=None, cancel: threading.Event | None = None) -> CollapseLog:
    """Collapse edges of ``mesh`` cheapest first and log every collapse.

    Parameters
    ----------
    mesh : Mesh
        Welded, clean input (see ``io.clean_mesh``).
    options : DecimateOptions
        Weights, limits, close pairs and parts (``simplify.options``); the
        default takes every default.
    locked : (n,) bool, optional
        Vertices that must neither move nor vanish.
    poses : (P, n, 3, 4) float64, optional
        Per pose, the affine map of every vertex from its bind position to its
        posed one (mesh units; ``simplify.poses``): the error of a collapse is
        then the mean over the bind pose and these poses.
    progress : callable(done: int, expected: int), optional
        Called from this thread about ten times a second while the kernel runs.
    cancel : threading.Event, optional
        When set, the kernel stops at the next progress check.

    Returns
    -------
    CollapseLog
        ``rejected`` counts the refused candidates by ``REJECT_REASONS``.
    """
    # The kernel runs on the renumbered mesh; the log's vertex ids are mapped
    # back at the end (its face and corner ids need nothing: faces keep their rows).
    mesh, order, locked, poses = _in_memory_order(mesh, locked, poses)
    verts, faces, wedges, kernel_options, scales, scale = _prepare(mesh, options, locked, poses)
    attributes = mesh.attributes
    # the renumbered copies are read by nothing past this point: freed before the kernels run
    del mesh, locked, poses
    n = len(verts.pos)
    parts = default_parts(n) if options.parts is None else options.parts
    if parts > 1 and (kernel_options.pair_radius > 0 or kernel_options.max_collapses < n):
        parts = 1       # close pairs cross parts; a collapse limit is a prefix of the whole order
    if parts > 1:
        # the partitioned run's working faces; the int64 ones are then freed
        faces = faces.astype(np.int32)
    # one progress counter (and stop flag) per kernel: each part's, then the whole mesh's
    states = [np.zeros(2, dtype=np.int64) for _ in range(kernel_count(parts))]
    result = {}

    def run():
        result["log"] = _run_kernels(verts, faces, wedges, kernel_options, parts, states)

    if progress is None and cancel is None:
        run()
    else:
        # The kernels release the GIL (nogil=True); this thread polls their counters.
        worker = threading.Thread(target=run, daemon=True)
        worker.start()
        while worker.is_alive():
            worker.join(0.1)
            if cancel is not None and cancel.is_set():
                for state in states:
                    state[1] = 1
            if progress is not None:
                progress(sum(int(state[0]) for state in states), n)
        if progress is not None:
            progress(sum(int(state[0]) for state in states), n)
    if "log" not in result:
        raise RuntimeError("the decimation kernel failed")
    log, rejected, passes = result["log"]
    del result, verts, wedges, faces
    give_back()     # the kernels' working arrays: the progressive mesh is built next
    s, r = log.survivor, log.removed
    if order is not None:
        s, r = order[s], order[r]
    error = np.sqrt(log.cost / np.maximum(log.area, np.finfo(float).tiny)) * scale
    merges = {}
    if attributes is not None:
        # back from sqrt(weight)-scaled to input units
        merges = dict(merge_offsets=_own(log.merge_offsets),
                      merge_survivor=_own(log.merge_survivor),
                      merge_removed=_own(log.merge_removed), merge_value=log.merge_value / scales)
    return CollapseLog(
        survivor=_own(s), removed=_own(r), position=_own(log.position), error=error,
        killed_offsets=_own(log.killed_offsets), killed_faces=_own(log.killed_faces),
        moved_offsets=_own(log.moved_offsets), moved_corners=_own(log.moved_corners),
        rejected=rejected_counts(rejected), passes=int(passes), **merges)


def _own(column):
    """``column``, copied if it is a view: a whole-mesh kernel's columns are
    views of its larger working arrays, which the log should not keep alive; a
    partitioned run's are arrays of their own already (tens of MB at 1M faces)."""
    return column.copy() if column.base is not None else column


Verdict = namedtuple("Verdict", "reason survivor position cost")
Verdict.__doc__ = """What the kernel's rules say about one collapse.

reason : str or None
    None if the collapse is legal, else the name of the first rule that
    refuses it (``simplify.rules.REASON_NAMES``).
survivor : int
    The vertex that would stay.
position : (3,) float64
    Where it would go, mesh units.
cost : float
    The quadric cost the queue would rank it by (unit-box frame; inf when
    never legal).
"""


def check_collapse(mesh: Mesh, a: int, b: int, options: DecimateOptions = DecimateOptions(), *,
                   locked=None) -> Verdict:
    """Would ``decimate`` collapse the edge (or close pair) (a, b) of ``mesh``
    as its first move? Runs the kernel's own rank and check steps on it, with
    ``decimate``'s ``options`` and ``locked`` (its limits and parts play no
    part); the queue (and so volume deferral) plays no part either.
    """
    unlimited = dataclasses.replace(options, min_vertices=0, max_collapses=None)
    verts, faces, wedges, kernel_options, _, scale = _prepare(mesh, unlimited, locked)
    n = len(verts.pos)
    if not (0 <= a < n and 0 <= b < n and a != b):
        raise ValueError(f"a and b must be two different vertices below {n}, got {a} and {b}")
    reason, s, cost, p = _check_kernel(int(a), int(b), verts, faces, wedges, kernel_options)
    return Verdict(None if reason == LEGAL else REASON_NAMES[reason], int(s),
                   verts.origin + scale * p, float(cost))


# The compiled kernel whose on-disk cache build.kernels_cold reads to tell a first run.
MAIN_KERNEL = _decimate_kernel
