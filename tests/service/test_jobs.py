"""Background builds: failures stay with their mesh, shutdown leaves builds resumable,
and runners of two stores sharing one catalogue see each other's deletes and failures."""

import threading
import time

import pytest

from lodserver.service import jobs as jobs_module
from lodserver.service.jobs import JobRunner
from lodserver.mesh import MeshError
from lodserver.service.store import Status

from ..meshes import DATA, progressive
from .conftest import DIALECTS


def _copy(tmp_path, name):
    """A copy of spot.obj at tmp_path/<name>.obj."""
    source = tmp_path / f"{name}.obj"
    source.write_bytes((DATA / "spot.obj").read_bytes())
    return source


def _queue(store, tmp_path, name):
    return store.create(name=name, source=_copy(tmp_path, name), file_type="obj",
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
    slow = store.create(name="slow", source=_copy(tmp_path, "slow"), file_type="obj",
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
    record = runner.accept(source=_copy(tmp_path, "spot"), name="spot.obj", file_type="obj",
                           options={})
    assert _wait(store, record.id).status is Status.READY
    runner.shutdown()
    assert len(parsed) == 1


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_a_delete_on_one_server_stops_the_build_on_another(two_stores, tmp_path, monkeypatch,
                                                           caplog):
    one, two = two_stores
    caplog.set_level("WARNING", logger=jobs_module.__name__)
    started, stopped = threading.Event(), threading.Event()

    def endless_build(mesh, *, cancel, progress, **options):
        started.set()
        done = 0
        while not cancel.wait(0.05):        # a build reporting progress, never finishing
            done += 1
            progress(done, 10**6)
        stopped.set()
        return progressive("grid")

    monkeypatch.setattr(jobs_module, "build", endless_build)
    builder = JobRunner(two, lease_seconds=3, poll_seconds=0.1)
    builder.start(warm=False)               # builds whatever the catalogue queues
    mesh_id = _queue(one, tmp_path, "far")
    assert started.wait(30)
    assert _wait(one, mesh_id, statuses=("building",)).status is Status.BUILDING
    deleted = time.monotonic()
    one.delete(mesh_id=mesh_id)              # another server's delete
    assert stopped.wait(10)
    # its next progress write found the row gone (well before a lease renewal),
    # and the log says so once, although no heartbeat has run into it yet
    assert time.monotonic() - deleted < 2
    builder.shutdown()
    said = [r.getMessage() for r in caplog.records if "lost its lease" in r.getMessage()]
    assert said == [f"the build of mesh {mesh_id} lost its lease (deleted, or taken over); "
                    "stopping it"]
    assert list((tmp_path / "blobs" / "artefacts").iterdir()) == []


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_progress_and_failures_are_seen_across_servers(two_stores, tmp_path, monkeypatch):
    one, two = two_stores
    halfway, go_on = threading.Event(), threading.Event()

    def failing_build(mesh, *, progress, **options):
        progress(0, 10)
        time.sleep(jobs_module.PROGRESS_INTERVAL)
        progress(5, 10)
        halfway.set()
        go_on.wait(30)
        raise MeshError("the mesh folds onto itself")

    monkeypatch.setattr(jobs_module, "build", failing_build)
    builder = JobRunner(two, lease_seconds=3, poll_seconds=0.1)
    builder.start(warm=False)
    mesh_id = _queue(one, tmp_path, "bad")
    assert halfway.wait(30)
    assert one.get(mesh_id=mesh_id).progress == 0.5
    go_on.set()
    failed = _wait(one, mesh_id)
    assert failed.status is Status.FAILED and failed.failure == "the mesh folds onto itself"
    builder.shutdown()
    assert list((tmp_path / "blobs" / "sources").iterdir()) == []


@pytest.mark.parametrize("catalog_url", DIALECTS, indirect=True)
def test_a_runner_that_only_serves_builds_nothing(two_stores, tmp_path):
    one, two = two_stores
    serving = JobRunner(one, workers=0, poll_seconds=0.1)
    serving.start(warm=False)
    record = serving.accept(source=_copy(tmp_path, "s"), name="s.obj", file_type="obj",
                            options={})
    time.sleep(0.5)
    assert one.get(mesh_id=record.id).status is Status.QUEUED
    builder = JobRunner(two, poll_seconds=0.1)
    builder.start(warm=False)
    assert _wait(one, record.id).status is Status.READY
    for runner in (serving, builder):
        runner.shutdown()
