import os
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from lodserver import io as lodio
from lodserver.io import (
    SUPPORTED_INPUT,
    SUPPORTED_OUTPUT,
    LoadReport,
    clean_mesh,
    load_mesh,
    save_mesh,
)
from lodserver.mesh import Mesh, MeshError

SPOT = Path(__file__).parent / "data" / "spot.obj"

# Measured with load_mesh; they agree with ../shared/meshes/SOURCES.md.
# name: (vertices, faces, welded, unreferenced, degenerate, duplicate)
SHARED_COUNTS = {
    "stanford-bunny.obj": (34834, 69451, 0, 1113, 0, 0),
    "fandisk.obj": (6475, 12946, 0, 0, 0, 0),
    "spot/spot.obj": (2930, 5856, 0, 0, 0, 0),
    "decimated-max.obj": (5272, 10540, 0, 0, 0, 0),
    "fertility.off": (4494, 9000, 0, 0, 0, 0),
    "camelhead.off": (11381, 22704, 0, 0, 0, 0),
    "Laurana50k.ply": (25126, 49954, 0, 2735, 0, 0),
    "bunny10k_textured/bunny10k_textured.obj": (5051, 9999, 0, 0, 0, 0),
    "Duck.glb": (2108, 4212, 291, 0, 0, 0),
    "Avocado/Avocado.gltf": (363, 682, 43, 0, 0, 0),
    "2CylinderEngine.glb": (60041, 110336, 24616, 0, 11160, 0),
    "office_chair.obj": (3474, 6865, 2, 0, 24, 4),
    "mountain.obj": (25600, 50562, 0, 0, 0, 0),
    "non_manif_hole.ply": (432, 755, 0, 0, 0, 0),
    "conrod.stl": (3223, 6439, 16103, 0, 0, 3),
    "soup.stl": (300, 100, 0, 0, 0, 0),
    "joined_tetrahedra.obj": (5, 7, 0, 0, 0, 1),
    # 36752 triangles decoded from the strips, none degenerate after welding.
    "brain.ply": (18391, 36752, 453, 0, 0, 0),
}


def assert_clean(mesh: Mesh, report: LoadReport) -> None:
    """No coincident vertices, bad faces or unused vertices, and the counts add up."""
    faces = mesh.faces
    assert len(np.unique(mesh.positions, axis=0)) == mesh.vertex_count
    assert (faces[:, 0] != faces[:, 1]).all()
    assert (faces[:, 1] != faces[:, 2]).all()
    assert (faces[:, 2] != faces[:, 0]).all()
    assert len(np.unique(np.sort(faces, axis=1), axis=0)) == mesh.face_count
    assert np.array_equal(np.unique(faces), np.arange(mesh.vertex_count))
    assert report.source_vertices == (
        report.welded_vertices + report.unreferenced_vertices + mesh.vertex_count
    )


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_spot_loads():
    mesh, report = load_mesh(SPOT)
    assert (mesh.vertex_count, mesh.face_count) == (2930, 5856)
    assert mesh.positions.dtype == np.float64 and mesh.faces.dtype == np.int64
    assert report.as_dict() == {
        "source_vertices": 2930,
        "welded_vertices": 0,
        "unreferenced_vertices": 0,
        "degenerate_faces": 0,
        "duplicate_faces": 0,
    }
    assert_clean(mesh, report)


@pytest.mark.parametrize("name", sorted(SHARED_COUNTS))
def test_shared_mesh_loads(shared_meshes, name):
    mesh, report = load_mesh(shared_meshes / name)
    assert_clean(mesh, report)
    counts = (
        mesh.vertex_count,
        mesh.face_count,
        report.welded_vertices,
        report.unreferenced_vertices,
        report.degenerate_faces,
        report.duplicate_faces,
    )
    assert counts == SHARED_COUNTS[name]


def test_scene_instances_are_placed_by_their_node_transforms(shared_meshes):
    path = shared_meshes / "2CylinderEngine.glb"
    scene = trimesh.load_scene(path, process=False)
    instances = scene.graph.nodes_geometry
    # Some geometries are placed several times.
    assert len(instances) > len(scene.geometry)

    mesh, report = load_mesh(path)
    placed = sum(
        len(scene.geometry[scene.graph[node][1]].vertices) for node in instances
    )
    assert report.source_vertices == placed == 84657
    assert report.degenerate_faces > 0
    np.testing.assert_allclose(
        [mesh.positions.min(axis=0), mesh.positions.max(axis=0)],
        scene.bounds,
        rtol=1e-9,
    )


def test_mirrored_instance_keeps_its_faces_outward(tmp_path):
    tetrahedron = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
        [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        process=False,
    )
    scene = trimesh.Scene()
    scene.add_geometry(tetrahedron, node_name="plain", geom_name="tet")
    scene.graph.update(
        frame_to="mirror",
        frame_from=scene.graph.base_frame,
        geometry="tet",
        matrix=[[-1, 0, 0, -3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
    )
    path = tmp_path / "mirrored.glb"
    scene.export(path)

    mesh, _ = load_mesh(path)
    corners = mesh.positions[mesh.faces]
    volumes = np.einsum(
        "ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])
    )
    # Both copies enclose +1/6: outward faces, so the signed volumes add up.
    assert mesh.face_count == 8
    assert volumes.sum() / 6 == pytest.approx(1 / 3)


def test_file_type_overrides_the_extension(tmp_path):
    upload = tmp_path / "upload.tmp"
    upload.write_bytes(SPOT.read_bytes())
    mesh, _ = load_mesh(upload, file_type="OBJ")
    assert mesh.face_count == 5856


# --- OBJ reader -----------------------------------------------------------------------


def test_obj_polygons_negative_indices_and_attribute_references(tmp_path):
    path = write(
        tmp_path / "poly.obj",
        "mtllib missing.mtl\n"
        "v 0 0 0\nv 1 0 0\nv 1 1 0 1.0\nv 0 1 0 0.5 0.5 0.5\nv\t2 2 2\n"
        "vt 0 0\nvn 0 0 1\n"
        "f 1/1/1 2/1/1 3/1/1 4/1/1\n"  # quad -> 2 triangles
        "f -4//1 -3//1 -2//1\n",  # relative indices: vertices 2, 3, 4
    )
    mesh, report = load_mesh(path)
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [1, 2, 3]]
    assert report.source_vertices == 5 and report.unreferenced_vertices == 1
    np.testing.assert_array_equal(mesh.positions[3], [0, 1, 0])


def test_obj_pentagon_is_fan_triangulated(tmp_path):
    vertices = "".join(f"v {np.cos(a)} {np.sin(a)} 0\n" for a in np.linspace(0, 5, 5))
    mesh, _ = load_mesh(write(tmp_path / "pentagon.obj", vertices + "f 1 2 3 4 5\n"))
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 3, 4]]


# --- PLY triangle strips --------------------------------------------------------------

STRIP_POSITIONS = np.array(
    [
        [0, 0, 0],
        [1, 0, 0],
        [0, 1, 0],
        [1, 1, 0],
        [0, 2, 0],
        [5, 5, 5],
        [6, 5, 5],
        [5, 6, 5],
    ],
    dtype=np.float64,
)
# 0 1 2 3 4 -> (0,1,2) (2,1,3) (2,3,4); the stitching triangles (3,4,4), (4,4,5),
# (4,5,5), (5,5,6) are dropped; (5,6,7) is the strip's 8th triangle, odd, so (6,5,7).
# The -1 starts a new strip whose first triangle is even again: (7,6,3).
STRIP = [0, 1, 2, 3, 4, 4, 5, 5, 6, 7, -1, 7, 6, 3]
STRIP_TRIANGLES = [[0, 1, 2], [2, 1, 3], [2, 3, 4], [6, 5, 7], [7, 6, 3]]


def ply_with_strips(encoding: str) -> bytes:
    header = (
        f"ply\nformat {encoding} 1.0\ncomment made by a test\n"
        f"element vertex {len(STRIP_POSITIONS)}\n"
        "property float x\nproperty float y\nproperty float z\nproperty uchar quality\n"
        "element tristrips 1\nproperty list int int vertex_indices\nend_header\n"
    ).encode()
    if encoding == "ascii":
        rows = "".join(f"{x} {y} {z} 7\n" for x, y, z in STRIP_POSITIONS)
        strips = " ".join(map(str, [len(STRIP), *STRIP])) + "\n"
        return header + (rows + strips).encode()
    endian = "<" if encoding == "binary_little_endian" else ">"
    vertex = np.zeros(
        len(STRIP_POSITIONS), dtype=[("p", endian + "f4", 3), ("quality", "u1")]
    )
    vertex["p"] = STRIP_POSITIONS
    strips = np.array([len(STRIP), *STRIP], dtype=endian + "i4")
    return header + vertex.tobytes() + strips.tobytes()


@pytest.mark.parametrize(
    "encoding", ["ascii", "binary_little_endian", "binary_big_endian"]
)
def test_ply_tristrips_are_decoded(tmp_path, encoding):
    path = tmp_path / "strips.ply"
    path.write_bytes(ply_with_strips(encoding))
    mesh, report = load_mesh(path)
    np.testing.assert_array_equal(mesh.positions, STRIP_POSITIONS)
    assert mesh.faces.tolist() == STRIP_TRIANGLES
    assert report.source_vertices == len(STRIP_POSITIONS)


def test_ply_tristrips_alongside_faces(tmp_path):
    path = write(
        tmp_path / "both.ply",
        "ply\nformat ascii 1.0\nelement vertex 4\n"
        "property float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\n"
        "element tristrips 1\nproperty list int int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n1 1 1\n3 0 1 3\n3 0 1 2\n",
    )
    mesh, _ = load_mesh(path)
    assert sorted(map(sorted, mesh.faces.tolist())) == [[0, 1, 2], [0, 1, 3]]


def test_truncated_tristrips_ply(tmp_path):
    path = tmp_path / "truncated.ply"
    path.write_bytes(ply_with_strips("binary_little_endian")[:-8])
    with pytest.raises(MeshError, match="truncated"):
        load_mesh(path)


# --- bad input ------------------------------------------------------------------------

TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"


@pytest.mark.parametrize(
    ("name", "content", "keyword"),
    [
        ("garbage.obj", "this is not\na mesh at all\n", "no faces"),
        ("empty.obj", "", "empty"),
        ("empty.stl", "", "empty"),
        ("points.xyz", "0 0 0\n", "unsupported"),
        (
            "nan.obj",
            "v nan 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 inf\nf 1 2 3\n",
            "2 of its 4 vertices",
        ),
        ("range.obj", TRIANGLE + "f 1 2 4\n", "do not exist"),
        ("zero.obj", TRIANGLE + "f 0 1 2\n", "do not exist"),
        ("text.obj", "v 0 0 zero\n" + "f 1 1 1\n", "not a number"),
        ("short.obj", TRIANGLE + "f 1 2\n", "fewer than 3"),
        ("flat.obj", TRIANGLE + "v 0 0 0\nf 1 2 1\nf 1 4 2\n", "degenerate"),
        (
            "points.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
            "property float y\nproperty float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n",
            "no faces",
        ),
        (
            "range.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
            "property float y\nproperty float z\nelement face 1\n"
            "property list uchar int vertex_indices\n"
            "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
            "outside [0, 2]",
        ),
        ("garbage.ply", "ply?\nnot really\n", "could not be parsed"),
        ("garbage.glb", "glTF but not really", "could not be parsed"),
        ("garbage.off", "OFF\nthree vertices\n", "could not be parsed"),
    ],
)
def test_bad_input_raises_mesh_error(tmp_path, name, content, keyword):
    path = write(tmp_path / name, content)
    with pytest.raises(MeshError, match="cannot load") as caught:
        load_mesh(path)
    message = str(caught.value)
    assert keyword in message
    assert name in message


def test_unsupported_extension_lists_supported_types(tmp_path):
    with pytest.raises(MeshError) as caught:
        load_mesh(write(tmp_path / "cloud.xyz", "0 0 0\n"))
    assert all(kind in str(caught.value) for kind in SUPPORTED_INPUT)


def test_missing_file(tmp_path):
    with pytest.raises(MeshError, match="no such file"):
        load_mesh(tmp_path / "absent.obj")


def test_directory_is_not_a_mesh(tmp_path):
    (tmp_path / "folder.obj").mkdir()
    with pytest.raises(MeshError, match="not a regular file"):
        load_mesh(tmp_path / "folder.obj")


# --- clean_mesh -----------------------------------------------------------------------


def test_clean_mesh_welds_in_first_occurrence_order():
    positions = [[2, 0, 0], [0, 0, 0], [0, 1, 0], [-0.0, 0, 0], [2, 0, 0], [9, 9, 9]]
    faces = [[3, 4, 2], [1, 0, 2], [2, 1, 0], [0, 1, 1]]
    mesh, report = clean_mesh(positions, faces)
    # vertex 3 (-0.0) welds into 1, vertex 4 into 0; 5 is unused.
    np.testing.assert_array_equal(mesh.positions, [[2, 0, 0], [0, 0, 0], [0, 1, 0]])
    # Face 1 is face 0 after welding; face 2 is that triangle wound the other way.
    assert mesh.faces.tolist() == [[1, 0, 2]]
    assert report == LoadReport(
        source_vertices=6,
        welded_vertices=2,
        unreferenced_vertices=1,
        degenerate_faces=1,
        duplicate_faces=2,
    )


@pytest.mark.parametrize(
    ("positions", "faces", "keyword"),
    [
        (np.zeros((3, 2)), [[0, 1, 2]], "shape (n, 3)"),
        (np.eye(3), [[0, 1]], "shape (m, 3)"),
        (np.eye(3), [[0.0, 1.0, 2.0]], "integer"),
        (np.eye(3), np.empty((0, 3), dtype=np.int64), "no faces"),
        (np.eye(3), [[0, 1, -1]], "outside"),
        (np.eye(3), [[0, 1, 1]], "degenerate"),
    ],
)
def test_clean_mesh_rejects_bad_arrays(positions, faces, keyword):
    with pytest.raises(MeshError) as caught:
        clean_mesh(positions, faces)
    assert keyword in str(caught.value)


@settings(max_examples=60, deadline=None)
@given(
    st.integers(3, 12).flatmap(
        lambda n: st.tuples(
            st.lists(
                st.tuples(*[st.sampled_from([0.0, -0.0, 1.0, 2.5])] * 3),
                min_size=n,
                max_size=n,
            ),
            st.lists(st.tuples(*[st.integers(0, n - 1)] * 3), min_size=1, max_size=20),
        )
    )
)
def test_clean_mesh_keeps_the_geometry_of_every_surviving_face(data):
    positions, faces = np.array(data[0]), np.array(data[1])
    try:
        mesh, report = clean_mesh(positions, faces)
    except MeshError as exc:
        assert "degenerate" in str(exc)
        return
    assert_clean(mesh, report)
    # Each kept face has the corner positions of an input face, in the same order.
    originals = {tuple(map(tuple, positions[face])) for face in faces}
    assert all(
        tuple(map(tuple, mesh.positions[face])) in originals for face in mesh.faces
    )
    dropped = report.degenerate_faces + report.duplicate_faces
    assert mesh.face_count + dropped == len(faces)
    # Cleaning is idempotent.
    again, second = clean_mesh(mesh.positions, mesh.faces)
    assert np.array_equal(again.positions, mesh.positions)
    assert np.array_equal(again.faces, mesh.faces)
    assert second == LoadReport(mesh.vertex_count, 0, 0, 0, 0)


# --- saving ---------------------------------------------------------------------------

# Text formats are written with 17 decimals; PLY, GLB and STL hold float32.
ROUND_TRIP_ATOL = {"obj": 1e-15, "off": 1e-15, "ply": 1e-6, "glb": 1e-6, "stl": 1e-6}


@pytest.mark.parametrize("kind", SUPPORTED_OUTPUT)
def test_save_load_round_trip(tmp_path, kind):
    mesh, _ = load_mesh(SPOT)
    path = tmp_path / f"spot.{kind}"
    save_mesh(mesh, path)
    back, report = load_mesh(path)
    assert (back.vertex_count, back.face_count) == (mesh.vertex_count, mesh.face_count)
    assert report.unreferenced_vertices == 0
    assert report.degenerate_faces == report.duplicate_faces == 0
    # STL stores corners per face and comes back re-indexed: compare face corners.
    np.testing.assert_allclose(
        back.positions[back.faces],
        mesh.positions[mesh.faces],
        rtol=0,
        atol=ROUND_TRIP_ATOL[kind],
    )
    assert os.listdir(tmp_path) == [path.name]


def test_save_file_type_overrides_the_extension(tmp_path):
    mesh, _ = load_mesh(SPOT)
    path = tmp_path / "upload.bin"
    save_mesh(mesh, path, file_type="ply")
    assert path.read_bytes().startswith(b"ply")


def test_save_unsupported_extension_writes_nothing(tmp_path):
    mesh, _ = load_mesh(SPOT)
    with pytest.raises(MeshError, match="unsupported file type 'gltf'"):
        save_mesh(mesh, tmp_path / "spot.gltf")
    assert os.listdir(tmp_path) == []


def test_failed_save_keeps_the_old_file_and_leaves_no_temporary(tmp_path, monkeypatch):
    mesh, _ = load_mesh(SPOT)
    path = tmp_path / "spot.ply"
    path.write_bytes(b"previous version")

    def crash(source, target):
        raise OSError("disk full")

    monkeypatch.setattr(lodio.os, "replace", crash)
    with pytest.raises(OSError, match="disk full"):
        save_mesh(mesh, path)
    assert os.listdir(tmp_path) == [path.name]
    assert path.read_bytes() == b"previous version"


def test_save_replaces_an_existing_file(tmp_path):
    mesh, _ = load_mesh(SPOT)
    path = tmp_path / "spot.obj"
    path.write_text("old")
    save_mesh(mesh, path)
    assert load_mesh(path)[0].face_count == mesh.face_count


def test_glb_is_a_well_formed_gltf_binary():
    """Header, 4-byte aligned chunks, accessor counts and POSITION bounds."""
    import json
    import struct

    from lodserver.io import encode_mesh

    mesh, _ = load_mesh(SPOT)
    data = encode_mesh(mesh, "glb")
    magic, version, total = struct.unpack_from("<4sII", data)
    assert (magic, version, total) == (b"glTF", 2, len(data))
    json_length, json_type = struct.unpack_from("<I4s", data, 12)
    assert json_type == b"JSON" and json_length % 4 == 0
    document = json.loads(data[20:20 + json_length])
    bin_length, bin_type = struct.unpack_from("<I4s", data, 20 + json_length)
    assert bin_type == b"BIN\x00" and bin_length % 4 == 0
    assert 28 + json_length + bin_length == len(data)
    positions, indices = document["accessors"]
    assert positions["count"] == mesh.vertex_count and indices["count"] == 3 * mesh.face_count
    as_float32 = mesh.positions.astype(np.float32)
    assert positions["min"] == as_float32.min(axis=0).tolist()
    assert positions["max"] == as_float32.max(axis=0).tolist()
    assert document["buffers"][0]["byteLength"] == bin_length
