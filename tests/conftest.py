"""Shared fixtures: where the real labelled scans live, and a skip when they are absent."""
from __future__ import annotations

from pathlib import Path

import pytest

#: ``../shared/data`` beside the repository (present in CI, see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to ``../shared/data``; the test is skipped, saying why, when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scans not available: {SHARED_DATA} is absent (it is present in CI)")
    return SHARED_DATA
