"""Old home of the loader's limits, now :mod:`lodserver.io.limits` (kept for
``jobs.py``'s import until it moves; the lead removes this shim)."""

from .io.limits import DEFAULT_MAX_TRIANGLES, LimitError, LoadLimits

__all__ = ["DEFAULT_MAX_TRIANGLES", "LimitError", "LoadLimits"]
