"""One asset model, one artefact format (lodserver.scene.asset, scene.artefact, scene.build).

A single mesh is the scene of one part without a document: stored as exactly
its ``.pm`` file, so every artefact stored before reads back; a scene is its zip.
"""

from __future__ import annotations

import threading

import numpy as np
import pytest

from lodserver.build import build
from lodserver.progressive import ArtefactError, encode_progressive, save_progressive
from lodserver.scene.artefact import decode_asset, encode_asset, load_artefact, save_asset
from lodserver.scene.asset import PartError, SceneAsset, artefact_summary, part_of
from lodserver.scene.build import build_asset

from ..meshes import mesh, progressive


def test_a_single_mesh_is_stored_as_its_pm_file_byte_for_byte(tmp_path):
    pm = progressive("grid")
    asset = SceneAsset.of_mesh(pm)
    assert asset.scene is None and asset.single is pm and asset.metadata is pm.metadata
    data = encode_asset(asset)
    assert data == encode_progressive(pm)
    save_asset(asset, tmp_path / "new.pm")
    assert (tmp_path / "new.pm").read_bytes() == data
    again = decode_asset(data)
    assert again.scene is None and len(again.parts) == 1
    assert np.array_equal(again.single.at(again.single.base_vertices + 7).faces,
                          pm.at(pm.base_vertices + 7).faces)
    assert encode_asset(again) == data


def test_an_artefact_written_before_the_asset_model_loads_as_a_single_mesh(tmp_path):
    pm = progressive("grid")
    save_progressive(pm, tmp_path / "old.pm")          # how a mesh's artefact was stored
    loaded = load_artefact(tmp_path / "old.pm")
    assert loaded.single is not None and loaded.single.vertex_count == pm.vertex_count
    assert encode_asset(loaded) == (tmp_path / "old.pm").read_bytes()


def test_a_single_mesh_answers_as_its_mesh_and_as_part_0():
    pm = progressive("grid")
    asset = SceneAsset.of_mesh(pm)
    assert asset.summary() == pm.summary()
    assert asset.materials is pm.materials
    assert part_of(asset, 0) is pm
    with pytest.raises(PartError, match="has 1 part \\(0 to 0\\); there is no part 1"):
        part_of(asset, 1)
    summary = artefact_summary(asset)
    assert summary["vertices"] == pm.vertex_count and "scene" not in summary


def test_bytes_that_are_no_artefact_are_one_sentence(tmp_path):
    with pytest.raises(ArtefactError):
        decode_asset(b"not an artefact at all", source="the upload")
    with pytest.raises(ArtefactError, match="not a readable lodserver scene"):
        decode_asset(b"PK\x03\x04" + b"\0" * 40, source="the upload")
    with pytest.raises(ArtefactError, match="cannot read"):
        load_artefact(tmp_path / "missing.pm")


def test_a_mesh_upload_builds_the_scene_of_one_part():
    asset = build_asset(mesh("grid"), build=build, options={})
    assert asset.scene is None and asset.single is not None
    # a fresh build: the shared progressive("grid") may carry a job's metadata
    assert encode_asset(asset) == encode_progressive(build(mesh("grid")))
    locked = build_asset(mesh("grid"), build=build, options={}, lock_border=True)
    # the border kept: the grid's coarsest level keeps every boundary vertex
    assert locked.single.base_vertices > asset.single.base_vertices


def test_a_cancelled_mesh_build_keeps_nothing():
    cancel = threading.Event()
    cancel.set()
    assert build_asset(mesh("grid"), build=build, options={}, cancel=cancel) is None
