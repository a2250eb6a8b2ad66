"""The compiled kernels ahead of time: one extension module built from the numba kernels
(:mod:`kbs.inference._numba_kernels`) by ``numba.pycc``, which a process imports in about a
millisecond, without importing numba.

Why. A ``kbs run`` process that loads numba's cached kernels pays about 0.6 s before its first
result: importing numba (0.15 s), numba's first dispatch (its typing and target registries,
``scipy.linalg`` for its BLAS check, the runtime's LLVM functions: 0.3-0.4 s) and each kernel's
machine code (about 5 ms each, 28 of them for a vehicle frame). The same machine code built once
into an extension module is loaded by the dynamic linker. It is built from the same LLVM IR by
the same numba, for this machine's CPU (``host``), with each kernel's own options (fastmath,
error model): the results are the JIT's to the last bit (tested on every kernel's calls of real
frames).

How. :func:`build` (run by the background warm-up after it has compiled the numba kernels, or by
``kbs warmup``) exports every signature the warm-up compiled, each through a one-line numba
function that calls the kernel (so that the kernel is compiled with its own options, not pycc's
defaults), and with the GIL released as the numba kernels release it. It writes
``_kbs_aot-<key>.so`` and then ``_kbs_aot-<key>.json`` (the exported signatures) in the state
folder (:func:`kbs.inference._flags._state_dir`), ``key`` a hash of :func:`stamp`: the kernels'
source, numba's and Python's versions and this CPU. :func:`load` imports the module of the current
key, or returns None.

pycc's functions do not check their arguments (an array of another dtype or layout is read as if
it were the exported one). :mod:`kbs.inference._compiled` therefore calls one only when every
argument is exactly of its exported type (the dtype, dimensions, layout, writeability and alignment
of an array, the type of a scalar), and the numba kernel otherwise.

Building needs a C compiler (pycc compiles and links a small C wrapper); without one, or when the
build fails for any other reason, the kernels stay numba's (the failure is written to
``_kbs_aot-<key>.failed`` and not retried for that key).
"""
from __future__ import annotations

import hashlib
import json
import os
import platform
import sys
import tempfile
from pathlib import Path
from typing import Any

#: the extension module's name (its ``PyInit`` function)
MODULE = "_kbs_aot"


def _cpu() -> str:
    """This CPU, as the machine code built for it needs it the same (the kernels are built for the
    host's instruction set): its model and feature flags on Linux, else the platform's names."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            info = {}
            for line in f:
                if not line.strip():
                    break  # the first processor
                key, _, value = line.partition(":")
                info[key.strip()] = value.strip()
        return f"{info.get('model name', '')}|{info.get('flags', '')}"
    except OSError:
        return f"{platform.machine()}|{platform.processor()}"


def stamp() -> str:
    """What an extension module was built from: the kernels' source, numba's and Python's versions
    (:func:`kbs.inference._flags._stamp`), this module (how it builds) and this CPU."""
    from kbs.inference import _flags

    me = Path(__file__).stat()
    return f"{_flags._stamp()}|{me.st_size}:{me.st_mtime_ns}|{platform.machine()}|{_cpu()}"


def key() -> str:
    return hashlib.sha256(stamp().encode()).hexdigest()[:16]


def paths(folder: Path | None = None) -> tuple[Path, Path, Path]:
    """The module, its table and its failure note for the current :func:`key`."""
    from kbs.inference import _flags

    base = (folder if folder is not None else _flags._state_dir()) / f"{MODULE}-{key()}"
    return base.with_suffix(".so"), base.with_suffix(".json"), base.with_suffix(".failed")


def wanted() -> bool:
    """Whether the ahead-of-time module may be built and used: not with ``KBS_AOT=0`` (numba's
    kernels only; ``KBS_JIT=1`` also keeps numba's, ``KBS_JIT=0`` the numpy reference)."""
    return os.environ.get("KBS_AOT", "1").strip() != "0"


def ready(folder: Path | None = None) -> bool:
    so, table, _ = paths(folder)
    return so.exists() and table.exists()


def failed(folder: Path | None = None) -> bool:
    return paths(folder)[2].exists()


def load(folder: Path | None = None) -> tuple[Any, dict] | None:
    """The extension module of the current key and its table of exports, or None (not built, or
    it does not import)."""
    try:
        so, table, _ = paths(folder)
        doc = json.loads(table.read_text())
        if doc.get("stamp") != stamp() or not so.exists():
            return None
        import importlib.machinery
        import importlib.util

        loader = importlib.machinery.ExtensionFileLoader(MODULE, str(so))
        spec = importlib.util.spec_from_file_location(MODULE, so, loader=loader)
        if spec is None:
            return None
        module = importlib.util.module_from_spec(spec)
        loader.exec_module(module)
        return module, doc["exports"]
    except (OSError, ValueError, ImportError, KeyError):
        return None


# -- building -----------------------------------------------------------------------------------------


def _describe(t: Any) -> list | None:
    """A numba argument type as the dispatcher checks it, or None when it does not check that kind:
    ``["array", dtype, ndim, layout, writeable, aligned]`` or ``["scalar", numpy type name]``."""
    from numba.core import types
    from numba.np.numpy_support import as_dtype

    if isinstance(t, types.Array):
        try:
            dt = as_dtype(t.dtype)
        except Exception:  # noqa: BLE001 - a dtype numpy has no name for: not exported
            return None
        if dt.isbuiltin != 1 or t.layout not in ("C", "F", "A"):
            return None
        return ["array", dt.str, int(t.ndim), t.layout, bool(t.mutable), bool(t.aligned)]
    if isinstance(t, (types.Boolean, types.Integer, types.Float)):
        return ["scalar", as_dtype(t).name]
    return None


def _exports(nb: Any) -> list[tuple[str, Any, list, list[str], dict]]:
    """(kernel name, numba signature with omitted arguments given their defaults' types, argument
    descriptors, parameter names, defaults) of every signature the numba kernels were compiled for."""
    import inspect

    from numba.core import types
    from numba.core.registry import CPUDispatcher
    from numba.core.typing import signature
    from numba.core.typing.typeof import typeof

    out = []
    for name, f in sorted(vars(nb).items()):
        if not isinstance(f, CPUDispatcher) or name.startswith("_"):
            continue
        params = inspect.signature(f.py_func).parameters
        names = list(params)
        defaults = {p: v.default for p, v in params.items() if v.default is not inspect.Parameter.empty}
        seen = set()
        for sig in f.nopython_signatures:
            args = [typeof(a.value) if isinstance(a, types.Omitted) else a for a in sig.args]
            desc = [_describe(a) for a in args]
            if len(args) != len(names) or any(d is None for d in desc) or tuple(args) in seen:
                continue
            seen.add(tuple(args))
            out.append((name, signature(sig.return_type, *args), desc, names, defaults))
    return out


def _wrapper(nb: Any, name: str, n: int):
    """A numba function of ``n`` arguments that calls kernel ``name``: exported instead of the
    kernel itself, so that the kernel is compiled with its own options (pycc compiles what it
    exports with its defaults: no fastmath)."""
    args = ", ".join(f"a{i}" for i in range(n))
    ns: dict = {"_k": getattr(nb, name)}
    exec(f"def _w({args}):\n    return _k({args})\n", ns)  # noqa: S102 - generated from a count
    return ns["_w"]


def build(folder: Path | None = None) -> Path:
    """Build the extension module of every exported signature into ``folder`` (the state folder by
    default) and write its table; returns the module's path. The numba kernels must have been
    compiled for the signatures wanted (the warm-up does it). Raises on failure (no compiler, pycc
    missing), after writing the failure note."""
    so, table, note = paths(folder)
    try:
        return _build(so, table)
    except BaseException as exc:
        try:
            note.write_text(f"{stamp()}\n{type(exc).__name__}: {exc}\n")
        except OSError:
            pass
        raise


def _build(so: Path, table: Path) -> Path:
    import warnings

    from kbs.inference import _numba_kernels as nb

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba.pycc is pending deprecation (a replacement is being written)
        import numba.pycc.compiler as pycc_compiler
        from numba.pycc import CC

    exports = _exports(nb)
    if not exports:
        raise RuntimeError("no compiled kernel signature to export: run the warm-up first")
    cc = CC(MODULE)
    cc.target_cpu = "host"
    cc.verbose = False
    doc: dict[str, list] = {}
    for i, (name, sig, desc, names, defaults) in enumerate(exports):
        symbol = f"{name}__{i}"
        cc.export(symbol, sig)(_wrapper(nb, name, len(desc)))
        doc.setdefault(name, []).append({"symbol": symbol, "args": desc, "params": names,
                                        "defaults": {k: v for k, v in defaults.items()
                                                     if isinstance(v, (bool, int, float))}})
    so.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=so.parent, prefix=".kbs-aot-") as tmp:
        cc.output_dir = tmp
        cc.output_file = MODULE + ".so"
        Flags = pycc_compiler.Flags

        class Releasing(Flags):  # type: ignore[misc, valid-type]
            """pycc's compile flags with the GIL released around each call, as the numba kernels
            (``nogil=True``) release it: threads run them side by side."""

            def __init__(self, *a: Any, **k: Any) -> None:
                super().__init__(*a, **k)
                self.release_gil = True

        setattr(pycc_compiler, "Flags", Releasing)  # noqa: B010 - a class attribute of numba, set for the build
        try:
            with open(os.devnull, "w") as null:
                old = os.dup(1)
                os.dup2(null.fileno(), 1)  # the C compiler's chatter
                try:
                    cc.compile()
                finally:
                    os.dup2(old, 1)
                    os.close(old)
        finally:
            setattr(pycc_compiler, "Flags", Flags)  # noqa: B010
        os.replace(Path(tmp) / cc.output_file, so)
    tmp_table = table.with_suffix(f".json.{os.getpid()}.tmp")  # two builders (kbs warmup, the background one) do not share it
    tmp_table.write_text(json.dumps({"stamp": stamp(), "python": sys.version, "exports": doc}, indent=1))
    os.replace(tmp_table, table)
    for old_file in so.parent.glob(f"{MODULE}-*"):  # the modules of other kernel versions
        if old_file.name.split(".")[0] != so.stem:
            try:
                old_file.unlink()
            except OSError:
                pass
    return so
