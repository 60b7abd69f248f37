"""Background builds: failures stay with their mesh, shutdown leaves builds resumable."""

import threading
import time

from lodserver.service import jobs as jobs_module
from lodserver.service.jobs import JobRunner
from lodserver.mesh import MeshError
from lodserver.service.store import Status

from ..meshes import DATA, progressive


def _queue(store, tmp_path, name):
    source = tmp_path / f"{name}.obj"
    source.write_bytes((DATA / "spot.obj").read_bytes())
    return store.create(name=name, source=source, file_type="obj",
                        options={"min_vertices": 0}).id


def _wait(store, mesh_id, statuses=("ready", "failed"), timeout=60):
    deadline = time.monotonic() + timeout
    while (record := store.get(mesh_id=mesh_id)).status.value not in statuses:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    return record


def test_a_failed_build_marks_only_its_mesh(store, tmp_path, monkeypatch):
    def fake_build(mesh, **options):
        if bad_turn.is_set():
            raise MeshError("the mesh folds onto itself")
        return progressive("grid")

    bad_turn = threading.Event()
    monkeypatch.setattr(jobs_module, "build", fake_build)
    runner = JobRunner(store)
    bad, good = _queue(store, tmp_path, "bad"), _queue(store, tmp_path, "good")
    bad_turn.set()
    runner.submit(bad)
    assert _wait(store, bad).failure == "the mesh folds onto itself"
    bad_turn.clear()
    runner.submit(good)
    assert _wait(store, good).status is Status.READY
    runner.shutdown()
    assert store.get(mesh_id=bad).status is Status.FAILED


def test_shutdown_requeues_a_running_build_but_not_a_finished_one(store, tmp_path, monkeypatch):
    started = threading.Event()

    def slow_build(mesh, *, cancel, **options):
        if options["min_vertices"] == 7:
            started.set()
            cancel.wait(30)
        return progressive("grid")

    monkeypatch.setattr(jobs_module, "build", slow_build)
    runner = JobRunner(store)
    done = _queue(store, tmp_path, "done")
    runner.submit(done)
    _wait(store, done)
    source = tmp_path / "slow.obj"
    source.write_bytes((DATA / "spot.obj").read_bytes())
    slow = store.create(name="slow", source=source, file_type="obj",
                        options={"min_vertices": 7}).id
    runner.submit(slow)
    assert started.wait(30)
    runner.shutdown()
    assert store.get(mesh_id=slow).status is Status.QUEUED
    assert store.get(mesh_id=done).status is Status.READY
    assert store.recover() == [slow]


def test_a_build_reuses_the_mesh_its_upload_check_parsed(store, tmp_path, monkeypatch):
    """The upload is parsed once: when it is checked; the build takes that mesh."""
    parsed = []
    check = jobs_module.check_mesh_file

    def counted(path, **options):
        parsed.append(path)
        return check(path, **options)

    monkeypatch.setattr(jobs_module, "check_mesh_file", counted)
    runner = JobRunner(store)
    source = tmp_path / "spot.obj"
    source.write_bytes((DATA / "spot.obj").read_bytes())
    record = runner.accept(source=source, name="spot.obj", file_type="obj", options={})
    assert _wait(store, record.id).status is Status.READY
    runner.shutdown()
    assert len(parsed) == 1
