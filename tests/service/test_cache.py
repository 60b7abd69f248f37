"""ArtefactCache: bounded in bytes, least recently used out first, one fetch per miss."""

from __future__ import annotations

import os
import threading
import time

import pytest

from lodserver.service.blobs import LocalBlobs, open_blobs, sha256_file
from lodserver.service.cache import ArtefactCache, file_name
from tests.services.s3 import s3_endpoint, s3_url  # noqa: F401 (fixtures)


def writer(data: bytes, calls: list | None = None, delay: float = 0.0):
    """A fetch that writes ``data`` (after ``delay`` seconds), counting its calls."""
    def fetch(dest):
        if calls is not None:
            calls.append(dest)
        time.sleep(delay)
        dest.write_bytes(data)
    return fetch


def files_in(folder) -> set[str]:
    return set(os.listdir(folder))


def test_a_miss_fetches_once_then_hits(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=1000)
    calls = []
    first = cache.path("artefacts/a.pm", writer(b"A" * 100, calls))
    assert first.read_bytes() == b"A" * 100 and first.parent == tmp_path / "cache"
    assert cache.path("artefacts/a.pm", writer(b"never", calls)) == first
    assert len(calls) == 1 and (cache.hits, cache.misses) == (1, 1)
    assert "artefacts/a.pm" in cache and cache.size == 100
    # the fetch wrote a temporary file in the cache folder, renamed after
    assert calls[0].parent == first.parent and calls[0].name.startswith(".")
    assert files_in(tmp_path / "cache") == {file_name("artefacts/a.pm")}


def test_bounded_least_recently_used_first(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=300)
    for key in "abc":
        cache.path(key, writer(key.encode() * 100))
    assert cache.size == 300
    cache.path("a", writer(b"never"))           # a is now the most recently used
    cache.path("d", writer(b"d" * 100))         # so b goes
    assert "b" not in cache and all(key in cache for key in "acd")
    assert cache.size == 300
    assert files_in(tmp_path / "cache") == {file_name(key) for key in "acd"}
    cache.path("e", writer(b"e" * 250))         # 250 more: c, a and d go
    assert [key for key in "abcde" if key in cache] == ["e"] and cache.size == 250
    # evicted keys are fetched again
    calls = []
    assert cache.path("b", writer(b"b" * 100, calls)).read_bytes() == b"b" * 100
    assert len(calls) == 1 and cache.size <= 300


def test_the_bound_holds_over_many_fetches(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=10_000)
    sizes = [(n * 7919) % 3000 + 1 for n in range(200)]
    for n, size in enumerate(sizes):
        cache.path(f"k{n % 37}", writer(os.urandom(size)))
        assert cache.size <= 10_000
        on_disk = sum(entry.stat().st_size for entry in os.scandir(tmp_path / "cache"))
        assert on_disk == cache.size


def test_a_file_larger_than_the_cache_is_served_then_dropped(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=100)
    big = cache.path("big", writer(b"x" * 500))
    assert big.read_bytes() == b"x" * 500
    cache.path("small", writer(b"y" * 10))
    assert "big" not in cache and not big.exists() and cache.size == 10


def test_concurrent_misses_fetch_once(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=10**6)
    calls, results = [], []
    start = threading.Barrier(8)

    def read():
        start.wait()
        results.append(cache.path("hot", writer(b"h" * 1000, calls, delay=0.3)).read_bytes())

    threads = [threading.Thread(target=read) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(calls) == 1
    assert results == [b"h" * 1000] * 8


def test_a_failed_fetch_reaches_every_waiter_and_caches_nothing(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=10**6)
    calls, errors = [], []
    start = threading.Barrier(4)

    def failing(dest):
        calls.append(dest)
        dest.write_bytes(b"partial")
        time.sleep(0.3)
        raise ConnectionError("the store went away")

    def read():
        start.wait()
        try:
            cache.path("k", failing)
        except ConnectionError as exc:
            errors.append(str(exc))

    threads = [threading.Thread(target=read) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(calls) == 1 and errors == ["the store went away"] * 4
    assert "k" not in cache and cache.size == 0 and files_in(tmp_path / "cache") == set()
    # the next request tries again
    assert cache.path("k", writer(b"ok")).read_bytes() == b"ok"


def test_an_open_file_stays_readable_after_eviction(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=1000)
    data = os.urandom(1000)
    reader = cache.open("a", writer(data))
    with reader:
        assert reader.read(10) == data[:10]
        cache.path("b", writer(b"b" * 1000))            # evicts a, unlinked
        assert "a" not in cache
        assert reader.read() == data[10:]


def test_a_leased_file_is_not_evicted(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=1000)
    with cache.lease("a", writer(b"a" * 600)) as path:
        cache.path("b", writer(b"b" * 600))
        assert path.exists() and "a" in cache          # over the bound while leased
        assert cache.size == 1200
        cache.path("c", writer(b"c" * 100))            # b goes, not a
        assert "b" not in cache and path.read_bytes() == b"a" * 600
    assert cache.size == 700 and "a" in cache            # released, within the bound
    cache.path("d", writer(b"d" * 400))                # now the least recent, a, goes
    assert cache.size == 500 and "a" not in cache and not path.exists()


def test_discard_refetches(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=1000)
    cache.path("a", writer(b"damaged"))
    cache.discard("a")
    assert "a" not in cache and files_in(tmp_path / "cache") == set()
    assert cache.path("a", writer(b"whole")).read_bytes() == b"whole"
    with cache.lease("a", writer(b"never")) as path:
        cache.discard("a")
        assert path.read_bytes() == b"whole"           # kept while leased
    assert not path.exists()


def test_a_restart_keeps_files_and_removes_temporaries(tmp_path):
    cache = ArtefactCache(tmp_path / "cache", max_bytes=1000)
    cache.path("old", writer(b"o" * 400))
    time.sleep(0.01)
    cache.path("new", writer(b"n" * 400))
    (tmp_path / "cache" / ".interrupted.tmp").write_bytes(b"half")
    (tmp_path / "cache" / "not-ours").write_bytes(b"?")
    reopened = ArtefactCache(tmp_path / "cache", max_bytes=500)   # smaller: one must go
    assert ".interrupted.tmp" not in files_in(tmp_path / "cache")
    assert "new" in reopened and "old" not in reopened and reopened.size == 400
    calls = []
    reopened.path("new", writer(b"never", calls))
    assert calls == []


def test_refuses_a_negative_bound(tmp_path):
    with pytest.raises(ValueError, match="at least 0"):
        ArtefactCache(tmp_path / "cache", max_bytes=-1)


def test_cache_in_front_of_s3(s3_url, tmp_path):
    """The use it is for: an object store's artefact read once per server."""
    blobs = open_blobs(s3_url)
    source = tmp_path / "a.pm"
    source.write_bytes(os.urandom(50_000))
    key = f"artefacts/{sha256_file(source)}.pm"
    blobs.put_file(key, source)
    gets = []

    def fetch(dest):
        gets.append(dest)
        blobs.get_file(key, dest)

    cache = ArtefactCache(tmp_path / "cache", max_bytes=10**6)
    for _ in range(3):
        assert cache.path(key, fetch).read_bytes() == source.read_bytes()
    assert len(gets) == 1
    # a local store needs no cache: its files are read in place
    local = LocalBlobs(tmp_path / "local")
    local.put_file(key, source)
    assert local.local_path(key).read_bytes() == source.read_bytes()
