"""glTF in and out: attributes, materials, images, LOD chains, checked by the Khronos validator.

Tests that need no shared mesh build their own: a UV sphere whose seam column and
poles weld into vertices with several wedges, and small glTF documents with the
buffers in data: URIs. The validator (npm ``gltf-validator``, pinned) is installed
once per session into ``.cache/gltf-validator`` (gitignored); its tests skip with
the reason when node or npm is missing or the install fails.
"""

import base64
import json
import shutil
import struct
import subprocess
import tempfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from lodserver.cli import main
from lodserver.io.glb import coverage_from_ratios, encode_glb, encode_lod_chain
from lodserver.io.gltf import face_normals
from lodserver.io import clean_mesh, encode_mesh, load_mesh, save_mesh
from lodserver.mesh import Materials, Mesh, MeshError

from ..conftest import glb_chunks, need
from ..meshes import DATA

REPO = Path(__file__).resolve().parents[2]
VALIDATOR_VERSION = "2.0.0-dev.3.10"
VALIDATOR_PREFIX = REPO / ".cache" / "gltf-validator"
VALIDATE_SCRIPT = Path(__file__).resolve().parents[1] / "gltf_validate.mjs"
SEVERITY = {0: "error", 1: "warning", 2: "info", 3: "hint"}
SPHERE_LAYOUT = (("NORMAL", 3), ("TEXCOORD_0", 2))


# --- helpers ------------------------------------------------------------------------------


def tiny_png(rgba=(255, 0, 0, 255)) -> bytes:
    """A valid 2x2 RGBA PNG of one colour."""
    row = b"\x00" + bytes(rgba) * 2  # filter byte, two pixels

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 2, 2, 8, 6, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(row * 2)) + chunk(b"IEND", b""))


def uv_sphere_arrays(rows: int = 6, columns: int = 12):
    """A unit lat-long sphere before welding: (rows+1) x (columns+1) grid vertices.

    The last column repeats the first column's positions (u = 1 against u = 0)
    and each pole row is one position (u = j / columns), so welding leaves
    ``(rows - 1) * columns + 2`` vertices of which the seam column and the poles
    have several wedges. Corner values are NORMAL (the position) and TEXCOORD_0.
    """
    theta = np.linspace(0.0, np.pi, rows + 1)
    phi = np.linspace(0.0, 2.0 * np.pi, columns + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    grid = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], axis=-1)
    grid[:, -1] = grid[:, 0]  # exactly the same positions, so they weld
    grid[0], grid[-1] = (0.0, 1.0, 0.0), (0.0, -1.0, 0.0)
    uv = np.stack([p / (2.0 * np.pi), t / np.pi], axis=-1)  # glTF: v grows downwards
    index = np.arange((rows + 1) * (columns + 1)).reshape(rows + 1, columns + 1)
    a, b = index[:-1, :-1].ravel(), index[1:, :-1].ravel()
    c, d = index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], axis=1), np.stack([a, d, c], axis=1)])
    positions = grid.reshape(-1, 3)
    values = np.hstack([positions, uv.reshape(-1, 2)])
    return positions, faces, values[faces]


def sphere_materials() -> Materials:
    """Two materials (a textured one and a plain red one) and an image nobody uses."""
    gltf = {
        "materials": [
            {"name": "textured", "pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}},
            {"name": "red", "pbrMetallicRoughness": {"baseColorFactor": [1, 0, 0, 1]}},
        ],
        "textures": [{"source": 0, "sampler": 0}, {"source": 1}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987}],
        "images": [{"mimeType": "image/png", "name": "red.png"},
                   {"mimeType": "image/png", "name": "unused.png"}],
    }
    return Materials(gltf, (tiny_png(), tiny_png((0, 0, 255, 255))))


def uv_sphere(rows: int = 6, columns: int = 12, *, materials: bool = True):
    """The cleaned sphere (Mesh, LoadReport); northern faces use material 0, southern 1."""
    positions, faces, corner_values = uv_sphere_arrays(rows, columns)
    face_material = None
    if materials:
        north = positions[faces].mean(axis=1)[:, 1] > 0
        face_material = np.where(north, 0, 1)
    return clean_mesh(positions, faces, corner_values=corner_values, layout=SPHERE_LAYOUT,
                      face_material=face_material,
                      materials=sphere_materials() if materials else None)


def sphere_with_every_attribute():
    """The sphere (no materials) with NORMAL, TEXCOORD_0, TEXCOORD_1 and COLOR_0."""
    positions, faces, corner_values = uv_sphere_arrays()
    uv = corner_values[..., 3:5]
    colour = np.concatenate([uv, np.full(uv.shape[:2] + (2,), 0.5)], axis=2)
    values = np.concatenate([corner_values, 2.0 * uv, colour], axis=2)
    layout = (*SPHERE_LAYOUT, ("TEXCOORD_1", 2), ("COLOR_0", 4))
    return clean_mesh(positions, faces, corner_values=values, layout=layout)


def glb_document(data: bytes) -> tuple[dict, bytes]:
    """The JSON and BIN chunks of GLB bytes."""
    json_length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + json_length])
    binary = data[28 + json_length:]
    return document, binary


def gltf_file(folder: Path, positions, faces, *, attributes=None, node=None, images=(),
              material=False, name="asset.gltf", extra=None) -> Path:
    """A .gltf with its buffer in a data: URI, one node (``node`` adds a transform) and one
    triangle primitive; ``images`` are image records, ``material`` adds a textured material."""
    blobs, views, accessors = [], [], []

    def add(array, kind, component):
        data = array.tobytes()
        offset = sum(len(blob) for blob in blobs)
        blobs.append(data + b"\0" * (-len(data) % 4))
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data)})
        accessors.append({"bufferView": len(views) - 1, "componentType": component,
                          "count": len(array), "type": kind})
        return len(accessors) - 1

    attribute_ids = {"POSITION": add(np.asarray(positions, "<f4"), "VEC3", 5126)}
    for key, values in (attributes or {}).items():
        values = np.asarray(values)
        if values.dtype == np.uint8:
            attribute_ids[key] = add(values, f"VEC{values.shape[1]}", 5121)
            accessors[-1]["normalized"] = True
        else:
            attribute_ids[key] = add(values.astype("<f4"), f"VEC{values.shape[1]}", 5126)
    primitive = {"attributes": attribute_ids,
                 "indices": add(np.asarray(faces, "<u2").ravel(), "SCALAR", 5123)}
    buffer = b"".join(blobs)
    document = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, **(node or {})}], "meshes": [{"primitives": [primitive]}],
        "accessors": accessors, "bufferViews": views,
        "buffers": [{"byteLength": len(buffer),
                     "uri": "data:application/octet-stream;base64," + base64.b64encode(buffer).decode()}],
    }
    if images:
        document["images"] = list(images)
        document["textures"] = [{"source": i} for i in range(len(images))]
    if material:
        document["materials"] = [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}]
        primitive["material"] = 0
    document.update(extra or {})
    path = folder / name
    path.write_text(json.dumps(document))
    return path


def oriented_faces(mesh: Mesh) -> set:
    """Faces as float32 corner positions, rotated to start at the smallest corner: the
    same set for two meshes with the same triangles, whatever their vertex and face order."""
    corners = mesh.positions[mesh.faces].astype(np.float32)
    found = set()
    for face in corners:
        rows = [tuple(row) for row in face]
        k = rows.index(min(rows))
        found.add(tuple(rows[k:] + rows[:k]))
    return found


def assert_same_wedges(mesh: Mesh, other: Mesh, atol: float) -> None:
    """Both meshes have the same wedges, as (position, attribute vector, material) rows, to
    ``atol``: each wedge of one has exactly one wedge of the other that close."""
    from scipy.spatial import cKDTree

    def rows(m):
        material = np.full(m.attributes.wedge_count, -1.0)
        if m.face_material is not None:
            material[m.attributes.corners.ravel()] = np.repeat(m.face_material, 3)
        return np.hstack([m.positions[m.wedge_vertices()], m.attributes.values, material[:, None]])

    ours, theirs = rows(mesh), rows(other)
    assert ours.shape == theirs.shape
    distance, nearest = cKDTree(theirs).query(ours, p=np.inf)
    assert distance.max() <= atol
    assert len(np.unique(nearest)) == len(theirs)  # a one-to-one match


# --- the validator ---------------------------------------------------------------------------


@pytest.fixture(scope="session")
def gltf_validator():
    """``validate(glb_bytes) -> report`` with the pinned Khronos glTF validator."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        need("the Khronos glTF validator needs node and npm, and they are not on PATH")
    package = VALIDATOR_PREFIX / "node_modules" / "gltf-validator" / "package.json"
    installed = package.is_file() and json.loads(package.read_text()).get("version")
    if installed != VALIDATOR_VERSION:
        VALIDATOR_PREFIX.mkdir(parents=True, exist_ok=True)
        try:
            result = subprocess.run(
                [npm, "install", "--prefix", str(VALIDATOR_PREFIX), "--no-audit", "--no-fund",
                 "--no-save", "--loglevel=error", f"gltf-validator@{VALIDATOR_VERSION}"],
                capture_output=True, text=True, timeout=600, check=False)
        except (OSError, subprocess.TimeoutExpired) as exc:
            need(f"installing gltf-validator@{VALIDATOR_VERSION} with npm failed: {exc}")
        if result.returncode != 0 or not package.is_file():
            tail = " ".join(result.stderr.strip().splitlines()[-3:])
            need(f"installing gltf-validator@{VALIDATOR_VERSION} with npm failed: {tail}")

    def validate(data: bytes) -> dict:
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "asset.glb"
            path.write_bytes(data)
            result = subprocess.run([node, str(VALIDATE_SCRIPT), str(VALIDATOR_PREFIX), str(path)],
                                    capture_output=True, text=True, timeout=300, check=False)
        assert result.returncode == 0, f"the validator script failed: {result.stderr}"
        return json.loads(result.stdout)[0]

    return validate


def assert_valid(validate, data: bytes, what: str) -> dict:
    """No validator errors; errors and warnings (if any) are listed in the message."""
    issues = validate(data)["issues"]
    listed = "\n".join(f"  {SEVERITY[m['severity']]} {m['code']} at {m.get('pointer', '-')}: "
                       f"{m['message']}" for m in issues["messages"] if m["severity"] <= 1)
    assert issues["numErrors"] == 0, f"{what}: the glTF validator reports\n{listed}"
    if issues["numWarnings"]:
        print(f"{what}: {issues['numWarnings']} validator warnings\n{listed}")
    return issues


def _chain_of(path: Path) -> bytes:
    from lodserver.build import build

    pm = build(path)
    ratios = [1.0, 0.5, 0.1]
    return encode_lod_chain([pm.at(ratio=r) for r in ratios], coverage_from_ratios(ratios))


def _geometry_only() -> bytes:
    mesh, _ = load_mesh(DATA / "spot.obj")
    return encode_mesh(Mesh(mesh.positions, mesh.faces), "glb")


def _served_level() -> bytes:
    """A level as the server writes it: straight into the GLB buffer."""
    from lodserver.build import build
    from lodserver.service.levels import encode_level

    mesh, _ = load_mesh(DATA / "spot.obj")
    pm = build(Mesh(mesh.positions, mesh.faces))
    return encode_level(pm, pm.level_for(ratio=0.3), file_type="glb")


def _reached_chain(path: Path) -> bytes:
    """A chain whose coarsest level edge collapse cannot reach (the engine's parts):
    made by clustering, positions only, beside levels with materials."""
    from lodserver.pipeline import export_lods

    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "chain.glb"
        done = export_lods(path, out, lods=(1, 0.1, 0.02), reach="cluster")
        # the scene's parts are built one by one: the far level is clustered, and
        # some parts need clustering at 10% already
        assert 2 in done.clustered
        return out.read_bytes()


# name: (shared file or None, bytes from a path or None)
VALIDATED = {
    "geometry only": (None, lambda _: _geometry_only()),
    "a level of spot as the server writes it": (None, lambda _: _served_level()),
    "generated sphere, two materials and an unused image": (None, lambda _: encode_glb(uv_sphere()[0])),
    "generated sphere, every attribute": (None, lambda _: encode_glb(sphere_with_every_attribute()[0])),
    "spot (tests/data, UVs)": (None, lambda _: encode_glb(load_mesh(DATA / "spot.obj")[0])),
    "LOD chain of spot": (None, lambda _: _chain_of(DATA / "spot.obj")),
    "Duck.glb": ("Duck.glb", lambda p: encode_glb(load_mesh(p)[0])),
    "Avocado.gltf": ("Avocado/Avocado.gltf", lambda p: encode_glb(load_mesh(p)[0])),
    "bunny10k_textured.obj": ("bunny10k_textured/bunny10k_textured.obj",
                              lambda p: encode_glb(load_mesh(p)[0])),
    "spot.obj": ("spot/spot.obj", lambda p: encode_glb(load_mesh(p)[0])),
    "2CylinderEngine.glb": ("2CylinderEngine.glb", lambda p: encode_glb(load_mesh(p)[0])),
    "Laurana50k.ply (vertex colours)": ("Laurana50k.ply", lambda p: encode_glb(load_mesh(p)[0])),
    "LOD chain of Duck": ("Duck.glb", _chain_of),
    "LOD chain of 2CylinderEngine, its far level clustered": ("2CylinderEngine.glb",
                                                               lambda p: _reached_chain(p)),
}


@pytest.mark.parametrize("name", list(VALIDATED))
def test_the_khronos_validator_accepts_every_glb_we_write(request, gltf_validator, name):
    shared, make = VALIDATED[name]
    path = request.getfixturevalue("shared_meshes") / shared if shared else None
    assert_valid(gltf_validator, make(path), name)


# --- loading --------------------------------------------------------------------------------


def test_sphere_wedges_and_seams_by_hand():
    rows, columns = 6, 12
    mesh, report = uv_sphere(rows, columns, materials=False)
    assert mesh.vertex_count == (rows - 1) * columns + 2
    # one triangle of each pole quad is degenerate after welding
    assert mesh.face_count == 2 * columns * (rows - 1)
    assert report.degenerate_faces == 2 * columns
    # interior rows: columns + 1 wedges (u = 0 and u = 1 at the seam); poles: one per column
    assert report.wedges == mesh.attributes.wedge_count == (rows - 1) * (columns + 1) + 2 * columns
    assert report.seam_vertices == (rows - 1) + 2
    # every corner still carries its own position as normal
    owner = mesh.wedge_vertices()
    np.testing.assert_allclose(mesh.attributes.values[:, :3], mesh.positions[owner], atol=1e-15)

    # the material is part of a wedge: the equator, between the two materials, doubles
    with_materials, split = uv_sphere(rows, columns)
    assert split.wedges == report.wedges + (columns + 1)
    assert split.seam_vertices == report.seam_vertices + (columns - 1)  # its seam vertex was one
    np.testing.assert_array_equal(with_materials.faces, mesh.faces)


def test_geometry_only_input_keeps_attributes_none():
    positions, faces, _ = uv_sphere_arrays()
    mesh, report = clean_mesh(positions, faces)
    assert mesh.attributes is None and mesh.face_material is None and mesh.materials is None
    assert (report.wedges, report.seam_vertices, report.dropped_attributes) == (0, 0, [])


def test_nan_uv_is_a_mesh_error():
    positions, faces, corner_values = uv_sphere_arrays()
    corner_values[5, 1, 4] = np.nan
    with pytest.raises(MeshError, match=r"NaN or infinite attribute values \(1 TEXCOORD_0"):
        clean_mesh(positions, faces, corner_values=corner_values, layout=SPHERE_LAYOUT)


def test_normals_follow_the_inverse_transpose_and_mirrors_keep_them_outward(tmp_path):
    # a tetrahedron whose corner normals are its face normals, placed by a node that
    # mirrors, rotates and scales unevenly: loaded normals must still be the faces' normals
    tetra = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    tetra_faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    positions = tetra[tetra_faces].reshape(-1, 3)  # unshared corners, one normal each
    faces = np.arange(12).reshape(4, 3)
    normals = np.repeat(face_normals(tetra, tetra_faces), 3, axis=0)
    rotation = [0.0, np.sin(0.3), 0.0, np.cos(0.3)]
    path = gltf_file(tmp_path, positions, faces, attributes={"NORMAL": normals},
                     node={"rotation": rotation, "scale": [-2.0, 1.0, 0.5]})
    mesh, report = load_mesh(path)
    assert mesh.face_count == 4 and report.seam_vertices == 4  # 3 wedges at every corner
    corner_normals = mesh.attributes.values[mesh.attributes.corners]
    expected = np.repeat(face_normals(mesh.positions, mesh.faces)[:, None], 3, axis=1)
    np.testing.assert_allclose(corner_normals, expected, atol=1e-6)
    volume = np.einsum("ij,ij->", mesh.positions[mesh.faces[:, 0]],
                       np.cross(mesh.positions[mesh.faces[:, 1]], mesh.positions[mesh.faces[:, 2]]))
    assert volume > 0  # outward winding survives the mirror


def test_gltf_colours_tangents_and_missing_normals(tmp_path):
    positions = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    colours = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 51]], dtype=np.uint8)  # normalized
    path = gltf_file(tmp_path, positions, [[0, 1, 2]],
                     attributes={"COLOR_0": colours, "TANGENT": [[1, 0, 0, 1]] * 3,
                                 "JOINTS_0": np.zeros((3, 4), np.uint8) + 255})
    mesh, report = load_mesh(path)
    # flattened: the skin means nothing without its nodes, the tangent is kept
    assert report.dropped_attributes == ["JOINTS_0"]
    assert mesh.attributes.layout == (("COLOR_0", 4), ("TANGENT", 4))
    np.testing.assert_allclose(mesh.attributes.values[mesh.attributes.corners[0]],
                               [[1, 0, 0, 1, 1, 0, 0, 1], [0, 1, 0, 1, 1, 0, 0, 1],
                                [0, 0, 0.2, 1, 1, 0, 0, 1]])


def test_gltf_image_bytes_from_a_data_uri_are_kept(tmp_path):
    png = tiny_png((1, 2, 3, 255))
    uri = "data:image/png;base64," + base64.b64encode(png).decode()
    path = gltf_file(tmp_path, [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]],
                     attributes={"TEXCOORD_0": [[0, 0], [1, 0], [0, 1]]},
                     images=[{"uri": uri}], material=True)
    mesh, report = load_mesh(path)
    assert mesh.materials.images == (png,)
    assert mesh.materials.gltf["images"][0]["mimeType"] == "image/png"
    assert mesh.face_material.tolist() == [0] and report.materials == 1


def test_gltf_image_file_next_to_it_is_read_and_a_missing_one_is_an_error(tmp_path):
    png = tiny_png()
    (tmp_path / "my texture.png").write_bytes(png)
    triangle = ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    path = gltf_file(tmp_path, *triangle, images=[{"uri": "my%20texture.png"}], material=True)
    assert load_mesh(path)[0].materials.images == (png,)

    path = gltf_file(tmp_path, *triangle, images=[{"uri": "missing.png"}], material=True,
                     name="broken.gltf")
    with pytest.raises(MeshError, match=r"broken\.gltf: its image 0 file 'missing\.png' is missing"):
        load_mesh(path)


def test_gltf_requiring_compression_it_does_not_use_loads(tmp_path):
    # compressed geometry is decoded (tests/io/test_gltf_compressed_*.py); a document
    # that requires the extension without using it is plain geometry
    path = gltf_file(tmp_path, [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]],
                     extra={"extensionsUsed": ["KHR_draco_mesh_compression"],
                            "extensionsRequired": ["KHR_draco_mesh_compression"]})
    assert load_mesh(path)[0].face_count == 1


def test_shared_textured_meshes_have_seams(shared_meshes):
    for name, layout in [("Duck.glb", ["NORMAL", "TEXCOORD_0"]), ("spot/spot.obj", ["TEXCOORD_0"]),
                         ("Avocado/Avocado.gltf", ["NORMAL", "TEXCOORD_0", "TANGENT"]),
                         ("bunny10k_textured/bunny10k_textured.obj", ["TEXCOORD_0"])]:
        mesh, report = load_mesh(shared_meshes / name)
        assert [n for n, _ in mesh.attributes.layout] == layout, name
        assert report.seam_vertices > 0 and report.wedges > mesh.vertex_count, name


def test_avocado_keeps_its_three_images_byte_for_byte(shared_meshes):
    folder = shared_meshes / "Avocado"
    mesh, report = load_mesh(folder / "Avocado.gltf")
    assert report.dropped_attributes == []      # its TANGENT is kept
    names = ["Avocado_baseColor.png", "Avocado_roughnessMetallic.png", "Avocado_normal.png"]
    assert mesh.materials.images == tuple((folder / n).read_bytes() for n in names)
    assert mesh.materials.gltf["materials"][0]["normalTexture"] == {"index": 2}


def test_engine_materials_become_one_primitive_each(shared_meshes):
    mesh, report = load_mesh(shared_meshes / "2CylinderEngine.glb")
    assert report.materials == 34 and report.dropped_attributes == []
    document, _ = glb_document(encode_glb(mesh))
    primitives = document["meshes"][0]["primitives"]
    used = sorted(set(mesh.face_material.tolist()))
    assert [p["material"] for p in primitives] == used
    assert len(document["materials"]) == 34  # unused ones too
    assert sum(document["accessors"][p["indices"]]["count"] for p in primitives) == 3 * mesh.face_count


# --- writing --------------------------------------------------------------------------------


def test_glb_layout_of_a_mesh_with_materials():
    mesh, report = uv_sphere()
    data = encode_glb(mesh)
    document, binary = glb_document(data)
    assert struct.unpack_from("<4sII", data) == (b"glTF", 2, len(data))
    assert document["buffers"] == [{"byteLength": len(binary)}]
    assert all(view["byteOffset"] % 4 == 0 for view in document["bufferViews"])
    primitives = document["meshes"][0]["primitives"]
    assert [p["material"] for p in primitives] == [0, 1]
    # one render vertex per wedge; wedges never span two materials, so none is written twice
    counts = [document["accessors"][p["attributes"]["POSITION"]]["count"] for p in primitives]
    assert sum(counts) == report.wedges
    for p in primitives:
        assert set(p["attributes"]) == {"POSITION", "NORMAL", "TEXCOORD_0"}
        position = document["accessors"][p["attributes"]["POSITION"]]
        assert "min" in position and "max" in position
    # images embedded byte for byte, the unused one too, with their mimeType
    for record, png in zip(document["images"], mesh.materials.images):
        view = document["bufferViews"][record["bufferView"]]
        assert binary[view["byteOffset"]:view["byteOffset"] + view["byteLength"]] == png
        assert record["mimeType"] == "image/png"
    assert document["textures"] == mesh.materials.gltf["textures"]
    assert document["samplers"] == mesh.materials.gltf["samplers"]


def test_glb_round_trip_of_the_generated_sphere(tmp_path):
    mesh, report = uv_sphere()
    path = tmp_path / "sphere.glb"
    save_mesh(mesh, path)
    back, again = load_mesh(path)
    assert (back.vertex_count, back.face_count) == (mesh.vertex_count, mesh.face_count)
    assert oriented_faces(back) == oriented_faces(mesh)
    assert_same_wedges(back, mesh, atol=1e-6)  # float32 in the file
    assert (again.wedges, again.seam_vertices) == (report.wedges, report.seam_vertices)
    assert back.materials.images == mesh.materials.images
    assert back.materials.gltf["materials"] == mesh.materials.gltf["materials"]
    assert sorted(back.face_material.tolist()) == sorted(mesh.face_material.tolist())


def test_glb_round_trip_of_every_attribute(tmp_path):
    mesh, report = sphere_with_every_attribute()
    path = tmp_path / "sphere.glb"
    save_mesh(mesh, path)
    document, _ = glb_document(path.read_bytes())
    attributes = document["meshes"][0]["primitives"][0]["attributes"]
    assert {name: document["accessors"][i]["type"] for name, i in attributes.items()} == {
        "POSITION": "VEC3", "NORMAL": "VEC3", "TEXCOORD_0": "VEC2", "TEXCOORD_1": "VEC2",
        "COLOR_0": "VEC4"}
    back, again = load_mesh(path)
    assert back.attributes.layout == mesh.attributes.layout
    assert_same_wedges(back, mesh, atol=1e-6)
    assert (again.wedges, again.seam_vertices) == (report.wedges, report.seam_vertices)


def test_glb_round_trip_of_the_duck(shared_meshes, tmp_path):
    mesh, report = load_mesh(shared_meshes / "Duck.glb")
    path = tmp_path / "duck.glb"
    save_mesh(mesh, path)
    back, again = load_mesh(path)
    assert (back.vertex_count, back.face_count) == (mesh.vertex_count, mesh.face_count)
    assert oriented_faces(back) == oriented_faces(mesh)
    assert_same_wedges(back, mesh, atol=1e-6)
    assert again.wedges == report.wedges and again.seam_vertices == report.seam_vertices
    assert back.materials.count == mesh.materials.count == 1
    assert back.materials.images == mesh.materials.images


def test_obj_round_trip_keeps_uvs_and_normals(tmp_path):
    mesh, report = uv_sphere(materials=False)
    path = tmp_path / "sphere.obj"
    save_mesh(mesh, path)
    text = path.read_text()
    assert text.count("\nvt ") + text.startswith("vt ") == report.wedges
    back, again = load_mesh(path)
    np.testing.assert_array_equal(back.positions, mesh.positions)  # 17 digits: exact
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.attributes.corners, mesh.attributes.corners)
    # v is written as 1 - v and read back as 1 - (1 - v): exact but for rounding
    np.testing.assert_allclose(back.attributes.values, mesh.attributes.values, rtol=0, atol=1e-15)
    assert again.seam_vertices == report.seam_vertices


def test_zero_normals_are_written_as_unit_vectors():
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float64)
    corner_values = np.zeros((1, 3, 3))  # a normal with no direction
    mesh, _ = clean_mesh(positions, [[0, 1, 2]], corner_values=corner_values,
                         layout=(("NORMAL", 3),))
    document, binary = glb_document(encode_glb(mesh))
    accessor = document["accessors"][document["meshes"][0]["primitives"][0]["attributes"]["NORMAL"]]
    view = document["bufferViews"][accessor["bufferView"]]
    normals = np.frombuffer(binary, "<f4", 9, view["byteOffset"]).reshape(3, 3)
    np.testing.assert_allclose(normals, [[0, 0, 1]] * 3)  # the triangle's own normal


def test_lod_chain_shares_materials_and_links_nodes():
    mesh, _ = uv_sphere()
    coarse, _ = uv_sphere(4, 6)
    data = encode_lod_chain([mesh, coarse], [0.25, 0.0])
    document, _ = glb_document(data)
    assert document["scenes"] == [{"nodes": [0]}]  # viewers without MSFT_lod draw the finest
    assert document["nodes"][0]["extensions"] == {"MSFT_lod": {"ids": [1]}}
    assert document["nodes"][0]["extras"] == {"MSFT_screencoverage": [0.25, 0.0]}
    assert [node["mesh"] for node in document["nodes"]] == [0, 1]
    assert document["extensionsUsed"] == ["MSFT_lod"]
    assert len(document["images"]) == 2 and len(document["materials"]) == 2  # once


@pytest.mark.parametrize("coverage, message", [
    ([0.5], "2 levels need 2"),
    ([0.1, 0.5], "not increase"),
    ([1.5, 0.0], "lie in"),
])
def test_lod_chain_rejects_bad_coverage(coverage, message):
    mesh, _ = uv_sphere()
    with pytest.raises(MeshError, match=message):
        encode_lod_chain([mesh, mesh], coverage)


def test_coverage_from_ratios():
    assert coverage_from_ratios([1.0]) == [0.0]
    np.testing.assert_allclose(coverage_from_ratios([1, 0.25, 0.01]), [0.25, 0.05, 0.0])
    with pytest.raises(MeshError, match="strictly decreasing"):
        coverage_from_ratios([0.5, 0.5])


def test_positions_only_glb_bytes_have_not_changed():
    """The geometry-only fast path writes what lodserver wrote before attributes existed."""
    import hashlib

    data = _geometry_only()
    assert hashlib.sha256(data).hexdigest().startswith("b83edef3e61df7bb")


def test_served_levels_are_the_fast_path_glb_but_for_json_padding():
    """``level_glb`` (the server's levels) holds the same JSON document and the same
    binary chunk as ``geometry_glb`` of the level's arrays."""
    from lodserver.build import build
    from lodserver.service.levels import encode_level
    from lodserver.io.glb import geometry_glb

    mesh, _ = load_mesh(DATA / "spot.obj")
    pm = build(Mesh(mesh.positions, mesh.faces))
    for level in (pm.base_vertices, pm.level_for(ratio=0.5), pm.vertex_count):
        served = bytes(encode_level(pm, level, file_type="glb", copy=False))
        direct = geometry_glb(*pm.arrays_at(level))
        assert glb_chunks(served) == glb_chunks(direct)


# --- lodserver export ------------------------------------------------------------------------


def test_export_writes_one_glb_with_msft_lod(tmp_path, capsys):
    asset = tmp_path / "spot.pm"
    assert main(["build", str(DATA / "spot.obj"), "-o", str(asset)]) == 0
    out = tmp_path / "spot.glb"
    assert main(["export", str(asset), "--lods", "1,0.5,0.1", "-o", str(out)]) == 0
    document, _ = glb_document(out.read_bytes())
    assert document["nodes"][0]["extensions"]["MSFT_lod"]["ids"] == [1, 2]
    assert document["nodes"][0]["extras"]["MSFT_screencoverage"] == coverage_from_ratios([1, 0.5, 0.1])
    face_counts = [sum(document["accessors"][p["indices"]]["count"] // 3
                       for p in mesh["primitives"]) for mesh in document["meshes"]]
    assert face_counts[0] == 5856 and face_counts[0] > face_counts[1] > face_counts[2]
    assert "3 levels" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spot.glb", "spot.pm"]  # no temporaries


def test_export_separate_from_a_mesh_file(tmp_path):
    out = tmp_path / "cow.glb"
    assert main(["export", str(DATA / "spot.obj"), "--lods", "1,0.2", "--separate",
                 "-o", str(out)]) == 0
    assert not out.exists()
    full, _ = load_mesh(tmp_path / "cow_lod0.glb")
    coarse, _ = load_mesh(tmp_path / "cow_lod1.glb")
    assert full.face_count == 5856 and coarse.face_count <= round(0.2 * 5856)
    assert coarse.attributes is not None  # the levels keep their UVs


@pytest.mark.parametrize("argv, message", [
    (["export", "{spot}", "--lods", "1,2", "-o", "x.glb"], "(0, 1]"),
    (["export", "{spot}", "--lods", "0.2,0.5", "-o", "x.glb"], "strictly decreasing"),
    (["export", "{spot}", "--lods", "1,half", "-o", "x.glb"], "comma-separated"),
    (["export", "{spot}", "-o", "x.obj"], "must end in .glb"),
    (["export", "missing.pm", "-o", "x.glb"], "cannot read"),
    (["export", "missing.obj", "-o", "x.glb"], "cannot load"),
])
def test_export_errors_are_one_sentence_and_exit_1(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    code = main([a.replace("{spot}", str(DATA / "spot.obj")) for a in argv])
    err = capsys.readouterr().err
    assert code == 1
    assert message in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == []
