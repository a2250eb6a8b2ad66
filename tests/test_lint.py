"""The library stays clean under the lint and type checks configured in pyproject.toml (ruff; mypy
with its per-module baseline), as CI runs them. Each is skipped, saying why, when its tool is not
installed (both are in the `test` extra)."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def _tool(name: str) -> str:
    exe = shutil.which(name, path=str(BIN)) or shutil.which(name)
    if exe is None:
        pytest.skip(f"{name} is not installed (pip install '.[test]' installs it)")
    return exe


def test_ruff_finds_nothing_in_the_library():
    r = subprocess.run([_tool("ruff"), "check", "--no-cache", "--config", str(ROOT / "pyproject.toml"), str(ROOT)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr


@pytest.mark.slow
def test_mypy_finds_nothing_in_the_library(tmp_path):
    """mypy checks the package kbs, which is the repository root: from a folder where kbs is a link
    to it."""
    mypy = _tool("mypy")
    (tmp_path / "kbs").symlink_to(ROOT, target_is_directory=True)
    r = subprocess.run([mypy, "-p", "kbs", "--config-file", str(ROOT / "pyproject.toml"),
                        "--cache-dir", str(tmp_path / ".mypy_cache")],
                       capture_output=True, text=True, cwd=tmp_path, timeout=900)
    assert r.returncode == 0 and "unused section" not in r.stdout + r.stderr, r.stdout + r.stderr
