"""One encoded image made smaller, in its own format: the texture levels' resampler.

:func:`scaled_image` decodes a PNG, JPEG or WebP image with Pillow, resamples it
to a given size with a Lanczos filter (the sharpest of Pillow's filters that
does not alias when shrinking) and encodes it again in the format it came in.
How a texel is filtered depends on what it holds (:data:`ROLES`):

- ``"colour"`` (base colour, emissive): sRGB-encoded, so each colour channel is
  taken to linear light, filtered there and encoded back; filtering the encoded
  values would darken every edge between light and dark texels. Alpha is
  filtered as it is (it is linear already).
- ``"normal"``: tangent-space vectors; filtered as vectors in [-1, 1] and made
  unit length again, since an average of unit vectors is shorter.
- ``"data"`` (metallic-roughness, occlusion and any other): filtered channel by
  channel as it is.

KTX2 (Basis Universal) is not decoded here: a supercompressed texture cannot
be resampled without transcoding it, so the caller keeps it as it is.
"""

from __future__ import annotations

import io

import numpy as np

from ..mesh import MeshError
from .images import image_type

# What a texture's texels hold, by how they must be filtered (see the module docstring).
ROLES = ("colour", "normal", "data")
# Images are decoded whole, in float32 per channel: this many pixels at most (a
# 8192 x 8192 texture), so that a file declaring a huge size is refused before decoding.
MAX_PIXELS = 8192 * 8192
# JPEG and lossy WebP are encoded again at this quality: above what web encoders
# usually write, so the second encoding adds no loss a viewer sees at the smaller size.
LOSSY_QUALITY = 90
# media type -> Pillow's format name
_FORMATS = {"image/png": "PNG", "image/jpeg": "JPEG", "image/webp": "WEBP"}


def image_size(data) -> tuple[int, int] | None:
    """(width, height) in pixels of a PNG, JPEG or WebP image, from its header
    alone (nothing decoded); None for KTX2 or bytes Pillow cannot read."""
    from PIL import Image

    if _FORMATS.get(image_type(data)) is None:
        return None
    try:
        with Image.open(io.BytesIO(bytes(data))) as image:
            return image.size
    except (OSError, ValueError, Image.DecompressionBombError):
        return None


def scaled_image(data, size: tuple[int, int], role: str = "data") -> bytes:
    """``data`` (PNG, JPEG or WebP bytes) resampled to ``size`` = (width, height)
    pixels, encoded in the same format: :func:`scaled_images` of one size."""
    return scaled_images(data, [size], role)[0]


def scaled_images(data, sizes, role: str = "data") -> list[bytes]:
    """``data`` (PNG, JPEG or WebP bytes) resampled to each of ``sizes`` ((width,
    height) pixels), each encoded in the same format; the image is decoded once.

    PNG keeps its channels (a palette image is filtered in RGB or RGBA and given a
    palette of 256 colours again); JPEG keeps its chroma subsampling and ICC
    profile, at :data:`LOSSY_QUALITY`; WebP stays lossless when it was (a ``VP8L``
    stream), else at :data:`LOSSY_QUALITY`. Raises MeshError (one sentence) for
    another format, a ``role`` not in :data:`ROLES`, more than :data:`MAX_PIXELS`
    pixels or bytes Pillow cannot decode.
    """
    from PIL import Image, JpegImagePlugin

    kind = image_type(data)
    if kind not in _FORMATS:
        raise MeshError(f"only PNG, JPEG and WebP images can be resampled, not {kind}")
    if role not in ROLES:
        raise MeshError(f"an image's role is one of {', '.join(ROLES)}, got {role!r}")
    try:
        with Image.open(io.BytesIO(bytes(data))) as image:
            if image.width * image.height > MAX_PIXELS:
                raise MeshError(f"a {image.width} x {image.height} image is over the "
                                f"{MAX_PIXELS} pixels images are resampled up to")
            options = {}
            if kind == "image/jpeg":
                sampling = JpegImagePlugin.get_sampling(image)
                options = {"quality": LOSSY_QUALITY,
                           **({"subsampling": sampling} if sampling >= 0 else {})}
            elif kind == "image/webp":
                lossless = bytes(data[12:16]) == b"VP8L"
                options = {"lossless": True} if lossless else {"quality": LOSSY_QUALITY}
            if image.info.get("icc_profile"):
                options["icc_profile"] = image.info["icc_profile"]
            image.load()
            palette = image.mode == "P"
            plain = _plain_mode(image)
            bands = _bands(plain, role)
            smalls = [_resampled(bands, plain.mode, (int(w), int(h)), role) for w, h in sizes]
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise MeshError(f"cannot resample this {kind} image: {exc}") from None
    out = []
    for small in smalls:
        if palette:     # a palette PNG stays one: far fewer bytes than RGB
            small = small.quantize(256, method=Image.Quantize.FASTOCTREE
                                   if small.mode == "RGBA" else Image.Quantize.MEDIANCUT)
        buffer = io.BytesIO()
        small.save(buffer, _FORMATS[kind], **options)
        out.append(buffer.getvalue())
    return out


def _plain_mode(image):
    """``image`` in a mode of 8 bits per channel, L, LA, RGB or RGBA (16-bit grey as
    it is, I;16): what the filters below work on."""
    if image.mode in ("L", "LA", "RGB", "RGBA", "I;16"):
        return image
    if image.mode == "P":
        return image.convert("RGBA" if "transparency" in image.info else "RGB")
    if image.mode in ("1",):
        return image.convert("L")
    return image.convert("RGBA" if "A" in image.mode else "RGB")


def _bands(image, role: str) -> list[np.ndarray]:
    """The channels of ``image`` (a :func:`_plain_mode` mode) as (h, w) float32 in
    [0, 1], colour channels in linear light for a ``"colour"`` image."""
    if image.mode == "I;16":
        return [np.asarray(image, dtype=np.float32) / 65535.0]
    colours = 3 if image.mode in ("RGB", "RGBA") else 1
    # 8-bit channels: linear light by a table of the 256 values, not a power per texel
    linear = _to_linear(np.arange(256, dtype=np.float32) / 255.0).astype(np.float32)
    return [linear[np.asarray(band)] if role == "colour" and k < colours
            else np.asarray(band, dtype=np.float32) / 255.0
            for k, band in enumerate(image.split())]


def _resampled(bands: list, mode: str, size: tuple[int, int], role: str):
    """The image of mode ``mode`` at ``size`` from its :func:`_bands`, filtered as
    ``role`` says."""
    from PIL import Image

    if mode == "I;16":
        out = _filter(bands[0], size)
        return Image.fromarray(np.rint(np.clip(out, 0, 1) * 65535).astype(np.uint16), "I;16")
    colours = 3 if mode in ("RGB", "RGBA") else 1
    if role == "normal" and colours == 3:
        vectors = [_filter(band * 2.0 - 1.0, size) for band in bands[:3]]
        length = np.sqrt(sum(v * v for v in vectors))
        length[length == 0] = 1.0
        out = [(v / length + 1.0) * 0.5 for v in vectors]
        out += [_filter(band, size) for band in bands[3:]]
    else:
        out = [_filter(band, size) for band in bands]
        if role == "colour":
            for k in range(colours):
                out[k] = _to_srgb(np.clip(out[k], 0.0, 1.0))
    planes = [Image.fromarray(np.rint(np.clip(band, 0, 1) * 255).astype(np.uint8), "L")
              for band in out]
    return planes[0] if len(planes) == 1 else Image.merge(mode, planes)


def _filter(band: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w) float32 ``band`` resampled to ``size`` (width, height) by Pillow's
    Lanczos filter on a 32-bit float image (no rounding between the passes)."""
    from PIL import Image

    return np.asarray(Image.fromarray(band, "F").resize(size, Image.Resampling.LANCZOS))


def _to_linear(values: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear light (IEC 61966-2-1)."""
    return np.where(values <= 0.04045, values / 12.92, ((values + 0.055) / 1.055) ** 2.4)


def _to_srgb(values: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] to sRGB-encoded values (IEC 61966-2-1)."""
    return np.where(values <= 0.0031308, values * 12.92,
                    1.055 * np.power(values, 1 / 2.4) - 0.055)
