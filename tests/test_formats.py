"""The output-format registry (``io.save.OUTPUT_FORMATS``) is the one list: every
format in it is accepted by the CLI and the routes, and nothing else is."""

import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from lodserver.cli import main
from lodserver.io import OUTPUT_FORMATS, SERVED_FORMATS, SUPPORTED_OUTPUT, save_mesh

from .api.test_api import _upload, _wait_ready
from .meshes import DATA, textured_sphere

# names no format in the registry has
NOT_FORMATS = ["gltf", "fbx", "pm", "txt", "GLB "]


def test_the_registry_derives_every_list():
    assert SUPPORTED_OUTPUT == tuple(name for name, f in OUTPUT_FORMATS.items() if f.writer)
    assert list(SERVED_FORMATS) == [name for name, f in OUTPUT_FORMATS.items() if f.served]
    assert all(f.suffix == f".{name}" and f.name == name for name, f in OUTPUT_FORMATS.items())
    # the json form is the server's own: no file writer, served only
    assert "json" in SERVED_FORMATS and "json" not in SUPPORTED_OUTPUT


@pytest.fixture(scope="module")
def asset(tmp_path_factory):
    folder = tmp_path_factory.mktemp("formats")
    source = folder / "sphere.glb"
    save_mesh(textured_sphere(8, 6), source)
    built = folder / "sphere.pm"
    assert main(["build", str(source), "-o", str(built)]) == 0
    return built


@pytest.mark.parametrize("name", SUPPORTED_OUTPUT)
def test_the_cli_writes_every_file_format(asset, tmp_path, name):
    out = tmp_path / f"level{OUTPUT_FORMATS[name].suffix}"
    assert main(["extract", str(asset), "--ratio", "0.5", "-o", str(out)]) == 0
    assert out.stat().st_size > 0


@pytest.mark.parametrize("name", ["json"] + NOT_FORMATS)
def test_the_cli_refuses_other_suffixes(asset, tmp_path, name, capsys):
    out = tmp_path / f"level.{name}"
    assert main(["extract", str(asset), "--ratio", "0.5", "-o", str(out)]) == 1
    assert "supported types are " + ", ".join(SUPPORTED_OUTPUT) in capsys.readouterr().err
    assert not out.exists()


def test_the_cli_help_names_every_file_format(capsys):
    with pytest.raises(SystemExit):
        main(["extract", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert all(name.upper() in help_text for name in SUPPORTED_OUTPUT)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    settings = Settings(data_dir=tmp_path_factory.mktemp("api") / "data", warm_kernels=False)
    with TestClient(create_app(settings)) as client:
        mesh_id = _upload(client, (DATA / "spot.obj").read_bytes()).json()["id"]
        assert _wait_ready(client, mesh_id)["status"] == "ready"
        yield client, mesh_id


@pytest.mark.parametrize("route", ["lod", "parts/0/lod"])
def test_the_routes_serve_every_served_format_and_nothing_else(served, route):
    client, mesh_id = served
    for name, media_type in SERVED_FORMATS.items():
        response = client.get(f"/meshes/{mesh_id}/{route}", params={"vertices": 100,
                                                                    "format": name})
        assert response.status_code == 200, (name, response.text)
        assert response.headers["content-type"].split(";")[0] == media_type
    refused = [name for name in OUTPUT_FORMATS if name not in SERVED_FORMATS] + NOT_FORMATS
    for name in refused:
        response = client.get(f"/meshes/{mesh_id}/{route}", params={"vertices": 100,
                                                                    "format": name})
        assert response.status_code == 422, name


def test_the_openapi_document_lists_the_served_formats(served):
    client, _ = served
    document = client.get("/openapi.json").json()
    for path in ("/meshes/{mesh_id}/lod", "/meshes/{mesh_id}/parts/{index}/lod"):
        (parameter,) = [p for p in document["paths"][path]["get"]["parameters"]
                        if p["name"] == "format"]
        assert parameter["schema"]["enum"] == list(SERVED_FORMATS)
