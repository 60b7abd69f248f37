"""Two independent steps at once, on the cores numba may use.

A build has a few pairs of steps that read the same inputs, write nothing in
common and spend their time in compiled code that releases the GIL (the
census beside the face quadrics, the two gathers of the renumbering, the
two derived passes of a progressive mesh). ``both`` runs such a pair in two
threads, or one after the other when numba is held to one thread
(``NUMBA_NUM_THREADS=1``), so that a "single-threaded" build is one.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numba


def both(first, second):
    """Call ``first()`` and ``second()`` and return both results, at once in
    two threads when numba may use more than one. Either one's exception is
    raised, as a plain call would."""
    if numba.get_num_threads() < 2:
        return first(), second()
    with ThreadPoolExecutor(1) as pool:
        pending = pool.submit(second)
        done = first()
        return done, pending.result()
