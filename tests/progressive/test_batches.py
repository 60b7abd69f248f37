"""Splits in batches of independent ones (``progressive.batches``): on real meshes with
attributes (Duck; Fox, skinned; a morphed scene mesh) and generated ones (a sphere with a
skin, morph targets and a custom attribute; one with close-pair contractions), the batched mesh
has the unbatched mesh's full and base levels exactly, every level is a valid mesh, the
splits of a batch applied in any order give the same state (every attribute), both ways,
and no split of a batch touches what another creates or moves."""

from __future__ import annotations

import numpy as np
import pytest

from lodserver import build
from lodserver.progressive.batches import batch_order, reordered, schedule

from ..meshes import SHARED, mesh, skinned_sphere, textured_sphere
from .test_appearance import corner_rows

_BUILT = {}


def _scene_mesh(name):
    from lodserver.io.scene import load_scene
    from lodserver.simplify.poses import scene_poses

    scene = load_scene(SHARED / "scenes" / name)
    index, found = max(scene.meshes.items(), key=lambda item: item[1].face_count)
    return build(found, poses=scene_poses(scene, index, found))


def _make(name):
    if name == "textured_sphere":
        return build(textured_sphere(hard_equator=True))
    if name == "skinned_sphere":
        # normals, UVs, tangents, a skin, two morph targets, a custom attribute
        return build(skinned_sphere())
    if name in ("spot", "torus"):
        return build(mesh(name))
    if name == "two_boxes_joined":
        # close pairs: contractions that kill no face, joining the two parts
        return build(mesh("two_boxes"), pair_threshold="50%")
    if not SHARED.is_dir():
        pytest.skip(f"shared meshes not found at {SHARED}")
    if name.startswith("scenes/"):
        return _scene_mesh(name.split("/", 1)[1])
    return build(mesh(name))


def built(name):
    """(unbatched, Schedule) of a named mesh, built once."""
    if name not in _BUILT:
        pm = _make(name)
        _BUILT[name] = (pm, schedule(pm))
    return _BUILT[name]


NAMES = ["textured_sphere", "skinned_sphere", "spot", "two_boxes_joined", "Duck.glb",
         "scenes/Fox.glb", "scenes/AnimatedMorphCube.glb"]


def _state(pm, level):
    """Every array a level holds, for exact comparison."""
    positions, faces = pm.arrays_at(level)
    values, corners = pm.wedges_at(level)
    return positions, faces, values, corners


def _batch_levels(result):
    """(start level, end level) of every batch of a ``Schedule``."""
    n0, starts = result.pm.base_vertices, result.batch_starts
    return [(n0 + int(a), n0 + int(b)) for a, b in zip(starts[:-1], starts[1:])]


def _rows(faces):
    """Faces rotated to start at their smallest vertex, sorted: equal for equal
    face sets whatever the face order."""
    roll = (np.argmin(faces, axis=1)[:, None] + np.arange(3)) % 3
    rotated = np.take_along_axis(faces, roll, axis=1)
    return rotated[np.lexsort(rotated.T[::-1])]


def _same(a, b):
    return all((x is None and y is None) or np.array_equal(x, y) for x, y in zip(a, b))


def _split(pm, state, t):
    """Split ``t`` alone on the mutable ``state`` (as ``replay._apply_splits`` and
    ``_apply_wedge_splits`` do for a range)."""
    positions, faces, values, corners = state
    j = t - pm.base_vertices
    s = pm.parent[t]
    positions[s] = pm.fine_position[j]
    positions[t] = pm.new_position[j]
    moved = pm.moved_corners[pm.moved_offsets[j]:pm.moved_offsets[j + 1]]
    faces.reshape(-1)[moved] = t
    born = slice(pm.face_counts[j], pm.face_counts[j + 1])
    faces[born] = pm.birth_faces[born]
    if values is not None:
        w0, top = int(pm.wedge_counts[0]), int(pm.wedge_counts[j + 1])
        for x in range(pm.wedge_counts[j], top):
            values[pm.wedge_parent[x]] = pm.wedge_fine_value[x - w0]
            values[x] = pm.wedge_new_value[x - w0]
        for c in moved:
            w = pm.corner_wedges.reshape(-1)[c]
            while w >= top:
                w = pm.wedge_parent[w]
            corners.reshape(-1)[c] = w
        corners[born] = pm.birth_corners[born]


def _collapse(pm, state, t):
    """Collapse ``t`` (undo its split) alone on ``state``."""
    positions, faces, values, corners = state
    j = t - pm.base_vertices
    s = pm.parent[t]
    positions[s] = pm.coarse_position[j]
    moved = pm.moved_corners[pm.moved_offsets[j]:pm.moved_offsets[j + 1]]
    faces.reshape(-1)[moved] = s
    if values is not None:
        w0, bottom = int(pm.wedge_counts[0]), int(pm.wedge_counts[j])
        for x in range(pm.wedge_counts[j + 1] - 1, bottom - 1, -1):
            values[pm.wedge_parent[x]] = pm.wedge_coarse_value[x - w0]
        for c in moved:
            w = pm.corner_wedges.reshape(-1)[c]
            while w >= bottom:
                w = pm.wedge_parent[w]
            corners.reshape(-1)[c] = w


def _room(pm, level):
    """A level's state in arrays of full-detail size (slots beyond it unused)."""
    positions, faces, values, corners = _state(pm, level)
    grown = [np.zeros_like(pm.positions), np.zeros_like(pm.faces), None, None]
    grown[0][:level], grown[1][:len(faces)] = positions, faces
    if values is not None:
        grown[2], grown[3] = np.zeros_like(pm.wedge_values), np.zeros_like(pm.corner_wedges)
        grown[2][:len(values)], grown[3][:len(corners)] = values, corners
    return grown


def _cut(pm, state, level):
    """``state`` cut to ``level``'s counts."""
    positions, faces, values, corners = state
    f = pm.faces_at_level(level)
    if values is None:
        return positions[:level], faces[:f], None, None
    w = int(pm.wedge_counts[level - pm.base_vertices])
    return positions[:level], faces[:f], values[:w], corners[:f]


@pytest.mark.parametrize("name", NAMES)
def test_full_and_base_levels_are_the_unbatched_ones_exactly(name):
    pm, result = built(name)
    batched = result.pm
    assert batched.split_count == pm.split_count
    assert batched.base_vertices == pm.base_vertices
    assert _same(_state(batched, batched.base_vertices), _state(pm, pm.base_vertices))
    # full detail: the same vertices, renumbered by the new split order, and the same
    # faces with the same attributes at every corner
    n0 = pm.base_vertices
    old_id = np.concatenate([np.arange(n0), n0 + result.order])
    assert np.array_equal(batched.positions, pm.positions[old_id])
    full, old = batched.at(batched.vertex_count), pm.at(pm.vertex_count)
    assert np.array_equal(_rows(old_id[full.faces]), _rows(old.faces))
    if old.attributes is not None:
        assert np.array_equal(corner_rows(full), corner_rows(old))
    for field in ("face_material",):
        a, b = getattr(pm, field), getattr(batched, field)
        assert (a is None and b is None) or np.array_equal(a, b)
    # the same collapses, each once: the same errors as a multiset
    assert np.array_equal(np.sort(batched.error), np.sort(pm.error))


@pytest.mark.parametrize("name", NAMES)
def test_batch_ids_rise_and_split_vertices_ascend_within_a_batch(name):
    pm, result = built(name)
    batched, batch = result.pm, result.batch
    assert batch.dtype == np.int32 and batch.shape == (pm.split_count,)
    assert batch[0] == 0 and np.all(np.diff(batch) >= 0) and np.all(np.diff(batch) <= 1)
    for low, high in _batch_levels(result):
        vs = batched.parent[low:high]
        # split vertices exist at the batch's start and come in ascending order
        assert np.all(vs < low) and np.all(np.diff(vs) > 0)


@pytest.mark.parametrize("name", NAMES)
def test_no_split_touches_what_another_split_of_its_batch_creates_or_changes(name):
    pm, result = built(name)
    batched = result.pm
    n0 = batched.base_vertices
    for level, high in _batch_levels(result):
        faces = batched.arrays_at(level)[1]
        vs = batched.parent[level:high]
        split = np.zeros(batched.vertex_count, dtype=bool)
        split[vs] = True
        # no face of the start level holds two split vertices: they are not adjacent
        assert np.all(split[faces].sum(axis=1) <= 1)
        for t in range(level, high):
            j = t - n0
            s = batched.parent[t]
            # new faces: their own vertices, or vertices of the start level that no
            # other split of the batch splits
            born = batched.birth_faces[batched.face_counts[j]:batched.face_counts[j + 1]]
            others = born[(born != s) & (born != t)]
            assert np.all(others < level) and not np.any(split[others])
            # moved corners: held by s at the start level
            moved = batched.moved_corners[batched.moved_offsets[j]:batched.moved_offsets[j + 1]]
            start_faces, end_faces = len(faces), batched.faces_at_level(high)
            old = moved[moved // 3 < start_faces]
            assert np.all(faces.reshape(-1)[old] == s)
            # none on a face another split of the batch brings
            assert not np.any((moved // 3 >= start_faces) & (moved // 3 < end_faces))


@pytest.mark.parametrize("name", NAMES)
def test_a_batch_applied_in_any_order_gives_the_same_state_both_ways(name):
    pm, result = built(name)
    batched = result.pm
    rng = np.random.default_rng(3)
    for i, (low, high) in enumerate(_batch_levels(result)):
        for _ in range(2):
            state = _room(batched, low)
            for t in rng.permutation(np.arange(low, high)):
                _split(batched, state, int(t))
            assert _same(_cut(batched, state, high), _state(batched, high)), f"batch {i} up"
            state = _room(batched, high)
            for t in rng.permutation(np.arange(low, high)):
                _collapse(batched, state, int(t))
            assert _same(_cut(batched, state, low), _state(batched, low)), f"batch {i} down"


def _edge_face_counts(faces):
    e = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


@pytest.mark.parametrize("name", NAMES)
def test_every_level_is_a_valid_mesh_reached_the_same_from_both_ends(name):
    pm, result = built(name)
    batched = result.pm
    manifold = _edge_face_counts(pm.faces).max() <= 2
    up = batched.cursor(batched.base_vertices)
    down = batched.cursor(batched.vertex_count)
    levels = list(batched.levels)
    if len(levels) > 400:
        levels = sorted(set(np.linspace(levels[0], levels[-1], 400).astype(int).tolist())
                        | set((batched.base_vertices + result.batch_starts).tolist()))
    for level in levels:
        f = batched.arrays_at(level)[1]
        assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
        assert len(np.unique(f)) == level, f"a vertex without faces at {level}"
        assert len(np.unique(np.sort(f, axis=1), axis=0)) == len(f)
        if manifold:
            assert _edge_face_counts(f).max() <= 2, f"non-manifold edge at level {level}"
        direct = batched.mesh_of(*batched.arrays_at(level), *batched.wedges_at(level))
        reached = up.seek(level).mesh()
        assert np.array_equal(reached.positions, direct.positions)
        assert np.array_equal(reached.faces, direct.faces)
        if direct.attributes is not None:
            assert np.array_equal(reached.attributes.values, direct.attributes.values)
            assert np.array_equal(reached.attributes.corners, direct.attributes.corners)
    for level in reversed(levels):
        positions, faces = down.seek(level).arrays()
        direct = batched.arrays_at(level)
        assert np.array_equal(positions, direct[0]) and np.array_equal(faces, direct[1])


def test_the_recorded_order_is_laid_out_as_it_was():
    pm = built("spot")[0]
    same = reordered(pm, np.arange(pm.split_count))
    for field in ("positions", "faces", "parent", "coarse_position", "error", "face_counts",
                  "moved_offsets", "moved_corners"):
        assert np.array_equal(getattr(same, field), getattr(pm, field)), field


def test_batches_split_a_share_of_the_level_and_the_window_bounds_them():
    pm = built("spot")[0]
    order, batch = batch_order(pm)
    assert np.array_equal(np.sort(order), np.arange(pm.split_count))
    sizes = np.bincount(batch)
    # far fewer batches than splits: most batches hold many splits
    assert len(sizes) < pm.split_count / 10
    # a window of nothing, or an error reach of nothing, keeps the recorded order
    order, _ = batch_order(pm, window=0.0)
    assert np.array_equal(order, np.arange(pm.split_count))
    order, batch = batch_order(pm, window=1.0, error_ratio=1.0)
    moved = np.flatnonzero(order != np.arange(pm.split_count))
    # with a reach of equal errors only, a split moves only among splits of its error
    assert np.all(pm.level_error[order[moved]] == pm.level_error[moved])
    for bad in (dict(window=-1), dict(error_ratio=1.5)):
        with pytest.raises(ValueError):
            batch_order(pm, **bad)


def test_the_build_option_batches_and_the_artefact_keeps_the_batches(tmp_path):
    source = mesh("spot")
    plain, batched = build(source), build(source, batched=True)
    assert plain.split_batch is None and "batched" not in plain.metadata["options"]
    assert batched.metadata["options"]["batched"] is True
    expected = schedule(plain)
    assert np.array_equal(batched.split_batch, expected.batch)
    assert np.array_equal(batched.parent, expected.pm.parent)
    assert np.array_equal(batched.faces, expected.pm.faces)
    batched.save(tmp_path / "b.pm")
    loaded = type(batched).load(tmp_path / "b.pm")
    assert np.array_equal(loaded.split_batch, batched.split_batch)
    middle = batched.vertex_count // 2
    assert _same(_state(loaded, middle), _state(batched, middle))
    plain.save(tmp_path / "p.pm")
    assert type(plain).load(tmp_path / "p.pm").split_batch is None
    # octree clustering's log batches too
    clustered = build(source, method="cluster", batched=True)
    assert clustered.split_batch is not None
    assert np.array_equal(clustered.at(clustered.vertex_count).positions[:clustered.base_vertices],
                          build(source, method="cluster").positions[:clustered.base_vertices])


def test_a_batch_numbering_that_skips_or_falls_is_refused():
    pm = built("spot")[1].pm
    from lodserver.progressive.mesh import STORED_FIELDS, ProgressiveMesh
    fields = {name: getattr(pm, name) for name in STORED_FIELDS}
    for bad in (pm.split_batch + 1, pm.split_batch[::-1].copy(), pm.split_batch[:-1]):
        with pytest.raises(ValueError, match="split_batch"):
            ProgressiveMesh(**{**fields, "split_batch": bad})
