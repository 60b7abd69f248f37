"""The entropy coder of version 4 packets: byte-oriented rANS, adaptive frequencies.

docs/packets.md, "Version 4", "The coder". One coded stream is a sequence of
non-negative integers, each with a *context* (a small integer the decoder
computes from what it has decoded before). Every integer is written as a
*bucket* (one of :data:`ALPHABET` symbols, coded with its context's
frequencies) followed by its *extra bits* (coded flat):

- ``v < 32``: bucket ``v``, no extra bits;
- otherwise, with ``n`` the bit length of ``v`` (``n >= 6``): bucket
  ``32 + 2 (n - 6) + h``, ``h`` the bit below the leading one, then the
  ``n - 2`` bits below ``h`` as extra bits, in chunks of at most 16 bits, the
  low chunk first.

Each context's frequencies adapt (:func:`frequencies`, :data:`FIRST_REBUILD`): no
table is sent, and a context costs nothing until it is used.

The coder is rANS (Duda 2013) as in Giesen's ``ryg_rans``: a 32-bit state
``x`` kept in ``[2^23, 2^31)`` (so a decoder in JavaScript stays in int32),
frequencies out of ``2^12``, renormalized one byte at a time. Decoding a symbol
of frequency ``f`` and start ``c`` from ``x``: ``slot = x & 4095``, the symbol
is the one whose range ``[c, c + f)`` holds ``slot``,
``x = f * (x >> 12) + slot - c``; ``n`` flat bits: ``bits = x & (2^n - 1)``,
``x >>= n``; after either, while ``x < 2^23``: ``x = (x << 8) | next byte``.
A stream starts with the state as a little-endian u32; it ends when its
symbols are read, and then the state must be ``2^23`` and every byte consumed.

The encoder (:func:`encode_symbols`) is compiled with numba; the decoder
(:func:`decode_symbols`) is plain Python, the reference for clients.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .format import PacketError, Reader, put_varint

PROB_BITS = 12
PROB_SCALE = 1 << PROB_BITS
STATE_LOW = 1 << 23                 # x stays in [STATE_LOW, 2^31)
DIRECT = 32                         # values below this are their own bucket
MAX_BIT_LENGTH = 44                 # larger values are refused (no record writes them)
ALPHABET = DIRECT + 2 * (MAX_BIT_LENGTH - 5)
RAW_CHUNK = 16                      # flat bits are coded at most this many at a time
# A symbol takes at least log2(4096 / 3987) bits of the state (3987: the largest
# frequency, every other bucket keeping 1), so a stream of L bytes codes fewer than
# 210 L symbols: a count past this bound is refused before it is read, as the
# browser's reader (static/rans.js) refuses it.
MAX_SYMBOLS_PER_BYTE = 256


@njit(cache=True, nogil=True)
def bucket_of(v):
    """The bucket of ``v >= 0`` and its number of extra bits."""
    if v < DIRECT:
        return v, 0
    n = 6
    while v >> n:
        n += 1
    return DIRECT + 2 * (n - 6) + ((v >> (n - 2)) & 1), n - 2


def value_of(bucket: int, extra: int) -> int:
    """The value of ``bucket`` with extra bits ``extra`` (the inverse of :func:`bucket_of`)."""
    if bucket < DIRECT:
        return bucket
    n = (bucket - DIRECT) // 2 + 6
    return (1 << (n - 1)) | (((bucket - DIRECT) & 1) << (n - 2)) | extra


def extra_bits(bucket: int) -> int:
    """How many extra bits follow ``bucket``."""
    return 0 if bucket < DIRECT else (bucket - DIRECT) // 2 + 4


# ---- the adaptive model -----------------------------------------------------------
# Every context starts with a count of 1 for each of the ALPHABET buckets; each coded
# bucket adds INCREMENT to its count (a light prior: a context learns its few buckets
# from a few dozen symbols). The context's frequencies are rebuilt from its counts
# (:func:`frequencies`) when it has coded FIRST_REBUILD symbols, then each time it has
# coded as many again as since the start, at most REBUILD_EVERY more.
FIRST_REBUILD, REBUILD_EVERY = 16, 64
INCREMENT = 32
# Frequencies reserve 1 for every bucket, and share the rest by count.
SHARED = PROB_SCALE - ALPHABET


@njit(cache=True, nogil=True)
def frequencies(counts, freq):
    """``freq[:]`` from ``counts`` (ALPHABET,), integers only, so that every decoder
    gets the same: ``1 + counts[i] * SHARED // total`` each, and what is left of
    ``PROB_SCALE`` to the first bucket of the largest count."""
    total = 0
    top = 0
    for i in range(ALPHABET):
        total += counts[i]
        if counts[i] > counts[top]:
            top = i
    used = 0
    for i in range(ALPHABET):
        freq[i] = 1 + counts[i] * SHARED // total
        used += freq[i]
    freq[top] += PROB_SCALE - used


@njit(cache=True, nogil=True)
def next_rebuild(coded):
    """When a context that has coded ``coded`` symbols rebuilds next."""
    return coded + min(coded, REBUILD_EVERY)


# ---- encoding ------------------------------------------------------------------------
@njit(cache=True, nogil=True, inline="always")
def _emit(out, used, x, x_max):
    while x >= x_max:
        if used == out.shape[0]:
            bigger = np.empty(2 * out.shape[0] + 16, dtype=np.uint8)
            bigger[:used] = out[:used]
            out = bigger
        out[used] = x & 255
        used += 1
        x >>= 8
    return out, used, x


@njit(cache=True, nogil=True)
def new_models(n_contexts):
    """The adaptive model of ``n_contexts`` contexts before any symbol: (counts,
    freq, start) each (n_contexts, ALPHABET), and per context the symbols coded and
    the count at which its frequencies are next rebuilt."""
    counts = np.ones((n_contexts, ALPHABET), dtype=np.int64)
    freq = np.empty((n_contexts, ALPHABET), dtype=np.int64)
    start = np.empty((n_contexts, ALPHABET), dtype=np.int64)
    coded = np.zeros(n_contexts, dtype=np.int64)
    rebuild = np.full(n_contexts, FIRST_REBUILD, dtype=np.int64)
    for c in range(n_contexts):
        frequencies(counts[c], freq[c])
        start[c, 0] = 0
        for b in range(1, ALPHABET):
            start[c, b] = start[c, b - 1] + freq[c, b - 1]
    return counts, freq, start, coded, rebuild


@njit(cache=True, nogil=True)
def _model(values, contexts, n_contexts):
    """The (start, freq) each symbol is coded with, running the adaptive model forward."""
    counts, freq, start, coded, rebuild = new_models(n_contexts)
    out = np.empty((values.shape[0], 2), dtype=np.int64)
    for i in range(values.shape[0]):
        c = contexts[i]
        b = bucket_of(values[i])[0]
        out[i, 0] = start[c, b]
        out[i, 1] = freq[c, b]
        counts[c, b] += INCREMENT
        coded[c] += 1
        if coded[c] == rebuild[c]:
            rebuild[c] = next_rebuild(coded[c])
            frequencies(counts[c], freq[c])
            for k in range(1, ALPHABET):
                start[c, k] = start[c, k - 1] + freq[c, k - 1]
    return out


@njit(cache=True, nogil=True)
def _encode(values, coding):
    """The rANS bytes of ``values`` (int64 >= 0), bucket ``i`` coded with ``coding[i]``
    (start, freq): symbols are coded last first, so that a decoder reads them first first."""
    out = np.empty(16 + values.shape[0], dtype=np.uint8)
    used = 0
    x = STATE_LOW
    for i in range(values.shape[0] - 1, -1, -1):
        v = values[i]
        extra = bucket_of(v)[1]
        # extra bits: the high chunk first (the decoder reads the low chunk first)
        chunks = (extra + RAW_CHUNK - 1) // RAW_CHUNK
        for k in range(chunks - 1, -1, -1):
            size = min(RAW_CHUNK, extra - k * RAW_CHUNK)
            bits = (v >> (k * RAW_CHUNK)) & ((1 << size) - 1)
            out, used, x = _emit(out, used, x, (STATE_LOW >> size) << 8)
            x = (x << size) | bits
        f = coding[i, 1]
        out, used, x = _emit(out, used, x, ((STATE_LOW >> PROB_BITS) << 8) * f)
        x = ((x // f) << PROB_BITS) + (x % f) + coding[i, 0]
    if used + 4 > out.shape[0]:
        bigger = np.empty(used + 4, dtype=np.uint8)
        bigger[:used] = out[:used]
        out = bigger
    for k in range(3, -1, -1):         # the state, most significant byte first ...
        out[used] = (x >> (8 * k)) & 255
        used += 1
    return out[:used][::-1].copy()    # ... so that reversed it reads little-endian


def encode_symbols(out: bytearray, values: np.ndarray, contexts: np.ndarray,
                   n_contexts: int) -> None:
    """Append one coded stream to ``out``: varint symbol count, then unless 0 varint
    byte length and the rANS bytes.

    ``values`` (m,) int64 >= 0 and below 2^44; ``contexts`` (m,) in ``[0, n_contexts)``.
    """
    values = np.ascontiguousarray(values, dtype=np.int64)
    contexts = np.ascontiguousarray(contexts, dtype=np.int64)
    put_varint(out, len(values))
    if not len(values):
        return
    if values.min() < 0 or values.max() >= 1 << MAX_BIT_LENGTH:
        raise ValueError(f"rANS streams code integers in [0, 2^{MAX_BIT_LENGTH})")
    if contexts.min() < 0 or contexts.max() >= n_contexts:
        raise ValueError(f"contexts must lie in [0, {n_contexts})")
    coded = _encode(values, _model(values, contexts, n_contexts))
    put_varint(out, len(coded))
    out += coded.tobytes()


# ---- decoding (the reference) ---------------------------------------------------------
class Context:
    """One context's adaptive model as a decoder keeps it: counts, frequencies, starts,
    and the bucket of every slot of ``[0, PROB_SCALE)``."""

    def __init__(self):
        self.counts = np.ones(ALPHABET, dtype=np.int64)
        self.coded, self.rebuild = 0, FIRST_REBUILD
        self._tables()

    def _tables(self) -> None:
        freq = np.empty(ALPHABET, dtype=np.int64)
        frequencies(self.counts, freq)
        self.freq = freq.tolist()
        self.start = [0] * ALPHABET
        for b in range(1, ALPHABET):
            self.start[b] = self.start[b - 1] + self.freq[b - 1]
        self.lookup = bytes(np.repeat(np.arange(ALPHABET, dtype=np.uint8), freq))

    def update(self, bucket: int) -> None:
        self.counts[bucket] += INCREMENT
        self.coded += 1
        if self.coded == self.rebuild:
            self.rebuild = next_rebuild(self.coded)
            self._tables()


class SymbolReader:
    """The symbols of one coded stream, read one at a time: :meth:`read` takes the
    context of the next symbol (in ``[0, n_contexts)``). Running out of bytes or
    symbols is a PacketError."""

    def __init__(self, reader: Reader, n_contexts: int, name: str | None = None):
        self.name = name or reader.name
        self.count = reader.varint()
        self.left = self.count
        self.models: dict = {}
        self.n_contexts = n_contexts
        self.data, self.at, self.x = b"", 0, STATE_LOW
        if self.count:
            self.data = reader.take(reader.varint())
            if len(self.data) < 4:
                raise PacketError(f"the packet's {self.name} stream is shorter than its state")
            if self.count > MAX_SYMBOLS_PER_BYTE * len(self.data):
                raise PacketError(f"the packet's {self.name} stream holds more symbols than "
                                  "its bytes can code")
            self.x = int.from_bytes(self.data[:4], "little")
            self.at = 4
            if not STATE_LOW <= self.x < 2**31:
                raise PacketError(f"the packet's {self.name} stream starts with a bad state")

    def _renormalize(self) -> None:
        while self.x < STATE_LOW:
            if self.at >= len(self.data):
                raise PacketError(f"the packet's {self.name} stream ends in the middle of a symbol")
            self.x = (self.x << 8) | self.data[self.at]
            self.at += 1

    def read(self, context: int) -> int:
        if self.left <= 0:
            raise PacketError(f"the packet's {self.name} stream holds fewer symbols than its "
                              "records read")
        if not 0 <= context < self.n_contexts:
            raise PacketError(f"the packet's {self.name} stream asks for context {context}"
                              f" of {self.n_contexts}")
        self.left -= 1
        model = self.models.get(context)
        if model is None:
            model = self.models[context] = Context()
        slot = self.x & (PROB_SCALE - 1)
        b = model.lookup[slot]
        self.x = model.freq[b] * (self.x >> PROB_BITS) + slot - model.start[b]
        self._renormalize()
        model.update(b)
        n = extra_bits(b)
        extra = 0
        for k in range(0, n, RAW_CHUNK):
            size = min(RAW_CHUNK, n - k)
            extra |= (self.x & ((1 << size) - 1)) << k
            self.x >>= size
            self._renormalize()
        return value_of(b, extra)

    def check_done(self) -> None:
        """Every symbol read, every byte consumed, the state back at its start."""
        if self.left or self.at != len(self.data) or self.x != STATE_LOW:
            raise PacketError(f"the packet's {self.name} stream does not end where its "
                              "symbols do")


def decode_symbols(reader: Reader, n_contexts: int, context_of) -> list[int]:
    """All symbols of one coded stream: ``context_of(i, decoded)`` gives the context of
    symbol ``i`` from the symbols decoded before it."""
    symbols = SymbolReader(reader, n_contexts)
    decoded: list[int] = []
    for i in range(symbols.count):
        decoded.append(symbols.read(context_of(i, decoded)))
    symbols.check_done()
    return decoded
