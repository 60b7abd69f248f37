"""The report of an export or an extract: what each asset's levels hold, as JSON.

``lodserver export --report FILE.json`` and ``lodserver extract --report``
write one document (``-``: to stdout); its keys are stable and documented in
``docs/pipeline.md`` ("The report"). Its version is :data:`REPORT_VERSION`:
keys are only added while it stays the same.

Counts and bytes come from the files written (``io.glb_levels``: what the file
holds, which engines load), errors and hints from the export
(``chains.Exported``). The coverage hint of a level is the fraction of the
screen height the asset may fill before the level's error reaches one pixel at
1080 lines: ``min(1, diagonal / (1080 * error))`` (as ``budget.coverage_from_errors``
hands levels over), None for an error of 0 (never a pixel).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ..io import write_atomic
from ..io.glb_levels import glb_levels
from ..mesh import MeshError
from .budget import SCREEN_PIXELS, part_diagonal

__all__ = ["REPORT_VERSION", "asset_entry", "extract_entry", "failed_entry", "folder_entries",
           "level_errors", "report_document", "write_report"]

REPORT_VERSION = 1


def level_errors(pm, chain, clustered) -> list:
    """A single mesh's collapse error at each level of ``chain`` (``ChainOptions``,
    mesh units): the level its ratio or error bound picks; None for the levels
    made by clustering (``clustered``), whose error is not measured."""
    if chain.errors is not None:
        diagonal = part_diagonal(pm)
        levels = [pm.level_for(error=e * diagonal) for e in chain.errors]
    else:
        levels = [pm.level_for(ratio=ratio) for ratio in chain.lods]
    return [None if k in clustered else float(pm.error_at_level(level))
            for k, level in enumerate(levels)]


def pixel_coverage(error, diagonal: float) -> float | None:
    """The screen height fraction at which ``error`` is one pixel at 1080p (module
    docstring); None when the error is 0 or unknown."""
    if error is None or error <= 0 or diagonal <= 0:
        return None
    return min(1.0, diagonal / (SCREEN_PIXELS * error))


def _level(k: int, counts: dict, error, diagonal: float, coverage, seconds) -> dict:
    return {"level": k, "triangles": counts["triangles"], "vertices": counts["vertices"],
            "error": error,
            "error_fraction": error / diagonal if error is not None and diagonal > 0 else None,
            "coverage": coverage, "pixel_coverage": pixel_coverage(error, diagonal),
            "bytes": {"geometry": counts["geometry"], "images": counts["images"]},
            "seconds": seconds}


def asset_entry(exported, files) -> dict:
    """The report of one exported asset: ``exported`` (``chains.Exported``) and
    ``files``, the local paths of its outputs (None when they are not local, as for
    an object-store folder: the levels' counts and bytes are then left out)."""
    count = len(exported.faces)
    per_level = [None] * count
    if files is not None:
        found = [glb_levels(Path(path).read_bytes()) for path in files]
        # one file per level, or one file of every level
        per_level = [levels[0] for levels in found] if len(found) == count and count > 1 \
            else found[0][:count]
    errors = list(exported.errors) + [None] * (count - len(exported.errors))
    seconds = list(exported.level_seconds) or [None] * count
    levels = []
    for k in range(count):
        counts = per_level[k] or {"triangles": exported.faces[k], "vertices": None,
                                  "geometry": None, "images": None}
        levels.append(_level(k, counts, errors[k], exported.diagonal,
                             exported.coverage[k] if k < len(exported.coverage) else None,
                             seconds[k]))
    warnings = list(exported.notes)
    if exported.clustered:
        warnings.append(f"levels {', '.join(map(str, exported.clustered))} made by vertex "
                        f"clustering: positions only")
    if count > 1 and not exported.clustered and exported.faces[-1] == exported.base_faces \
            and exported.faces[-2] == exported.faces[-1]:
        warnings.append(f"the mesh simplifies no further than {exported.base_faces} faces")
    entry = {"source": str(exported.source), "status": "written",
             "outputs": [str(path) for path in exported.outputs],
             "seconds": exported.seconds, "diagonal": exported.diagonal,
             "warnings": warnings, "levels": levels}
    if exported.drawn:
        entry["drawn"] = list(exported.drawn)
    return entry


def extract_entry(pm, level: int, path: Path, seconds: float) -> dict:
    """The report of ``lodserver extract``: one level (vertex count ``level``) of
    ``pm`` written to ``path``; counts and bytes from a GLB, the mesh's own counts
    and the file's bytes as geometry for another format."""
    error, diagonal = float(pm.error_at_level(level)), part_diagonal(pm)
    data = Path(path).read_bytes()
    if path.suffix.lower() == ".glb":
        counts = glb_levels(data)[0]
    else:
        counts = {"triangles": pm.faces_at_level(level), "vertices": level,
                  "geometry": len(data), "images": None}
    return {"source": str(path), "status": "written", "outputs": [str(path)],
            "seconds": seconds, "diagonal": diagonal, "warnings": [],
            "levels": [_level(0, counts, error, diagonal, None, seconds)]}


def failed_entry(source: str, status: str, reason: str | None = None) -> dict:
    """An asset of a folder export not written this run: ``status`` ``"up to date"``
    or ``"failed"`` (with its ``reason``)."""
    entry = {"source": source, "status": status, "outputs": [], "seconds": None,
             "diagonal": None, "warnings": [], "levels": []}
    if reason is not None:
        entry["reason"] = reason
    return entry


def folder_entries(report, source: str, local: bool) -> list[dict]:
    """The entries of a folder export (``pipeline.FolderReport``) of the folder
    ``source``, by source: those written (their outputs read back when ``local``;
    not from an object-store folder), up to date and failed."""
    def where(relative) -> str:
        return f"{str(source).rstrip('/')}/{Path(relative).as_posix()}"

    entries = [asset_entry(done, done.outputs if local else None) for done in report.written]
    entries += [failed_entry(where(relative), "up to date") for relative in report.up_to_date]
    entries += [failed_entry(where(relative), "failed", reason)
                for relative, reason in report.failed.items()]
    return sorted(entries, key=lambda entry: entry["source"])


def report_document(command: str, assets: list[dict], seconds: float) -> dict:
    """The whole report: ``{"lodserver_report": REPORT_VERSION, "command", "seconds",
    "assets"}``."""
    return {"lodserver_report": REPORT_VERSION, "command": command, "seconds": seconds,
            "assets": assets}


def write_report(document: dict, target: str) -> None:
    """``document`` as JSON to ``target``: ``"-"`` for stdout, else a file (its
    folder created) written whole or not at all (``io.write_atomic``); MeshError
    (one sentence) when it cannot be."""
    text = json.dumps(document, indent=2, allow_nan=False) + "\n"
    if target == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    try:
        Path(target).parent.mkdir(parents=True, exist_ok=True)
        write_atomic(Path(target), text.encode())
    except OSError as exc:
        raise MeshError(f"cannot write the report {target}: {exc.strerror or exc}") from None
