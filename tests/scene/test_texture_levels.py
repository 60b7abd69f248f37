"""Texture levels (``export --texture-scale``, ``scene.textures``, ``io.image_scale``):
each level's images at its size, in their format, filtered as their role needs,
KTX2 kept as it is, each (image, size) written once."""

import io
import json
import struct

import numpy as np
import pytest
from PIL import Image

from lodserver.cli import main
from lodserver.io.image_scale import image_size, scaled_image
from lodserver.io.images import image_type
from lodserver.mesh import Materials, MeshError
from lodserver.scene.textures import (TextureLevels, scaled_size, texture_levels,
                                      texture_scales)

from ..io.test_gltf import assert_valid, gltf_validator  # noqa: F401 (a fixture)
from ..meshes import DATA

KTX2 = b"\xabKTX 20\xbb\r\n\x1a\n" + bytes(range(64))


def _document(data: bytes) -> tuple[dict, bytes]:
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length]), data[20 + length + 8:]


def _images(document: dict, binary: bytes) -> list[bytes]:
    out = []
    for image in document.get("images", ()):
        view = document["bufferViews"][image["bufferView"]]
        start = view.get("byteOffset", 0)
        out.append(binary[start:start + view["byteLength"]])
    return out


def _encoded(image: Image.Image, kind: str, **options) -> bytes:
    out = io.BytesIO()
    image.save(out, kind, **options)
    return out.getvalue()


def _materials(images: list[bytes], roles=("baseColorTexture",)) -> Materials:
    """One material naming image k by slot ``roles[k]`` (normalTexture at the top)."""
    material = {"pbrMetallicRoughness": {}}
    for index, role in enumerate(roles):
        if role in ("normalTexture", "emissiveTexture"):
            material[role] = {"index": index}
        else:
            material["pbrMetallicRoughness"][role] = {"index": index}
    gltf = {"materials": [material], "textures": [{"source": k} for k in range(len(images))],
            "images": [{"mimeType": image_type(data) or "image/ktx2", "name": f"i{k}.png"}
                       for k, data in enumerate(images)]}
    return Materials(gltf, tuple(images))


def test_auto_scales_follow_the_square_root_of_the_face_share():
    assert texture_scales("auto", [1000, 500, 200, 50]) == [1.0, 1.0, 0.5, 0.25]
    assert texture_scales("auto", [1000, 1000]) == [1.0, 1.0]
    assert texture_scales((1, 0.5), [10, 5]) == [1.0, 0.5]
    with pytest.raises(MeshError, match="2 levels need 2 texture scales, got 3"):
        texture_scales((1, 0.5, 0.25), [10, 5])
    assert scaled_size((2048, 1024), 0.25) == (512, 256)
    assert scaled_size((128, 100), 0.25) == (64, 64)           # at least 64 px
    assert scaled_size((40, 1000), 0.5) == (40, 512)           # never above the original
    assert scaled_size((1000, 600), 1.0) == (1000, 600)        # full size: untouched


@pytest.mark.parametrize("kind, options", [("PNG", {}), ("JPEG", {"quality": 85}),
                                           ("WEBP", {"lossless": True}),
                                           ("WEBP", {"quality": 80})])
def test_formats_are_kept(kind, options):
    rng = np.random.default_rng(1)
    pixels = rng.integers(0, 255, (256, 256, 3), dtype=np.uint8)
    data = _encoded(Image.fromarray(pixels, "RGB"), kind, **options)
    small = scaled_image(data, (128, 64), "data")
    assert image_type(small) == image_type(data)
    assert image_size(small) == (128, 64)
    if kind == "WEBP":      # lossless stays lossless, lossy stays lossy
        assert (small[12:16] == b"VP8L") == bool(options.get("lossless"))
    if kind == "JPEG":
        from PIL import JpegImagePlugin
        with Image.open(io.BytesIO(small)) as image, Image.open(io.BytesIO(data)) as source:
            assert JpegImagePlugin.get_sampling(image) == JpegImagePlugin.get_sampling(source)


def test_base_colour_is_filtered_in_linear_light():
    # black and white texels averaged: half the light, which sRGB encodes as 188, not 128
    checker = (np.indices((256, 256)).sum(axis=0) % 2 * 255).astype(np.uint8)
    data = _encoded(Image.fromarray(np.dstack([checker] * 3), "RGB"), "PNG")
    colour = np.asarray(Image.open(io.BytesIO(scaled_image(data, (64, 64), "colour"))))
    plain = np.asarray(Image.open(io.BytesIO(scaled_image(data, (64, 64), "data"))))
    assert abs(float(np.median(colour)) - 188) <= 2
    assert abs(float(np.median(plain)) - 128) <= 2


def test_normal_maps_stay_unit_vectors():
    rng = np.random.default_rng(2)
    vectors = rng.normal(size=(128, 128, 3)) + [0, 0, 2.5]
    vectors /= np.linalg.norm(vectors, axis=2, keepdims=True)
    data = _encoded(Image.fromarray(np.rint((vectors + 1) * 127.5).astype(np.uint8), "RGB"), "PNG")
    small = np.asarray(Image.open(io.BytesIO(scaled_image(data, (64, 64), "normal"))))
    lengths = np.linalg.norm(small / 127.5 - 1.0, axis=2)
    assert np.abs(lengths - 1.0).max() < 0.02
    # the same texels filtered as data average to shorter vectors
    plain = np.asarray(Image.open(io.BytesIO(scaled_image(data, (64, 64), "data"))))
    assert np.linalg.norm(plain / 127.5 - 1.0, axis=2).mean() < 0.97


def test_ktx2_is_kept_untouched_and_said():
    png = _encoded(Image.new("RGB", (512, 512), (200, 10, 10)), "PNG")
    levels = TextureLevels(_materials([png, KTX2], ("baseColorTexture", "normalTexture")),
                           [1.0, 0.5, 0.25])
    assert any("KTX2" in note for note in levels.notes)
    for k, materials in enumerate(levels.separate):
        assert materials.images[1] == KTX2
        assert image_size(materials.images[0]) == (512 >> k, 512 >> k)
    # one file: the KTX2 image once, the PNG once per size
    assert levels.chain.images.count(KTX2) == 1 and len(levels.chain.images) == 4
    assert levels.offsets == [0, 1, 2]
    textures = levels.chain.gltf["textures"]
    for k, offset in enumerate(levels.offsets):
        material = levels.chain.gltf["materials"][offset]
        colour = textures[material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
        normal = textures[material["normalTexture"]["index"]]
        assert image_size(levels.chain.images[colour["source"]]) == (512 >> k, 512 >> k)
        assert levels.chain.images[normal["source"]] == KTX2


def test_nothing_to_scale_is_none():
    png = _encoded(Image.new("RGB", (64, 64)), "PNG")
    assert texture_levels(_materials([png]), None, [10, 5]) is None
    assert texture_levels(None, "auto", [10, 5]) is None
    assert texture_levels(_materials([png]), "auto", [10, 10]) is None
    # a 64 px image is at its smallest already: every level names the one image
    levels = texture_levels(_materials([png]), "auto", [1000, 10])
    assert len(levels.chain.images) == 1 and levels.offsets == [0, 0]


def test_export_separate_levels_have_scaled_images(shared_meshes, tmp_path,
                                                   gltf_validator):  # noqa: F811
    out = tmp_path / "avocado.glb"
    assert main(["export", str(shared_meshes / "Avocado" / "Avocado.gltf"), "-o", str(out),
                 "--lods", "1,0.2,0.05", "--separate", "--texture-scale", "auto"]) == 0
    sizes, faces = [], []
    for k in range(3):
        data = (tmp_path / f"avocado_lod{k}.glb").read_bytes()
        document, binary = _document(data)
        images = _images(document, binary)
        assert [image_type(image) for image in images] == ["image/png"] * 3
        sizes.append({image_size(image) for image in images})
        faces.append(sum(document["accessors"][p["indices"]]["count"] // 3
                         for mesh in document["meshes"] for p in mesh["primitives"]))
        assert_valid(gltf_validator, data, f"avocado level {k}")
    for k, scale in enumerate(texture_scales("auto", faces)):
        side = scaled_size((2048, 2048), scale)
        assert sizes[k] == {side}
    assert sizes[0] == {(2048, 2048)} and max(sizes[-1]) < (2048, 2048)


def test_export_one_file_names_each_levels_images(tmp_path, gltf_validator):  # noqa: F811
    out = tmp_path / "spot.glb"
    assert main(["export", str(DATA / "spot.obj"), "-o", str(out), "--lods", "1,0.2,0.05",
                 "--texture-scale", "1,0.5,0.5", "--compress", "meshopt"]) == 0
    data = out.read_bytes()
    document, binary = _document(data)
    images = _images(document, binary)
    assert sorted(image_size(image) for image in images) == [(512, 512), (1024, 1024)]
    for k, mesh in enumerate(document["meshes"]):
        for primitive in mesh["primitives"]:
            material = document["materials"][primitive["material"]]
            texture = document["textures"][
                material["pbrMetallicRoughness"]["baseColorTexture"]["index"]]
            wanted = (1024, 1024) if k == 0 else (512, 512)
            assert image_size(images[texture["source"]]) == wanted
    assert_valid(gltf_validator, data, "spot with texture levels")


def test_bad_texture_scales_are_usage_errors(tmp_path, capsys):
    for flag in ("big", "1,2", "0,0.5"):
        with pytest.raises(SystemExit) as caught:
            main(["export", str(DATA / "spot.obj"), "-o", str(tmp_path / "x.glb"),
                  "--texture-scale", flag])
        assert caught.value.code == 2
        assert "texture scale" in capsys.readouterr().err
    assert main(["export", str(DATA / "spot.obj"), "-o", str(tmp_path / "x.glb"),
                 "--lods", "1,0.5", "--texture-scale", "1,0.5,0.25"]) == 1
    assert "2 levels need 2 texture scales, got 3" in capsys.readouterr().err
    assert not (tmp_path / "x.glb").exists()


def test_a_folder_rebuilds_when_the_texture_scale_changes(tmp_path):
    from lodserver.pipeline import export_folder

    folder = tmp_path / "assets"
    folder.mkdir()
    for name in ("spot.obj", "spot.mtl", "spot_texture.png"):
        (folder / name).write_bytes((DATA / name).read_bytes())
    runs = [export_folder(folder, tmp_path / "lods", lods=(1, 0.1), texture_scale=scale)
            for scale in (None, None, "auto", "auto")]
    assert [len(run.written) for run in runs] == [1, 0, 1, 0]
    document, binary = _document((tmp_path / "lods" / "spot.glb").read_bytes())
    assert sorted(image_size(image) for image in _images(document, binary)) == \
        [(256, 256), (1024, 1024)]


def test_an_image_declaring_a_huge_size_is_kept_not_decoded():
    import struct as bytes_layout
    import zlib

    png = bytearray(_encoded(Image.new("RGB", (512, 512)), "PNG"))
    # IHDR (at byte 8: length, type, then width and height) rewritten to 60000 x 60000
    header = bytes(png[12:16]) + bytes_layout.pack(">II", 60000, 60000) + bytes(png[24:29])
    png[16:29] = header[4:]
    png[29:33] = bytes_layout.pack(">I", zlib.crc32(header) & 0xFFFFFFFF)
    bomb = bytes(png)
    with pytest.raises(MeshError, match="image"):
        scaled_image(bomb, (64, 64))
    levels = TextureLevels(_materials([bomb]), [1.0, 0.25])
    assert levels.separate[1].images == (bomb,) and levels.notes


def test_a_webp_texture_with_its_png_fallback_is_scaled_in_both():
    """EXT_texture_webp: the texture's extension names the WebP image, ``source`` its
    PNG fallback; both are scaled, each level's texture naming its own pair."""
    pixels = Image.new("RGB", (256, 256), (30, 120, 200))
    png, webp = _encoded(pixels, "PNG"), _encoded(pixels, "WEBP", quality=80)
    gltf = {"materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
            "textures": [{"source": 0, "extensions": {"EXT_texture_webp": {"source": 1}}}],
            "images": [{"mimeType": "image/png"}, {"mimeType": "image/webp"}]}
    levels = TextureLevels(Materials(gltf, (png, webp)), [1.0, 0.5])
    for k, materials in enumerate(levels.separate):
        [texture] = materials.gltf["textures"]
        fallback = materials.images[texture["source"]]
        preferred = materials.images[texture["extensions"]["EXT_texture_webp"]["source"]]
        assert image_type(fallback) == "image/png" and image_type(preferred) == "image/webp"
        assert image_size(fallback) == image_size(preferred) == (256 >> k, 256 >> k)
    chain = levels.chain.gltf
    second = chain["textures"][chain["materials"][levels.offsets[1]]["pbrMetallicRoughness"]
                               ["baseColorTexture"]["index"]]
    assert image_size(levels.chain.images[second["extensions"]["EXT_texture_webp"]["source"]]) \
        == (128, 128)
