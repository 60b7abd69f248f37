"""Old home of glTF reading and GLB writing, now :mod:`lodserver.io.gltf` and
:mod:`lodserver.io.glb`; these names stay importable from here until their
callers move (the lead removes this shim)."""

from .io.glb import (coverage_from_ratios, encode_glb, encode_lod_chain, geometry_glb, level_glb,
                     render_primitives)
from .io.gltf import face_normals, image_mime_type, read_gltf, transform_normals

__all__ = ["coverage_from_ratios", "encode_glb", "encode_lod_chain", "face_normals",
           "geometry_glb", "image_mime_type", "level_glb", "read_gltf", "render_primitives",
           "transform_normals"]
