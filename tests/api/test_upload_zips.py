"""Zip uploads through the real app: kept as they came (compressed), unpacked once
(by the parse worker, never by the server), their unpacked size tied to the
largest upload; and the bytes that queued builds hold bounded (503 with
Retry-After past the budget) on a SQLite and a PostgreSQL catalogue."""

import io
import random
import zipfile
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from lodserver.api.main import create_app
from lodserver.api.settings import Settings
from ..meshes import DATA
from ..services.postgres import postgres_server, postgres_url  # noqa: F401 (fixtures)
from . import settled

SPOT_FILES = ("spot.obj", "spot.mtl", "spot_texture.png")
SPOT = (DATA / "spot.obj").read_bytes()
MIB = 2**20


def _client(tmp_path, **overrides):
    options = {"data_dir": tmp_path / "data", "warm_kernels": False, **overrides}
    return TestClient(create_app(Settings(**options)))


def _zip(entries) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        for name, data in entries:
            archive.writestr(name, data)
    return buffer.getvalue()


def _padding(count: int, seed: int = 1) -> list[tuple[str, bytes]]:
    """``count`` entries of 1 MiB that deflate about 80 times: within every ratio rule."""
    rng = random.Random(seed)
    return [(f"pad/{i}.bin", rng.randbytes(12000) + bytes(MIB - 12000)) for i in range(count)]


def _written() -> int:
    """Bytes this process and its children (the parse workers) passed to write()."""
    pids = ["self"]
    for task in Path("/proc/self/task").iterdir():
        try:
            pids += (task / "children").read_text().split()
        except OSError:
            continue        # a thread that ended meanwhile
    total = 0
    for pid in pids:
        try:
            lines = Path(f"/proc/{pid}/io").read_text().splitlines()
        except OSError:
            continue        # a worker that ended meanwhile
        total += next(int(line.split()[1]) for line in lines if line.startswith("wchar"))
    return total


def test_a_zip_is_kept_compressed_and_only_what_the_mesh_names_is_unpacked(tmp_path):
    """The server lists the archive and keeps it as it came; its parse extracts the
    mesh and the files it names, never the 16 MiB of files nothing names."""
    padding = _padding(16)
    unpacked = sum(len(data) for _, data in padding)
    archive = _zip([(name, (DATA / name).read_bytes()) for name in SPOT_FILES] + padding)
    with _client(tmp_path) as client:
        # a first upload, built, starts the parse worker and compiles the kernels (a
        # fresh checkout writes numba's cache then), so neither is counted below
        first = client.post("/meshes", files={"file": ("spot.obj", SPOT)})
        assert first.status_code == 202
        assert settled(client, first.json()["id"])["status"] == "ready"
        before = _written()
        created = client.post("/meshes", files={"file": ("spot.zip", archive)})
        written = _written() - before
        assert created.status_code == 202, created.text
        assert created.json()["main"] == "spot.obj"
        assert written < len(archive) + unpacked // 4, (written, len(archive), unpacked)
        mesh_id = created.json()["id"]
        stored = client.get(f"/meshes/{mesh_id}").json()
        # the zip as it came (its comment rewritten to name the main file), not 16 MiB
        assert stored["file_type"] == "zip"
        assert abs(stored["source_bytes"] - len(archive)) < 1024, stored["source_bytes"]
        sources = list((tmp_path / "data" / "sources").glob("*.zip"))
        assert [path.stat().st_size for path in sources] == [stored["source_bytes"]]
        with zipfile.ZipFile(sources[0]) as kept:
            assert kept.comment == b"lodserver-main:spot.obj"
            assert all(info.compress_type == zipfile.ZIP_DEFLATED for info in kept.infolist())
        assert settled(client, mesh_id)["status"] == "ready"
        assert client.get(f"/meshes/{mesh_id}/materials").status_code == 200
        assert list((tmp_path / "data" / "tmp").iterdir()) == []


def test_a_corrupt_file_the_mesh_names_is_422(tmp_path):
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        for name in SPOT_FILES:
            archive.writestr(name, (DATA / name).read_bytes())
    data = bytearray(buffer.getvalue())
    data[data.find(b"newmtl")] ^= 0x20          # inside spot.mtl's stored bytes
    with _client(tmp_path) as client:
        refused = client.post("/meshes", files={"file": ("spot.zip", bytes(data))})
        assert refused.status_code == 422, refused.text
        assert "CRC" in refused.json()["message"]
        assert client.get("/meshes").json()["meshes"] == []
        assert list((tmp_path / "data" / "tmp").iterdir()) == []


def test_a_stored_zip_is_built_again_after_a_restart_by_its_main_field(tmp_path):
    """The main file named by the form survives in the stored zip's comment: a build
    resumed from the stored source (nothing parsed in memory) picks the same one."""
    archive = _zip([("a.obj", SPOT), ("b.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")])
    with _client(tmp_path, workers=0) as client:
        created = client.post("/meshes", files={"file": ("two.zip", archive)},
                              data={"main": "a.obj"})
        assert created.status_code == 202, created.text
        mesh_id = created.json()["id"]
    with _client(tmp_path) as client:
        built = settled(client, mesh_id)
        assert built["status"] == "ready", built
        assert built["faces"] == SPOT.count(b"\nf ")


def test_the_unpacked_limit_is_a_ratio_of_the_largest_upload(tmp_path):
    archive = _zip([("spot.obj", SPOT)] + _padding(3))      # about 40 KB, unpacks to 3 MiB
    with _client(tmp_path, max_upload_bytes=MIB, zip_unpacked_ratio=2) as client:
        refused = client.post("/meshes", files={"file": ("spot.zip", archive)})
        assert refused.status_code == 413, refused.text
        assert f"more than {2 * MIB} bytes uncompressed" in refused.json()["message"]
        assert client.get("/meshes").json()["meshes"] == []
        assert list((tmp_path / "data" / "tmp").iterdir()) == []
    with _client(tmp_path, max_upload_bytes=MIB, zip_unpacked_ratio=4) as client:
        taken = client.post("/meshes", files={"file": ("spot.zip", archive)})
        assert taken.status_code == 202, taken.text


@pytest.fixture(params=["sqlite", "postgresql"])
def catalog_url(request, tmp_path):
    if request.param == "sqlite":
        return None
    from lodserver.service.catalog import PostgresCatalog
    url = request.getfixturevalue("postgres_url")
    catalog = PostgresCatalog(url)
    catalog._run("DELETE FROM meshes")
    catalog.close()
    return url


def test_the_bytes_held_by_queued_builds_are_bounded(tmp_path, catalog_url):
    """Nothing builds here (workers=0): each upload's source stays while it is queued."""
    budget = len(SPOT) * 5 // 2
    with _client(tmp_path, workers=0, catalog_url=catalog_url,
                 queued_source_bytes=budget) as client:
        first, second = (client.post("/meshes", files={"file": ("spot.obj", SPOT)})
                         for _ in range(2))
        assert first.status_code == second.status_code == 202, (first.text, second.text)
        refused = client.post("/meshes", files={"file": ("spot.obj", SPOT)})
        assert refused.status_code == 503, refused.text
        assert int(refused.headers["Retry-After"]) > 0
        assert "waiting to be built" in refused.json()["message"]
        assert len(client.get("/meshes").json()["meshes"]) == 2
        assert list((tmp_path / "data" / "tmp").iterdir()) == []
        # a build done (here: a mesh deleted) gives its room back
        assert client.delete(f"/meshes/{first.json()['id']}").status_code == 204
        assert client.post("/meshes", files={"file": ("spot.obj", SPOT)}).status_code == 202
        # an upload that could never fit is a 413, not a 503 to retry forever
        big = SPOT + b"# padding\n" * len(SPOT)
        never = client.post("/meshes", files={"file": ("spot.obj", big)})
        assert never.status_code == 413, never.text
