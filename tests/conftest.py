"""Shared fixtures: where the real labelled scans live, and a skip when they are absent."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

# The compiled kernels in every test process and in the kbs commands the tests start (they
# inherit the environment): the same code path everywhere, so that results compare exactly.
# (By default kbs uses them once a background warm-up has cached them; see kbs.inference._flags.)
os.environ.setdefault("KBS_JIT", "1")

#: ``../shared/data`` beside the repository (present in CI, see ../shared/data/README.md).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path to ``../shared/data``; the test is skipped, saying why, when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scans not available: {SHARED_DATA} is absent (it is present in CI)")
    return SHARED_DATA
