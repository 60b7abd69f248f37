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
from lodserver.io.save import _EXPORT_OPTIONS
from lodserver.mesh import Materials, Mesh, MeshError

from ..conftest import glb_chunks

SPOT = Path(__file__).resolve().parents[1] / "data" / "spot.obj"

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
        # one wedge per distinct vt of a vertex: 3225 vt lines, 277 vertices on the UV seam
        "wedges": 3225,
        "seam_vertices": 277,
        "materials": 1,     # spot.mtl: its texture
        "dropped_attributes": [],
        "missing_files": [],
    }
    assert [name for name, _ in mesh.attributes.layout] == ["TEXCOORD_0"]
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

    monkeypatch.setattr(os, "replace", crash)
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
    """Header, 4-byte aligned chunks, accessor counts and POSITION bounds (positions-only path)."""
    from lodserver.io import encode_mesh

    loaded, _ = load_mesh(SPOT)
    mesh = Mesh(loaded.positions, loaded.faces)  # without its UVs
    data = encode_mesh(mesh, "glb")
    document, binary = glb_chunks(data)
    bin_length = len(binary)
    assert bin_length % 4 == 0
    positions, indices = document["accessors"]
    assert positions["count"] == mesh.vertex_count and indices["count"] == 3 * mesh.face_count
    as_float32 = mesh.positions.astype(np.float32)
    assert positions["min"] == as_float32.min(axis=0).tolist()
    assert positions["max"] == as_float32.max(axis=0).tolist()
    assert document["buffers"][0]["byteLength"] == bin_length


# --- attributes and materials -----------------------------------------------------------

PNG = (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00\x00\x01\x00\x00\x00\x01\x08\x06\x00\x00"
       b"\x00\x1f\x15\xc4\x89\x00\x00\x00\rIDATx\x9cc\xf8\xcf\xc0\xf0\x1f\x00\x05\x00\x01\xff"
       b"\x89\x99=\x1d\x00\x00\x00\x00IEND\xaeB`\x82")  # a 1x1 PNG


def corner_table(mesh: Mesh, name: str) -> np.ndarray:
    """(m, 3, width) values of attribute ``name`` at every face corner."""
    return mesh.attributes.values[mesh.attributes.corners][..., mesh.attributes.columns(name)]


def test_clean_mesh_builds_wedges_and_drops_corners_with_their_faces():
    # two triangles over a square; vertex 0 and 2 are shared. Face 2 repeats face 0
    # (wound the other way) with other UVs: dropped with them.
    positions = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    faces = [[0, 1, 2], [0, 2, 3], [2, 1, 0]]
    uv = np.array([
        [[0, 0], [1, 0], [1, 1]],
        [[0, 0], [0.5, 0.5], [0, 1]],  # vertex 2 gets a second UV: a seam
        [[9, 9], [9, 9], [9, 9]],
    ], dtype=np.float64)
    mesh, report = clean_mesh(positions, faces, corner_values=uv, layout=(("TEXCOORD_0", 2),))
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert mesh.attributes.corners.tolist() == [[0, 1, 2], [0, 3, 4]]
    assert (report.duplicate_faces, report.wedges, report.seam_vertices) == (1, 5, 1)
    np.testing.assert_array_equal(corner_table(mesh, "TEXCOORD_0"), uv[:2])
    # -0.0 and 0.0 are one wedge, as they are one position
    uv[1, 0] = [-0.0, 0.0]
    assert clean_mesh(positions, faces, corner_values=uv, layout=(("TEXCOORD_0", 2),))[1].wedges == 5


def test_clean_mesh_puts_the_material_in_the_wedge():
    positions = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    faces = [[0, 1, 2], [0, 2, 3]]
    normals = np.tile([0.0, 0.0, 1.0], (2, 3, 1))
    materials = Materials({"materials": [{"name": "a"}, {"name": "b"}]})
    mesh, report = clean_mesh(positions, faces, corner_values=normals, layout=(("NORMAL", 3),),
                              face_material=[0, 1], materials=materials)
    assert mesh.face_material.tolist() == [0, 1] and mesh.materials is materials
    # the shared edge (vertices 0 and 2) has one wedge per material
    assert (report.wedges, report.seam_vertices, report.materials) == (6, 2, 2)


@pytest.mark.parametrize(("kwargs", "keyword"), [
    ({"corner_values": np.zeros((1, 3, 3)), "layout": (("TEXCOORD_0", 2),)}, "shape (1, 3, 2)"),
    ({"corner_values": np.zeros((1, 3, 2)), "layout": (("UV", 2),)}, "unknown attribute"),
    ({"corner_values": np.full((1, 3, 2), np.inf), "layout": (("TEXCOORD_0", 2),)},
     "3 TEXCOORD_0 corners"),
    ({"face_material": [0]}, "[-1, -1]"),
    ({"face_material": [0.5]}, "integers"),
])
def test_clean_mesh_rejects_bad_attributes(kwargs, keyword):
    with pytest.raises(MeshError) as caught:
        clean_mesh(np.eye(3), [[0, 1, 2]], **kwargs)
    assert keyword in str(caught.value)


def test_obj_vt_and_vn_per_corner(tmp_path):
    path = write(
        tmp_path / "square.obj",
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 1 0\n"
        "vt 0 0\nvt 1 0\nvt 1 1 0\nvt 0 1\nvt 0.25 0.75\n"
        "vn 0 0 1\nvn 0 0 2\n"
        "f 1/1/1 2/2/1 3/3/2 4/4/2\n"  # a quad: two triangles sharing vertices 1 and 3
        "f 2/-1 5/-3 3/1\n",  # relative vt, no vn: a flat normal
    )
    mesh, report = load_mesh(path)
    assert mesh.attributes.layout == (("NORMAL", 3), ("TEXCOORD_0", 2))
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [1, 4, 2]]
    uv = corner_table(mesh, "TEXCOORD_0")
    # glTF's v runs down: v_gltf = 1 - v_obj
    np.testing.assert_array_equal(uv[0], [[0, 1], [1, 1], [1, 0]])
    np.testing.assert_array_equal(uv[2], [[0.25, 0.25], [1, 0], [0, 1]])
    normals = corner_table(mesh, "NORMAL")
    np.testing.assert_array_equal(normals[0], [[0, 0, 1], [0, 0, 1], [0, 0, 2]])  # as stored
    np.testing.assert_array_equal(normals[2], [[0, 0, 1]] * 3)  # flat, from the winding
    # vertex 0 has one (vt, vn) in both quad triangles; vertices 1 and 2 differ in face 2
    assert (report.wedges, report.seam_vertices) == (7, 2)
    assert report.dropped_attributes == [] and mesh.materials is None


def test_obj_nan_texture_coordinate_is_a_mesh_error(tmp_path):
    path = write(tmp_path / "nan.obj", TRIANGLE + "vt nan 0\nf 1/1 2/1 3/1\n")
    with pytest.raises(MeshError, match="nan.obj: face corners have NaN .*TEXCOORD_0"):
        load_mesh(path)


def test_obj_bad_vt_reference(tmp_path):
    path = write(tmp_path / "vt.obj", TRIANGLE + "vt 0 0\nf 1/1 2/2 3/1\n")
    with pytest.raises(MeshError, match="refer to texture coordinates that do not exist"):
        load_mesh(path)


def test_obj_vertex_colours_become_linear_rgba(tmp_path):
    path = write(tmp_path / "colours.obj",
                 "v 0 0 0 1 0 0\nv 1 0 0 0 0.5 0\nv 0 1 0 0 0 0.04\nf 1 2 3\n")
    mesh, _ = load_mesh(path)
    colours = corner_table(mesh, "COLOR_0")[0]
    srgb_half = ((0.5 + 0.055) / 1.055) ** 2.4  # the sRGB curve
    np.testing.assert_allclose(colours, [[1, 0, 0, 1], [0, srgb_half, 0, 1], [0, 0, 0.04 / 12.92, 1]])


def test_obj_materials_from_mtllib_and_usemtl(tmp_path):
    (tmp_path / "textures").mkdir()
    (tmp_path / "textures" / "wood grain.png").write_bytes(PNG)
    write(tmp_path / "parts.mtl",
          "newmtl wood\nKd 1 0.5 0\nmap_Kd -s 1 1 1 -o 0 0 textures\\wood grain.png\n"
          "newmtl glass\nKd 0.2 0.2 0.2\nd 0.25\n"
          "newmtl unused\nTr 0.5\n")
    path = write(tmp_path / "parts.obj",
                 "mtllib parts.mtl\n" + TRIANGLE + "v 1 1 0\nvt 0 0\n"
                 "f 1 2 3\nusemtl glass\nf 2 4 3\nusemtl wood\nf 1/1 2/1 4/1\nusemtl paint\nf 1 4 3\n")
    mesh, report = load_mesh(path)
    assert mesh.face_material.tolist() == [-1, 1, 0, 3]
    records = mesh.materials.gltf["materials"]
    assert [r["name"] for r in records] == ["wood", "glass", "unused", "paint"]
    wood = records[0]["pbrMetallicRoughness"]
    assert wood["baseColorTexture"] == {"index": 0}
    assert (wood["metallicFactor"], wood["roughnessFactor"]) == (0.0, 1.0)
    np.testing.assert_allclose(wood["baseColorFactor"], [1, ((0.5 + 0.055) / 1.055) ** 2.4, 0, 1])
    assert records[1]["pbrMetallicRoughness"]["baseColorFactor"][3] == 0.25
    assert records[1]["alphaMode"] == "BLEND" and records[2]["alphaMode"] == "BLEND"
    assert mesh.materials.images == (PNG,)
    assert mesh.materials.gltf["images"] == [{"mimeType": "image/png", "name": "wood grain.png"}]
    assert mesh.materials.gltf["textures"] == [{"source": 0}]
    assert report.materials == 4 and report.missing_files == []


def test_obj_missing_mtllib_is_reported_and_a_missing_texture_is_an_error(tmp_path):
    path = write(tmp_path / "a.obj", "mtllib gone.mtl\nusemtl skin\n" + TRIANGLE + "f 1 2 3\n")
    mesh, report = load_mesh(path)
    assert report.missing_files == ["gone.mtl"]
    assert [r["name"] for r in mesh.materials.gltf["materials"]] == ["skin"]

    write(tmp_path / "b.mtl", "newmtl skin\nmap_Kd skin.png\n")
    path = write(tmp_path / "b.obj", "mtllib b.mtl\nusemtl skin\n" + TRIANGLE + "f 1 2 3\n")
    with pytest.raises(MeshError, match="b.obj: its material 'skin' uses the texture 'skin.png', "
                                        "which is missing"):
        load_mesh(path)


PLY_ATTRIBUTES = (
    "ply\nformat ascii 1.0\nelement vertex 4\n"
    "property float x\nproperty float y\nproperty float z\n"
    "property float nx\nproperty float ny\nproperty float nz\n"
    "property uchar red\nproperty uchar green\nproperty uchar blue\n"
    "property float s\nproperty float t\nproperty float quality\n"
    "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
    "0 0 0 0 0 1 255 0 0 0 0 7\n1 0 0 0 0 1 0 255 0 1 0 7\n"
    "1 1 0 0 0 1 0 0 255 1 1 7\n0 1 0 0 0 1 0 0 0 0 1 7\n"
    "3 0 1 2\n3 0 2 3\n"
)


def binary_ply_attributes() -> bytes:
    """PLY_ATTRIBUTES as binary little-endian, with its types."""
    header = PLY_ATTRIBUTES[:PLY_ATTRIBUTES.index("end_header")].replace("ascii", "binary_little_endian")
    vertex = np.zeros(4, dtype=[("p", "<f4", 3), ("n", "<f4", 3), ("rgb", "u1", 3),
                                ("st", "<f4", 2), ("quality", "<f4")])
    rows = np.array([line.split() for line in PLY_ATTRIBUTES.splitlines()[-6:-2]], dtype=float)
    vertex["p"], vertex["n"], vertex["rgb"] = rows[:, :3], rows[:, 3:6], rows[:, 6:9]
    vertex["st"], vertex["quality"] = rows[:, 9:11], rows[:, 11]
    faces = np.array([(3, (0, 1, 2)), (3, (0, 2, 3))], dtype=[("n", "u1"), ("i", "<i4", 3)])
    return (header + "end_header\n").encode() + vertex.tobytes() + faces.tobytes()


@pytest.mark.parametrize("binary", [False, True])
def test_ply_vertex_normals_colours_and_uvs(tmp_path, binary):
    path = tmp_path / "square.ply"
    path.write_bytes(binary_ply_attributes() if binary else PLY_ATTRIBUTES.encode())
    mesh, report = load_mesh(path)
    assert mesh.attributes.layout == (("NORMAL", 3), ("TEXCOORD_0", 2), ("COLOR_0", 4))
    np.testing.assert_array_equal(corner_table(mesh, "NORMAL"), np.tile([0, 0, 1], (2, 3, 1)))
    # PLY's v runs up, glTF's down
    np.testing.assert_array_equal(corner_table(mesh, "TEXCOORD_0")[0], [[0, 1], [1, 1], [1, 0]])
    np.testing.assert_array_equal(corner_table(mesh, "COLOR_0")[0],
                                  [[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 1]])
    assert report.dropped_attributes == ["quality"]
    assert report.seam_vertices == 0 and report.wedges == 4


def test_ply_per_face_texcoords(tmp_path):
    path = write(
        tmp_path / "meshlab.ply",
        "ply\nformat ascii 1.0\nelement vertex 4\n"
        "property float x\nproperty float y\nproperty float z\n"
        "element face 2\nproperty list uchar int vertex_indices\n"
        "property list uchar float texcoord\nend_header\n"
        "0 0 0\n1 0 0\n1 1 0\n0 1 0\n"
        "3 0 1 2 6 0 0 1 0 1 1\n3 0 2 3 6 0.5 0.5 1 1 0 1\n",
    )
    mesh, report = load_mesh(path)
    assert mesh.vertex_count == 4 and mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3]]
    np.testing.assert_array_equal(corner_table(mesh, "TEXCOORD_0"),
                                  [[[0, 1], [1, 1], [1, 0]], [[0.5, 0.5], [1, 0], [0, 0]]])
    assert report.seam_vertices == 1 and report.dropped_attributes == []


def test_tristrips_ply_reports_its_extra_property(tmp_path):
    path = tmp_path / "strips.ply"
    path.write_bytes(ply_with_strips("ascii"))
    mesh, report = load_mesh(path)
    assert mesh.attributes is None and report.dropped_attributes == ["quality"]


def test_obj_without_uvs_or_normals_writes_what_it_always_wrote(tmp_path):
    mesh, _ = load_mesh(SPOT)
    plain = Mesh(mesh.positions, mesh.faces)
    assert lodio.encode_mesh(plain, "obj") == trimesh.Trimesh(
        plain.positions, plain.faces, process=False).export(
        file_type="obj", **_EXPORT_OPTIONS["obj"]).encode()


@settings(max_examples=60, deadline=None)
@given(
    st.integers(3, 10).flatmap(
        lambda n: st.tuples(
            st.lists(st.tuples(*[st.sampled_from([0.0, -0.0, 1.0])] * 3), min_size=n, max_size=n),
            st.lists(st.tuples(*[st.integers(0, n - 1)] * 3), min_size=1, max_size=16),
            st.randoms(use_true_random=False),
        )
    )
)
def test_clean_mesh_wedges_are_the_distinct_corner_values_of_each_vertex(data):
    positions, faces, rng = np.array(data[0]), np.array(data[1]), data[2]
    # UVs from a small set, so that corners of one vertex often agree
    uv = np.array([[rng.choice([0.0, -0.0, 0.5]) for _ in range(2)] for _ in range(3 * len(faces))])
    corner_values = uv.reshape(-1, 3, 2)
    layout = (("TEXCOORD_0", 2),)
    try:
        mesh, report = clean_mesh(positions, faces, corner_values=corner_values, layout=layout)
    except MeshError as exc:
        assert "degenerate" in str(exc)
        return
    values = mesh.attributes.values[mesh.attributes.corners]  # (m', 3, 2)
    # one wedge per distinct (vertex, value) among the corners (0.0 == -0.0)
    keys = {(v, *np.abs(row)) for v, row in zip(mesh.faces.ravel(), values.reshape(-1, 2))}
    assert report.wedges == mesh.attributes.wedge_count == len(keys)
    # each kept face carries the corner values of an input face with its corner positions
    originals = {tuple(map(tuple, np.hstack([positions[f], corner_values[i]])))
                 for i, f in enumerate(faces)}
    for face, corner in zip(mesh.faces, values):
        assert tuple(map(tuple, np.hstack([mesh.positions[face], corner]))) in originals
    # cleaning again changes nothing
    again, second = clean_mesh(mesh.positions, mesh.faces, corner_values=values, layout=layout)
    np.testing.assert_array_equal(again.attributes.corners, mesh.attributes.corners)
    np.testing.assert_array_equal(again.attributes.values, mesh.attributes.values)
    assert (second.wedges, second.seam_vertices) == (report.wedges, report.seam_vertices)
