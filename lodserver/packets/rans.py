"""The entropy coder of version 4 packets: byte-oriented rANS over static tables.

docs/packets.md, "Version 4: the coder". One coded stream is a sequence of
non-negative integers, each with a *context* (a small integer the decoder
computes from what it has decoded before). Every integer is written as a
*bucket* (one of :data:`ALPHABET` symbols, coded with its context's frequency
table) followed by its *extra bits* (coded flat):

- ``v < 16``: bucket ``v``, no extra bits;
- otherwise, with ``n`` the bit length of ``v`` (``n >= 5``): bucket
  ``16 + 2 (n - 5) + h``, ``h`` the bit below the leading one, then the
  ``n - 2`` bits below ``h`` as extra bits, in chunks of at most 16 bits, the
  low chunk first.

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
DIRECT = 16                         # values below this are their own bucket
MAX_BIT_LENGTH = 44                 # larger values are refused (no record writes them)
ALPHABET = DIRECT + 2 * (MAX_BIT_LENGTH - 4)
RAW_CHUNK = 16                      # flat bits are coded at most this many at a time


@njit(cache=True, nogil=True)
def bucket_of(v):
    """The bucket of ``v >= 0`` and its number of extra bits."""
    if v < DIRECT:
        return v, 0
    n = 5
    while v >> n:
        n += 1
    return DIRECT + 2 * (n - 5) + ((v >> (n - 2)) & 1), n - 2


def value_of(bucket: int, extra: int) -> int:
    """The value of ``bucket`` with extra bits ``extra`` (the inverse of :func:`bucket_of`)."""
    if bucket < DIRECT:
        return bucket
    n = (bucket - DIRECT) // 2 + 5
    return (1 << (n - 1)) | (((bucket - DIRECT) & 1) << (n - 2)) | extra


def extra_bits(bucket: int) -> int:
    """How many extra bits follow ``bucket``."""
    return 0 if bucket < DIRECT else (bucket - DIRECT) // 2 + 3


# ---- tables ------------------------------------------------------------------------
def bucket_counts(values: np.ndarray, contexts: np.ndarray, n_contexts: int) -> np.ndarray:
    """(n_contexts, ALPHABET) int64: how often each bucket occurs in each context."""
    counts = np.zeros((n_contexts, ALPHABET), dtype=np.int64)
    _count(np.ascontiguousarray(values, dtype=np.int64),
           np.ascontiguousarray(contexts, dtype=np.int64), counts)
    return counts


@njit(cache=True, nogil=True)
def _count(values, contexts, counts):
    for i in range(values.shape[0]):
        counts[contexts[i], bucket_of(values[i])[0]] += 1


def normalized(counts: np.ndarray) -> np.ndarray:
    """Frequencies summing to ``PROB_SCALE`` (each symbol that occurs gets at least 1)
    from one context's counts; all zeros for a context that never occurs."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    freq = np.zeros(len(counts), dtype=np.int64)
    if total == 0:
        return freq
    present = counts > 0
    freq[present] = np.maximum(1, np.round(counts[present] * PROB_SCALE / total).astype(np.int64))
    # give or take the rounding's difference from the largest frequencies, keeping each >= 1
    while (excess := int(freq.sum()) - PROB_SCALE) != 0:
        order = np.argsort(-freq, kind="stable")
        for i in order[:max(1, min(abs(excess), int(present.sum())))]:
            if excess > 0 and freq[i] > 1:
                freq[i] -= 1
                excess -= 1
            elif excess < 0:
                freq[i] += 1
                excess += 1
    return freq


def put_tables(out: bytearray, freqs: np.ndarray) -> None:
    """Each context's table: varint ``k`` (1 + its largest symbol; 0 for a context that
    never occurs), then ``k`` varint frequencies."""
    for row in freqs:
        used = np.flatnonzero(row)
        k = int(used[-1]) + 1 if len(used) else 0
        put_varint(out, k)
        for f in row[:k]:
            put_varint(out, int(f))


def read_tables(reader: Reader, n_contexts: int, name: str) -> list:
    """The tables :func:`put_tables` wrote: per context ``None`` (never occurs) or
    ``(freq, start, lookup)``, ``lookup`` the symbol of every slot of ``[0, 4096)``."""
    tables = []
    for _ in range(n_contexts):
        k = reader.varint()
        if k == 0:
            tables.append(None)
            continue
        if k > ALPHABET:
            raise PacketError(f"the packet's {name} stream has a table of {k} symbols; "
                              f"at most {ALPHABET} exist")
        freq = [reader.varint() for _ in range(k)]
        if sum(freq) != PROB_SCALE:
            raise PacketError(f"the packet's {name} stream has a table that does not "
                              f"sum to {PROB_SCALE}")
        start = [0] * k
        for i in range(1, k):
            start[i] = start[i - 1] + freq[i - 1]
        lookup = bytes(np.repeat(np.arange(k, dtype=np.uint8), freq))
        tables.append((freq, start, lookup))
    return tables


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
def _encode(values, contexts, freq, start):
    """The rANS bytes of ``values`` (int64 >= 0) in ``contexts`` with tables ``freq``
    and ``start`` (n_contexts, ALPHABET): symbols are coded last first, so that a
    decoder reads them first first."""
    out = np.empty(16 + values.shape[0], dtype=np.uint8)
    used = 0
    x = STATE_LOW
    for i in range(values.shape[0] - 1, -1, -1):
        v = values[i]
        b, extra = bucket_of(v)
        # extra bits: the high chunk first (the decoder reads the low chunk first)
        chunks = (extra + RAW_CHUNK - 1) // RAW_CHUNK
        for k in range(chunks - 1, -1, -1):
            size = min(RAW_CHUNK, extra - k * RAW_CHUNK)
            bits = (v >> (k * RAW_CHUNK)) & ((1 << size) - 1)
            out, used, x = _emit(out, used, x, (STATE_LOW >> size) << 8)
            x = (x << size) | bits
        f = freq[contexts[i], b]
        out, used, x = _emit(out, used, x, ((STATE_LOW >> PROB_BITS) << 8) * f)
        x = ((x // f) << PROB_BITS) + (x % f) + start[contexts[i], b]
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
    """Append one coded stream to ``out``: varint symbol count; then, unless 0, the
    tables of its ``n_contexts`` contexts, varint byte length and the rANS bytes.

    ``values`` (m,) int64 >= 0 and below 2^44; ``contexts`` (m,) in ``[0, n_contexts)``.
    """
    values = np.ascontiguousarray(values, dtype=np.int64)
    contexts = np.ascontiguousarray(contexts, dtype=np.int64)
    put_varint(out, len(values))
    if not len(values):
        return
    if values.min() < 0 or values.max() >= 1 << MAX_BIT_LENGTH:
        raise ValueError(f"rANS streams code integers in [0, 2^{MAX_BIT_LENGTH})")
    freq = np.array([normalized(row) for row in bucket_counts(values, contexts, n_contexts)],
                    dtype=np.int64)
    start = np.zeros_like(freq)
    np.cumsum(freq[:, :-1], axis=1, out=start[:, 1:])
    put_tables(out, freq)
    coded = _encode(values, contexts, freq, start)
    put_varint(out, len(coded))
    out += coded.tobytes()


# ---- decoding (the reference) ---------------------------------------------------------
class SymbolReader:
    """The symbols of one coded stream, read one at a time: :meth:`read` takes the
    context of the next symbol. Running out of bytes, a context without a table or
    a symbol past its table is a PacketError."""

    def __init__(self, reader: Reader, n_contexts: int, name: str | None = None):
        self.name = name or reader.name
        self.count = reader.varint()
        self.left = self.count
        self.tables, self.data, self.at, self.x = [], b"", 0, STATE_LOW
        if self.count:
            self.tables = read_tables(reader, n_contexts, self.name)
            self.data = reader.take(reader.varint())
            if len(self.data) < 4:
                raise PacketError(f"the packet's {self.name} stream is shorter than its state")
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
        self.left -= 1
        table = self.tables[context]
        if table is None:
            raise PacketError(f"the packet's {self.name} stream has no table for a symbol")
        freq, start, lookup = table
        slot = self.x & (PROB_SCALE - 1)
        if slot >= len(lookup):
            raise PacketError(f"the packet's {self.name} stream decodes past its table")
        b = lookup[slot]
        self.x = freq[b] * (self.x >> PROB_BITS) + slot - start[b]
        self._renormalize()
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
