"""Whether the compiled kernels (:mod:`kbs.inference._compiled`, numba) are used.

Decided once per process, when kbs is imported, from ``KBS_JIT``:

- ``1``: always (a kernel not yet in numba's on-disk cache is compiled on first use);
- ``0``: never: the plain-numpy reference of every kernel runs (same iterations, same results to
  rounding; the tests compare the two);
- unset or ``auto`` (the default): when the kernels have been compiled and cached since kbs was
  installed or changed. Until then the process runs the numpy reference and starts, once, a
  background process (``python -m kbs.inference._warmup``) that compiles and caches every kernel
  (10-30 s), so that no run pays for the compilation; the next processes use the compiled code.
  The same background process then builds the kernels ahead of time into one extension module
  (:mod:`kbs.inference._aot`, about 15 s, needs a C compiler), which the processes after it
  import instead of loading numba (:mod:`kbs.inference._compiled`); ``KBS_JIT=1`` keeps numba's.

Tests switch it with ``monkeypatch.setattr(kbs.inference._flags, "JIT", False)``.
"""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

_SOURCE = Path(__file__).with_name("_numba_kernels.py")
#: staler than this, a warm-up lock is taken to belong to a warm-up that died
_LOCK_SECONDS = 900.0


def _stamp() -> str:
    """What the warm-up compiled: the kernels' source (size, mtime) and numba's version."""
    st = _SOURCE.stat()
    try:
        from importlib.metadata import version

        nb = version("numba")
    except Exception:  # noqa: BLE001 - not installed: nothing can be compiled
        nb = "none"
    return f"{st.st_size}:{st.st_mtime_ns}:{nb}:{sys.version_info[:2]}"


def _state_dir() -> Path:
    """Where the marker, the lock and the ahead-of-time module live: ``KBS_CACHE_DIR`` when set,
    else the package's ``__pycache__`` when writable (where numba caches too), else the user's
    cache folder."""
    chosen = os.environ.get("KBS_CACHE_DIR")
    if chosen:
        path = Path(chosen)
        path.mkdir(parents=True, exist_ok=True)
        return path
    here = _SOURCE.parent / "__pycache__"
    try:
        here.mkdir(exist_ok=True)
        if os.access(here, os.W_OK):
            return here
    except OSError:
        pass
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "kbs"
    base.mkdir(parents=True, exist_ok=True)
    return base


def marker() -> Path:
    return _state_dir() / "kbs-jit-ready"


def ready() -> bool:
    """Whether the warm-up compiled and cached the kernels of this source and numba version."""
    try:
        return marker().read_text() == _stamp()
    except OSError:
        return False


def start_warmup() -> bool:
    """Start the background compilation unless one is running; True when one was started."""
    try:
        lock = _state_dir() / "kbs-jit-warmup.lock"
        try:
            if time.time() - lock.stat().st_mtime > _LOCK_SECONDS:
                lock.unlink()
        except FileNotFoundError:
            pass
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        os.close(fd)
        env = {**os.environ, "KBS_JIT": "1"}
        subprocess.Popen([sys.executable, "-m", "kbs.inference._warmup", str(lock)], env=env,
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         start_new_session=True, close_fds=True)
        return True
    except OSError:  # somebody else is at it, or nowhere to write: the numpy path it is
        return False


def _aot_wanted() -> bool:
    from kbs.inference import _aot

    return _aot.wanted()


def _aot_state() -> tuple[bool, bool]:
    """(built, failed) of the ahead-of-time module of this source, numba and CPU (:mod:`kbs.inference._aot`)."""
    from kbs.inference import _aot

    try:
        return _aot.ready(), _aot.failed()
    except OSError:
        return False, True


def _decide() -> bool:
    mode = os.environ.get("KBS_JIT", "auto").strip().lower()
    if mode == "0":
        return False
    if mode == "1":
        return True
    if ready():
        built, failed = _aot_state()
        if not built and not failed and _aot_wanted():  # numba's kernels are cached, their ahead-of-time module not yet
            start_warmup()
        return True
    start_warmup()
    return False


JIT: bool = _decide()
