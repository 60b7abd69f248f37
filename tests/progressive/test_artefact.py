"""The .pm artefact: round trip and clear errors on damaged files."""

import numpy as np
import pytest

from lodserver.progressive import (
    ArtefactError,
    decode_progressive,
    encode_progressive,
    load_progressive,
)
from lodserver.progressive.mesh import ProgressiveMesh

from ..meshes import progressive


def _same(a: ProgressiveMesh, b: ProgressiveMesh):
    for name in ("positions", "faces", "parent", "coarse_position", "error", "face_counts",
                 "moved_offsets", "moved_corners"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.base_vertices == b.base_vertices and a.metadata == b.metadata


def test_round_trip_through_a_file(tmp_path):
    pm = progressive("spot")
    path = tmp_path / "spot.pm"
    pm.save(path)
    loaded = ProgressiveMesh.load(path)
    _same(pm, loaded)
    level = pm.level_for(ratio=0.25)
    assert np.array_equal(loaded.arrays_at(level)[1], pm.arrays_at(level)[1])
    assert not list(tmp_path.glob(".*.tmp"))


@pytest.mark.parametrize("damage, message", [
    (lambda b: b[:10], "truncated"),
    (lambda b: b[:-7], "truncated"),
    (lambda b: b"NOTAMESH" + b[8:], "magic"),
    (lambda b: b[:8] + (99).to_bytes(4, "little") + b[12:], "version"),
    (lambda b: b[:200] + bytes([b[200] ^ 0xFF]) + b[201:], "checksum"),
    (lambda b: b"", "truncated"),
])
def test_damaged_artefacts_are_refused_with_a_reason(damage, message):
    data = encode_progressive(progressive("grid"))
    with pytest.raises(ArtefactError, match=message):
        decode_progressive(damage(data))


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ArtefactError, match="cannot read"):
        load_progressive(tmp_path / "nope.pm")


def test_the_codec_writes_named_arrays_and_knows_no_progressive_mesh():
    import ast
    from pathlib import Path

    from lodserver.progressive import artefact

    pm = progressive("grid")
    fields = {name: getattr(pm, name) for name in artefact.STORED_FIELDS}
    data = artefact.encode_artefact(fields)
    assert data == encode_progressive(pm)
    back = artefact.decode_artefact(data)
    assert back["base_vertices"] == pm.base_vertices and back["metadata"] == pm.metadata
    for name in artefact.ARRAYS:
        assert np.array_equal(back[name], getattr(pm, name)), name
    _same(ProgressiveMesh(**back), pm)
    # the codec imports nothing of the progressive package: mesh.py imports it
    tree = ast.parse(Path(artefact.__file__).read_text())
    siblings = [(node.module or "") for node in ast.walk(tree)
                if isinstance(node, ast.ImportFrom) and node.level == 1]
    absolute = [node.module for node in ast.walk(tree)
                if isinstance(node, ast.ImportFrom) and node.level == 0]
    assert "mesh" not in siblings and "lodserver.progressive.mesh" not in absolute
