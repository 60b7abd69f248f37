"""How much a mesh file may ask of the loader, checked before the work is done.

A small file can declare a huge mesh: a glTF accessor of 30 million vertices
with no data behind it, a PLY header of four million rows, a buffer that names
a gigabyte file. The readers compare every such declared size with
:class:`LoadLimits` (and with the bytes actually present) *before* they
allocate anything for it, and refuse with a :class:`LimitError`.

Counts are of what the file declares, before cleaning: a mesh of 2 million
triangles that welds down to fewer is still a mesh of 2 million triangles to
parse. ``None`` as a limit means "no limit" (the trusted command line).
"""

from __future__ import annotations

from dataclasses import dataclass

from ..mesh import MeshError

# The server's default triangle limit (the server's settings use the same constant).
# Sized from memory per triangle: a build peaks at about 300-350 bytes per triangle
# over its input, a binary PLY or GLB near the limit (under the default upload limit)
# parses within the parse worker's default 4 GiB, and a progressive mesh kept loaded
# takes about 170 bytes per triangle with its packet records. So one build at the
# limit, its parse and the default 8 loaded meshes at the limit fit in a machine of
# about 24 GB; twice the limit would not.
DEFAULT_MAX_TRIANGLES = 10_000_000


class LimitError(MeshError):
    """An upload exceeds a configured limit (bytes, triangles, vertices, ...)."""


class OutOfMemory(LimitError):
    """Reading a file needed more memory than the process may use (its address-space
    limit): the file is refused, and a parse worker that hit its limit is replaced,
    since the heap it grew may stay mapped."""


@dataclass(frozen=True)
class LoadLimits:
    """Upper bounds on what one mesh file may declare; ``None`` means unbounded.

    max_triangles : int
        Triangles of any one mesh (a glTF mesh before instancing, or a whole OBJ,
        PLY, OFF or STL file).
    max_vertices : int
        Vertices declared (for a glTF scene: placed, after instancing); by
        default three times ``max_triangles``.
    max_primitives : int
        glTF primitives in the document's meshes.
    max_instances : int
        glTF nodes of the default scene, plus the instances every
        ``EXT_mesh_gpu_instancing`` node adds beyond its first.
    max_triangles_total : int
        Triangles after instancing (a glTF mesh placed by ten nodes, or by one
        node with ten GPU instances, counts ten times); by default ``max_triangles``.
    max_file_bytes : int
        Bytes of the mesh file and of any one file it references (buffers,
        images, MTL libraries, textures).
    max_json_bytes : int
        Bytes of a glTF JSON document (a .gltf file or a GLB's JSON chunk).
    max_json_depth : int
        Nesting depth of that JSON (glTF needs about ten; deeper is an attack).
    carried_ratio : int
        A glTF scene's carried data (animations, skins, GPU instancing
        accessors, morph targets, tangents, skin and custom attributes, and the
        joint transforms of skinned nodes), counted in bytes as it is held once
        read (attribute values float64 per vertex, accessors in their own type,
        128 bytes a transform), may be at most this many times the bytes
        uploaded (the file and the buffers it names), or ``min_carried_bytes``,
        whichever is more. A file that names one accessor for 255 morph
        targets, or aliases one bufferView for many samplers, is small and
        expands far past what it holds; a file that stores its data holds about
        what it expands to (float32 read as float64 is twice, int16 quantized
        deltas three times, and the rest of the file dilutes it). A build's
        memory grows with these columns: tens of bytes for each byte counted.
    min_carried_bytes : int
        That bound for small files (a few kilobytes of glTF may still carry
        some: sparse morph targets, short clips on many nodes).
    """

    max_triangles: int | None = DEFAULT_MAX_TRIANGLES
    max_vertices: int | None = -1
    max_primitives: int | None = 4096
    max_instances: int | None = 65536
    max_triangles_total: int | None = -1
    max_file_bytes: int | None = 1 << 30
    max_json_bytes: int | None = 64 << 20
    max_json_depth: int | None = 64
    carried_ratio: int | None = 4
    min_carried_bytes: int | None = 2 << 20

    def __post_init__(self):
        # -1 marks "derive from max_triangles", so LoadLimits(max_triangles=k) scales both
        triangles = self.max_triangles
        if self.max_vertices == -1:
            object.__setattr__(self, "max_vertices", None if triangles is None else 3 * triangles)
        if self.max_triangles_total == -1:
            object.__setattr__(self, "max_triangles_total", triangles)
        for name, value in self.__dict__.items():
            if value is not None and (not isinstance(value, int) or value < 0):
                raise ValueError(f"LoadLimits.{name} must be a non-negative integer or None, "
                                 f"got {value!r}")

    @classmethod
    def unbounded(cls) -> LoadLimits:
        """No size limits, only the JSON depth guard (a parser cannot recurse forever)."""
        return cls(max_triangles=None, max_vertices=None, max_primitives=None,
                   max_instances=None, max_triangles_total=None, max_file_bytes=None,
                   max_json_bytes=None, carried_ratio=None)

    def carried_bytes(self, upload_bytes: int) -> int | None:
        """The most bytes of carried data a file of ``upload_bytes`` may expand to
        (``carried_ratio``), None for no bound."""
        if self.carried_ratio is None:
            return None
        return max(self.min_carried_bytes or 0, self.carried_ratio * upload_bytes)

    def check(self, name: str, count: int, what: str) -> None:
        """Raise a LimitError if ``count`` exceeds the limit ``name``.

        ``what`` says what was counted, as it reads after "it declares"
        (e.g. ``"30000000 vertices in accessor 0"`` reads badly, so pass
        ``"vertices in accessor 0"``).
        """
        limit = getattr(self, name)
        if limit is not None and count > limit:
            raise LimitError(f"it declares {count} {what}; this loader accepts at most {limit}")
