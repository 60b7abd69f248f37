"""Compressed glTF out: lodserver's quantized and meshopt GLBs, decoded without
lodserver's reader, equal the uncompressed output within the quantization step.

The independent decoder (:func:`decode_independently`) is meshoptimizer's Python
package for the bitstreams and its filter functions, numpy for accessors and node
transforms; what it reads is cleaned into a Mesh and compared face by face with
the float32 output read back (``gltf_tools.attribute_errors``). Steps: positions a
14-bit grid over the largest side (half a step per axis, one allowed), int8 normals
and tangents (octahedral or direct: two degrees allowed), UVs in [0, 1] 16 bits.
"""

import json
import struct

import numpy as np
import pytest

from lodserver.build import build
from lodserver.cli import main
from lodserver.io import clean_mesh, encode_mesh, load_mesh
from lodserver.io.glb import COMPRESSIONS, coverage_from_ratios, encode_glb, encode_lod_chain
from lodserver.io.quantize import POSITION_BITS
from lodserver.mesh import MeshError

from ..conftest import SHARED_MESHES
from ..meshes import DATA
from .gltf_tools import attribute_errors, extent
from .test_gltf import assert_valid, gltf_validator  # noqa: F401 (a fixture)

meshoptimizer = pytest.importorskip("meshoptimizer")

_DTYPES = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
_NORMALIZED = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
DEGREES = 2.0


def split_glb(data: bytes) -> tuple[dict, bytes]:
    length = struct.unpack_from("<I", data, 12)[0]
    document = json.loads(data[20:20 + length])
    return document, data[20 + length + 8:]


def decode_independently(data: bytes, node: int = 0):
    """The mesh node ``node`` draws, decoded with meshoptimizer's package: (positions
    (n, 3) placed by the node's transform, faces (m, 3), {attribute: (n, k) float})."""
    document, binary = split_glb(data)
    views = []
    for view in document["bufferViews"]:
        extension = view.get("extensions", {}).get("EXT_meshopt_compression")
        if extension is None:
            start = view.get("byteOffset", 0)
            views.append(binary[start:start + view["byteLength"]])
            continue
        source = np.frombuffer(binary, np.uint8, extension["byteLength"],
                               extension.get("byteOffset", 0))
        count, stride = extension["count"], extension["byteStride"]
        if extension["mode"] == "ATTRIBUTES":
            decoded = meshoptimizer.decode_vertex_buffer(count, stride, source).view(np.uint8)
            if extension.get("filter") == "OCTAHEDRAL":
                decoded = meshoptimizer.decode_filter_oct(decoded.copy(), count, stride)
            views.append(decoded.tobytes())
        else:
            indices = meshoptimizer.decode_index_buffer(count, 4, source)
            views.append(indices.astype("<u2" if stride == 2 else "<u4").tobytes())

    def accessor(index):
        record = document["accessors"][index]
        dtype = np.dtype(_DTYPES[record["componentType"]])
        width = _WIDTHS[record["type"]]
        view = document["bufferViews"][record["bufferView"]]
        stride = view.get("byteStride", dtype.itemsize * width)
        raw = np.frombuffer(views[record["bufferView"]], np.uint8, record["count"] * stride,
                            record.get("byteOffset", 0)).reshape(record["count"], stride)
        values = np.ascontiguousarray(raw[:, :dtype.itemsize * width]).view(dtype)
        values = values.astype(np.float64)
        if record.get("normalized"):
            values = np.maximum(values / _NORMALIZED[record["componentType"]], -1.0)
        return values

    placed = document["nodes"][node]
    scale = np.asarray(placed.get("scale", (1, 1, 1)))
    translation = np.asarray(placed.get("translation", (0, 0, 0)))
    positions, faces, columns, materials, start = [], [], {}, [], 0
    for primitive in document["meshes"][placed["mesh"]]["primitives"]:
        local = accessor(primitive["attributes"]["POSITION"])
        positions.append(local * scale + translation)
        faces.append(accessor(primitive["indices"]).astype(np.int64).reshape(-1, 3) + start)
        materials.append(np.full(len(faces[-1]), primitive.get("material", -1)))
        for name, index in primitive["attributes"].items():
            if name != "POSITION":
                columns.setdefault(name, []).append(accessor(index))
        start += len(local)
    return (np.concatenate(positions), np.concatenate(faces),
            {name: np.concatenate(parts) for name, parts in columns.items()},
            np.concatenate(materials).astype(np.int32))


def as_mesh(decoded, layout, materials):
    """A cleaned Mesh of :func:`decode_independently`'s arrays, columns in ``layout``."""
    positions, faces, attributes, face_material = decoded
    corner = None
    if layout:
        columns = []
        for name, width in layout:
            values = attributes[name]
            if name == "NORMAL":
                values = values / np.linalg.norm(values, axis=1, keepdims=True)
            columns.append(values[:, :width])
        corner = np.concatenate(columns, axis=1)[faces]
    return clean_mesh(positions, faces, corner_values=corner, layout=layout,
                      face_material=face_material, materials=materials)[0]


def _step(mesh) -> float:
    return extent(mesh.positions) / (2 ** POSITION_BITS - 1)


def _acmr(faces: np.ndarray, cache: int = 16) -> float:
    """Average cache miss ratio (misses per triangle) of a FIFO cache of ``cache``."""
    fifo, misses = [], 0
    for vertex in faces.ravel().tolist():
        if vertex not in fifo:
            misses += 1
            fifo.append(vertex)
            if len(fifo) > cache:
                fifo.pop(0)
    return misses / len(faces)


@pytest.mark.parametrize("compress", ["quantize", "meshopt"])
@pytest.mark.parametrize("name", ["Duck.glb", "Avocado/Avocado.gltf"])
def test_compressed_glb_decodes_to_the_uncompressed_output(shared_meshes, tmp_path, name,
                                                           compress, gltf_validator):  # noqa: F811
    mesh, _ = load_mesh(shared_meshes / name)
    plain = tmp_path / "plain.glb"
    plain.write_bytes(encode_glb(mesh))
    reference, _ = load_mesh(plain)
    data = encode_glb(mesh, compress)
    document, _ = split_glb(data)
    wanted = ["KHR_mesh_quantization"] + (["EXT_meshopt_compression"]
                                          if compress == "meshopt" else [])
    assert set(wanted) <= set(document["extensionsRequired"])
    decoded = as_mesh(decode_independently(data), reference.attributes.layout,
                      reference.materials)
    assert decoded.face_count == reference.face_count
    errors = attribute_errors(reference, decoded, _step(reference))
    for attribute, error in errors.items():
        bound = DEGREES if attribute in ("NORMAL", "TANGENT") else 2 / 65535
        assert error <= bound, f"{name} {compress}: {attribute} off by {error:.3g}"
    # lodserver reads its own output to the same values
    path = tmp_path / "compressed.glb"
    path.write_bytes(data)
    again, _ = load_mesh(path)
    assert attribute_errors(reference, again, _step(reference)).keys() == errors.keys()
    assert_valid(gltf_validator, data, f"{name} {compress}")
    images = sum(map(len, mesh.materials.images)) if mesh.materials is not None else 0
    assert len(data) - images < 0.75 * (len(plain.read_bytes()) - images)


def test_compressed_primitives_are_in_vertex_cache_order(shared_meshes):
    mesh, _ = load_mesh(shared_meshes / "Duck.glb")
    plain_positions, plain = decode_independently(encode_glb(mesh))[:2]
    data = encode_glb(mesh, "meshopt")
    positions, optimized = decode_independently(data)[:2]
    node = split_glb(data)[0]["nodes"][0]

    def triangles(positions, faces):
        # each triangle by its corners on the output's position grid, winding kept
        grid = np.rint((positions - node["translation"]) / node["scale"]).astype(np.int64)
        corners = [tuple(map(tuple, grid[face])) for face in faces]
        return sorted(min(c[k:] + c[:k] for k in range(3)) for c in corners)

    assert triangles(positions, optimized) == triangles(plain_positions, plain)
    # fewer vertices transformed per triangle (the strip-like order of meshopt a little
    # fewer than the progressive mesh's order, the cache order of quantize far fewer),
    # and vertices numbered as first used
    quantized = decode_independently(encode_glb(mesh, "quantize"))[1]
    assert _acmr(quantized) < 0.9 * _acmr(plain)
    assert _acmr(optimized) < _acmr(plain)
    for faces in (optimized, quantized):
        first = np.unique(faces.ravel(), return_index=True)[1]
        assert (np.diff(faces.ravel()[np.sort(first)]) == 1).all()


@pytest.mark.parametrize("compress", ["quantize", "meshopt"])
def test_compressed_chain_keeps_msft_lod_and_one_grid(tmp_path, compress,
                                                      gltf_validator):  # noqa: F811
    mesh, _ = load_mesh(DATA / "spot.obj")
    pm = build(mesh)
    ratios = [1.0, 0.5, 0.1]
    levels = [pm.at(ratio=r) for r in ratios]
    data = encode_lod_chain(levels, coverage_from_ratios(ratios), compress)
    document, _ = split_glb(data)
    assert document["nodes"][0]["extensions"]["MSFT_lod"]["ids"] == [1, 2]
    assert_valid(gltf_validator, data, f"spot's chain, {compress}")
    transforms = {json.dumps({k: n.get(k) for k in ("translation", "scale")})
                  for n in document["nodes"]}
    assert len(transforms) == 1 and "null" not in transforms.pop()
    for node, level in enumerate(levels):
        decoded = decode_independently(data, node)
        assert len(decoded[1]) == level.face_count
        assert np.abs(np.sort(decoded[0], axis=0)[[0, -1]]
                      - np.sort(level.positions, axis=0)[[0, -1]]).max() <= _step(levels[0])


def test_geometry_only_mesh_compresses_too(tmp_path):
    mesh, _ = load_mesh(DATA / "spot.obj")
    from lodserver.mesh import Mesh
    bare = Mesh(mesh.positions, mesh.faces)
    for compress in ("quantize", "meshopt"):
        decoded = decode_independently(encode_mesh(bare, "glb", compress=compress))
        assert np.abs(np.sort(decoded[0], axis=0) - np.sort(bare.positions, axis=0)).max() \
            <= _step(bare)
    with pytest.raises(MeshError, match="obj cannot be written with compress='meshopt'"):
        encode_mesh(bare, "obj", compress="meshopt")
    with pytest.raises(MeshError, match="compress must be one of none, quantize, meshopt"):
        encode_glb(bare, "zip")
    assert COMPRESSIONS == ("none", "quantize", "meshopt")


def test_export_writes_the_chosen_compression(tmp_path, capsys):
    source = DATA / "spot.obj"
    found = {}
    for compress in (None, "none", "meshopt"):
        out = tmp_path / f"{compress}.glb"
        flags = [] if compress is None else ["--compress", compress]
        assert main(["export", str(source), "-o", str(out), "--lods", "1,0.25", *flags]) == 0
        document, _ = split_glb(out.read_bytes())
        found[compress] = (document.get("extensionsRequired", []), out.stat().st_size)
        assert document["nodes"][0]["extensions"]["MSFT_lod"]["ids"] == [1]
        assert load_mesh(out)[0].face_count > 0
    assert found[None][0] == ["KHR_mesh_quantization"]          # the default: quantize
    assert found["none"][0] == []
    assert found["meshopt"][0] == ["KHR_mesh_quantization", "EXT_meshopt_compression"]
    assert found["meshopt"][1] < found[None][1] < found["none"][1]


def test_export_refuses_an_unknown_compression(tmp_path, capsys):
    with pytest.raises(SystemExit) as caught:
        main(["export", str(DATA / "spot.obj"), "-o", str(tmp_path / "x.glb"),
              "--compress", "zip"])
    assert caught.value.code == 2
    assert "invalid choice: 'zip'" in capsys.readouterr().err


@pytest.mark.skipif(not SHARED_MESHES.is_dir(), reason="shared meshes not found")
def test_scene_export_compresses_its_levels(tmp_path):
    from lodserver.io.scene import load_scene
    out = tmp_path / "fox.glb"
    assert main(["export", str(SHARED_MESHES / "scenes" / "Fox.glb"), "-o", str(out),
                 "--lods", "1,0.5", "--compress", "meshopt"]) == 0
    document, _ = split_glb(out.read_bytes())
    assert "EXT_meshopt_compression" in document["extensionsRequired"]
    scene = load_scene(out)
    assert [m.face_count for m in scene.meshes.values()]
    assert "skins" in document and "animations" in document


def test_equal_materials_share_one_primitive():
    from lodserver.mesh import Materials, Mesh
    mesh, _ = load_mesh(DATA / "spot.obj")
    red = {"pbrMetallicRoughness": {"baseColorFactor": [1, 0, 0, 1]}}
    blue = {"pbrMetallicRoughness": {"baseColorFactor": [0, 0, 1, 1]}}
    materials = Materials({"materials": [red, dict(red), blue], "textures": [], "samplers": [],
                           "images": []}, ())
    face_material = (np.arange(mesh.face_count) % 3).astype(np.int32)
    painted = Mesh(mesh.positions, mesh.faces, mesh.attributes, face_material, materials)
    plain, _ = split_glb(encode_glb(painted))
    assert [p["material"] for p in plain["meshes"][0]["primitives"]] == [0, 1, 2]
    for compress in ("quantize", "meshopt"):
        data = encode_glb(painted, compress)
        document, _ = split_glb(data)
        primitives = document["meshes"][0]["primitives"]
        assert [p["material"] for p in primitives] == [0, 2]
        assert len(document["materials"]) == 3        # the list as it was
        # the primitives read back from their shared views (accessor byteOffsets)
        decoded = as_mesh(decode_independently(data), painted.attributes.layout, materials)
        assert decoded.face_count == mesh.face_count
        errors = attribute_errors(painted, decoded, _step(painted))
        assert errors["TEXCOORD_0"] <= 2 / 65535


@pytest.mark.parametrize("compress", ["quantize", "meshopt"])
def test_extract_writes_the_chosen_compression(tmp_path, capsys, compress,
                                               gltf_validator):  # noqa: F811
    """``extract --compress``: one level, decoded by meshoptimizer's package to the
    level ``extract`` writes uncompressed, its triangles in vertex cache order."""
    asset = tmp_path / "spot.pm"
    assert main(["build", str(DATA / "spot.obj"), "-o", str(asset)]) == 0
    plain, packed = tmp_path / "plain.glb", tmp_path / f"{compress}.glb"
    assert main(["extract", str(asset), "--ratio", "0.25", "-o", str(plain)]) == 0
    assert main(["extract", str(asset), "--ratio", "0.25", "-o", str(packed),
                 "--compress", compress]) == 0
    data = packed.read_bytes()
    document, _ = split_glb(data)
    assert "KHR_mesh_quantization" in document["extensionsRequired"]
    assert ("EXT_meshopt_compression" in document["extensionsRequired"]) == \
        (compress == "meshopt")
    reference, _ = load_mesh(plain)
    decoded = as_mesh(decode_independently(data), reference.attributes.layout,
                      reference.materials)
    assert decoded.face_count == reference.face_count
    errors = attribute_errors(reference, decoded, _step(reference))
    assert errors and all(error <= 2 / 65535 for name, error in errors.items()
                          if name.startswith("TEXCOORD"))
    faces = decode_independently(data)[1]
    assert _acmr(faces) < _acmr(decode_independently(plain.read_bytes())[1])
    assert_valid(gltf_validator, data, f"extract --compress {compress}")
    image = len((DATA / "spot_texture.png").read_bytes())
    assert len(data) - image < 0.75 * (len(plain.read_bytes()) - image)
    capsys.readouterr()
    assert main(["extract", str(asset), "--ratio", "0.25", "-o", str(tmp_path / "x.ply"),
                 "--compress", compress]) == 1
    err = capsys.readouterr().err
    assert "ply cannot be written with compress" in err and len(err.strip().splitlines()) == 1
