"""Independent peers that are never dependencies of plcstack, imported only by the tests that
drive them (marked so the default run leaves them out): a test that cannot get its peer fails
naming it, never skips."""

from __future__ import annotations

import importlib
from types import ModuleType

import pytest

__all__ = ["hsl_peer"]


def hsl_peer() -> ModuleType:
    """HslCommunication (PyPI ``hslcommunication`` 1.2.0), or the test fails saying how to
    get it (its licence allows local test use only, so it is never installed by plcstack)."""
    try:
        return importlib.import_module("HslCommunication")
    except ImportError as exc:
        pytest.fail(
            "HslCommunication cannot be imported "
            f"({exc}): pip install --target /tmp/hsl --no-deps hslcommunication==1.2.0 and run "
            "with PYTHONPATH=/tmp/hsl",
            pytrace=False,
        )
