"""The progressive file (docs/packets.md, "The progressive file"): its index,
every chunk decoding (reference decoder) to the json level at its end, both
ways; ``GET /meshes/{id}/progressive`` the bytes ``lodserver export
--progressive`` writes, immutable at the mesh's version, ``Range`` honoured
(416 past the end); a Khronos-valid GLB whose base level any viewer draws."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.packets import apply_packet, decode_any, state_from_json
from lodserver.service.progressive_file import (
    EXTENSION,
    MATERIALS_HERE,
    chunk_splits,
    progressive_glb,
    read_index,
)

from ..io.test_gltf import assert_valid, gltf_validator  # noqa: F401 (a fixture)
from ..meshes import DATA, SHARED, textured_spot_glb
from ..packets.test_packets import _same
from . import uploaded

REPO = Path(__file__).resolve().parents[2]
RIGGED = SHARED / "scenes" / "RiggedSimple.glb"


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """spot with its texture (UV, a material, an image) uploaded as a GLB and built."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("progressive") / "data",
                        warm_kernels=False)
    with TestClient(create_app(settings)) as client:
        yield client, uploaded(client, "spot.glb", textured_spot_glb(), name="spot")


def _levels(client, mesh_id, level, part=None, bits=None):
    route = f"/meshes/{mesh_id}" + ("" if part is None else f"/parts/{part}") + "/lod"
    params = {"vertices": level, "format": "json", **({} if bits is None else {"bits": bits})}
    return client.get(route, params=params).json()


def _check_chunks(data, summary_of, json_level):
    """Every part's base and chunks: the base the json level (its materials link
    aside), every chunk from its start to its end state, both ways, in order."""
    record, start = read_index(data)
    assert record["packetVersion"] == 4
    for part in record["parts"]:
        summary = summary_of(part["part"])
        base, offset, length = part["base"]
        assert base == summary["base_vertices"]
        document = json.loads(data[start + offset:start + offset + length])
        expected = json_level(part["part"], base)
        assert document.pop("materials", MATERIALS_HERE) == MATERIALS_HERE
        expected.pop("materials", None)
        assert document == expected
        size = part["chunkSplits"]
        assert size == chunk_splits(summary["vertices"] - base)
        ends = [chunk[1] for chunk in part["splits"]]
        assert ends == [*range(base + size, summary["vertices"], size), summary["vertices"]]
        assert [c[:2] for c in part["collapses"]] == [c[1::-1] for c in reversed(part["splits"])]
        # laid out in order: the chunks to any level are one range of bytes
        spans = [chunk[2:] for chunk in part["splits"] + part["collapses"]]
        assert all(a[0] + a[1] == b[0] for a, b in zip(spans, spans[1:]))
        assert spans[0][0] == offset + length
        state = state_from_json(document)
        for chunks in (part["splits"], part["collapses"]):
            for first, last, at, length in chunks:
                packet = data[start + at:start + at + length]
                assert packet[4] == 4
                state = apply_packet(state, decode_any(packet))
                _same(state, state_from_json(json_level(part["part"], last)))
    return record


def test_the_route_serves_the_file_of_the_cli_and_every_chunk_decodes(served, tmp_path):
    source = tmp_path / "spot.glb"
    source.write_bytes(textured_spot_glb())
    client, mesh_id = served
    summary = client.get(f"/meshes/{mesh_id}").json()
    response = client.get(f"/meshes/{mesh_id}/progressive", params={"v": summary["version"]})
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "model/gltf-binary"
    assert "immutable" in response.headers["cache-control"]
    assert response.headers["accept-ranges"] == "bytes"
    data = response.content
    asset = client.app.state.store.load(mesh_id=mesh_id)
    assert data == progressive_glb(asset, name="spot")
    record = _check_chunks(data, lambda p: summary,
                           lambda p, level: _levels(client, mesh_id, level))
    assert record["summary"]["vertices"] == summary["vertices"]
    assert record["summary"]["error_curve"] == summary["error_curve"]
    # the CLI writes the same bytes from the same file
    out = tmp_path / "spot.glb"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    result = subprocess.run([sys.executable, "-m", "lodserver.cli", "export", str(source),
                             "--progressive", "-o", str(out)], capture_output=True, text=True,
                            env=env, timeout=900)
    assert result.returncode == 0, result.stderr
    assert out.read_bytes() == data


def test_a_file_on_another_grid_decodes_to_the_json_levels_at_those_bits(served, tmp_path):
    """``?bits=K`` (``export --progressive --bits K``): the base is ``/lod?format=
    json&bits=K`` and every chunk's end the json level at K bits, both ways; the
    CLI writes the same bytes; a grid outside [8, 24] is refused."""
    client, mesh_id = served
    summary = client.get(f"/meshes/{mesh_id}").json()
    default = read_index(client.get(f"/meshes/{mesh_id}/progressive").content)[0]
    bits = default["parts"][0]["bits"] - 2
    response = client.get(f"/meshes/{mesh_id}/progressive", params={"bits": bits})
    assert response.status_code == 200, response.text
    data = response.content
    record = _check_chunks(data, lambda p: summary,
                           lambda p, level: _levels(client, mesh_id, level, bits=bits))
    assert record["parts"][0]["bits"] == bits
    assert len(data) < len(client.get(f"/meshes/{mesh_id}/progressive").content)
    source = tmp_path / "spot.glb"
    source.write_bytes(textured_spot_glb())
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = tmp_path / "out" / "spot.glb"
    result = subprocess.run([sys.executable, "-m", "lodserver.cli", "export", str(source),
                             "--progressive", "--bits", str(bits), "-o", str(out)],
                            capture_output=True, text=True, env=env, timeout=900)
    assert result.returncode == 0, result.stderr
    assert out.read_bytes() == data
    refused = client.get(f"/meshes/{mesh_id}/progressive", params={"bits": 30})
    assert refused.status_code == 422, refused.text


def test_ranges_are_answered_and_a_range_past_the_end_is_refused(served):
    client, mesh_id = served
    whole = client.get(f"/meshes/{mesh_id}/progressive").content
    size = len(whole)
    for asked, (start, stop) in {"bytes=0-99": (0, 100), f"bytes=100-{size + 50}": (100, size),
                                 "bytes=-16": (size - 16, size), "bytes=20-": (20, size)}.items():
        response = client.get(f"/meshes/{mesh_id}/progressive", headers={"Range": asked})
        assert response.status_code == 206, (asked, response.text)
        assert response.content == whole[start:stop]
        assert response.headers["content-range"] == f"bytes {start}-{stop - 1}/{size}"
    for asked in (f"bytes={size}-", f"bytes={size + 10}-{size + 20}"):
        response = client.get(f"/meshes/{mesh_id}/progressive", headers={"Range": asked})
        assert response.status_code == 416, response.text
        assert response.headers["content-range"] == f"bytes */{size}"
        assert "/work" not in response.text and "/tmp" not in response.text
    # a range that is not one range of bytes: the whole file, as HTTP allows
    several = client.get(f"/meshes/{mesh_id}/progressive", headers={"Range": "bytes=0-1,5-6"})
    assert several.status_code == 200 and several.content == whole
    missing = client.get("/meshes/no-such-mesh/progressive")
    assert missing.status_code == 404


def test_the_file_is_a_valid_glb_drawing_the_base_level(served, gltf_validator):  # noqa: F811
    client, mesh_id = served
    data = client.get(f"/meshes/{mesh_id}/progressive").content
    assert_valid(gltf_validator, data, "the progressive file")
    document = json.loads(data[20:20 + int.from_bytes(data[12:16], "little")])
    assert EXTENSION in document["extensionsUsed"]
    assert EXTENSION not in document.get("extensionsRequired", [])
    assert document["images"] and document["materials"]


def test_a_scene_file_holds_every_part_and_its_document(tmp_path):
    if not RIGGED.is_file():
        pytest.skip(f"shared scene not found at {RIGGED}")
    settings = Settings(data_dir=tmp_path / "data", warm_kernels=False)
    with TestClient(create_app(settings)) as client:
        mesh_id = uploaded(client, "RiggedSimple.glb", RIGGED.read_bytes())
        summary = client.get(f"/meshes/{mesh_id}").json()
        assert summary["scene"], summary
        data = client.get(f"/meshes/{mesh_id}/progressive").content
        record = _check_chunks(
            data, lambda p: summary["parts"][p],
            lambda p, level: _levels(client, mesh_id, level, part=p))
        assert len(record["parts"]) == len(summary["parts"])
        document = json.loads(data[20:20 + int.from_bytes(data[12:16], "little")])
        assert document.get("skins") and document.get("animations")


@pytest.mark.parametrize("flags, code, phrase", [
    (["-o", "OUT/spot.txt"], 1, "-o a .glb file"),
    (["-o", "OUT/spot.glb", "--lods", "1,0.5"], 2, "--lods apply to LOD chains"),
    (["-o", "OUT/spot.glb", "--texture-scale", "auto", "--reach", "merge"], 2,
     "--reach, --texture-scale apply to LOD chains"),
    (["-o", "OUT/spot.glb", "--bits", "30"], 2, "--bits must be in [8, 24], got 30"),
    (["-o", "OUT", "--bits", "12", "NOT_PROGRESSIVE"], 2, "--bits sets the grid of --progressive"),
])
def test_the_cli_refuses_what_it_cannot_write_with_a_sentence(tmp_path, flags, code, phrase):
    flags = [flag.replace("OUT", str(tmp_path)) for flag in flags]
    progressive = [] if "NOT_PROGRESSIVE" in flags else ["--progressive"]
    flags = [flag for flag in flags if flag != "NOT_PROGRESSIVE"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    result = subprocess.run([sys.executable, "-m", "lodserver.cli", "export",
                             str(DATA / "spot.obj"), *progressive, *flags],
                            capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == code, result.stderr
    assert phrase in result.stderr and "Traceback" not in result.stderr
    assert not list(tmp_path.iterdir())        # nothing written


def test_a_file_kept_as_a_body_file_answers_ranges_too(tmp_path):
    """A file larger than LODSERVER_BODY_FILE_BYTES is streamed from a body file
    (api/caching.BodyFileResponse): its ranges are answered the same way."""
    settings = Settings(data_dir=tmp_path / "data", warm_kernels=False, body_file_bytes=4096)
    with TestClient(create_app(settings)) as client:
        mesh_id = uploaded(client, "spot.glb", textured_spot_glb(), name="spot")
        whole = client.get(f"/meshes/{mesh_id}/progressive").content
        again = client.get(f"/meshes/{mesh_id}/progressive", headers={"Range": "bytes=10-99"})
        assert again.status_code == 206 and again.content == whole[10:100]
        assert again.headers["content-range"] == f"bytes 10-99/{len(whole)}"
        past = client.get(f"/meshes/{mesh_id}/progressive",
                          headers={"Range": f"bytes={len(whole)}-"})
        assert past.status_code == 416, past.text
        assert str(tmp_path) not in past.text and "bodies" not in past.text
