"""The first run's moving line: ``build.CompileTicker`` while numba compiles."""

from __future__ import annotations

import io

import numpy as np
from numba import njit

from lodserver.build import CompileTicker


def test_the_line_moves_while_a_kernel_compiles_and_ends_after():
    @njit(cache=False)
    def fresh_kernel(values):       # defined here: never cached, so it compiles
        total = 0.0
        for i in range(values.shape[0]):
            total += np.sin(values[i]) * np.cos(values[i]) + np.sqrt(abs(values[i]))
        return total

    stream = io.StringIO()
    ticker = CompileTicker(stream, every=0.001, always=True)
    fresh_kernel(np.arange(4.0))
    ticker.stop()
    text = stream.getvalue()
    assert ticker.done >= 1
    lines = text.split("\r")
    assert any("now fresh_kernel" in line for line in lines)     # shown while compiling
    assert text.endswith("\n") and "compiled" in lines[-1]
    fresh_kernel(np.arange(3.0))        # after stop: no longer listening
    assert stream.getvalue() == text


def test_nothing_is_written_when_nothing_compiles_or_the_stream_is_not_a_terminal():
    stream = io.StringIO()
    CompileTicker(stream, every=0.001, always=True).stop()
    assert stream.getvalue() == ""
    quiet = CompileTicker(stream, every=0.001)      # a StringIO is not a terminal
    assert not quiet.enabled
    quiet.stop()
    assert stream.getvalue() == ""
