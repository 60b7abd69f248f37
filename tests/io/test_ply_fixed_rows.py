"""The binary PLY reader of fixed-size rows (``io/ply.read_ply_binary_triangles``)
gives ``load_mesh`` the same mesh and report as trimesh's path, and leaves every
other PLY to trimesh."""

from dataclasses import asdict

import numpy as np
import pytest

from lodserver.io import load_mesh
from lodserver.io import load as load_module
from lodserver.io.ply import read_ply_binary_triangles

RNG = np.random.default_rng(7)
VERTICES = 9


def ply(endian: str, vertex_props, vertex_rows, face_props, face_rows, extra="") -> bytes:
    """A binary PLY of ``endian`` ("<" or ">") from structured rows."""
    name = {"<": "binary_little_endian", ">": "binary_big_endian"}[endian]
    header = (f"ply\nformat {name} 1.0\ncomment a test\nelement vertex {len(vertex_rows)}\n"
              + "".join(f"property {p}\n" for p in vertex_props)
              + f"element face {len(face_rows)}\n" + "".join(f"property {p}\n" for p in face_props)
              + extra + "end_header\n")
    return header.encode() + vertex_rows.tobytes() + face_rows.tobytes()


def positions_table(endian, kind="f4", more=()):
    dtype = [(axis, endian + kind) for axis in "xyz"] + [(n, endian + k) for n, k in more]
    rows = np.zeros(VERTICES, dtype=dtype)
    for axis in "xyz":
        rows[axis] = RNG.random(VERTICES)
    for n, k in more:
        rows[n] = RNG.integers(0, 255, VERTICES) if k == "u1" else RNG.random(VERTICES)
    return rows


def triangles(endian, count_type="u1", index_type="i4", sides=3, faces=8, more=()):
    dtype = [("n", endian + count_type), ("i", endian + index_type, sides)] + list(more)
    rows = np.zeros(faces, dtype=dtype)
    rows["n"] = sides
    rows["i"] = [RNG.choice(VERTICES, sides, replace=False) for _ in range(faces)]
    # every vertex used: trimesh drops an unused one from a file with UVs but keeps
    # the file's indices (see test_an_unused_vertex_is_counted)
    if faces >= 3:
        rows["i"][:3, :3] = np.arange(VERTICES).reshape(3, 3)
    for field in more:
        rows[field[0]] = 6 if field[0] == "tn" else RNG.random(rows[field[0]].shape)
    return rows


def files(endian):
    """(name, bytes, read by the fixed-row reader) for one byte order."""
    e = endian
    plain = ply(e, ["float x", "float y", "float z"], positions_table(e),
                ["list uchar int vertex_indices"], triangles(e))
    doubles = ply(e, ["double x", "double y", "double z"], positions_table(e, "f8"),
                  ["list uint uint vertex_indices"], triangles(e, "u4", "u4"))
    look = ply(e, ["float x", "float y", "float z", "float nx", "float ny", "float nz",
                   "uchar red", "uchar green", "uchar blue", "float s", "float t",
                   "float quality"],
               positions_table(e, more=[("nx", "f4"), ("ny", "f4"), ("nz", "f4"), ("r", "u1"),
                                        ("g", "u1"), ("b", "u1"), ("s", "f4"), ("t", "f4"),
                                        ("q", "f4")]),
               ["list uchar int vertex_indices"], triangles(e))
    meshlab = ply(e, ["float x", "float y", "float z"], positions_table(e),
                  ["list uchar int vertex_indices", "list uchar float texcoord"],
                  triangles(e, more=[("tn", e + "u1"), ("uv", e + "f4", 6)]))
    quads = ply(e, ["float x", "float y", "float z"], positions_table(e),
                ["list uchar int vertex_indices"], triangles(e, sides=4))
    mixed_rows = triangles(e, faces=4).tobytes() + triangles(e, sides=4, faces=1).tobytes()
    mixed = ply(e, ["float x", "float y", "float z"], positions_table(e),
                ["list uchar int vertex_indices"], np.frombuffer(mixed_rows, np.uint8))
    mixed = mixed.replace(b"element face 65", b"element face 5")
    edges = np.zeros(3, dtype=[("a", e + "i4"), ("b", e + "i4")])
    edges["a"], edges["b"] = [0, 1, 2], [1, 2, 3]
    with_edges = ply(e, ["float x", "float y", "float z"], positions_table(e),
                     ["list uchar int vertex_indices"], triangles(e),
                     "element edge 3\nproperty int vertex1\nproperty int vertex2\n")
    with_edges += edges.tobytes()
    return [("plain", plain, True), ("doubles", doubles, True), ("look", look, True),
            ("meshlab", meshlab, True), ("quads", quads, False), ("edges", with_edges, True),
            ("mixed", mixed, False)]


# the mixed file (triangles, then a quad) is neither this reader's nor trimesh's
CASES = [(endian, *case) for endian in "<>" for case in files(endian)[:-1]]


@pytest.mark.parametrize("endian,name,data,fixed", CASES,
                         ids=[f"{c[1]}{c[0]}" for c in CASES])
def test_fixed_rows_load_as_trimesh_loads_them(tmp_path, monkeypatch, endian, name, data, fixed):
    path = tmp_path / f"{name}.ply"
    path.write_bytes(data)
    assert (read_ply_binary_triangles(path) is not None) == fixed
    mesh, report = load_mesh(path)
    monkeypatch.setattr(load_module, "read_ply_binary_triangles", lambda path: None)
    expected, expected_report = load_mesh(path)
    np.testing.assert_array_equal(mesh.positions, expected.positions)
    np.testing.assert_array_equal(mesh.faces, expected.faces)
    assert (mesh.attributes is None) == (expected.attributes is None)
    if mesh.attributes is not None:
        assert mesh.attributes.layout == expected.attributes.layout
        np.testing.assert_array_equal(mesh.attributes.values, expected.attributes.values)
        np.testing.assert_array_equal(mesh.attributes.corners, expected.attributes.corners)
    if name == "meshlab":
        # trimesh splits the file's vertices along the UV seams, which cleaning
        # welds back; this reader counts the file's own vertices
        assert report.source_vertices == VERTICES and report.welded_vertices == 0
        assert (expected_report.source_vertices - expected_report.welded_vertices
                == report.source_vertices)
        report.source_vertices = expected_report.source_vertices
        report.welded_vertices = expected_report.welded_vertices
    assert asdict(report) == asdict(expected_report)


def test_rows_of_differing_lists_are_not_read_as_fixed(tmp_path):
    path = tmp_path / "mixed.ply"
    path.write_bytes(files("<")[-1][1])
    assert read_ply_binary_triangles(path) is None


def test_a_scalar_after_a_list_and_an_unused_vertex_are_read(tmp_path):
    # trimesh refuses the first ("PLY is unexpected length") and drops the vertex
    # no face uses from a file with UVs; this reader keeps the file as it is
    positions = positions_table("<", more=[("s", "f4"), ("t", "f4")])
    rows = triangles("<", faces=3, more=[("q", "<f4")])
    rows["i"] = [[0, 1, 2], [3, 4, 5], [6, 7, 0]]     # vertex 8 unused
    path = tmp_path / "quality.ply"
    path.write_bytes(ply("<", ["float x", "float y", "float z", "float s", "float t"], positions,
                         ["list uchar int vertex_indices", "float quality"], rows))
    mesh, report = load_mesh(path)
    assert report.source_vertices == VERTICES and report.unreferenced_vertices == 1
    assert report.dropped_attributes == ["face quality"]
    xyz = np.column_stack([positions[axis] for axis in "xyz"]).astype(np.float64)
    np.testing.assert_array_equal(mesh.positions[mesh.faces], xyz[rows["i"]])


def test_a_truncated_fixed_row_file_is_left_to_trimesh(tmp_path):
    path = tmp_path / "cut.ply"
    path.write_bytes(files("<")[0][1][:-20])
    assert read_ply_binary_triangles(path) is None
    with pytest.raises(Exception, match="cut.ply"):
        load_mesh(path)


def test_ascii_is_left_to_trimesh(tmp_path):
    path = tmp_path / "a.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                    "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    assert read_ply_binary_triangles(path) is None
    assert load_mesh(path)[0].faces.tolist() == [[0, 1, 2]]
