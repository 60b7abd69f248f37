"""Reading mesh files into a clean :class:`~lodserver.mesh.Mesh`, and writing them back.

Every reader below produces the same arrays, which :func:`clean_mesh` then
welds and cleans:

- ``positions``     : (n, 3) float64, vertex positions in the file's units.
- ``faces``         : (m, 3) int64, triangle vertex indices into ``positions``.

and, where the file has appearance data:

- ``corner_values`` : (m, 3, d) float64, each face corner's attribute vector,
  columns named by ``layout`` (glTF names: NORMAL, TEXCOORD_0, TEXCOORD_1,
  COLOR_0; UVs with v down as glTF has them, colours linear RGBA in 0..1).
- ``face_material`` : (m,) int32 into ``materials`` (glTF records plus image bytes), -1 for none.

Polygons are fan-triangulated. A glTF/GLB scene is flattened: every instance of
every triangle geometry is placed by its node transform (normals by its
inverse transpose). :func:`clean_mesh` welds positions only, so the topology is
the positions' and attributes ride along as wedges (distinct attribute vectors
per vertex and material); a file without any attributes or materials yields
``attributes=None``, exactly as when lodserver kept positions only.

Where the arrays come from, one module each:

- :mod:`.obj`: OBJ and MTL, a reader of its own (trimesh's splits seams).
- :mod:`.gltf`: glTF/GLB, which keeps the image bytes as stored; compressed
  geometry decoded by :mod:`.meshopt` (EXT_meshopt_compression) and :mod:`.draco`
  (KHR_draco_mesh_compression).
- :mod:`.ply`: PLY headers (counts checked before anything is read) and
  ``tristrips`` files, which trimesh loads as point clouds.
- :mod:`.load`: the dispatch; everything else through
  ``trimesh.load_scene(..., process=False)``, after its counts are checked.
- :mod:`.clean`: :func:`clean_mesh` and :class:`LoadReport`.
- :mod:`.save` and :mod:`.glb`: writing (:data:`OUTPUT_FORMATS`, the one list of
  output formats; :func:`save_mesh`, :func:`encode_mesh`, GLB and MSFT_lod chains,
  quantized by :mod:`.quantize` and reordered by :mod:`.vertex_order` when asked);
  :mod:`.files`: :func:`write_atomic`.
- :mod:`.references`, :mod:`.limits`, :mod:`.images`: what a file may refer to,
  how much it may declare, what its images are.

PLY and OBJ vertex colours are display (sRGB) values by convention; they are
converted to linear, which is what glTF's COLOR_0 holds.

Precision and what each output format keeps: see :mod:`.save`.

A file from someone else is read with ``load_mesh(path, root=folder,
limits=LoadLimits(...))``: every file it names must lie inside ``folder``
(:mod:`.references`), and every size it declares is checked before it is
allocated (:mod:`.limits`).
"""

from __future__ import annotations

from .clean import LoadReport, clean_mesh
from .files import write_atomic
from .limits import LimitError, LoadLimits
from .load import SUPPORTED_INPUT, load_mesh
from .save import (OUTPUT_FORMATS, SERVED_FORMATS, SUPPORTED_OUTPUT, OutputFormat,
                   encode_mesh, save_mesh)

__all__ = ["LimitError", "LoadLimits", "LoadReport", "OUTPUT_FORMATS", "OutputFormat",
           "SERVED_FORMATS", "SUPPORTED_INPUT", "SUPPORTED_OUTPUT", "clean_mesh", "encode_mesh",
           "load_mesh", "save_mesh", "write_atomic"]
