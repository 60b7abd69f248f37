"""The judge: sampling, exact point-to-triangle distance, two-sided surface distance."""

from pathlib import Path

import numpy as np
import pytest
import trimesh

from lodserver.mesh import Mesh
from lodserver.metrics import point_to_mesh_distance, sample_surface, surface_distance
from lodserver.metrics.nearest import nearest_on_mesh

SPOT = Path(__file__).resolve().parents[1] / "data" / "spot.obj"


@pytest.fixture(scope="module")
def spot() -> Mesh:
    loaded = trimesh.load(SPOT, process=False)
    return Mesh(np.asarray(loaded.vertices), np.asarray(loaded.faces))


def icosphere(subdivisions=3) -> Mesh:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return Mesh(np.asarray(sphere.vertices), np.asarray(sphere.faces))


# ---------------------------------------------------------------------------
# Brute-force reference: every point against every triangle, written
# independently of the kernel (normal equations instead of edge-side tests).
# ---------------------------------------------------------------------------


def _segment_distance(p, u, v):
    """|p - closest point of segment uv|, p (k, 1, 3) against segments (1, m, 3)."""
    d = v - u
    den = (d * d).sum(-1)
    t = np.where(den > 0, ((p - u) * d).sum(-1) / np.where(den > 0, den, 1.0), 0.0)
    t = np.clip(t, 0.0, 1.0)
    return np.linalg.norm(p - (u + t[..., None] * d), axis=-1)


def brute_force_distance(points, positions, faces):
    p = np.asarray(points, float)[:, None, :]
    a, b, c = (
        np.asarray(positions, float)[np.asarray(faces)[:, i]][None] for i in range(3)
    )
    e0, e1, ap = b - a, c - a, p - a
    # interior candidate: minimise |ap - s e0 - t e1| over the plane, keep it if
    # (s, t) lands inside the triangle
    g00, g01, g11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
    r0, r1 = (e0 * ap).sum(-1), (e1 * ap).sum(-1)
    det = g00 * g11 - g01 * g01
    flat = det <= 1e-12 * g00 * g11  # degenerate: only its edges count
    safe = np.where(flat, 1.0, det)
    s = (g11 * r0 - g01 * r1) / safe
    t = (g00 * r1 - g01 * r0) / safe
    inside = ~flat & (s >= 0) & (t >= 0) & (s + t <= 1)
    face = np.linalg.norm(ap - s[..., None] * e0 - t[..., None] * e1, axis=-1)
    face = np.where(inside, face, np.inf)
    edges = np.minimum.reduce(
        [
            _segment_distance(p, a, b),
            _segment_distance(p, b, c),
            _segment_distance(p, c, a),
        ]
    )
    return np.minimum(face, edges).min(axis=1)


def random_soup(rng, count=150):
    tris = rng.normal(size=(count, 3, 3))
    tris[:, 1:] = tris[:, :1] + 0.3 * rng.normal(size=(count, 2, 3))
    tris[0] = [[0, 0, 0], [1, 2, 3], [2, 4, 6]]  # exactly collinear
    tris[1] = [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [1, -1, 0]]  # repeated corner
    tris[2] = [[-1, 2, 0.25]] * 3  # a single point
    a, b = rng.normal(size=(2, 3))
    tris[3] = [a, b, a + 0.37 * (b - a)]  # collinear up to rounding
    tris[4] = [[0, 0, 0], [1e-9, 0, 0], [0, 0, 1]]  # needle
    tris[5] = [[0, 0, 0], [2, 0, 0], [1, 1e-9, 0]]  # flat cap
    return tris.reshape(-1, 3), np.arange(3 * count).reshape(-1, 3)


# ---------------------------------------------------------------------------
# point_to_mesh_distance
# ---------------------------------------------------------------------------


def test_single_triangle_hand_computed():
    positions = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    faces = np.array([[0, 1, 2]])
    cases = [
        ((0.25, 0.25, 2.0), 2.0),  # above the interior
        ((0.25, 0.25, -3.0), 3.0),  # below it
        ((0.2, 0.3, 0.0), 0.0),  # on it
        ((0.5, -3.0, 4.0), 5.0),  # beside edge (0,0,0)-(1,0,0)
        ((1.0, 1.0, 0.0), np.sqrt(0.5)),  # beside the hypotenuse
        ((-3.0, 0.5, 0.0), 3.0),  # beside edge (0,0,0)-(0,1,0)
        ((3.0, -1.0, 0.0), np.sqrt(5.0)),  # beyond corner (1,0,0)
        ((-3.0, -4.0, 0.0), 5.0),  # beyond corner (0,0,0)
        ((-1.0, 3.0, 2.0), 3.0),  # beyond corner (0,1,0): (1, 2, 2)
    ]
    points = np.array([p for p, _ in cases])
    expected = np.array([d for _, d in cases])
    np.testing.assert_allclose(
        point_to_mesh_distance(points, positions, faces),
        expected,
        rtol=1e-15,
        atol=1e-15,
    )


def test_nearest_point_not_nearest_vertex():
    # a big triangle whose corners are all far from a point just above its middle
    positions = np.array([[-10.0, -10, 0], [10, -10, 0], [0, 10, 0]])
    d = point_to_mesh_distance([[0.0, 0.0, 0.5]], positions, [[0, 1, 2]])
    assert d[0] == pytest.approx(0.5, rel=1e-15)


# exact up to rounding: rtol 1e-12; the atol (~100 ulps of the coordinates)
# only matters for points that happen to lie within 1e-4 of the surface.
def _assert_matches_brute_force(points, positions, faces):
    ours = point_to_mesh_distance(points, positions, faces)
    expected = brute_force_distance(points, positions, faces)
    scale = np.abs(positions).max()
    np.testing.assert_allclose(ours, expected, rtol=1e-12, atol=1e-14 * scale)
    # the reported face and point really are at that distance
    d2, face, closest = nearest_on_mesh(
        np.asarray(points, float), Mesh(positions, faces)
    )
    np.testing.assert_allclose(
        np.linalg.norm(points - closest, axis=1), ours, rtol=1e-12, atol=1e-14 * scale
    )
    np.testing.assert_allclose(
        brute_force_distance(closest, positions, faces), 0.0, atol=1e-12 * scale
    )
    per_face = np.array(
        [
            brute_force_distance(points[i : i + 1], positions, faces[f : f + 1])[0]
            for i, f in enumerate(face)
        ]
    )
    np.testing.assert_allclose(per_face, ours, rtol=1e-12, atol=1e-14 * scale)


def test_matches_brute_force_on_icosphere():
    sphere = icosphere(subdivisions=2)
    rng = np.random.default_rng(1)
    points = rng.uniform(-1.6, 1.6, size=(400, 3))
    points[:50] *= 0.02  # near the centre: many faces almost equally near
    _assert_matches_brute_force(points, sphere.positions, sphere.faces)


def test_matches_brute_force_on_triangle_soup_with_degenerates():
    rng = np.random.default_rng(2)
    positions, faces = random_soup(rng)
    points = rng.uniform(-3, 3, size=(400, 3))
    # points aimed at the degenerate triangles, so those are the nearest ones
    points[:60] = positions[rng.integers(0, 18, 60)] + 0.05 * rng.normal(size=(60, 3))
    _assert_matches_brute_force(points, positions, faces)


def test_matches_brute_force_on_spot(spot):
    rng = np.random.default_rng(3)
    lo, hi = spot.positions.min(axis=0), spot.positions.max(axis=0)
    pad = 0.2 * (hi - lo)
    points = rng.uniform(lo - pad, hi + pad, size=(300, 3))
    _assert_matches_brute_force(points, spot.positions, spot.faces)


def test_degenerate_only_mesh_is_a_segment():
    positions = np.array([[0.0, 0, 0], [2, 0, 0], [1, 0, 0]])
    d = point_to_mesh_distance([[1.0, 3, 4], [5, 0, 4]], positions, [[0, 1, 2]])
    np.testing.assert_allclose(d, [5.0, 5.0], rtol=1e-15)


def test_rejects_bad_input():
    positions = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    with pytest.raises(ValueError):
        point_to_mesh_distance(np.zeros((2, 2)), positions, [[0, 1, 2]])
    with pytest.raises(ValueError):
        point_to_mesh_distance([[np.nan, 0, 0]], positions, [[0, 1, 2]])
    with pytest.raises(ValueError):
        point_to_mesh_distance([[0.0, 0, 0]], positions, [[0, 1, 3]])
    assert point_to_mesh_distance(np.zeros((0, 3)), positions, [[0, 1, 2]]).shape == (
        0,
    )


# ---------------------------------------------------------------------------
# sample_surface
# ---------------------------------------------------------------------------


def test_samples_lie_on_the_surface_and_follow_area(spot):
    points = sample_surface(spot.positions, spot.faces, 5000, seed=4)
    assert points.shape == (5000, 3)
    assert point_to_mesh_distance(points, spot.positions, spot.faces).max() < 1e-12

    # two triangles of area 1/2 and 3/2, plus a zero-area one that must get nothing
    positions = np.array(
        [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [13, 0, 0], [10, 1, 0]]
    )
    faces = np.array([[0, 1, 2], [0, 0, 1], [3, 4, 5], [3, 4, 4]])
    points = sample_surface(positions, faces, 40_000, seed=5)
    on_big = points[:, 0] >= 10
    assert on_big.mean() == pytest.approx(0.75, abs=0.01)
    # uniform over a triangle: the sample mean is the centroid
    np.testing.assert_allclose(points[on_big].mean(axis=0), [11, 1 / 3, 0], atol=0.02)
    np.testing.assert_allclose(
        points[~on_big].mean(axis=0), [1 / 3, 1 / 3, 0], atol=0.01
    )
    assert (points[:, 1] >= 0).all() and (points[:, 2] == 0).all()


def test_sampling_is_deterministic(spot):
    a = sample_surface(spot.positions, spot.faces, 100, seed=7)
    b = sample_surface(spot.positions, spot.faces, 100, seed=7)
    c = sample_surface(spot.positions, spot.faces, 100, seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_zero_area_surface_cannot_be_sampled():
    positions = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(ValueError, match="zero area"):
        sample_surface(positions, [[0, 1, 2]], 10)


# ---------------------------------------------------------------------------
# surface_distance
# ---------------------------------------------------------------------------

KEYS = {
    "rms",
    "hausdorff",
    "rms_ab",
    "rms_ba",
    "hausdorff_ab",
    "hausdorff_ba",
    "diagonal",
}


def test_identical_meshes_are_zero_apart(spot):
    result = surface_distance(spot, spot, samples=20_000)
    assert set(result) == KEYS
    assert result["rms"] < 1e-12 and result["hausdorff"] < 1e-12
    lo, hi = spot.positions.min(axis=0), spot.positions.max(axis=0)
    assert result["diagonal"] == pytest.approx(np.linalg.norm(hi - lo), rel=1e-15)


def test_scaled_sphere():
    sphere = icosphere(subdivisions=4)
    bigger = Mesh(sphere.positions * 1.01, sphere.faces)
    result = surface_distance(sphere, bigger, samples=50_000)
    diagonal = 2 * np.sqrt(3)  # the unit icosphere has corners on the axes
    assert result["diagonal"] == pytest.approx(diagonal, rel=1e-12)
    expected = 0.01 / diagonal
    for key in ("rms", "rms_ab", "rms_ba", "hausdorff"):
        assert result[key] == pytest.approx(expected, rel=0.03), key


def test_translation_bounds(spot):
    shift = np.array([0.003, -0.002, 0.001])
    moved = Mesh(spot.positions + shift, spot.faces)
    result = surface_distance(spot, moved, samples=20_000)
    bound = np.linalg.norm(shift) / result["diagonal"]
    # no point moves farther than the shift; faces facing the shift see less
    assert result["hausdorff"] <= bound * (1 + 1e-9)
    assert 0.2 * bound < result["rms"] < bound
    assert result["rms"] == pytest.approx(
        np.sqrt((result["rms_ab"] ** 2 + result["rms_ba"] ** 2) / 2)
    )
    assert result["hausdorff"] == max(result["hausdorff_ab"], result["hausdorff_ba"])


def test_swapping_sides_swaps_the_directions(spot):
    rng = np.random.default_rng(9)
    noisy = Mesh(
        spot.positions + 0.002 * rng.normal(size=spot.positions.shape), spot.faces
    )
    ab = surface_distance(spot, noisy, samples=100_000)
    ba = surface_distance(noisy, spot, samples=100_000)
    rescale = (
        ba["diagonal"] / ab["diagonal"]
    )  # each call normalises by its own reference
    assert ab["rms_ab"] == pytest.approx(ba["rms_ba"] * rescale, rel=0.02)
    assert ab["rms_ba"] == pytest.approx(ba["rms_ab"] * rescale, rel=0.02)
    assert ab["rms"] == pytest.approx(ba["rms"] * rescale, rel=0.02)


def test_deterministic_with_seed(spot):
    rng = np.random.default_rng(10)
    noisy = Mesh(
        spot.positions + 0.002 * rng.normal(size=spot.positions.shape), spot.faces
    )
    first = surface_distance(spot, noisy, samples=20_000, seed=3)
    again = surface_distance(spot, noisy, samples=20_000, seed=3)
    other = surface_distance(spot, noisy, samples=20_000, seed=4)
    assert first == again
    assert first != other
    assert other["rms"] == pytest.approx(first["rms"], rel=0.05)


def test_tuples_junk_vertices_and_degenerate_faces(spot):
    rng = np.random.default_rng(11)
    noisy = Mesh(
        spot.positions + 0.002 * rng.normal(size=spot.positions.shape), spot.faces
    )
    plain = surface_distance(spot, noisy, samples=20_000)
    assert (
        surface_distance(
            (spot.positions, spot.faces), (noisy.positions, noisy.faces), samples=20_000
        )
        == plain
    )

    # far-away unreferenced vertices, and zero-area faces lying along existing edges
    n = len(noisy.positions)
    junk = np.vstack([noisy.positions, [[100.0, 100, 100], [-50, 0, 0]]])
    edges = noisy.faces[:200]
    degenerate = np.column_stack([edges[:, 0], edges[:, 1], edges[:, 0]])
    cluttered = Mesh(junk, np.vstack([noisy.faces, degenerate, [[0, 0, 0], [n, n, n]]]))
    result = surface_distance(spot, cluttered, samples=20_000)
    for key in KEYS:
        assert result[key] == pytest.approx(plain[key], rel=1e-12, abs=1e-15), key

    # as the reference, unreferenced vertices do not stretch the diagonal
    reference = Mesh(np.vstack([spot.positions, [[100.0, 100, 100]]]), spot.faces)
    assert surface_distance(reference, noisy, samples=20_000) == plain


# ---------------------------------------------------------------------------
# attribute_deviation: appearance attributes at corresponding surface points
# ---------------------------------------------------------------------------

from lodserver.mesh import Attributes  # noqa: E402
from lodserver.metrics import attribute_deviation  # noqa: E402
from lodserver.metrics.attributes import closest_barycentrics  # noqa: E402
from lodserver.metrics.surface import sample_barycentric, sample_mesh  # noqa: E402

PLANE_LAYOUT = (("NORMAL", 3), ("TEXCOORD_0", 2), ("COLOR_0", 4))


def textured_plane(cells=8, uv=lambda xy: 0.2 + 0.4 * xy, normal=(0.0, 0.0, 1.0),
                   color=(0.5, 0.25, 1.0, 1.0), z=0.0) -> Mesh:
    """The unit square at height z, cells x cells quads, one wedge per vertex:
    UVs a function of (x, y), constant normal and colour."""
    t = np.linspace(0.0, 1.0, cells + 1)
    x, y = np.meshgrid(t, t, indexing="ij")
    xy = np.column_stack([x.ravel(), y.ravel()])
    positions = np.column_stack([xy, np.full(len(xy), z)])
    i = np.arange(cells)[:, None] * (cells + 1) + np.arange(cells)[None, :]
    i = i.ravel()
    faces = np.concatenate([
        np.column_stack([i, i + cells + 1, i + cells + 2]),
        np.column_stack([i, i + cells + 2, i + 1]),
    ])
    values = np.column_stack([
        np.broadcast_to(normal, (len(xy), 3)), uv(xy), np.broadcast_to(color, (len(xy), 4)),
    ])
    return Mesh(positions, faces, Attributes(PLANE_LAYOUT, values, faces))


def test_attribute_deviation_identical_is_zero():
    plane = textured_plane()
    result = attribute_deviation(plane, plane, samples=5_000)
    assert result["geometry"]["rms"] == 0.0 and result["geometry"]["hausdorff"] == 0.0
    for name in ("NORMAL", "TEXCOORD_0", "COLOR_0"):
        assert result[name]["max"] == pytest.approx(0.0, abs=1e-12), name
    assert result["NORMAL"]["excluded"] == 0
    assert result["TEXCOORD_1"] is None and result["texture"] is None


def test_attribute_deviation_shifted_uvs():
    plane = textured_plane()
    shifted = textured_plane(uv=lambda xy: 0.2 + 0.4 * xy + [0.1, 0.0])
    result = attribute_deviation(plane, shifted, samples=5_000)
    uv = result["TEXCOORD_0"]
    for key in ("rms", "p50", "p99", "max", "rms_ab", "rms_ba"):
        assert uv[key] == pytest.approx(0.1, rel=1e-9), key
    assert result["NORMAL"]["max"] == pytest.approx(0.0, abs=1e-12)
    assert result["COLOR_0"]["max"] == pytest.approx(0.0, abs=1e-12)


def test_attribute_deviation_other_triangulation_of_a_linear_field():
    # barycentric interpolation reproduces an affine UV field on any
    # triangulation, so only the candidate's own weights are under test here
    fine = textured_plane(cells=9, uv=lambda xy: xy @ [[0.3, 0.1], [-0.2, 0.5]] + 0.25)
    coarse = textured_plane(cells=2, uv=lambda xy: xy @ [[0.3, 0.1], [-0.2, 0.5]] + 0.25)
    result = attribute_deviation(fine, coarse, samples=20_000)
    assert result["geometry"]["hausdorff"] < 1e-12
    assert result["TEXCOORD_0"]["max"] < 1e-12


def test_attribute_deviation_tilted_normals_and_colour():
    plane = textured_plane()
    angle = np.radians(10.0)
    tilted = textured_plane(normal=(3.0 * np.sin(angle), 0.0, 3.0 * np.cos(angle)),  # not unit
                            color=(0.5, 0.25, 1.0, 0.6))
    result = attribute_deviation(plane, tilted, samples=5_000)
    assert result["NORMAL"]["rms"] == pytest.approx(10.0, rel=1e-6)
    assert result["NORMAL"]["max"] == pytest.approx(10.0, rel=1e-6)
    # one channel of four off by 0.4: RMS over channels = 0.4 / 2
    assert result["COLOR_0"]["rms"] == pytest.approx(0.2, rel=1e-9)


def test_attribute_deviation_geometry_matches_surface_distance():
    plane = textured_plane()
    lifted = textured_plane(cells=5, z=0.03)
    result = attribute_deviation(plane, lifted, samples=4_000, seed=7)
    plain = surface_distance(plane, lifted, samples=4_000, seed=7)
    for key, value in result["geometry"].items():
        assert value == plain[key], key
    assert result["diagonal"] == plain["diagonal"]
    assert result["geometry"]["rms"] == pytest.approx(0.03 / np.sqrt(2), rel=1e-9)


def test_attribute_deviation_without_attributes_reports_none():
    plane = textured_plane()
    bare = Mesh(plane.positions, plane.faces)
    for a, b in ((plane, bare), (bare, plane), ((plane.positions, plane.faces), bare)):
        result = attribute_deviation(a, b, samples=1_000)
        assert result["geometry"]["rms"] == 0.0
        assert all(result[name] is None for name in ("NORMAL", "TEXCOORD_0", "COLOR_0"))
    with pytest.raises(ValueError):
        attribute_deviation(plane, plane, samples=0)


def test_attribute_deviation_texture_colour():
    plane = textured_plane()  # u in [0.2, 0.6]
    shifted = textured_plane(uv=lambda xy: 0.2 + 0.4 * xy + [0.1, 0.0])
    # colour = 2 x (texel column), so a 0.1 shift in u over 100 texels is 20 levels
    image = np.repeat((2.0 * np.arange(100))[None, :, None], 7, axis=0).repeat(3, axis=2)
    result = attribute_deviation(plane, shifted, samples=5_000, texture=image)
    assert result["texture"]["rms"] == pytest.approx(20.0, rel=1e-9)
    assert result["texture"]["max"] == pytest.approx(20.0, rel=1e-9)
    same = attribute_deviation(plane, plane, samples=2_000, texture=image.astype(np.uint8))
    assert same["texture"]["max"] == pytest.approx(0.0, abs=1e-9)


def seamed_plane(cells=8, shift=0.0) -> Mesh:
    """The unit square moved by ``shift`` along x, with two UV charts split by a
    seam at local x = 0.5: u = x / 2 on the left, x / 2 + 0.25 on the right
    (seam vertices have one wedge per chart), v = y."""
    plane = textured_plane(cells=cells)
    chart = (plane.positions[plane.faces].mean(axis=1)[:, 0] > 0.5).astype(np.int64)
    keys = 2 * plane.faces + chart[:, None]
    unique, corners = np.unique(keys.ravel(), return_inverse=True)
    vertex, side = unique // 2, unique % 2
    xy = plane.positions[vertex, :2]
    values = np.column_stack([np.broadcast_to((0.0, 0.0, 1.0), (len(unique), 3)),
                              0.5 * xy[:, 0] + 0.25 * side, xy[:, 1],
                              np.ones((len(unique), 4))])
    return Mesh(plane.positions + [shift, 0.0, 0.0], plane.faces,
                Attributes(PLANE_LAYOUT, values, corners.reshape(-1, 3)))


def test_attribute_deviation_seam_is_seen_in_max_not_p99():
    # moved by 0.004, the candidate's seam sits 0.004 to the right: reference
    # points just right of the reference seam find their closest point in the
    # candidate's left chart (0.252 away in u); everywhere else u differs by 0.002
    reference = seamed_plane()
    candidate = seamed_plane(cells=4, shift=0.004)
    assert reference.attributes.wedge_count == len(reference.positions) + 9
    result = attribute_deviation(reference, candidate, samples=50_000)
    uv = result["TEXCOORD_0"]
    assert uv["max"] == pytest.approx(0.25 + 0.002, rel=1e-6)
    assert uv["p50"] == pytest.approx(0.002, rel=1e-6)
    assert uv["p99"] == pytest.approx(0.002, rel=1e-6)
    # sampled, so from below
    assert 0.99 * 0.004 < result["geometry"]["hausdorff"] * np.sqrt(2) <= 0.004 * (1 + 1e-12)


def test_sample_barycentric_matches_sample_surface(spot):
    points, face, bary = sample_barycentric(spot, 5_000, 3)
    assert np.array_equal(points, sample_mesh(spot, 5_000, 3))
    assert np.array_equal(points, sample_surface(spot.positions, spot.faces, 5_000, seed=3))
    rebuilt = np.einsum("kc,kcd->kd", bary, spot.positions[spot.faces[face]])
    assert np.allclose(rebuilt, points, atol=1e-12)
    assert (bary >= 0).all() and np.allclose(bary.sum(axis=1), 1.0)


def test_closest_barycentrics_rebuild_the_closest_point():
    rng = np.random.default_rng(12)
    soup = Mesh(*random_soup(rng, 300))
    points = rng.normal(size=(3_000, 3))
    _, face, closest = nearest_on_mesh(points, soup)
    bary = closest_barycentrics(soup.positions, soup.faces, face, closest)
    assert (bary >= 0).all() and np.allclose(bary.sum(axis=1), 1.0)
    rebuilt = np.einsum("kc,kcd->kd", bary, soup.positions[soup.faces[face]])
    scale = np.abs(soup.positions).max()
    assert np.abs(rebuilt - closest).max() < 1e-9 * scale
    # a flat triangle: the point lies on its long edge, 30% of the way
    flat = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 0, 0]])
    q = np.array([[0.3, 0.0, 0.0]])
    w = closest_barycentrics(flat, np.array([[0, 1, 2]]), np.array([0]), q)
    assert np.allclose(w @ flat, q)
