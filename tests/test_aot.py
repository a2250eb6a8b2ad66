"""The kernels built ahead of time (kbs.inference._aot) and the calls that choose them
(kbs.inference._compiled): the same results as numba's kernels to the last bit, numba's kernel for
any call whose argument types the build did not export, and no numba in a process that needs none."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from kbs.inference import _aot, _compiled, _flags

ROOT = Path(__file__).resolve().parents[1]


# -- the generated calls, on a stand-in module (no build) -------------------------------------------


class _Exports:
    """A stand-in for the built module: records which export was called."""

    def __init__(self) -> None:
        self.calls: list[str] = []

    def __getattr__(self, symbol: str):
        def export(*args):
            self.calls.append(symbol)
            return symbol

        return export


class _Numba:
    def __init__(self) -> None:
        self.calls: list[tuple] = []

    def kern(self, X, w, n, flag=True):
        self.calls.append((X, w, n, flag))
        return "numba"


_ENTRIES = [
    {"symbol": "kern__0", "params": ["X", "w", "n", "flag"], "defaults": {"flag": True},
     "args": [["array", "<f8", 2, "C", True, True], ["scalar", "float64"], ["scalar", "int64"], ["scalar", "bool"]]},
    {"symbol": "kern__1", "params": ["X", "w", "n", "flag"], "defaults": {"flag": True},
     "args": [["array", "<f8", 2, "C", False, True], ["scalar", "float64"], ["scalar", "int64"], ["scalar", "bool"]]},
]


@pytest.fixture
def fake(monkeypatch):
    nb, mod = _Numba(), _Exports()
    monkeypatch.setattr(_compiled, "_numba", lambda: nb)
    return _compiled._dispatcher("kern", mod, _ENTRIES), mod, nb


def test_a_call_goes_to_the_export_whose_types_it_has_exactly(fake):
    fn, mod, nb = fake
    X = np.zeros((4, 3))
    assert fn(X, 1.0, 3) == "kern__0"  # the default filled in, as numba types an omitted argument
    assert fn(X, np.float64(1.0), np.int64(3), np.bool_(False)) == "kern__0"
    ro = X.copy()
    ro.flags.writeable = False
    assert fn(ro, 1.0, 3, False) == "kern__1"  # read-only: the read-only export
    assert fn(X, w=1.0, n=3) == "kern__0"  # by keyword too
    assert mod.calls == ["kern__0", "kern__0", "kern__1", "kern__0"] and nb.calls == []


@pytest.mark.parametrize("args", [
    (np.zeros((4, 3), order="F"), 1.0, 3),  # another layout
    (np.zeros((6, 3))[::2], 1.0, 3),  # not contiguous
    (np.zeros((4, 3), dtype=np.float32), 1.0, 3),  # another dtype
    (np.zeros((4, 3), dtype=">f8"), 1.0, 3),  # another byte order
    (np.zeros(4), 1.0, 3),  # another number of dimensions
    ([[0.0, 0.0, 0.0]], 1.0, 3),  # not an array
    (np.zeros((4, 3)), 1, 3),  # an int where a float is exported
    (np.zeros((4, 3)), 1.0, 3.0),  # a float where an int is
    (np.zeros((4, 3)), 1.0, True),  # a bool where an int is
    (np.zeros((4, 3)), 1.0, np.int32(3)),  # another integer type
])
def test_any_other_call_goes_to_numbas_kernel(fake, args):
    """pycc's exports read their arguments as the exported types without checking them (an array
    of another dtype crashed the process, one of another layout was read as C-ordered): such calls
    go to numba's kernel, which compiles them as it always did."""
    fn, mod, nb = fake
    assert fn(*args) == "numba"
    assert mod.calls == [] and len(nb.calls) == 1
    assert _compiled.FALLBACKS.get("kern", 0) >= 1


def test_the_module_of_another_source_or_cpu_is_not_loaded(tmp_path, monkeypatch):
    monkeypatch.setattr(_flags, "_state_dir", lambda: tmp_path)
    assert _aot.load() is None  # not built
    so, table, _ = _aot.paths()
    assert so.name.startswith(_aot.MODULE + "-") and _aot.key() in so.name
    so.write_bytes(b"not a module")
    table.write_text(json.dumps({"stamp": "another source", "exports": {}}))
    assert _aot.load() is None  # a stale stamp
    table.write_text(json.dumps({"stamp": _aot.stamp(), "exports": {}}))
    assert _aot.load() is None  # it does not import: numba's kernels then
    monkeypatch.setattr(_aot, "_cpu", lambda: "another CPU")
    assert _aot.paths()[0] != so  # another CPU, another key


# -- the real build ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """The kernels built ahead of time into a folder of their own (about 15 s), by the warm-up's
    own steps, in a fresh process (KBS_JIT=1, as the background warm-up runs)."""
    folder = tmp_path_factory.mktemp("aot")
    code = ("from kbs.inference import _warmup, _aot\n"
            "_warmup.warm()\n"
            "print(_aot.build())\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900,
                       env={**os.environ, "KBS_JIT": "1", "KBS_CACHE_DIR": str(folder)})
    if r.returncode != 0:
        notes = [n.read_text() for n in folder.glob("*.failed")]
        if any("CompileError" in n or "LinkError" in n for n in notes):
            pytest.skip(f"no working C compiler here: {notes[0][-300:]}")
        raise AssertionError(r.stderr[-3000:])
    return folder


_FRAME = r"""
import json, sys
import numpy as np
X = np.load(sys.argv[1]) if sys.argv[1].endswith(".npy") else None
import kbs
from kbs.inference import _compiled
seg = kbs.Segmenter(sys.argv[2], jobs=1)
r = seg.segment(X.astype(np.float64)[:, :3])
np.savez(sys.argv[3], cluster=r.cluster, label=r.label, membership=r.membership)
print(json.dumps({"numba": "numba" in sys.modules, "fallbacks": _compiled.FALLBACKS,
                  "aot": _compiled._aot() is not None, "scipy": any(m.split(".")[0] == "scipy" for m in sys.modules)}))
"""


def _frame(scan: Path, rules: str, out: Path, env: dict) -> dict:
    r = subprocess.run([sys.executable, "-c", _FRAME, str(scan), rules, str(out)], capture_output=True, text=True,
                       timeout=600, env={**os.environ, **env})
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def _scans(tmp_path: Path) -> list[tuple[Path, str]]:
    from kbs.io import read_cloud
    from conftest import SHARED_DATA

    if SHARED_DATA.is_dir():
        out = [(SHARED_DATA / "semantickitti" / "000001.points.npy", "outdoor")]
        isprs = read_cloud(SHARED_DATA / "isprs" / "samp61-utm.pcd").xyz
        np.save(tmp_path / "samp61.npy", isprs - isprs.mean(axis=0))
        out.append((tmp_path / "samp61.npy", "airborne"))
        return out
    from scenes import ground_and_rocks

    X, _ = ground_and_rocks()
    np.save(tmp_path / "rocks.npy", X)
    return [(tmp_path / "rocks.npy", "outdoor")]


@pytest.mark.slow
def test_a_run_with_the_built_kernels_gives_numbas_results_bit_for_bit_without_numba(built, tmp_path):
    """A vehicle frame (outdoor) and an airborne sample (airborne), in fresh processes: with the
    module built ahead of time every kernel call finds its export (none goes to numba, which is
    never imported), and the clusters, labels and memberships are numba's kernels' to the last bit.
    The vehicle frame imports no scipy at all: the kernels' 3 x 3 eigensolver is their own (numba's
    ``np.linalg.eigh`` imported scipy's LAPACK, about 0.1 s), and the outdoor rules need no k-d tree.
    (The airborne rules' surface queries use scipy's k-d tree.)"""
    for scan, rules in _scans(tmp_path):
        a = _frame(scan, rules, tmp_path / "aot.npz", {"KBS_CACHE_DIR": str(built), "KBS_JIT": "auto"})
        j = _frame(scan, rules, tmp_path / "jit.npz", {"KBS_JIT": "1"})
        scipy = a.pop("scipy")
        assert a == {"numba": False, "fallbacks": {}, "aot": True}, (scan, a)
        assert not (rules == "outdoor" and scipy), scan
        assert j["numba"] and not j["aot"]
        with np.load(tmp_path / "aot.npz") as fa, np.load(tmp_path / "jit.npz") as fj:
            for key in ("cluster", "label", "membership"):
                assert np.array_equal(fa[key], fj[key]), (scan, key)


@pytest.mark.slow
def test_the_built_kernels_release_the_gil_as_numbas_do(built, monkeypatch):
    """The surface's k-nearest kernel runs in threads (LocalGround with workers): another thread
    runs Python while it computes."""
    monkeypatch.setattr(_flags, "_state_dir", lambda: built)
    loaded = _aot.load(built)
    assert loaded is not None
    module, exports = loaded
    rng = np.random.default_rng(0)
    T = np.ascontiguousarray(rng.random((200_000, 2)) * 100)
    nb = __import__("kbs.inference._numba_kernels", fromlist=["plane_grid"])
    *grid, ok = nb.plane_grid(T, 2.0 * float(np.sqrt(100 * 100 / T.shape[0])))
    assert ok
    Q = np.ascontiguousarray(rng.random((400_000, 2)) * 100)
    heights = np.zeros(T.shape[0])
    owners = np.zeros(0, dtype=np.int64)
    fn = _compiled._dispatcher("grid_knn", module, exports["grid_knn"])
    started, done = threading.Event(), threading.Event()
    span: list[float] = []
    ticks: list[float] = []

    def work():
        started.set()
        t0 = time.perf_counter()
        fn(Q, T, *grid, 16, 3.0, heights, owners, -1, 16, 0)
        span.extend((t0, time.perf_counter()))
        done.set()

    t = threading.Thread(target=work)
    t.start()
    started.wait()
    n = 0
    while not done.is_set():  # Python in this thread while the kernel computes in the other
        n += 1
        if n % 1000 == 0:
            ticks.append(time.perf_counter())
    t.join()
    assert _compiled.FALLBACKS.get("grid_knn", 0) == 0
    t0, t1 = span
    middle = [x for x in ticks if t0 + 0.25 * (t1 - t0) < x < t0 + 0.75 * (t1 - t0)]
    assert middle, (t1 - t0, len(ticks))  # holding the GIL, the kernel would leave this thread none
