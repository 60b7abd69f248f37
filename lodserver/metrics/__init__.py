"""Geometric error between two triangle meshes: the judge for simplifiers.

The benchmark compares our output with meshoptimizer, pymeshlab and
fast-simplification through :func:`surface_distance` alone, so every number it
reports comes from the same samples and the same exact distance code.

- :func:`sample_surface` draws area-weighted uniform points on a surface.
- :func:`point_to_mesh_distance` gives the exact Euclidean distance from points
  to the nearest point on any triangle (not the nearest vertex), through a
  bounding-volume hierarchy queried in parallel.
- :func:`surface_distance` combines them into the two-sided metric.
- :func:`attribute_deviation` compares normals, UVs, colours and texture
  colour at the same samples.

Degenerate (zero-area) triangles get no samples but still count as surface
(a segment or a point) when distances are measured to them. Unreferenced
vertices are ignored everywhere, including in the bounding-box diagonal.

Modules: ``nearest`` (the BVH and exact point-to-triangle distance),
``surface`` (samples, the two-sided distance), ``attributes``.
"""

from .attributes import attribute_deviation
from .surface import point_to_mesh_distance, sample_surface, surface_distance

__all__ = ["sample_surface", "point_to_mesh_distance", "surface_distance", "attribute_deviation"]
