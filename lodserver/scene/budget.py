"""One triangle budget for a whole scene: which level of each part to draw.

A scene is parts (progressive meshes, one per glTF mesh) drawn by nodes: part
``p`` is instanced ``c_p`` times, its largest instance scale is ``s_p``. At level
index ``i`` (``i = level - base_vertices``) it has ``F_p[i]`` faces
(``pm.face_counts``, non-decreasing in ``i``) and error ``E_p[i]``
(``pm.level_error``: the worst collapse applied, mesh units, non-increasing, 0 at
full detail). Its *world error* is ``s_p * E_p[i]``: a uniform scale stretches
every distance by it, a non-uniform one by at most its largest singular value.

:func:`scene_levels` picks one level per part in one of three ways:

- ``ratio`` (the scene budget): the total ``sum_p c_p F_p[i_p]`` is at most
  ``ratio`` times the scene's full triangle count, and the world errors are as
  low as that total allows in the *lexicographic minimax* sense: first the worst
  world error of the scene is as low as possible, then, with the parts that set
  it fixed, the worst of the others, and so on. The first round is the minimax
  level choice: for a bound ``e`` every part takes its coarsest level with
  ``s_p E_p[i] <= e``; the cost of that choice falls as ``e`` grows, so the
  smallest ``e`` within the budget is found by bisection. It is one of the
  world-error values of the merged curves, and bisecting over the bit patterns of
  non-negative float64 (ordered like the values) finds it exactly in at most 64
  steps without sorting the merged curves. The parts whose level changes between
  ``e`` and the next float below it are the bottleneck: they keep their level,
  and the leftover budget goes to the others in the next round, and so on (at
  most one round per part). This spends the leftover where the error is largest,
  which is what a greedy "refine where the error drops most" approximates, but
  never raises the worst error to do it. What is left then buys finer levels of
  the same error (the curve's plateaus: :func:`_fill_plateaus`), worst parts
  first. One round costs at most 64 x parts x log2(levels) comparisons in a
  compiled loop, after one copy of the curves into one array
  (``tests/test_scene_budget.py`` prints how long a large scene takes).
- ``error``: each part at its coarsest level whose world error is at most
  ``error`` times the scene's bounding-box diagonal.
- ``per_mesh``: each part at ``ratio`` of its own faces (``pm.level_for(ratio=)``),
  what ``export --lods --per-mesh`` asks for.

A part's level never leaves its range: a part that cannot go lower keeps its
base mesh, and a budget below the sum of the base meshes leaves every part at
its base (the total then exceeds the budget: edge collapse stops there).

:func:`chain_levels` chooses the levels of an LOD chain, each part only
coarsening along it; :func:`scene_instances` reads ``c_p``, ``s_p`` and the
world bounding box from a :class:`~lodserver.io.scene.Scene`;
:func:`coverage_from_errors` turns the levels' world errors into
``MSFT_screencoverage`` hints.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..io.animation import node_worlds
from ..mesh import MeshError

# the viewport height, in pixels, the screen coverage hints are made for (1080p)
SCREEN_PIXELS = 1080


# ---- the compiled search ------------------------------------------------------

@njit(cache=True, nogil=True)
def _coarsest(curve, scale, bound):
    """Index of the coarsest level with ``scale * curve <= bound`` (the curve is
    non-increasing), or the last index if none is."""
    lo, hi = 0, len(curve) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if scale * curve[mid] <= bound:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True, nogil=True)
def _cost(curves, faces, offsets, ends, scales, weights, active, bound, out):
    """Triangles of the active parts each at its coarsest level within ``bound``
    (world units), or its finest allowed; writes the level indices into ``out``."""
    total = 0
    for p in range(len(scales)):
        if active[p]:
            i = _coarsest(curves[offsets[p]:ends[p]], scales[p], bound)
            out[p] = i
            total += weights[p] * faces[offsets[p] + i]
    return total


@njit(cache=True, nogil=True)
def _lexicographic(curves, faces, offsets, ends, scales, weights, budget):
    """(P,) level index per part: lexicographic minimax of the world errors within
    ``budget`` triangles (see the module docstring). Part p's level errors
    (float64) and face counts (int64), coarsest first, are
    ``curves[offsets[p]:offsets[p+1]]`` and the same slice of ``faces``; its
    levels past ``ends[p]`` are not allowed."""
    parts = len(scales)
    chosen = np.zeros(parts, np.int64)
    active = np.ones(parts, np.bool_)
    here = np.zeros(parts, np.int64)
    below = np.zeros(parts, np.int64)
    bits = np.zeros(1, np.int64)
    as_float = bits.view(np.float64)
    left = budget
    # the first round's upper end: the worst world error at the base meshes
    top = 0.0
    for p in range(parts):
        top = max(top, scales[p] * curves[offsets[p]])
    as_float[0] = top
    hi = bits[0]
    if _cost(curves, faces, offsets, ends, scales, weights, active, top, here) > left:
        return here         # not even every base mesh fits: all stay at their base
    while True:
        # invariant: the active parts fit in what is left at the bound of bit pattern hi
        if _cost(curves, faces, offsets, ends, scales, weights, active, 0.0, here) <= left:
            for p in range(parts):
                if active[p]:
                    chosen[p] = here[p]
            return chosen   # all that is left fits at full detail (error 0)
        lo = 0              # the bit pattern of 0.0, which does not fit
        while hi - lo > 1:
            mid = lo + (hi - lo) // 2
            bits[0] = mid
            fits = _cost(curves, faces, offsets, ends, scales, weights, active, as_float[0],
                         here) <= left
            if fits:
                hi = mid
            else:
                lo = mid
        bits[0] = hi
        _cost(curves, faces, offsets, ends, scales, weights, active, as_float[0], here)
        bits[0] = hi - 1
        _cost(curves, faces, offsets, ends, scales, weights, active, as_float[0], below)
        # the parts whose level changes just below the bound set it: they keep it
        remaining = 0
        for p in range(parts):
            if active[p]:
                if here[p] != below[p]:
                    active[p] = False
                    chosen[p] = here[p]
                    left -= weights[p] * faces[offsets[p] + here[p]]
                else:
                    remaining += 1
        if remaining == 0:
            return chosen
        hi -= 1             # the others fit just below this bound, at the same levels


# ---- the public functions ------------------------------------------------------

def _curves(pms: dict, order: list):
    """The parts' error curves and face counts, coarsest first, concatenated:
    (curves (L,) float64, faces (L,) int64, offsets (P+1,) int64), part
    ``order[k]`` at ``offsets[k]:offsets[k+1]``. (One copy, about 16 bytes a
    level; numba's typed lists would avoid it but compile for seconds in every
    new process.)"""
    offsets = np.zeros(len(order) + 1, np.int64)
    offsets[1:] = np.cumsum([len(pms[p].level_error) for p in order])
    curves = np.concatenate([np.asarray(pms[p].level_error, np.float64) for p in order])
    faces = np.concatenate([np.asarray(pms[p].face_counts, np.int64) for p in order])
    return curves, faces, offsets


def _scales(pms: dict, instances: dict, order: list):
    """(scales (P,) float64, weights (P,) int64): each part's largest instance scale
    (0 for a part no node draws) and its instance count."""
    missing = [p for p in order if p not in instances]
    if missing:
        raise MeshError(f"parts {missing} have no instance list")
    scales, weights = np.zeros(len(order)), np.zeros(len(order), np.int64)
    for k, p in enumerate(order):
        values = np.asarray(instances[p], np.float64).ravel()
        if not np.isfinite(values).all() or (values < 0).any():
            raise MeshError(f"part {p}'s instance scales must be finite and non-negative")
        weights[k] = len(values)
        scales[k] = values.max() if len(values) else 0.0
    return scales, weights


def _fill_plateaus(index, curves, faces, offsets, ends, scales, weights, budget) -> None:
    """Spend what the lexicographic choice leaves of ``budget`` on finer levels of
    the same error, worst world error first (in place on ``index``).

    A level's error is the worst collapse applied to reach it, so the curve has
    plateaus: finer levels behind a large collapse report its error until it is
    undone. The search stops at a plateau's coarse end, which the error cannot
    tell apart from its fine end; the faces left are better spent there (the
    collapses undone are real detail) than not at all. No part's error changes.
    """
    left = budget - int(np.dot(weights, faces[offsets[:-1] + index]))
    for k in np.argsort(-(scales * curves[offsets[:-1] + index]), kind="stable"):
        if left <= 0:
            break
        if weights[k] == 0:
            continue        # drawn by no node: it costs nothing and shows nothing
        part = slice(offsets[k], ends[k])
        curve, counts, i = curves[part], faces[part], int(index[k])
        # the plateau's fine end: the last level whose error is still curve[i]
        end = int(np.searchsorted(-curve, -curve[i], side="right")) - 1
        affordable = int(np.searchsorted(counts, counts[i] + left // int(weights[k]),
                                         side="right")) - 1
        j = max(i, min(end, affordable))
        left -= int(weights[k]) * int(counts[j] - counts[i])
        index[k] = j


def part_diagonal(pm) -> float:
    """The diagonal of ``pm``'s full-detail bounding box (mesh units)."""
    if not len(pm.positions):
        return 0.0
    return float(np.linalg.norm(np.ptp(np.asarray(pm.positions), axis=0)))


def scene_levels(pms: dict, instances: dict, *, ratio: float | None = None,
                 error: float | None = None, per_mesh: bool = False,
                 diagonal: float | None = None, finest: dict | None = None) -> dict:
    """The level (vertex count) of each part for one scene-wide criterion.

    Parameters
    ----------
    pms : dict of int to ProgressiveMesh
        The parts.
    instances : dict of int to (k,) float array or list of float
        Per part, one world scale factor per instance (:func:`scene_instances`);
        an empty list: drawn by no node (its faces count 0, it stays at its base).
    ratio : float, optional
        In (0, 1]: the scene's triangles (each part's faces times its instance
        count) at most ``ratio`` times its full count, world errors lexicographic
        minimax (module docstring). With ``per_mesh``: each part's own ratio.
    error : float, optional
        >= 0: each part at its coarsest level whose world error is at most
        ``error * diagonal``.
    per_mesh : bool
        ``ratio`` per part rather than for the scene.
    diagonal : float, optional
        The scene's world bounding-box diagonal (:func:`scene_instances`); without
        it, the largest part's world diagonal (part diagonal x largest scale), a
        lower bound of it.
    finest : dict of int to int, optional
        With ``ratio``: part -> the finest level it may take (the previous level
        of a chain, so that every part only coarsens along it:
        :func:`chain_levels`).

    Returns
    -------
    dict of int to int
        Part -> level, each within ``pm.levels``.

    Raises
    ------
    MeshError
        Unless exactly one of ``ratio`` and ``error`` is given (``per_mesh`` needs
        ``ratio``), or on a ratio outside (0, 1], a negative error or a bad
        instance list.
    """
    if (ratio is None) == (error is None):
        raise MeshError("give exactly one of ratio or error")
    if per_mesh and ratio is None:
        raise MeshError("per_mesh levels are chosen by ratio, not by error")
    order = sorted(pms)
    scales, weights = _scales(pms, instances, order)
    if ratio is not None:
        ratio = float(ratio)
        if not 0 < ratio <= 1:
            raise MeshError(f"ratio must be in (0, 1], got {ratio}")
        if per_mesh:
            return {p: pms[p].level_for(ratio=ratio) for p in order}
        if not order:
            return {}
        curves, faces, offsets = _curves(pms, order)
        full = int(np.dot(weights, faces[offsets[1:] - 1]))
        # floor: the total is at most ratio x full, never rounded up past it
        budget = math.floor(ratio * full)
        ends = offsets[1:].copy()
        for k, p in enumerate(order):
            if finest is not None and p in finest:
                ends[k] = offsets[k] + pms[p].check_level(finest[p]) - pms[p].base_vertices + 1
        index = _lexicographic(curves, faces, offsets, ends, scales, weights, budget)
        _fill_plateaus(index, curves, faces, offsets, ends, scales, weights, budget)
        return {p: pms[p].base_vertices + int(index[k]) for k, p in enumerate(order)}
    error = float(error)
    if not (math.isfinite(error) and error >= 0):
        raise MeshError(f"error must be a non-negative number, got {error}")
    if diagonal is None:
        diagonal = max((part_diagonal(pms[p]) * scales[k] for k, p in enumerate(order)),
                       default=0.0)
    bound = error * float(diagonal)
    levels = {}
    for k, p in enumerate(order):
        curve = np.asarray(pms[p].level_error)
        # the coarsest level within the bound; the last (full detail) always is
        levels[p] = pms[p].base_vertices + int(np.argmax(scales[k] * curve <= bound))
    return levels


def chain_levels(pms: dict, instances: dict, *, lods=None, errors=None, per_mesh: bool = False,
                 diagonal: float | None = None) -> list[dict]:
    """Per level of an LOD chain (finest first), part -> level: :func:`scene_levels`
    at each of ``lods`` (scene budget, or ``per_mesh``) or ``errors``.

    Along a chain by scene budget each part only coarsens: level k's choice may
    not be finer than level k-1's (``finest=``). Without that, the leftover of a
    smaller budget can land on a part the larger one had starved, and a part
    would get finer as the chain coarsens; with it, each level is the best
    choice among those, its worst error no higher (the previous level's parts
    are each within its worst error). By error or per mesh the chain is
    monotone by itself.
    """
    if errors is not None:
        return [scene_levels(pms, instances, error=e, diagonal=diagonal) for e in errors]
    chain, finest = [], None
    for ratio in lods:
        chosen = scene_levels(pms, instances, ratio=ratio, per_mesh=per_mesh,
                              finest=None if per_mesh else finest)
        chain.append(chosen)
        finest = chosen
    return chain


def world_errors(pms: dict, instances: dict, levels: dict) -> dict:
    """Part -> its world error at ``levels[p]`` (its error times its largest scale)."""
    order = sorted(levels)
    scales, _ = _scales(pms, instances, order)
    return {p: float(scales[k] * pms[p].error_at_level(levels[p])) for k, p in enumerate(order)}


def scene_faces(pms: dict, instances: dict, levels: dict) -> int:
    """Triangles drawn with each part at ``levels[p]``, once per instance."""
    return sum(len(instances[p]) * pms[p].faces_at_level(level) for p, level in levels.items())


def coverage_from_errors(errors, diagonal: float, pixels: int = SCREEN_PIXELS) -> list[float]:
    """``MSFT_screencoverage`` hints for levels of these world errors (finest first).

    Screen coverage is the fraction of the viewport height the object spans.
    Taking the object's size on screen as its bounding-box diagonal ``D``, at
    coverage ``c`` a world error ``e`` projects to ``e / D * c * pixels`` pixels;
    level ``k + 1`` is good enough (under one pixel at ``pixels`` lines, 1080p)
    once ``c <= D / (pixels * e[k + 1])``, so level ``k`` hands over at
    ``coverage[k] = min(1, D / (pixels * e[k + 1]))``; the coarsest gets 0. Each
    value is at most the one before (a coarser level never has the smaller
    error; equal errors give equal hints): the hints stay monotone.

    >>> [round(c, 4) for c in coverage_from_errors([0.0, 0.001, 0.01], 1.0)]
    [0.9259, 0.0926, 0.0]
    """
    errors = np.asarray(errors, np.float64)
    if errors.ndim != 1 or len(errors) == 0:
        raise MeshError("coverage hints need the error of at least one level")
    coverage = np.ones(len(errors))
    coarser = errors[1:]
    with np.errstate(divide="ignore"):
        coverage[:-1] = np.where(coarser > 0, float(diagonal) / (pixels * coarser), 1.0)
    coverage = np.minimum.accumulate(np.clip(coverage, 0.0, 1.0))
    coverage[-1] = 0.0
    return [float(c) for c in coverage]


# ---- a scene's instances ----------------------------------------------------------

def _largest_scale(matrices: np.ndarray) -> np.ndarray:
    """(k,) largest singular value of the linear part of each (k, 4, 4) matrix."""
    return np.linalg.norm(matrices[:, :3, :3], ord=2, axis=(1, 2))


def _carried_float(scene, index):
    from ..io.gltf_attributes import as_float

    values, record, _ = scene.carried[index]
    return as_float(np.asarray(values), record)


def _instancing_matrices(columns: dict, count: int) -> np.ndarray:
    """(k, 4, 4) float64 local transforms of ``count`` GPU instances from their
    ``EXT_mesh_gpu_instancing`` columns (``TRANSLATION`` (k, 3), ``ROTATION`` (k, 4)
    x y z w, ``SCALE`` (k, 3), each optional), all at once: ``T @ R @ S`` as
    ``io.gltf._local_matrix`` makes it for one node (an unnormalised quaternion is
    normalised, a zero one is no rotation), with the same operations in the same
    order, so each matrix is the same to the bit."""
    widths = {"TRANSLATION": 3, "ROTATION": 4, "SCALE": 3}
    for name, values in columns.items():
        if values.ndim != 2 or values.shape[1] != widths[name]:
            raise MeshError(f"its EXT_mesh_gpu_instancing {name} values have "
                            f"{values.shape[-1]} components, not {widths[name]}")
    local = np.zeros((count, 4, 4))
    local[:, 3, 3] = 1.0
    linear = np.repeat(np.eye(3)[None], count, axis=0)
    if "ROTATION" in columns:
        x, y, z, w = np.asarray(columns["ROTATION"][:count], np.float64).T
        norm = x * x + y * y + z * z + w * w
        turned = norm > 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):   # rows of a zero one unused
            s = 2.0 / norm
            rotation = np.stack([
                np.stack([1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)], -1),
                np.stack([s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)], -1),
                np.stack([s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)], -1),
            ], 1)
        linear[turned] = rotation[turned]
    if "SCALE" in columns:
        linear = linear * np.asarray(columns["SCALE"][:count], np.float64)[:, None, :]
    local[:, :3, :3] = linear
    if "TRANSLATION" in columns:
        local[:, :3, 3] = columns["TRANSLATION"][:count]
    return local


def _node_matrices(scene, number: int, world: list) -> np.ndarray:
    """How node ``number`` draws its mesh: (k, j, 4, 4) transforms, k instances of
    j transforms each. One instance per ``EXT_mesh_gpu_instancing`` entry, else
    one; each the node's world transform, or for a skinned node the bind pose of
    each of its j joints (joint world x inverse bind matrix: glTF ignores the
    node's own transform then), a vertex going where a blend of them takes it."""
    document = scene.document
    node = document["nodes"][number]
    base = world[number][None]
    if "skin" in node:
        skin = document["skins"][node["skin"]]
        joints = [world[j] for j in skin.get("joints", ())]
        if joints:
            bind = np.repeat(np.eye(4)[None], len(joints), axis=0)
            if skin.get("inverseBindMatrices") in scene.carried:
                raw = _carried_float(scene, skin["inverseBindMatrices"])
                bind[:len(raw)] = raw[:len(joints)].reshape(-1, 4, 4).transpose(0, 2, 1)
            base = np.stack(joints) @ bind
    instancing = (node.get("extensions") or {}).get("EXT_mesh_gpu_instancing")
    if isinstance(instancing, dict) and instancing.get("attributes"):
        attributes = instancing["attributes"]
        columns = {name: _carried_float(scene, attributes[name]) for name in
                   ("TRANSLATION", "ROTATION", "SCALE") if attributes.get(name) in scene.carried}
        count = min((len(v) for v in columns.values()), default=0)
        return base[None] @ _instancing_matrices(columns, count)[:, None]
    return base[None]


def instance_matrices(scene, part: int, world) -> np.ndarray:
    """(k, 4, 4) world transforms of every instance of ``part`` (a glTF mesh index)
    in its rest pose, ``world`` the nodes' world matrices (``io.animation.node_worlds``);
    a skinned node's by its first joint's bind pose."""
    drawn = [_node_matrices(scene, number, world)[:, 0]
             for number in scene.mesh_nodes.get(part, ())]
    return np.concatenate(drawn) if drawn else np.zeros((0, 4, 4))


def scene_instances(scene, pms: dict | None = None) -> tuple[dict, float]:
    """Per part, one world scale factor per instance, and the scene's world diagonal.

    Parameters
    ----------
    scene : Scene
        As :func:`lodserver.io.scene.load_scene` reads it; its parts are the glTF
        meshes in ``scene.meshes`` (or ``pms``' keys).
    pms : dict of int to ProgressiveMesh, optional
        The parts' progressive meshes, for their bounding boxes; else
        ``scene.meshes``' positions.

    Returns
    -------
    (instances, diagonal)
        ``instances[p]``: (k,) float64, the largest singular value of each
        transform that draws part ``p`` (node world transforms, instancing,
        skinned nodes' bind pose); ``diagonal``: the diagonal of the world
        bounding box of every part's every instance (the corners of each part's
        box, transformed), world units.
    """
    parts = sorted(pms if pms is not None else scene.meshes)
    # every node's rest-pose world transform, whether or not a scene lists it
    world = node_worlds(scene.document, scene.carried)
    users = scene.mesh_nodes
    instances, low, high = {}, np.full(3, np.inf), np.full(3, -np.inf)
    for p in parts:
        scales, matrices = [np.zeros(0)], [np.zeros((0, 4, 4))]
        for number in users.get(p, ()):
            drawn = _node_matrices(scene, number, world)
            # an instance's scale: the largest of its joints' (a blend of rigid or
            # scaled joints stretches no more than its most stretching joint)
            largest = _largest_scale(drawn.reshape(-1, 4, 4)).reshape(drawn.shape[:2])
            scales.append(largest.max(axis=1, initial=0.0))
            matrices.append(drawn.reshape(-1, 4, 4))
        instances[p] = np.concatenate(scales)
        matrices = np.concatenate(matrices)
        positions = np.asarray(pms[p].positions if pms is not None else scene.meshes[p].positions)
        if len(matrices) and len(positions):
            box = np.stack([positions.min(axis=0), positions.max(axis=0)])
            corners = np.array([[box[i, 0], box[j, 1], box[k, 2], 1.0]
                                for i in (0, 1) for j in (0, 1) for k in (0, 1)])
            placed = (matrices @ corners.T).transpose(0, 2, 1)[..., :3].reshape(-1, 3)
            low, high = np.minimum(low, placed.min(axis=0)), np.maximum(high, placed.max(axis=0))
    diagonal = float(np.linalg.norm(high - low)) if np.isfinite(low).all() else 0.0
    return instances, diagonal
