"""The switch between the compiled kernels and the numpy reference, and the background warm-up
that compiles them once so that no run pays for it (kbs.inference._flags)."""
from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from kbs.inference import _flags


@pytest.fixture
def state(tmp_path, monkeypatch):
    monkeypatch.setattr(_flags, "_state_dir", lambda: tmp_path)
    return tmp_path


def test_explicit_settings(monkeypatch, state):
    monkeypatch.setenv("KBS_JIT", "0")
    assert _flags._decide() is False
    monkeypatch.setenv("KBS_JIT", "1")
    assert _flags._decide() is True
    assert not list(state.iterdir())  # neither starts a warm-up


def test_auto_uses_the_compiled_kernels_only_once_the_warm_up_has_cached_them(monkeypatch, state):
    monkeypatch.setenv("KBS_JIT", "auto")
    started = []
    monkeypatch.setattr(_flags, "start_warmup", lambda: started.append(1) or True)
    assert _flags._decide() is False and started == [1]  # cold: numpy now, warm-up started
    (state / "kbs-jit-ready").write_text("a stale stamp")
    assert _flags._decide() is False and started == [1, 1]  # the kernels changed since
    (state / "kbs-jit-ready").write_text(_flags._stamp())
    assert _flags._decide() is True and started == [1, 1, 1]  # numba's cached: the warm-up builds the ahead-of-time module
    from kbs.inference import _aot

    so, table, note = _aot.paths()
    note.write_text("no C compiler")
    assert _flags._decide() is True and started == [1, 1, 1]  # it failed once for this source: not again
    note.unlink()
    monkeypatch.setenv("KBS_AOT", "0")
    assert _flags._decide() is True and started == [1, 1, 1]  # not wanted
    monkeypatch.delenv("KBS_AOT")
    so.write_bytes(b"")
    table.write_text("{}")
    assert _flags._decide() is True and started == [1, 1, 1]  # built


@pytest.mark.slow
def test_one_warm_up_at_a_time_and_it_writes_the_marker(state):
    lock = state / "kbs-jit-warmup.lock"
    lock.touch()
    assert _flags.start_warmup() is False  # another one is running
    lock.unlink()
    # run it in the foreground as the background process does (the cache is warm in CI by now,
    # so this mostly loads it); it removes its lock and leaves the marker
    lock.touch()
    r = subprocess.run([sys.executable, "-c", "import kbs.inference._flags as f, pathlib;"
                        f"f._state_dir = lambda: pathlib.Path({str(state)!r});"
                        "import kbs.inference._warmup as w, sys; sys.argv = ['w', sys.argv[1]]; w.main()", str(lock)],
                       capture_output=True, text=True, timeout=600,
                       env={**os.environ, "KBS_AOT": "0"})  # the ahead-of-time build: tests/test_aot.py
    assert r.returncode == 0, r.stderr
    assert not lock.exists()
    assert (state / "kbs-jit-ready").read_text() == _flags._stamp()


def test_a_stale_lock_does_not_block_for_ever(state, monkeypatch):
    lock = state / "kbs-jit-warmup.lock"
    lock.touch()
    old = time.time() - 2 * _flags._LOCK_SECONDS
    import os

    os.utime(lock, (old, old))
    popen = []
    monkeypatch.setattr(_flags.subprocess, "Popen", lambda *a, **k: popen.append(a))
    assert _flags.start_warmup() is True and len(popen) == 1


def test_kbs_warmup_compiles_in_the_foreground_then_says_it_is_done(state, monkeypatch):
    from click.testing import CliRunner

    from kbs.cli.main import cli
    from kbs.inference import _aot

    built = []

    def build():  # the real build (15 s): tests/test_aot.py
        so, table, _ = _aot.paths()
        so.write_bytes(b"")
        table.write_text("{}")
        built.append(so)
        return so

    monkeypatch.setattr(_aot, "build", build)
    r = CliRunner().invoke(cli, ["warmup"])
    assert r.exit_code == 0, r.output
    assert "compiled and cached the kernels" in r.output
    assert "built the kernels ahead of time" in r.output and len(built) == 1
    assert (state / "kbs-jit-ready").read_text() == _flags._stamp()
    r = CliRunner().invoke(cli, ["warmup"])
    assert r.exit_code == 0 and "already cached" in r.output and "already built" in r.output and len(built) == 1


def test_kbs_warmup_says_when_the_ahead_of_time_module_cannot_be_built(state, monkeypatch):
    from click.testing import CliRunner

    from kbs.cli.main import cli
    from kbs.inference import _aot

    def no_compiler():
        raise RuntimeError("no C compiler")

    monkeypatch.setattr(_aot, "build", no_compiler)
    r = CliRunner().invoke(cli, ["warmup"])
    assert r.exit_code == 0, r.output
    assert "ahead-of-time module was not built (RuntimeError: no C compiler)" in r.output
    monkeypatch.setenv("KBS_AOT", "0")
    r = CliRunner().invoke(cli, ["warmup"])
    assert r.exit_code == 0 and "ahead-of-time" not in r.output


#: kernels that only other kernels call (compiled into their callers, never from Python)
CALLED_BY_KERNELS_ONLY = {"sorted_quantile"}


@pytest.mark.slow
def test_the_warm_up_compiles_every_kernel_kbs_calls():
    """The background warm-up calls every cached kernel the library calls from Python, so that no
    run after it compiles one in the foreground (seconds each): grid_knn, plane_grid, gg_predict,
    plane_inlier_counts and nearest_other_distances were missing until session 29. In a fresh
    process, so that no other test's calls count."""
    code = (
        "import warnings, numba\n"
        "from kbs.inference import _numba_kernels, _flags, _warmup\n"
        "_flags.marker = lambda: type('M', (), {'write_text': lambda self, text: None})()\n"
        "warnings.simplefilter('error')\n"
        "_warmup.warm()\n"
        "k = {n: f for n, f in vars(_numba_kernels).items() if isinstance(f, numba.core.registry.CPUDispatcher)}\n"
        "cached = {n for n, f in k.items() if type(f._cache).__name__ != 'NullCache'}\n"
        f"print(len(cached), sorted(n for n in cached - set({sorted(CALLED_BY_KERNELS_ONLY)!r}) if not k[n].signatures))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    n, missing = out.stdout.strip().split(" ", 1)
    assert missing == "[]" and int(n) >= 35, out.stdout


def test_kbs_warmup_says_when_the_cache_folder_cannot_be_used(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from kbs.cli.main import cli

    (tmp_path / "a file").write_text("")
    monkeypatch.setenv("KBS_CACHE_DIR", str(tmp_path / "a file" / "kbs"))
    r = CliRunner().invoke(cli, ["warmup"])
    assert r.exit_code == 2, r.output
    assert "KBS_CACHE_DIR=" in r.output and "cannot hold the compiled kernels' marker" in r.output
