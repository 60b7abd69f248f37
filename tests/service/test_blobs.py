"""Blobs: the same behaviour from a local folder and from a real S3 server (moto)."""

from __future__ import annotations

import hashlib
import os
import threading
import time

import pytest

from lodserver.service.blobs import (
    BlobKeyError,
    BlobNotFoundError,
    FsspecBlobs,
    LocalBlobs,
    check_key,
    open_blobs,
    sha256_file,
)
from lodserver.service.errors import StoreError
from tests.services.s3 import s3_endpoint, s3_url  # noqa: F401 (fixtures)


@pytest.fixture(params=["local", "s3"])
def blobs(request, tmp_path):
    """A LocalBlobs in tmp_path, or an FsspecBlobs in a fresh moto bucket."""
    if request.param == "local":
        return open_blobs(tmp_path / "store")
    return open_blobs(request.getfixturevalue("s3_url"))


def test_open_blobs_dispatches_on_the_url(tmp_path, s3_url):
    assert isinstance(open_blobs(tmp_path / "a"), LocalBlobs)
    assert isinstance(open_blobs((tmp_path / "b").as_uri()), LocalBlobs)
    assert (tmp_path / "b").is_dir()
    assert isinstance(open_blobs(s3_url), FsspecBlobs)


def test_put_get_round_trip(blobs, tmp_path):
    source = tmp_path / "source.bin"
    data = os.urandom(300_000)
    source.write_bytes(data)
    blobs.put_file("sources/abc.obj", source)
    assert source.read_bytes() == data          # put_file copies by default
    assert blobs.exists("sources/abc.obj") and blobs.size("sources/abc.obj") == len(data)
    with blobs.open("sources/abc.obj") as file:
        assert file.read(10) == data[:10]
        assert file.read() == data[10:]
    blobs.get_file("sources/abc.obj", tmp_path / "copy.bin")
    assert (tmp_path / "copy.bin").read_bytes() == data
    assert not [name for name in os.listdir(tmp_path) if name.endswith(".tmp")]
    blobs.put_bytes("sources/abc.obj", b"replaced")
    assert blobs.get_bytes("sources/abc.obj") == b"replaced"


def test_move_takes_the_file(blobs, tmp_path):
    source = tmp_path / "upload.bin"
    source.write_bytes(b"upload")
    blobs.put_file("sources/x.ply", source, move=True)
    assert not source.exists()
    assert blobs.get_bytes("sources/x.ply") == b"upload"


def test_missing_objects_are_a_clear_error(blobs, tmp_path):
    assert not blobs.exists("artefacts/none.pm")
    for call in (lambda: blobs.open("artefacts/none.pm"), lambda: blobs.size("artefacts/none.pm"),
                 lambda: blobs.get_file("artefacts/none.pm", tmp_path / "out"),
                 lambda: blobs.get_bytes("artefacts/none.pm")):
        with pytest.raises(BlobNotFoundError, match="no stored object has the key "
                                                    "'artefacts/none.pm'") as caught:
            call()
        assert isinstance(caught.value, StoreError) and str(tmp_path) not in str(caught.value)
    assert not (tmp_path / "out").exists()
    blobs.delete("artefacts/none.pm")         # deleting nothing is fine


def test_delete_and_keys(blobs):
    for key in ("artefacts/a.pm", "artefacts/b.pm", "sources/c.obj"):
        blobs.put_bytes(key, key.encode())
    assert sorted(blobs.keys()) == ["artefacts/a.pm", "artefacts/b.pm", "sources/c.obj"]
    assert sorted(blobs.keys("artefacts")) == ["artefacts/a.pm", "artefacts/b.pm"]
    assert list(blobs.keys("nothing")) == []
    blobs.delete("artefacts/a.pm")
    assert not blobs.exists("artefacts/a.pm")
    assert sorted(blobs.keys()) == ["artefacts/b.pm", "sources/c.obj"]


@pytest.mark.parametrize("key", ["", "/abs.pm", "a/../b", "..", "a//b", "a/./b", ".hidden",
                                 "a/.x.tmp", "a\\b", "a b", "s3://x/y", "x" * 600, None])
def test_bad_keys_are_refused_before_the_store_is_touched(blobs, key):
    with pytest.raises(BlobKeyError):
        blobs.put_bytes(key, b"x")
    with pytest.raises(BlobKeyError):
        blobs.open(key)
    assert list(blobs.keys()) == []


def test_good_keys():
    for key in ("a", "artefacts/" + "0" * 64 + ".pm", "sources/Ab_-9.obj", "a/b/c.d.e"):
        assert check_key(key) == key


def test_local_keys_stay_in_the_folder(tmp_path):
    blobs = LocalBlobs(tmp_path / "store")
    with pytest.raises(BlobKeyError):
        blobs.put_bytes("../escape", b"x")
    assert not (tmp_path / "escape").exists()
    assert blobs.local_path("artefacts/a.pm") is None
    blobs.put_bytes("artefacts/a.pm", b"x")
    assert blobs.local_path("artefacts/a.pm") == tmp_path / "store" / "artefacts" / "a.pm"


def test_sha256_file(tmp_path):
    data = os.urandom(3 * 2**20 + 5)          # more than one read
    (tmp_path / "f").write_bytes(data)
    assert sha256_file(tmp_path / "f") == hashlib.sha256(data).hexdigest()


def test_local_writes_are_atomic_for_readers(tmp_path):
    """A reader polling the key while it is rewritten sees only whole versions."""
    blobs = LocalBlobs(tmp_path / "store")
    versions = [bytes([n]) * 2_000_000 for n in range(6)]
    blobs.put_bytes("artefacts/a.pm", versions[0])
    seen, done = set(), threading.Event()

    def read():
        while not done.is_set():
            data = blobs.get_bytes("artefacts/a.pm")
            seen.add(data in versions)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for version in versions[1:]:
            source = tmp_path / "next.bin"
            source.write_bytes(version)
            blobs.put_file("artefacts/a.pm", source)
    finally:
        done.set()
        reader.join()
    assert seen == {True}
    assert blobs.get_bytes("artefacts/a.pm") == versions[-1]


def test_local_temporaries_are_never_keys(tmp_path):
    blobs = LocalBlobs(tmp_path / "store")
    blobs.put_bytes("artefacts/a.pm", b"x")
    (tmp_path / "store" / "artefacts" / ".a.pm.0123.tmp").write_bytes(b"partial")
    assert list(blobs.keys()) == ["artefacts/a.pm"]


def test_s3_large_file_is_multipart_and_never_seen_partial(s3_url, tmp_path):
    """A file above s3fs's block size goes up in parts; while it does, the key
    holds the previous object or nothing, never a prefix of the new one."""
    part = 5 * 2**20
    blobs = FsspecBlobs(s3_url, part_bytes=part)
    data = os.urandom(2 * part + 2**20)        # three parts
    source = tmp_path / "big.bin"
    source.write_bytes(data)
    blobs.put_bytes("artefacts/big.pm", b"old")
    observed, done = [], threading.Event()

    def read():
        while not done.is_set():
            try:
                observed.append(len(blobs.get_bytes("artefacts/big.pm")))
            except BlobNotFoundError:
                observed.append(None)

    reader = threading.Thread(target=read)
    reader.start()
    try:
        blobs.put_file("artefacts/big.pm", source)
    finally:
        done.set()
        reader.join()
    assert set(observed) <= {3, len(data)} and observed
    assert blobs.get_bytes("artefacts/big.pm") == data
    # S3 gives a multipart object the ETag "<md5 of the part md5s>-<parts>"
    assert blobs.fs.info(f"{blobs.root}/artefacts/big.pm")["ETag"].strip('"').endswith("-3")


def test_s3_missing_bucket_is_a_clear_error(s3_url):
    with pytest.raises(StoreError, match="no bucket 'lodserver-no-such-bucket'"):
        open_blobs("s3://lodserver-no-such-bucket/prefix")
    with pytest.raises(StoreError, match="names a bucket"):
        open_blobs("s3://")


def test_s3_unreachable_endpoint_is_a_clear_error(s3_url, monkeypatch):
    from tests.services.s3 import free_port

    monkeypatch.setenv("AWS_ENDPOINT_URL", f"http://127.0.0.1:{free_port()}")
    with pytest.raises(StoreError) as caught:
        # one attempt: s3fs and botocore would otherwise retry for about 10 s (the
        # config makes this file system an instance of its own, free to change)
        blobs = FsspecBlobs(s3_url, check=False,
                            config_kwargs={"retries": {"max_attempts": 1}})
        blobs.fs.retries = 1
        blobs.put_bytes("a", b"x")
    assert "'a'" in str(caught.value) and "127.0.0.1" not in str(caught.value)
    # at start: "could not be reached", not "no bucket" (one botocore attempt;
    # s3fs still retries a few times, about 2 s)
    with pytest.raises(StoreError, match="could not be reached while reaching"):
        FsspecBlobs(s3_url, config_kwargs={"retries": {"max_attempts": 1}})


def test_s3_objects_are_shared_between_instances(s3_url):
    """Two servers are two Blobs over one URL: what one writes or deletes the
    other sees at once (no listing cache)."""
    first, second = FsspecBlobs(s3_url), FsspecBlobs(s3_url)
    assert list(second.keys()) == []
    first.put_bytes("artefacts/a.pm", b"one")
    assert second.exists("artefacts/a.pm") and list(second.keys()) == ["artefacts/a.pm"]
    first.delete("artefacts/a.pm")
    assert not second.exists("artefacts/a.pm") and list(second.keys()) == []


def test_s3_a_store_that_stops_reading_an_upload_is_unavailable_in_bounded_time(
        s3_endpoint, s3_url, tmp_path, monkeypatch):
    """botocore's read timeout bounds the wait for an answer, not the writing of a
    body: a store that stops reading mid-upload would hold the put (and the build
    or request behind it) for ever. The call's own deadline ends it."""
    from urllib.parse import urlsplit

    from lodserver.service import blobs as blobs_module
    from lodserver.service.errors import StoreUnavailable
    from tests.services.gate import Gate

    where = urlsplit(s3_endpoint)
    gate = Gate((where.hostname, where.port))
    try:
        monkeypatch.setenv("AWS_ENDPOINT_URL", gate.endpoint)
        monkeypatch.setattr(blobs_module, "CALL_SECONDS", 3.0)
        blobs = FsspecBlobs(s3_url, part_bytes=5 * 2**20,
                            config_kwargs={"retries": {"max_attempts": 1}})
        source = tmp_path / "big.bin"
        source.write_bytes(os.urandom(12 * 2**20))     # above any loopback socket buffer
        gate.stall_requests_to(b"PUT /")
        started = time.monotonic()
        with pytest.raises(StoreUnavailable) as caught:
            blobs.put_file("artefacts/big.pm", source)
        assert gate.seen.is_set()
        assert time.monotonic() - started < 60, "the deadline did not end the put"
        assert "'artefacts/big.pm'" in str(caught.value) and "127.0.0.1" not in str(caught.value)
        # the parts already sent are not left in the bucket: the upload was aborted
        # (the abort went up while the stalled connection still hung)
        bucket = s3_url.removeprefix("s3://").split("/")[0]
        unfinished = blobs.fs.call_s3("list_multipart_uploads", Bucket=bucket)
        assert unfinished.get("Uploads", []) == []
        assert not blobs.exists("artefacts/big.pm")
    finally:
        gate.close()


def test_s3_a_refused_part_aborts_the_upload(s3_url, tmp_path, monkeypatch):
    """Any end of a multipart upload short of completing it aborts it, so no
    invisible parts stay billed in the bucket."""
    blobs = FsspecBlobs(s3_url, part_bytes=5 * 2**20)
    source = tmp_path / "big.bin"
    source.write_bytes(os.urandom(11 * 2**20))
    sent = []
    real = blobs.fs._call_s3

    async def refuse_the_second_part(method, *args, **kwargs):
        if method == "upload_part":
            sent.append(kwargs["PartNumber"])
            if kwargs["PartNumber"] == 2:
                raise PermissionError("refused")
        return await real(method, *args, **kwargs)

    monkeypatch.setattr(blobs.fs, "_call_s3", refuse_the_second_part)
    with pytest.raises(StoreError, match="refused access while storing 'artefacts/big.pm'"):
        blobs.put_file("artefacts/big.pm", source)
    monkeypatch.setattr(blobs.fs, "_call_s3", real)
    assert sent == [1, 2]
    bucket = s3_url.removeprefix("s3://").split("/")[0]
    assert blobs.fs.call_s3("list_multipart_uploads", Bucket=bucket).get("Uploads", []) == []
    assert not blobs.exists("artefacts/big.pm")
    blobs.put_file("artefacts/big.pm", source)
    assert blobs.get_bytes("artefacts/big.pm") == source.read_bytes()
