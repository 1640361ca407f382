"""Build hook: the documentation goes into the wheel as ``plcstack/docs/``.

The pages live in ``docs/`` at the top of the repository (where they are read and tested); a
wheel user has no such folder, so ``build_py`` copies them into the package and
``plcstack docs`` prints them from there. Everything else is configured in pyproject.toml.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildWithDocs(build_py):
    def run(self) -> None:
        super().run()
        source = Path(__file__).resolve().parent / "docs"
        # the pages and the files they show (docs/tags/*.csv, ...)
        shutil.copytree(source, Path(self.build_lib) / "plcstack" / "docs", dirs_exist_ok=True)


setup(cmdclass={"build_py": BuildWithDocs})
