"""Hostile scene uploads through the real app (TestClient, as test_upload_safety): each
is answered by a 4xx whose message is one sentence naming no server path, leaving
nothing in the data directory, or is built correctly; a scene whose part cannot be
built fails and stores nothing. The files are those of tests/io/test_hostile_scenes.py.
What a small file would cost once read (GPU instances, aliased accessors, expanded
morph targets) is a 413, or built at most 20 times its size; the red team's full-size
files also go to a real ``serve`` process, its peak RSS read from /proc.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings

from ..conftest import glb_chunks
from ..io import test_gltf
from ..io.test_gltf import assert_valid
from ..io.test_hostile_scenes import (
    Glb,
    _custom,
    _morphed,
    aliased_clips,
    instanced,
    one_sentence,
    skinned_document,
)
from ..server import server_process
from ..test_scene_export import accessor_values
from . import settled

gltf_validator = test_gltf.gltf_validator    # the session fixture, shared


def _client(tmp_path, **overrides):
    options = {"data_dir": tmp_path / "data", "warm_kernels": False, **overrides}
    return TestClient(create_app(Settings(**options)))


def _upload(client, glb: Glb, filename="hostile.glb"):
    return client.post("/meshes", files={"file": (filename, glb.glb())})


def _stored(data_dir) -> list:
    """Every file under the data directory's sources, artefacts and tmp folders."""
    return [p for folder in ("sources", "artefacts", "tmp") if (data_dir / folder).exists()
            for p in (data_dir / folder).rglob("*") if p.is_file()]


def _edit(change):
    glb = skinned_document()
    change(glb)
    return glb


def _set(path, value):
    """An edit setting document[path[0]][path[1]]... = value."""
    def change(glb):
        where = glb.document
        for key in path[:-1]:
            where = where[key]
        where[path[-1]] = value
    return change


def _cycle(glb):
    glb.document["nodes"][1]["children"] = [2]
    glb.document["nodes"][2]["children"] = [1]


def _nan_ibm(glb):
    glb.document["skins"][0]["inverseBindMatrices"] = glb.add(
        np.array([np.eye(4).ravel(), [np.nan] * 16]), "MAT4")


def _three_ibm(glb):
    glb.document["skins"][0]["inverseBindMatrices"] = glb.add(
        np.tile(np.eye(4).ravel(), (3, 1)), "MAT4")


def _huge_keyframes(glb):
    for index in (5, 6):
        glb.document["accessors"][index]["count"] = 10_000_000


def _unbacked_keyframes(glb):
    for index in (5, 6):
        del glb.document["accessors"][index]["bufferView"]
        glb.document["accessors"][index]["count"] = 10_000_000


def _backwards_times(glb):
    glb.document["animations"][0]["samplers"][0]["input"] = glb.add(
        np.array([0.0, 2.0, 1.0]), "SCALAR")


def _cubic_wrong_count(glb):
    glb.document["animations"][0]["samplers"][0]["interpolation"] = "CUBICSPLINE"


def _bad_joint(glb):
    joints = np.zeros((25, 4))
    joints[3, 1] = 9
    glb.document["meshes"][0]["primitives"][0]["attributes"]["JOINTS_0"] = \
        glb.add(joints, "VEC4", 5123)


def _negative_weights(glb):
    weights = np.zeros((25, 4))
    weights[:, 0], weights[:, 1] = 1.5, -0.5
    glb.document["meshes"][0]["primitives"][0]["attributes"]["WEIGHTS_0"] = \
        glb.add(weights, "VEC4")


def _weights(glb):
    glb.document["meshes"][0]["weights"] = [0.0, 0.5, 1.0]
    return glb


HOSTILE = {
    "node cycle": (_edit(_cycle), "cycle|child twice"),
    "own parent": (_edit(_set(["nodes", 2, "children"], [2])), "of itself"),
    "joint not a node": (_edit(_set(["skins", 0, "joints"], [1, 50])), "joint node 50"),
    "nan inverse bind": (_edit(_nan_ibm), "not finite"),
    "wrong ibm count": (_edit(_three_ibm), "3 inverse bind matrices for 2 joints"),
    "joint out of range": (_edit(_bad_joint), "uses joint 9"),
    "negative weights": (_edit(_negative_weights), "negative skin weights"),
    "10M keyframes, tiny buffer": (_edit(_huge_keyframes), "runs past the end"),
    "10M keyframes, no buffer": (_edit(_unbacked_keyframes), "without a bufferView"),
    "times backwards": (_edit(_backwards_times), "not increasing"),
    "cubic of the wrong count": (_edit(_cubic_wrong_count), "3 keyframes but 3 outputs"),
    "channel to a missing node": (_edit(_set(["animations", 0, "channels", 0, "target",
                                              "node"], 77)), "node 77"),
    "channel to a missing sampler": (_edit(_set(["animations", 0, "channels", 0, "sampler"],
                                                4)), "sampler 4"),
    "mesh weights of the wrong count": (_weights(_morphed([2])), "3 morph weights for 2"),
    "300 custom attributes": (_custom([(f"_X{i}", "SCALAR") for i in range(300)]),
                              "300 vertex attributes"),
}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    with _client(root) as client:
        yield client, root / "data"


@pytest.mark.parametrize("case", list(HOSTILE))
def test_a_hostile_scene_upload_is_a_422_sentence_leaving_nothing(server, case):
    client, data = server
    glb, match = HOSTILE[case]
    start = time.monotonic()
    response = _upload(client, glb)
    assert response.status_code == 422, response.text
    message = response.json()["message"]
    one_sentence(message, data, data.parent)
    assert re.search(match, message), message
    assert "hostile.glb" in message
    assert time.monotonic() - start < 60
    assert _stored(data) == []


# what a small upload would cost once read, refused from its declarations (413)
COSTLY = {
    "70,000 GPU instances": (instanced(70_000), "69999 GPU instances"),
    "60 samplers over distinct ranges of one view": (
        aliased_clips(60, 20_000, distinct=True), "animations, skins and instancing accessors"),
    "255 targets naming one accessor": (_morphed([255], size=100), "morph targets of mesh 0"),
    "1000 morph targets": (_morphed([1000], size=60), "morph targets of mesh 0"),
}


@pytest.mark.parametrize("case", list(COSTLY))
def test_a_costly_scene_upload_is_a_413_sentence_leaving_nothing(server, case):
    client, data = server
    glb, match = COSTLY[case]
    response = _upload(client, glb)
    assert response.status_code == 413, response.text
    message = response.json()["message"]
    one_sentence(message, data, data.parent)
    assert re.search(match, message) and "hostile.glb" in message, message
    assert _stored(data) == []


def test_aliased_sampler_outputs_are_stored_and_written_once(tmp_path, gltf_validator):
    """60 samplers whose outputs alias one bufferView: built, the artefact and every
    scene body at most 20 times the upload (written once each, not 60 times), the
    GLB valid, its samplers naming one accessor of the same values."""
    source = aliased_clips(60, 20_000)
    upload = source.glb()
    with _client(tmp_path) as client:
        created = client.post("/meshes", files={"file": ("clips.glb", upload)})
        assert created.status_code == 202, created.text
        body = settled(client, created.json()["id"], timeout=180)
        assert body["status"] == "ready", body.get("failure")
        artefacts = [p for p in (tmp_path / "data" / "artefacts").rglob("*") if p.is_file()]
        assert artefacts and sum(p.stat().st_size for p in artefacts) <= 20 * len(upload)
        for route, params in (("chain", {"lods": "1,0.5"}),
                              ("lod", {"format": "glb", "ratio": 0.5})):
            level = client.get(f"/meshes/{body['id']}/{route}", params=params)
            assert level.status_code == 200, level.text
            assert len(level.content) <= 20 * len(upload)
    assert_valid(gltf_validator, level.content, "the aliased clips")
    document, binary = glb_chunks(level.content)
    outputs = {s["output"] for s in document["animations"][0]["samplers"]}
    assert len(document["animations"][0]["samplers"]) == 60 and len(outputs) == 1
    first = source.document["animations"][0]["samplers"][0]["output"]
    view = source.document["bufferViews"][source.document["accessors"][first]["bufferView"]]
    expected = np.frombuffer(bytes(source.binary), "<f4", 20_000 * 3, view["byteOffset"])
    assert np.array_equal(accessor_values(document, binary, outputs.pop()).ravel(), expected)


def _zero_weights(glb):
    glb.document["meshes"][0]["primitives"][0]["attributes"]["WEIGHTS_0"] = \
        glb.add(np.zeros((25, 4)), "VEC4")


def _weights_without_targets(glb):
    glb.document["animations"][0]["channels"].append(
        {"sampler": 0, "target": {"node": 0, "path": "weights"}})


def _many_animations(glb):
    glb.document["animations"] = glb.document["animations"] * 10_000


@pytest.mark.parametrize("glb", [
    _custom([("_" + "N" * 10_000, "VEC2"), ("_MATRIX", "MAT4"), ("_OK", "SCALAR")]),
    _morphed([2, 5]),
    _edit(_zero_weights),
    _edit(_weights_without_targets),
    _edit(_many_animations),
], ids=["long and matrix custom names", "targets of different counts", "all weights zero",
        "weights channel without targets", "10k animations"])
def test_odd_but_valid_scenes_are_built(tmp_path, glb):
    with _client(tmp_path) as client:
        created = _upload(client, glb)
        assert created.status_code == 202, created.text
        body = settled(client, created.json()["id"], timeout=180)
        assert body["status"] == "ready", body.get("failure")
        assert len(repr(body)) < 100_000          # the 10 kB name is not echoed whole
        level = client.get(f"/meshes/{body['id']}/lod", params={"format": "glb",
                                                                "ratio": 0.5})
        assert level.status_code == 200, level.text


def _with_part(faces, positions) -> Glb:
    """The grid, and a second mesh ("flat") of ``faces`` over ``positions``."""
    glb = skinned_document(skin=False, animation=False)
    position = glb.add(positions, "VEC3", min=positions.min(0).tolist(),
                       max=positions.max(0).tolist())
    indices = glb.add(np.asarray(faces).ravel(), "SCALAR", 5125)
    glb.document["meshes"].append({"name": "flat", "primitives": [
        {"attributes": {"POSITION": position}, "indices": indices}]})
    glb.document["nodes"].append({"name": "flat", "mesh": 1})
    glb.document["scenes"][0]["nodes"].append(len(glb.document["nodes"]) - 1)
    return glb


_SCATTERED = np.random.default_rng(0).random((12, 3))
_CHAIN = [(i, i + 1, i + 2) for i in range(10)]


@pytest.mark.parametrize("glb", [
    _with_part([(i, i, i + 1) for i in range(10)], _SCATTERED),    # a repeated corner each
    _with_part(_CHAIN, np.zeros((12, 3))),                           # every corner one point
], ids=["repeated corners", "one point"])
def test_a_scene_with_a_part_of_only_degenerate_faces_is_refused_whole(tmp_path, glb):
    with _client(tmp_path) as client:
        response = _upload(client, glb)
        assert response.status_code == 422, response.text
        message = response.json()["message"]
        one_sentence(message, tmp_path)
        assert message == ("cannot load hostile.glb: all 10 faces are degenerate after "
                           "welding coincident vertices")
        assert _stored(tmp_path / "data") == []


def test_a_part_of_zero_area_faces_is_built_as_it_is(tmp_path):
    """Collinear but distinct corners are no error: the part is built, and the scene
    served at a level."""
    line = np.column_stack([np.linspace(0, 1, 12), np.zeros(12), np.zeros(12)]) + [3, 0, 0]
    with _client(tmp_path) as client:
        created = _upload(client, _with_part(_CHAIN, line))
        assert created.status_code == 202, created.text
        body = settled(client, created.json()["id"], timeout=180)
        assert body["status"] == "ready", body.get("failure")
        assert [(p["name"], p["faces"]) for p in body["parts"]] == [("grid", 32), ("flat", 10)]
        level = client.get(f"/meshes/{body['id']}/lod", params={"format": "glb", "ratio": 0.5})
        assert level.status_code == 200, level.text


def _memory_mb(pid: int) -> dict:
    """VmRSS and VmHWM (peak) of process ``pid``, MiB."""
    fields = dict(line.split(":", 1) for line in
                  Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return {key: int(fields[key].split()[0]) // 1024 for key in ("VmRSS", "VmHWM")}


def test_the_red_teams_scenes_against_a_real_server(tmp_path):
    """The red team's files, full size, against a real ``serve`` process: 5M GPU
    instances and 255 targets naming one accessor refused, 250 sampler outputs
    aliasing one 12 MB bufferView built; the server's peak RSS grows by less than
    512 MB over all three, artefact and bodies at most 20 times the upload."""
    if not Path("/proc/self/status").is_file():
        pytest.skip("peak RSS is read from /proc")
    cases = [(instanced(5_000_000), 413, "4999999 GPU instances"),
             (_morphed([255], size=100), 413, "morph targets of mesh 0"),
             (aliased_clips(250, 1_000_000), 202, None)]
    with server_process(tmp_path / "data", timeout=120) as (base, process):
        before = _memory_mb(process.pid)["VmRSS"]
        for glb, status, match in cases:
            upload = glb.glb()
            response = httpx.post(f"{base}/meshes", files={"file": ("hostile.glb", upload)},
                                  timeout=300)
            assert response.status_code == status, response.text
            if match is not None:
                assert match in response.json()["message"], response.text
                continue
            mesh = response.json()["id"]
            deadline = time.monotonic() + 300
            while (body := httpx.get(f"{base}/meshes/{mesh}").json())["status"] not in (
                    "ready", "failed"):
                assert time.monotonic() < deadline, "the aliased clips did not build in 300 s"
                time.sleep(0.5)
            assert body["status"] == "ready", body.get("failure")
            artefacts = [p for p in (tmp_path / "data" / "artefacts").rglob("*") if p.is_file()]
            assert sum(p.stat().st_size for p in artefacts) <= 20 * len(upload)
            for route, params in (("chain", {"lods": "1,0.5"}),
                                  ("lod", {"format": "glb", "ratio": 0.5})):
                served = httpx.get(f"{base}/meshes/{mesh}/{route}", params=params, timeout=300)
                assert served.status_code == 200 and len(served.content) <= 20 * len(upload)
        peak = _memory_mb(process.pid)["VmHWM"]
    assert peak - before < 512, f"the server grew from {before} MB to a peak of {peak} MB"
