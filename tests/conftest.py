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


# -- slow end-to-end tests -------------------------------------------------------------------------
# `pytest` alone skips the tests marked slow (3 s or more each on a loaded 2-core machine: whole
# real scans, `kbs` subprocesses on more than a toy cloud, Dask clusters, a headless browser, a pip
# install; mark a new test slow when `pytest --durations=20` shows it there), saying so; `pytest --runslow` runs every test, and it is what
# .ci/run and the README's test command run.


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run the tests marked slow (CI runs them all: .ci/run)")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow end-to-end test: pytest --runslow runs it (as .ci/run does)")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
