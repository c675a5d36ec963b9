"""Shared fixtures: location of the reference material (``../shared/reference``)."""
import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def reference_dir():
    """The reference folder, or None: $SLICERSIM_REFERENCE_DIR, else ../shared/reference."""
    env = os.environ.get("SLICERSIM_REFERENCE_DIR")
    path = Path(env) if env else ROOT.parent / "shared" / "reference"
    return path if (path / "cases").is_dir() and (path / "config").is_dir() else None


@pytest.fixture(scope="session")
def refdir():
    path = reference_dir()
    if path is None:
        pytest.skip("reference material not found (../shared/reference or $SLICERSIM_REFERENCE_DIR): "
                    "reference-reproduction tests need it")
    return path
