"""An export's farthest level as an octahedral impostor (``export --impostor``).

The export writes every level but the farthest as it would
(``pipeline.export_lods``, ``scene.export``), and the farthest as the impostor
of the full-detail asset (``bake.impostor``: a quad, one draw call, two
triangles) in the file that level would have had, ``OUT_lodN.glb``. The
impostor is baked before any file is written, so a bake that fails leaves no
chain without its farthest level. A scene that is not static (animated,
skinned, morphed: ``merge.static_reason``) keeps its farthest level, and the
export's notes say why it has no impostor.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

from ..chains import ChainOptions, Exported
from ..io import write_atomic
from ..io.glb import coverage_from_ratios, lod_name
from ..mesh import Mesh

__all__ = ["baked_impostor", "scene_full_mesh", "with_impostor", "without_farthest"]


def without_farthest(chain: ChainOptions) -> ChainOptions:
    """``chain`` (with ``impostor``) less its farthest level, which the impostor takes."""
    scale = chain.texture_scale
    return dataclasses.replace(chain, lods=chain.lods[:-1], impostor=False,
                               texture_scale=scale[:-1] if isinstance(scale, tuple) else scale)


def scene_full_mesh(scene) -> tuple[Mesh | None, str | None]:
    """``(the scene's parts in world space as one mesh, None)`` for a static scene,
    ``(None, why it has no impostor)`` for another."""
    from .merge import static_reason, world_mesh

    reason = static_reason(scene)
    if reason is not None:
        return None, f"no impostor: {reason}"
    return world_mesh(scene), None


def baked_impostor(full: Mesh, output: Path, level: int) -> tuple[bytes, float]:
    """The GLB of ``full``'s impostor for level ``level`` of ``output``, and the
    seconds its bake took."""
    from ..bake.impostor import bake_impostor, impostor_glb

    begun = time.perf_counter()
    blob = impostor_glb(bake_impostor(full), name=lod_name(output.stem, level))
    return blob, time.perf_counter() - begun


def with_impostor(exported: Exported, output: Path, blob: bytes, lods, seconds: float,
                  start: float) -> Exported:
    """``exported`` (every level but the farthest, written) with the impostor
    ``blob`` written as the farthest (``lods``: the ratios of every level): two
    faces, two triangles drawn, no collapse error (None); the last two levels'
    screen-coverage hints from the ratios (``glb.coverage_from_ratios``: the
    kept chain's last hint is 0, drawn however small, which the impostor now is)."""
    level = len(exported.outputs)
    path = output.with_name(f"{output.stem}_lod{level}{output.suffix}")
    begun = time.perf_counter()
    write_atomic(path, blob)
    written = time.perf_counter() - begun
    coverage = [*exported.coverage[:-1], *coverage_from_ratios(lods)[-2:]]
    return dataclasses.replace(
        exported, outputs=[*exported.outputs, path], faces=[*exported.faces, 2],
        coverage=coverage, seconds=time.perf_counter() - start,
        drawn=[*exported.drawn, 2] if exported.drawn else [],
        errors=[*exported.errors, None] if exported.errors else [],
        level_seconds=[*exported.level_seconds, seconds + written],
        notes=[*exported.notes, f"level {level} is an octahedral impostor"])
