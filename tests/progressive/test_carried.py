"""Carried attributes (tangents, skin influences, morph deltas, custom values) through
decimation and the progressive mesh: exact at every level both ways, and valid at every
level (unit tangents orthogonal to the normal, influences of existing joints whose
weights sum to 1, deltas inside the input's range)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lodserver import build
from lodserver.mesh import Attributes, Mesh
from lodserver.simplify.carried import carried_groups, solved_part

from ..meshes import skinned_sphere
from .test_appearance import corner_rows, same_level


@pytest.fixture(scope="module")
def sphere():
    m = skinned_sphere()
    return m, build(m)


def test_only_solved_columns_reach_the_kernel(sphere):
    m, _ = sphere
    part = solved_part(m)
    assert [name for name, _ in part.attributes.layout] == ["NORMAL", "TEXCOORD_0"]
    assert np.array_equal(part.attributes.corners, m.attributes.corners)
    groups, skin = carried_groups(m.attributes.layout)
    assert skin.tolist() == [[9, 13]] and len(groups) == 5


def test_all_splits_give_back_the_input_with_carried_columns(sphere):
    m, pm = sphere
    assert pm.attribute_layout == m.attributes.layout and pm.split_count > 0.9 * m.vertex_count
    full = pm.at(pm.vertex_count)
    np.testing.assert_array_equal(corner_rows(full), corner_rows(m))
    assert same_level(pm.cursor(pm.base_vertices).seek(pm.vertex_count).mesh(), full)


def test_forward_then_backward_is_the_identity(sphere):
    _, pm = sphere
    cursor = pm.cursor(pm.base_vertices)
    start = cursor.mesh()
    assert same_level(cursor.seek(pm.vertex_count).seek(pm.base_vertices).mesh(), start)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_a_level_is_the_same_from_every_direction(sphere, data):
    _, pm = sphere
    levels = st.integers(pm.base_vertices, pm.vertex_count)
    start, target = data.draw(levels), data.draw(levels)
    reached = pm.cursor(start).seek(target).mesh()
    assert same_level(reached, pm.at(target))
    assert same_level(pm.cursor(pm.vertex_count).seek(target).mesh(), reached)


def _levels(pm, count=10):
    return np.unique(np.linspace(pm.base_vertices, pm.vertex_count, count).astype(int))


def test_every_level_has_valid_carried_values(sphere):
    m, pm = sphere
    a = m.attributes
    lo, hi = a.values.min(axis=0), a.values.max(axis=0)
    for level in _levels(pm):
        values = pm.at(level).attributes.values
        normal, tangent = values[:, 0:3], values[:, 5:8]
        np.testing.assert_allclose(np.linalg.norm(tangent, axis=1), 1.0, atol=1e-9)
        assert np.abs((normal * tangent).sum(1)).max() < 1e-9
        assert set(np.unique(values[:, 8])) <= {-1.0, 1.0}
        joints, weights = values[:, 9:13], values[:, 13:17]
        assert np.array_equal(joints, np.rint(joints)) and set(np.unique(joints)) <= {0, 1, 2}
        assert weights.min() >= 0.0
        np.testing.assert_allclose(weights.sum(1), 1.0, atol=1e-12)
        deltas = values[:, 17:24]
        assert (deltas >= lo[17:24] - 1e-12).all() and (deltas <= hi[17:24] + 1e-12).all()


def test_influences_blend_at_coarse_levels(sphere):
    """Merging wedges of differently weighted vertices gives weights neither end had."""
    m, pm = sphere
    rows = {tuple(r) for r in np.round(m.attributes.values[:, 13:17], 9)}
    coarse = pm.at(pm.level_for(ratio=0.1)).attributes.values[:, 13:17]
    assert any(tuple(r) not in rows for r in np.round(coarse, 9))


def test_a_mesh_whose_attributes_are_all_carried():
    m = skinned_sphere()
    keep = np.arange(9, 17)         # JOINTS_0, WEIGHTS_0
    layout = tuple(item for item in m.attributes.layout if item[0] in ("JOINTS_0", "WEIGHTS_0"))
    only = Mesh(m.positions, m.faces,
                Attributes(layout, m.attributes.values[:, keep], m.attributes.corners))
    pm = build(only)
    assert pm.split_count > 0.9 * only.vertex_count
    assert same_level(pm.cursor(pm.base_vertices).seek(pm.vertex_count).mesh(),
                      pm.at(pm.vertex_count))
    np.testing.assert_array_equal(corner_rows(pm.at(pm.vertex_count)), corner_rows(only))
    weights = pm.at(pm.level_for(ratio=0.2)).attributes.values[:, 4:8]
    np.testing.assert_allclose(weights.sum(1), 1.0, atol=1e-12)


def test_carried_columns_survive_the_artefact(sphere, tmp_path):
    from lodserver.progressive.mesh import ProgressiveMesh
    _, pm = sphere
    pm.save(tmp_path / "skinned.pm")
    again = ProgressiveMesh.load(tmp_path / "skinned.pm")
    assert again.attribute_layout == pm.attribute_layout
    level = pm.level_for(ratio=0.3)
    assert same_level(again.at(level), pm.at(level))


def test_skin_and_morph_deltas_agree_on_every_wedge_of_a_vertex(sphere):
    """The sides of the UV seam must skin and morph alike at every level, or the seam
    tears open when the asset moves (simplify.carried's table)."""
    m, pm = sphere
    per_vertex = slice(9, 23)       # JOINTS_0, WEIGHTS_0, TARGET0_POSITION, TARGET1_POSITION
    for level in _levels(pm, 16):
        lv = pm.at(level)
        owner = lv.wedge_vertices()
        used = owner >= 0
        values = lv.attributes.values[used, per_vertex]
        order = np.argsort(owner[used], kind="stable")
        first = np.unique(owner[used][order], return_index=True)[1]
        reference = np.repeat(values[order][first], np.diff(np.append(first, len(order))), axis=0)
        assert np.array_equal(values[order], reference), level
