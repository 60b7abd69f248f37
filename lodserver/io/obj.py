"""Reading OBJ files and their MTL materials.

A small reader of its own (``v``, ``vt``, ``vn``, ``f``, ``usemtl``,
``mtllib``): trimesh's OBJ loader splits vertices along UV and normal seams and
drops unreferenced vertices, so its vertex counts would not be the file's and
the :class:`~.clean.LoadReport` would not say what the cleaning did. ``vt`` v
is flipped to glTF's convention (``v_gltf = 1 - v_obj``); MTL ``Kd``,
``d``/``Tr`` and ``map_Kd`` become glTF metallic-roughness materials. Vertex
colours are display (sRGB) values by convention and are converted to linear.

``v`` and ``f`` lines are counted in the bytes before any list is built, and
``mtllib`` and ``map_Kd`` files are read by the rule of :mod:`.references`.
"""

from __future__ import annotations

import os
import re
from io import BytesIO
from pathlib import Path

import numpy as np

from ..mesh import Materials, MeshError
from .clean import fan_triangulate, srgb_to_linear
from .gltf import face_normals
from .images import image_type
from .limits import LoadLimits
from .references import MissingReferenceError, read_reference, resolve_reference


# Image formats converted to PNG for glTF, and the most pixels converted (8192 x 8192).
_CONVERTIBLE = ("BMP", "TGA", "TIFF", "GIF", "PPM", "WEBP", "SGI", "PCX")


_MAX_CONVERTED_PIXELS = 1 << 26


# MTL map options and how many values follow each (-o, -s, -t take up to 3).
_MTL_MAP_OPTIONS = {"-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1,
                    "-imfchan": 1, "-mm": 2, "-texres": 1, "-o": 3, "-s": 3, "-t": 3}


def read_obj(path: Path, root: Path | None = None, limits: LoadLimits | None = None) -> dict:
    """Positions (n, 3) of the ``v`` lines and triangles (m, 3) of the ``f`` lines,
    with per-corner ``vt``/``vn``, vertex colours and ``usemtl`` materials where present.

    ``v`` and ``f`` lines are counted in the raw bytes first, so a file of
    millions of vertices and one face is refused before Python holds a list
    of them (about 200 bytes a vertex).
    """
    limits = limits or LoadLimits.unbounded()
    raw = path.read_bytes()
    limits.check("max_vertices", _count_lines(raw, b"v"), "vertices ('v' lines)")
    # each 'f' line is a triangle at least; polygons are counted exactly below
    limits.check("max_triangles", _count_lines(raw, b"f"), "triangles or more ('f' lines)")
    text = re.sub(r"\\\r?\n", " ", raw.decode("utf-8", errors="replace"))
    del raw
    rows, corners, sizes, defined_before = [], [], [], []
    uvs, normals, colours, material_runs, libraries = [], [], {}, [], []
    # (face, vt count, vn count) for faces with v/vt/vn references only, so that
    # files without them pay nothing for resolving relative vt/vn indices
    slashed = []
    for number, line in enumerate(text.splitlines(), 1):
        parts = line.split()
        if not parts:
            continue
        key = parts[0]
        if key == "v":
            if len(parts) < 4:
                raise MeshError(
                    f"line {number} is a vertex with fewer than 3 coordinates"
                )
            rows.append(parts[1:4])
            if len(parts) == 7:  # "v x y z r g b", the usual vertex colour extension
                colours[len(rows) - 1] = parts[4:7]
        elif key == "f":
            if len(parts) < 4:
                raise MeshError(f"line {number} is a face with fewer than 3 vertices")
            if "/" in line:
                slashed.append((len(sizes), len(uvs), len(normals)))
            corners.extend(parts[1:])
            sizes.append(len(parts) - 1)
            defined_before.append(len(rows))
        elif key == "vt":
            if len(parts) < 2:
                raise MeshError(f"line {number} is a texture coordinate without values")
            uvs.append(parts[1:3] if len(parts) > 2 else [parts[1], "0"])
        elif key == "vn":
            if len(parts) < 4:
                raise MeshError(f"line {number} is a normal with fewer than 3 coordinates")
            normals.append(parts[1:4])
        elif key == "usemtl":
            name = line.split(None, 1)[1].strip() if len(parts) > 1 else ""
            material_runs.append((len(sizes), name))
        elif key == "mtllib" and len(parts) > 1:
            libraries.append(line.split(None, 1)[1].strip())
    if not sizes:
        raise MeshError(f"it has no faces ({len(rows)} vertices, no 'f' lines)")
    try:
        positions = np.array(rows, dtype=np.float64)
    except ValueError as exc:
        raise MeshError(f"a vertex coordinate is not a number ({exc})") from exc
    sizes = np.array(sizes, dtype=np.int64)
    limits.check("max_triangles", int((sizes - 2).sum()), "triangles (its polygons fanned)")
    # OBJ indices are 1-based; negative ones count back from the last element so far.
    vertex_base = np.repeat(np.array(defined_before, dtype=np.int64), sizes)
    if not slashed:
        indices = _obj_indices(corners, vertex_base, len(positions), "vertices")
        arrays = {"positions": positions, "faces": fan_triangulate(indices, sizes)}
        uv_index = normal_index = None
    else:
        fields = [corner.split("/") for corner in corners]
        indices = _obj_indices([f[0] for f in fields], vertex_base, len(positions), "vertices")
        face, uv_count, normal_count = np.array(slashed, dtype=np.int64).T
        uv_base, normal_base = np.zeros((2, len(sizes)), dtype=np.int64)
        uv_base[face], normal_base[face] = uv_count, normal_count
        uv_index = _obj_indices([f[1] if len(f) > 1 and f[1] else "0" for f in fields],
                                np.repeat(uv_base, sizes), len(uvs), "texture coordinates",
                                optional=True)
        normal_index = _obj_indices([f[2] if len(f) > 2 and f[2] else "0" for f in fields],
                                    np.repeat(normal_base, sizes), len(normals), "normals",
                                    optional=True)
        triangles = fan_triangulate(np.arange(len(indices)), sizes)  # corner numbers
        arrays = {"positions": positions, "faces": indices[triangles]}
        uv_index, normal_index = uv_index[triangles], normal_index[triangles]
    arrays.update(_obj_corner_values(arrays["positions"], arrays["faces"], uv_index, uvs,
                                     normal_index, normals, colours))
    if material_runs or libraries:
        arrays.update(_obj_materials(material_runs, libraries, path.parent, sizes, root, limits))
    return arrays


def _obj_indices(tokens: list, base: np.ndarray, count: int, what: str,
                 optional: bool = False) -> np.ndarray:
    """0-based indices (k,) of OBJ corner references; -1 where an optional one is absent (0)."""
    try:
        raw = np.array(tokens).astype(np.int64)
    except (ValueError, OverflowError) as exc:  # "1e23" or 99999999999999999999
        raise MeshError(f"a face {what} index is not an integer ({exc})") from exc
    indices = np.where(raw > 0, raw - 1, base + raw)
    absent = (raw == 0) if optional else np.zeros(len(raw), dtype=bool)
    bad = ~absent & ((raw == 0) | (indices < 0) | (indices >= count))
    if bad.any():
        raise MeshError(
            f"{int(bad.sum())} face corners refer to {what} that do not exist (the "
            f"file has {count} {what}; first bad index {int(raw[bad][0])})"
        )
    return np.where(absent, -1, indices)


def _obj_corner_values(positions, faces, uv_index, uvs, normal_index, normals, colours) -> dict:
    """``corner_values``/``layout`` from OBJ ``vn``, ``vt`` and ``v`` colours; {} if none.

    A corner without a ``vn`` gets its face's flat normal and one without a
    ``vt`` gets (0, 0), so that faces which have them keep them.
    """
    layout, columns, dropped = [], [], []
    if normal_index is not None and (normal_index >= 0).any():
        try:
            table = np.array(normals, dtype=np.float64)
        except ValueError as exc:
            raise MeshError(f"a normal coordinate is not a number ({exc})") from exc
        corner = table[normal_index]
        missing = normal_index < 0
        if missing.any():
            flat = np.broadcast_to(face_normals(positions, faces)[:, None], corner.shape)
            corner[missing] = flat[missing]
        layout.append(("NORMAL", 3))
        columns.append(corner)
    if uv_index is not None and (uv_index >= 0).any():
        try:
            table = np.array(uvs, dtype=np.float64)
        except ValueError as exc:
            raise MeshError(f"a texture coordinate is not a number ({exc})") from exc
        table[:, 1] = 1.0 - table[:, 1]  # OBJ's v points up, glTF's down
        corner = table[uv_index]
        corner[uv_index < 0] = 0.0
        layout.append(("TEXCOORD_0", 2))
        columns.append(corner)
    if colours and len(colours) == len(positions):
        try:
            rgb = np.array([colours[i] for i in range(len(positions))], dtype=np.float64)
        except ValueError as exc:
            raise MeshError(f"a vertex colour is not a number ({exc})") from exc
        if rgb.size and rgb.max() > 1.0:
            rgb = rgb / 255.0  # some writers use 0..255
        rgba = np.column_stack([srgb_to_linear(np.clip(rgb, 0.0, 1.0)), np.ones(len(rgb))])
        layout.append(("COLOR_0", 4))
        columns.append(rgba[faces])
    elif colours:
        dropped.append("COLOR_0")  # colours on some vertices only: no colour for the rest
    arrays = {"dropped_attributes": dropped}
    if layout:
        arrays.update(corner_values=np.concatenate(columns, axis=2), layout=tuple(layout))
    return arrays


def _count_lines(data: bytes, key: bytes) -> int:
    """How many lines of ``data`` start with the keyword ``key`` (then a space or tab)."""
    count = sum(data.count(b"\n" + key + gap) for gap in (b" ", b"\t"))
    return count + any(data.startswith(key + gap) for gap in (b" ", b"\t"))


def _obj_materials(material_runs: list, libraries: list, folder: Path, sizes: np.ndarray,
                   root: Path | None = None, limits: LoadLimits | None = None) -> dict:
    """Materials of the ``mtllib`` files and the face material of each triangle.

    Every material of every library is kept, in file order, then any ``usemtl``
    name no library defines (as a plain material of that name). Faces before the
    first ``usemtl`` (or after ``usemtl`` with no name) have none (-1). A missing
    library is reported, not an error: the mesh is still usable. A missing
    texture is an error: its material would silently lose its look.
    """
    limits = limits or LoadLimits.unbounded()
    records, textures, images, image_index, missing = [], [], [], {}, []
    # each library and each texture is read once, however many lines name it
    libraries_read = set()
    for library in libraries:
        for file, data in _mtl_files(library, folder, missing, root, limits, libraries_read):
            for name, properties in _read_mtl(data):
                record = _mtl_record(name, properties)
                if "map_Kd" in properties:
                    key, data, label = _mtl_texture(properties["map_Kd"], file.parent, name,
                                                    root, limits, known=image_index)
                    if key not in image_index:
                        data, mime = _gltf_image(data, label)
                        image_index[key] = len(images)
                        images.append((data, {"mimeType": mime, "name": label}))
                        textures.append({"source": image_index[key]})
                    # one texture per image, so the two share an index
                    record["pbrMetallicRoughness"]["baseColorTexture"] = {"index": image_index[key]}
                records.append(record)
    index = {record["name"]: i for i, record in reversed(list(enumerate(records)))}
    for _, name in material_runs:
        if name and name not in index:
            index[name] = len(records)
            records.append(_mtl_record(name, {}))
    result = {"missing_files": missing}
    if not records:
        return result
    # a polygon takes the material of the last usemtl before it; run 0 is "before any"
    run_material = np.array([-1] + [index[name] if name else -1 for _, name in material_runs],
                            dtype=np.int32)
    starts = np.array([start for start, _ in material_runs], dtype=np.int64)
    polygon_material = run_material[np.searchsorted(starts, np.arange(len(sizes)), side="right")]
    gltf = {"materials": records, "textures": textures, "samplers": [],
            "images": [record for _, record in images]}
    result.update(materials=Materials(gltf, tuple(data for data, _ in images)),
                  face_material=np.repeat(polygon_material, sizes - 2).astype(np.int32))
    return result


def _mtl_files(library: str, folder: Path, missing: list, root: Path | None,
               limits: LoadLimits, read_before: set) -> list[tuple[Path, bytes]]:
    """The files an ``mtllib`` line names (several may share a line) and their bytes,
    noting missing ones and skipping those in ``read_before`` (then adding them); a
    name that may not be read (see :mod:`.references`) is an error."""
    def read(name: str):
        file = resolve_reference(name, folder, root, "material library", url=False)
        if file in read_before:
            return None
        data = read_reference(file, name, "material library", limit=limits.max_file_bytes,
                              follow=root is None)
        read_before.add(file)
        return file, data

    try:
        found = [read(library)]
    except MissingReferenceError:
        found = []
        for name in library.split():
            try:
                found.append(read(name))
            except MissingReferenceError:
                missing.append(name)
    return [item for item in found if item is not None]


def _read_mtl(data: bytes) -> list[tuple[str, dict]]:
    """``(name, {"Kd": [r, g, b], "d": a, "Tr": t, "map_Kd": [args]})`` per ``newmtl``."""
    materials = []
    for line in data.decode("utf-8", errors="replace").splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "newmtl":
            materials.append((line.split(None, 1)[1].strip() if len(parts) > 1 else "", {}))
        elif materials and parts[0] in ("Kd", "d", "Tr") and len(parts) > 1:
            try:
                values = [float(value) for value in parts[1:4]]
            except ValueError:
                continue  # e.g. "Kd spectral file.rfl": not a colour we can use
            materials[-1][1][parts[0]] = values if parts[0] == "Kd" else values[0]
        elif materials and parts[0] == "map_Kd" and len(parts) > 1:
            materials[-1][1]["map_Kd"] = parts[1:]
    return materials


def _mtl_record(name: str, properties: dict) -> dict:
    """A glTF metallic-roughness material for MTL ``Kd`` and ``d``/``Tr`` (matte, not metal)."""
    kd = properties.get("Kd", [1.0, 1.0, 1.0])
    kd = (kd * 3)[:3] if len(kd) < 3 else kd  # "Kd 0.5" means grey
    alpha = properties.get("d", 1.0 - properties.get("Tr", 0.0))
    colour = [*srgb_to_linear(np.clip(kd, 0.0, 1.0)).tolist(), float(np.clip(alpha, 0.0, 1.0))]
    record = {"name": name, "pbrMetallicRoughness": {
        "baseColorFactor": colour, "metallicFactor": 0.0, "roughnessFactor": 1.0}}
    if colour[3] < 1.0:
        record["alphaMode"] = "BLEND"
    return record


def _mtl_texture(arguments: list, folder: Path, material: str, root: Path | None = None,
                 limits: LoadLimits | None = None, known=()) -> tuple[Path, bytes | None, str]:
    """The resolved path, bytes and file name of a ``map_Kd`` (options skipped);
    no bytes (None) for a path in ``known``, which is not read again."""
    limits = limits or LoadLimits.unbounded()
    at = 0
    while at < len(arguments) - 1 and arguments[at] in _MTL_MAP_OPTIONS:
        taken = 1
        # -o/-s/-t take one to three numbers; the others a fixed count
        while taken <= _MTL_MAP_OPTIONS[arguments[at]] and at + taken < len(arguments) - 1:
            if _MTL_MAP_OPTIONS[arguments[at]] == 3:
                try:
                    float(arguments[at + taken])
                except ValueError:
                    break
            taken += 1
        at += taken
    name = " ".join(arguments[at:])
    what = f"material {material!r} texture"
    try:
        resolved = resolve_reference(name, folder, root, what, url=False)
        file = Path(os.path.abspath(resolved))
        data = None if file in known else read_reference(
            resolved, name, what, limit=limits.max_file_bytes, follow=root is None)
    except MissingReferenceError:
        raise MeshError(f"its material {material!r} uses the texture {name!r}, "
                        "which is missing") from None
    return file, data, Path(name.replace("\\", "/")).name


def _gltf_image(data: bytes, name: str) -> tuple[bytes, str]:
    """Image bytes glTF can carry (PNG or JPEG, byte for byte) and their mimeType.

    Other formats (TGA, BMP, ...) are re-encoded as PNG with Pillow, if installed:
    only the plain raster formats of :data:`_CONVERTIBLE` (Pillow would also
    hand EPS to Ghostscript), and only up to :data:`_MAX_CONVERTED_PIXELS`
    pixels, checked from the header before anything is decoded.
    """
    mime = image_type(data)
    if mime in ("image/png", "image/jpeg"):
        return data, mime
    try:
        from PIL import Image
    except ImportError:
        raise MeshError(f"its texture {name!r} is neither PNG nor JPEG, the formats glTF "
                        "carries; convert it, or install Pillow to have it converted") from None
    try:
        converted = BytesIO()
        image = Image.open(BytesIO(data), formats=_CONVERTIBLE)
        width, height = image.size
        if width * height > _MAX_CONVERTED_PIXELS:
            raise MeshError(f"its texture {name!r} has {width} x {height} pixels; at most "
                            f"{_MAX_CONVERTED_PIXELS} are converted")
        image.save(converted, format="PNG")
    except MeshError:
        raise
    except Exception as exc:  # Pillow raises many kinds on an unreadable image
        raise MeshError(f"its texture {name!r} is neither PNG nor JPEG and could not be "
                        f"converted ({type(exc).__name__}: {exc})") from exc
    return converted.getvalue(), "image/png"
