"""The parse pool's failures that are not the file's own answer: a result that cannot
be pickled or sent back (a MemoryError or a pickling error in the worker), or that is
too large to hand over, is refused as a LimitError (HTTP 413) in one sentence, and
the pool replaces its worker. Real worker processes (``ParsePool``, spawned)."""

from __future__ import annotations

import os

import pytest

from lodserver.io.limits import LimitError, OutOfMemory
from lodserver.service.parsing import ParsePool, pickled_size


class _Unsendable:
    """A result whose pickling runs out of memory, as a huge one does in the worker."""

    def __reduce__(self):
        raise MemoryError


def _unsendable():
    return _Unsendable()


def _unpicklable():
    return lambda: None         # a local function has no name to be pickled by


@pytest.fixture
def pool():
    pool = ParsePool(workers=1, queue=1)
    yield pool
    pool.shutdown()


@pytest.mark.parametrize("job, match", [
    (_unsendable, "ran out of memory sending its result back"),
    (_unpicklable, "could not send its result back"),
])
def test_a_result_that_cannot_be_sent_back_is_refused_and_its_worker_replaced(pool, job,
                                                                             match):
    before = pool.call(os.getpid)
    with pytest.raises(LimitError, match=match):
        pool.call(job)
    after = pool.call(os.getpid)
    assert after != before          # a fresh worker
    assert pool.admitted == 0


def test_a_parse_result_too_large_to_hand_over_is_refused(shared_meshes):
    path = shared_meshes / "Duck.glb"
    pool = ParsePool(workers=1, queue=1, result_bytes=10_000)
    try:
        with pytest.raises(OutOfMemory, match=r"Duck\.glb: what it holds once read takes "
                           r"\d+ bytes, more than the 10000 this server hands over"):
            pool.parse(path, file_type="glb", root=path.parent, max_triangles=10**6,
                       limits=None)
        pool.result_bytes = None        # no bound: the same worker parses it
        mesh, report = pool.parse(path, file_type="glb", root=path.parent,
                                  max_triangles=10**6, limits=None)
        assert mesh.face_count > 0 and pickled_size((mesh, report)) > 10_000
    finally:
        pool.shutdown()


def test_through_the_app_a_result_too_large_is_a_413_sentence(tmp_path, shared_meshes):
    from fastapi.testclient import TestClient

    from lodserver.api.main import create_app
    from lodserver.api.settings import Settings

    settings = Settings(data_dir=tmp_path / "data", warm_kernels=False)
    with TestClient(create_app(settings)) as client:
        client.app.state.jobs.parser.result_bytes = 10_000
        data = (shared_meshes / "Duck.glb").read_bytes()
        response = client.post("/meshes", files={"file": ("duck.glb", data)})
        assert response.status_code == 413, response.text
        message = response.json()["message"]
        assert message.startswith("cannot load duck.glb: what it holds once read takes ")
        assert "\n" not in message and str(tmp_path) not in message and "/work/" not in message
        assert client.get("/meshes").json()["meshes"] == []
