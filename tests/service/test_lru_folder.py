"""LruFolder: the bounded, leased, least-recently-used folder under the artefact
cache and the body files."""

from __future__ import annotations

import os
import re

import pytest

from lodserver.service.lru_folder import LruFolder

NAMES = re.compile(r"[a-z]")


def writer(data: bytes):
    def fetch(dest):
        dest.write_bytes(data)
    return fetch


def test_a_write_makes_room_least_recently_used_first(tmp_path):
    folder = LruFolder(tmp_path, 10, names=NAMES, what="test file")
    assert folder.write("a", b"1234") and folder.write("b", b"1234")
    assert folder.touch("a")                    # b is now the least recently used
    assert folder.write("c", b"1234")
    assert "b" not in folder and "a" in folder and folder.size == 8
    assert sorted(os.listdir(tmp_path)) == ["a", "c"]


def test_a_leased_file_stays_and_a_write_without_room_is_refused(tmp_path):
    folder = LruFolder(tmp_path, 10, names=NAMES, what="test file")
    assert folder.write("a", b"12345678")
    path, size = folder.lease("a")
    assert size == 8 and not folder.write("b", b"87654321")
    assert path.read_bytes() == b"12345678" and not (tmp_path / "b").exists()
    folder.release("a")
    assert folder.write("b", b"87654321") and "a" not in folder


def test_a_fetched_file_larger_than_the_bound_stays_until_the_next(tmp_path):
    folder = LruFolder(tmp_path, 10, names=NAMES, what="test file")
    folder.fetch("a", writer(b"x" * 20))
    assert "a" in folder and folder.size == 20
    folder.fetch("b", writer(b"y" * 5))
    assert "a" not in folder and folder.size == 5


def test_a_failed_fetch_keeps_nothing(tmp_path):
    folder = LruFolder(tmp_path, 10, names=NAMES, what="test file")

    def broken(dest):
        dest.write_bytes(b"part")
        raise OSError("the store went away")

    with pytest.raises(OSError):
        folder.fetch("a", broken)
    assert "a" not in folder and os.listdir(tmp_path) == []


def test_a_discarded_leased_file_goes_with_its_last_lease(tmp_path):
    folder = LruFolder(tmp_path, 10, names=NAMES, what="test file")
    folder.fetch("a", writer(b"123"))
    path, _ = folder.lease("a")
    folder.lease("a")
    folder.discard("a")
    assert "a" not in folder and path.exists()
    folder.release("a")
    assert path.exists()
    folder.release("a")
    assert not path.exists()


def test_opening_keeps_its_own_files_and_removes_temporaries(tmp_path):
    (tmp_path / "a").write_bytes(b"123")
    (tmp_path / ".a.tmp").write_bytes(b"12")
    (tmp_path / "NOT-OURS").write_bytes(b"1")
    folder = LruFolder(tmp_path, 10, names=NAMES, what="test file")
    assert "a" in folder and folder.size == 3
    assert sorted(os.listdir(tmp_path)) == ["NOT-OURS", "a"]
