"""Folder exports on Dask and through an object store (issue 14): the same bytes,
manifest, lines and failures as the local pool.

The cluster is a scheduler and two worker processes on loopback
(``tests/services/dask.py``: started here, or ``LODSERVER_TEST_DASK_SCHEDULER``),
the object store moto's S3 server (``tests/services/s3.py``).
"""

import os
import re
import signal
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import trimesh

from lodserver import schedulers
from lodserver.cli import main
from lodserver.pipeline import export_folder, find_sources

from .meshes import DATA
from .services.dask import dask_client, dask_scheduler  # noqa: F401 (fixtures)
from .services.dask import need_distributed
from .services.s3 import s3_endpoint, s3_url  # noqa: F401 (fixtures)
from .test_pipeline import _assets

LODS = (1, 0.3)


def _contents(folder: Path) -> dict:
    """Every visible file under ``folder`` (relative name -> bytes): what a reader sees."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and not any(part.startswith(".")
                                       for part in p.relative_to(folder).parts)}


def _objects(url: str) -> dict:
    """Every object under ``url`` (relative key -> bytes)."""
    import fsspec

    fs, root = fsspec.core.url_to_fs(url, skip_instance_cache=True)
    return {key[len(root) + 1:]: fs.cat_file(key) for key in sorted(fs.find(root))}


def _upload(folder: Path, url: str) -> None:
    import fsspec

    fs, root = fsspec.core.url_to_fs(url, skip_instance_cache=True)
    for name in _contents(folder):
        fs.put_file(str(folder / name), f"{root}/{name}")


def _lines(text: str) -> list[str]:
    """The per-asset lines and the summary, timings removed, sorted (completion order
    differs between runs)."""
    lines = [re.sub(r"in \d+\.\d+ s", "in T s", line) for line in text.splitlines()
             if " -> " in line or "FAILED" in line or " assets in " in line
             or "assets failed" in line]
    return sorted(lines)


def _gltf_pair(folder: Path) -> None:
    """A .gltf with its buffer in a separate .bin beside it (trimesh's writer)."""
    folder.mkdir(parents=True, exist_ok=True)
    files = trimesh.exchange.gltf.export_gltf(trimesh.creation.icosphere(2))
    for name, data in files.items():
        (folder / ("ball.gltf" if name.endswith(".gltf") else name)).write_bytes(data)
    assert any(name.endswith(".bin") for name in files)     # the buffer is its own file


def test_export_on_dask_is_the_local_export_byte_for_byte(tmp_path, dask_scheduler):
    source = _assets(tmp_path / "assets")
    _gltf_pair(source / "gltf")
    local = export_folder(source, tmp_path / "local", lods=LODS)
    seen = []
    remote = export_folder(source, tmp_path / "dask", lods=LODS, scheduler=dask_scheduler,
                           progress=lambda path, outcome: seen.append(str(path)))
    assert _contents(tmp_path / "dask") == _contents(tmp_path / "local")   # manifest too
    assert sorted(map(str, remote.failed)) == ["props/broken.stl"]
    assert remote.failed == local.failed        # the same reason, from the worker
    assert [e.source for e in remote.written] == [e.source for e in local.written]
    assert [[p.relative_to(tmp_path / "dask") for p in e.outputs] for e in remote.written] == [
        [p.relative_to(tmp_path / "local") for p in e.outputs] for e in local.written]
    assert [e.faces for e in remote.written] == [e.faces for e in local.written]
    assert sorted(seen) == ["gltf/ball.gltf", "props/ball.ply", "props/broken.stl", "spot.obj"]


def test_a_second_run_on_dask_rebuilds_only_what_changed(tmp_path, dask_client):
    source = _assets(tmp_path / "assets")
    (source / "props" / "broken.stl").unlink()
    out = tmp_path / "lods"
    assert len(export_folder(source, out, lods=LODS, scheduler=dask_client).written) == 2
    again = export_folder(source, out, lods=LODS, scheduler=dask_client)
    assert not again.written and len(again.up_to_date) == 2
    sphere = trimesh.creation.icosphere(2)
    (source / "props" / "ball.ply").write_bytes(sphere.export(file_type="ply"))
    edited = export_folder(source, out, lods=LODS, scheduler=dask_client)
    assert [str(e.source.relative_to(source)) for e in edited.written] == ["props/ball.ply"]
    # and the result is what a local run from scratch writes
    export_folder(source, tmp_path / "local", lods=LODS)
    assert _contents(out) == _contents(tmp_path / "local")


def test_the_cli_on_dask_prints_the_local_lines(tmp_path, dask_scheduler, capsys):
    source = _assets(tmp_path / "assets")
    assert main(["export", str(source), "-o", str(tmp_path / "lods"), "--lods", "1,0.3"]) == 1
    local = _lines(capsys.readouterr().err)
    assert main(["export", str(source), "-o", str(tmp_path / "lods2"), "--lods", "1,0.3",
                 "--scheduler", dask_scheduler]) == 1
    remote = _lines(capsys.readouterr().err)
    assert [line.replace("lods2:", "lods:") for line in remote] == local
    assert any("props/broken.stl: FAILED: " in line for line in remote)
    assert any("2 written, 0 up to date, 1 failed" in line for line in remote)


def _executing(dask_worker) -> list[str]:
    # runs on each worker (client.run passes the worker as ``dask_worker``)
    return [str(task.key) for task in dask_worker.state.executing]


def test_a_worker_killed_mid_batch_costs_only_a_retry(tmp_path, dask_client):
    """kill -9 of the worker building the slow asset: the scheduler runs that task
    again on a live worker, and the batch ends with the local run's bytes."""
    source = _assets(tmp_path / "assets")
    (source / "props" / "broken.stl").unlink()
    # several seconds of build on a busy 2-core machine: time to see it run and kill it
    slow = trimesh.creation.icosphere(7)
    (source / "slow.ply").write_bytes(slow.export(file_type="ply"))
    export_folder(source, tmp_path / "local", lods=LODS)

    with ThreadPoolExecutor(1) as pool:
        batch = pool.submit(export_folder, source, tmp_path / "dask", lods=LODS,
                            scheduler=dask_client)
        deadline, victim = time.monotonic() + 120, None
        while victim is None:
            assert time.monotonic() < deadline and not batch.done(), "slow.ply never ran"
            running = dask_client.run(_executing)
            victim = next((worker for worker, keys in running.items()
                           if any("slow.ply" in key for key in keys)), None)
            time.sleep(0.05)
        pid = dask_client.run(os.getpid, workers=[victim])[victim]
        os.kill(pid, signal.SIGKILL)
        report = batch.result(timeout=300)
    assert not report.failed and len(report.written) == 3
    assert _contents(tmp_path / "dask") == _contents(tmp_path / "local")
    dask_client.wait_for_workers(2, timeout=120)     # the nanny restarts it
    assert pid not in dask_client.run(os.getpid).values()


def test_s3_folders_in_and_out_on_the_local_pool(tmp_path, s3_url):
    source = _assets(tmp_path / "assets")
    _gltf_pair(source / "gltf")          # its .bin is fetched with it
    export_folder(source, tmp_path / "local", lods=LODS)
    _upload(source, f"{s3_url}/assets")
    assert [str(p) for p in find_sources(f"{s3_url}/assets")] == [
        str(p) for p in find_sources(source)]

    report = export_folder(f"{s3_url}/assets", f"{s3_url}/lods", lods=LODS, jobs=2)
    assert sorted(map(str, report.failed)) == ["props/broken.stl"]
    assert sorted(report.written[0].outputs) == [f"{s3_url}/lods/gltf/ball.glb"]
    assert _objects(f"{s3_url}/lods") == _contents(tmp_path / "local")   # spot's texture too
    # incremental through the object store's manifest; one object replaced: rebuilt alone
    again = export_folder(f"{s3_url}/assets", f"{s3_url}/lods", lods=LODS)
    assert not again.written and len(again.up_to_date) == 3
    import fsspec
    fs, root = fsspec.core.url_to_fs(s3_url, skip_instance_cache=True)
    fs.pipe_file(f"{root}/assets/props/ball.ply",
                 trimesh.creation.icosphere(1).export(file_type="ply"))
    edited = export_folder(f"{s3_url}/assets", f"{s3_url}/lods", lods=LODS)
    assert [str(e.source) for e in edited.written] == [f"{s3_url}/assets/props/ball.ply"]
    # a local folder to the object store and back again
    export_folder(source, f"{s3_url}/mixed", lods=LODS)
    export_folder(f"{s3_url}/assets", tmp_path / "back", lods=LODS)
    assert _objects(f"{s3_url}/mixed") == _contents(tmp_path / "local")
    assert (tmp_path / "back" / "gltf" / "ball.glb").read_bytes() == (
        tmp_path / "local" / "gltf" / "ball.glb").read_bytes()


def test_only_files_inside_the_source_prefix_are_fetched(tmp_path, s3_url):
    """A texture named '../../secret.png' is not fetched from outside the prefix: the
    loader then reports it missing, as it would any missing texture."""
    import fsspec
    fs, root = fsspec.core.url_to_fs(s3_url, skip_instance_cache=True)
    fs.pipe_file(f"{root}/secret.png", (DATA / "spot_texture.png").read_bytes())
    obj = (DATA / "spot.obj").read_bytes()
    fs.pipe_file(f"{root}/assets/a/spot.obj", obj)
    fs.pipe_file(f"{root}/assets/a/spot.mtl", b"newmtl m\nmap_Kd ../../secret.png\n")
    report = export_folder(f"{s3_url}/assets", f"{s3_url}/lods", lods=LODS)
    assert "'../../secret.png', which is missing" in report.failed[Path("a/spot.obj")]
    assert not fs.exists(f"{root}/lods/a/spot.glb")


def test_the_cli_on_a_local_cluster_with_s3_folders(tmp_path, s3_url, capsys):
    """--scheduler local: a LocalCluster of --jobs processes (they inherit the AWS
    variables), reading and writing the object store."""
    need_distributed()
    source = _assets(tmp_path / "assets")
    export_folder(source, tmp_path / "local", lods=LODS)
    _upload(source, f"{s3_url}/assets")
    # --compress none: what export_folder writes by default, compared below
    command = ["export", f"{s3_url}/assets", "-o", f"{s3_url}/lods", "--lods", "1,0.3",
               "--scheduler", "local", "--jobs", "2", "--compress", "none"]
    assert main(command) == 1
    err = capsys.readouterr().err
    assert "spot.obj -> spot.glb: 2 levels of 5856, " in err
    assert "props/broken.stl: FAILED: " in err and "2 written, 0 up to date, 1 failed" in err
    assert _objects(f"{s3_url}/lods") == _contents(tmp_path / "local")
    (source / "props" / "broken.stl").unlink()
    fs_root = f"{s3_url}/assets/props/broken.stl"
    import fsspec
    fs, key = fsspec.core.url_to_fs(fs_root, skip_instance_cache=True)
    fs.rm(key)
    assert main(command) == 0
    assert "0 written, 2 up to date, 0 failed" in capsys.readouterr().err


def test_without_dask_the_scheduler_flag_names_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)      # import fails as if absent
    source = _assets(tmp_path / "assets")
    assert main(["export", str(source), "-o", str(tmp_path / "lods"),
                 "--scheduler", "local"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == ("lodserver export: running on Dask needs the distributed extra: "
                   "pip install 'lodserver[distributed]'")
    assert not (tmp_path / "lods" / "spot.glb").exists()


def test_bad_schedulers_are_one_sentence(tmp_path, monkeypatch, capsys):
    need_distributed()
    source = _assets(tmp_path / "assets")
    assert main(["export", str(source), "-o", str(tmp_path / "lods"), "--scheduler",
                 "nowhere"]) == 1
    assert "the scheduler must be 'local' or a Dask address" in capsys.readouterr().err
    monkeypatch.setattr(schedulers, "CONNECT_SECONDS", 1)
    assert main(["export", str(source), "-o", str(tmp_path / "lods"), "--scheduler",
                 "tcp://127.0.0.1:9"]) == 1
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in err
    assert "Traceback" not in err
    assert main(["export", str(DATA / "spot.obj"), "-o", str(tmp_path / "x.glb"),
                 "--scheduler", "local"]) == 1
    assert "--scheduler runs the assets of a folder" in capsys.readouterr().err
    with pytest.raises(schedulers.SchedulerError, match="must be 'local'"):
        export_folder(source, tmp_path / "lods", scheduler=42)
    assert not (tmp_path / "lods" / "spot.glb").exists()
