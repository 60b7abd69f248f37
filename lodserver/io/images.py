"""What an image's bytes are, by their signature: the one sniffer every module uses.

glTF carries PNG and JPEG (core), WebP (EXT_texture_webp) and KTX2
(KHR_texture_basisu). A file's declared mimeType is a claim; the bytes are
the fact, so a loader keeps only images whose bytes are one of these and
records the sniffed type, and a server sends only that type.
"""

from __future__ import annotations

# (offset, signature) pairs per media type; WebP is a RIFF container of form WEBP.
_SIGNATURES = (
    ("image/png", ((0, b"\x89PNG\r\n\x1a\n"),)),
    ("image/jpeg", ((0, b"\xff\xd8\xff"),)),
    ("image/webp", ((0, b"RIFF"), (8, b"WEBP"))),
    ("image/ktx2", ((0, b"\xabKTX 20\xbb\r\n\x1a\n"),)),
)

IMAGE_TYPES = tuple(kind for kind, _ in _SIGNATURES)


def image_type(data) -> str | None:
    """The media type of encoded image bytes (PNG, JPEG, WebP, KTX2), or None.

    Parameters
    ----------
    data : bytes-like
        The start of the image file is enough (16 bytes).
    """
    head = bytes(data[:16])
    for kind, parts in _SIGNATURES:
        if all(head[at:at + len(magic)] == magic for at, magic in parts):
            return kind
    return None
