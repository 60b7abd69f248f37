"""A writable folder for numba's cache of compiled kernels, found before numba loads.

numba keeps every ``cache=True`` kernel on disk, in ``NUMBA_CACHE_DIR`` when it
is set, else in ``__pycache__`` beside the module, else in the user's cache
folder (``~/.cache/numba``); it takes the first it can *write*, even just to
read a cache, and with none (a read-only container: ``docker run --read-only``
leaves the image's cache, the package and HOME read-only) decorating the first
kernel fails at import with "cannot cache function ...: no locator available".

:func:`ensure_writable_cache` runs first thing in ``lodserver/__init__.py``.
When none of those folders is writable it points ``NUMBA_CACHE_DIR`` at a
folder of this user's under the temporary directory, which processes started
later (the parse workers) inherit. A read-only ``NUMBA_CACHE_DIR`` (the
image's, compiled while it was built) is mirrored there as symbolic links, so
its kernels still load without compiling; numba writes its new or updated
files beside them (replacing a link, never writing through it).
"""

from __future__ import annotations

import logging
import os
import stat
import sys
import tempfile
from pathlib import Path

__all__ = ["ensure_writable_cache"]

log = logging.getLogger(__name__)
_PACKAGE = Path(__file__).resolve().parent


def ensure_writable_cache() -> Path | None:
    """Make sure numba has a writable cache folder (module docstring); the folder
    chosen when ``NUMBA_CACHE_DIR`` had to be set, else None."""
    configured = os.environ.get("NUMBA_CACHE_DIR")
    if configured:
        if _writable(Path(configured)):
            return None
        seed = Path(configured)
    else:
        # numba's own order: beside the modules, then the user's cache folder
        user_cache = Path(os.environ.get("XDG_CACHE_HOME")
                          or os.path.expanduser("~/.cache")) / "numba"
        if _writable(_PACKAGE / "simplify" / "__pycache__") or _writable(user_cache):
            return None
        seed = None
    folder = _private_folder()
    if folder is None:
        log.warning("numba has no writable folder for its cache: set NUMBA_CACHE_DIR to a "
                    "writable folder (a volume, or a tmpfs such as docker run --tmpfs /tmp)")
        return None
    if seed is not None and seed.is_dir():
        _mirror(seed, folder)
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    config = sys.modules.get("numba.core.config")
    if config is not None:          # numba read the variable already: tell it too
        config.CACHE_DIR = str(folder)
    log.info("numba's cache folder is not writable; compiled kernels are cached in %s",
             folder)
    return folder


def _writable(folder: Path) -> bool:
    """numba's own test of a cache folder: created if missing, a file made in it."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def _private_folder() -> Path | None:
    """``lodserver-numba-<uid>`` under the temporary directory, if it is this
    user's own and nobody else can write it (a cache is loaded with pickle: a
    folder someone else controls would run their code); else a new private one.
    None when no temporary directory is writable."""
    try:
        base = Path(tempfile.gettempdir())
    except OSError:     # gettempdir found no writable folder, not even the working one
        return None
    folder = base / f"lodserver-numba-{os.getuid()}"
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        info = folder.lstat()
        if (stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid()
                and not info.st_mode & 0o022 and _writable(folder)):
            return folder
        return Path(tempfile.mkdtemp(prefix="lodserver-numba-", dir=base))
    except OSError:
        return None


def _mirror(source: Path, folder: Path) -> None:
    """A symbolic link in ``folder`` to every file under ``source``, sub-folders
    recreated; names already present (numba's own files, or another process's
    links made meanwhile) are left alone. Unreadable parts are skipped."""
    for here, _, files in os.walk(source):
        target = folder / Path(here).relative_to(source)
        try:
            target.mkdir(mode=0o700, exist_ok=True)
        except OSError:
            continue
        for name in files:
            try:
                os.symlink(Path(here, name), target / name)
            except OSError:
                pass
