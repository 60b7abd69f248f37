"""Freed memory handed back to the operating system, between a build's steps.

A partitioned decimation's kernels run in worker threads, and glibc's malloc
gives each thread an arena of its own: the part copies, queues and logs a
kernel frees stay in its thread's arena, which the main thread's later
arrays cannot reuse, so every step after the kernels would add its arrays
on top of theirs. ``give_back`` asks malloc to return the free pages of
every arena (``malloc_trim``); elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util

__all__ = ["give_back"]


def _trim():
    """glibc's ``malloc_trim``, or None where the C library has none."""
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


_MALLOC_TRIM = _trim()


def give_back() -> None:
    """Return the free pages of every malloc arena to the operating system."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)
