"""Loaded artefacts kept in memory, bounded by count and by bytes.

Serving a level must not reread the artefact, so the store keeps the meshes and
scenes it loaded (``store.LocalStore.load``); what bounds that memory is bytes,
not a count: one scene of a few triangles can carry hundreds of megabytes of
morph targets or animation. An artefact's bytes (:func:`loaded_nbytes`) are its
arrays, counted once however many views share them, its images, a scene's
carried accessors and document, and the packet records encoded for its meshes
since it was loaded (``packets.records``). Records grow after an artefact is
kept, so an entry's records are measured again each time it is used and each
time another artefact is kept; the least recently used entries are dropped
until the count and the bytes are within bounds, but never the one just used
(the request using it holds it anyway: dropping it would only make the next
request read it again).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np
import orjson

from ..packets import cached_records, record_cache, records_ready

# Bytes a loaded mesh takes per triangle, arrays and packet records together (the
# 1.1M-face bunny: 144 MB of arrays, 39 MB of records); the default byte bound of
# loaded artefacts is this times the triangle limit: room for one mesh at it.
LOADED_BYTES_PER_TRIANGLE = 170


def _arrays_nbytes(arrays, seen: set) -> int:
    """Bytes of ``arrays`` not counted yet: views of one buffer are counted once
    (by the memory they span, ``seen`` holding the spans already counted)."""
    total = 0
    for array in arrays:
        if not isinstance(array, np.ndarray) or array.nbytes == 0:
            continue
        span = (array.__array_interface__["data"][0], array.nbytes)
        if span not in seen:
            seen.add(span)
            total += array.nbytes
    return total


def fixed_nbytes(asset) -> int:
    """The bytes of ``asset`` (a ``scene.asset.SceneAsset``) that never change once
    it is loaded: every part's arrays (stored and derived), the images once, a
    scene's carried accessors and its document (as JSON text: the least its
    objects take)."""
    seen: set = set()
    total = 0
    for part in asset.parts:
        total += _arrays_nbytes(vars(part.pm).values(), seen)
    materials = asset.materials
    if materials is not None:
        total += sum(len(image) for image in materials.images)
    scene = asset.scene
    if scene is not None:
        total += _arrays_nbytes((values for values, _, _ in scene.carried.values()), seen)
        total += len(orjson.dumps(scene.document))
    return total


def records_nbytes(asset) -> int:
    """Bytes of the packet records encoded so far for ``asset``'s parts."""
    total = 0
    for pm in (part.pm for part in asset.parts):
        if pm not in record_cache:
            continue
        for forward in (True, False):
            if records_ready(pm, forward):
                streams = cached_records(pm, forward)
                total += sum(int(s.nbytes) for s in streams.streams)
                total += sum(int(m.nbytes) for m in streams.marks)
                total += sum(len(c) for chunks in streams.chunks for c in chunks)
    return total


def loaded_nbytes(asset) -> int:
    """What ``asset`` holds in memory now, in bytes: :func:`fixed_nbytes` plus
    :func:`records_nbytes`."""
    return fixed_nbytes(asset) + records_nbytes(asset)


class LoadedArtefacts:
    """Artefacts by mesh id and digest, least recently used dropped past ``count``
    entries or ``nbytes`` bytes (module docstring). Safe to use from several threads.

    Parameters
    ----------
    count : int
        Most entries kept.
    nbytes : int
        Most bytes kept (:func:`loaded_nbytes`), but for the entry used last.
    """

    def __init__(self, *, count: int, nbytes: int):
        if count < 1:
            raise ValueError(f"loaded_meshes must be at least 1, got {count}")
        if nbytes < 1:
            raise ValueError(f"loaded_bytes must be at least 1, got {nbytes}")
        self.count, self.nbytes = count, nbytes
        self._lock = threading.Lock()
        # id -> [digest, artefact, fixed bytes, records bytes]
        self._entries: OrderedDict[str, list] = OrderedDict()

    def __len__(self) -> int:
        with self._lock:
            return len(self._entries)

    def __contains__(self, mesh_id: str) -> bool:
        with self._lock:
            return mesh_id in self._entries

    @property
    def held(self) -> int:
        """Bytes of the entries as last measured."""
        with self._lock:
            return sum(entry[2] + entry[3] for entry in self._entries.values())

    def get(self, mesh_id: str, digest: str):
        """The artefact kept for ``mesh_id`` at ``digest``, now the most recently
        used, or None."""
        with self._lock:
            entry = self._entries.get(mesh_id)
            if entry is None or entry[0] != digest:
                return None
            self._entries.move_to_end(mesh_id)
        records = records_nbytes(entry[1])      # outside the lock: it may wait for an encoder
        with self._lock:
            entry[3] = records
            self._shrink()
        return entry[1]

    def put(self, mesh_id: str, digest: str, artefact) -> None:
        """Keep ``artefact`` as ``mesh_id``'s at ``digest``, the most recently used."""
        entry = [digest, artefact, fixed_nbytes(artefact), records_nbytes(artefact)]
        with self._lock:
            others = list(self._entries.values())
        for other in others:
            other[3] = records_nbytes(other[1])
        with self._lock:
            self._entries[mesh_id] = entry
            self._entries.move_to_end(mesh_id)
            self._shrink()

    def pop(self, mesh_id: str) -> None:
        with self._lock:
            self._entries.pop(mesh_id, None)

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()

    def _shrink(self) -> None:
        """Drop the least recently used entries past either bound, never the last."""
        total = sum(entry[2] + entry[3] for entry in self._entries.values())
        while len(self._entries) > 1 and (len(self._entries) > self.count
                                          or total > self.nbytes):
            _, dropped = self._entries.popitem(last=False)
            total -= dropped[2] + dropped[3]
