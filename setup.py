"""Packaging hook (the rest is in pyproject.toml): the browser viewer goes into the wheel.

The viewer's source is the top-level ``static/`` folder, served from the
checkout in development. A wheel has no checkout, so ``build_py`` copies the
folder into the package as ``lodserver/_static/``, where ``Settings.static_dir``
finds it when the checkout's copy is absent (``pip install .`` then serves
``/viewer/`` from anywhere).
"""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

VIEWER = Path(__file__).resolve().parent / "static"


class build_py_with_viewer(build_py):
    """``build_py``, then ``static/`` copied to ``<build_lib>/lodserver/_static``."""

    def run(self):
        super().run()
        if getattr(self, "editable_mode", False):
            return      # an editable install serves the checkout's static/ itself
        if not (VIEWER / "index.html").is_file():
            raise SystemExit(f"cannot package the viewer: no index.html in {VIEWER}")
        target = Path(self.build_lib) / "lodserver" / "_static"
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(VIEWER, target, ignore=shutil.ignore_patterns("node_modules", ".*"))


setup(cmdclass={"build_py": build_py_with_viewer})
