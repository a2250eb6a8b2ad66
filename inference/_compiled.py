"""The compiled kernels, by name: ``_compiled.gg_run(...)`` and the others of
:mod:`kbs.inference._numba_kernels` (numba), called from their ahead-of-time build
(:mod:`kbs.inference._aot`) when one is built for this machine and the kernels' source.

A name is resolved at its first use, then kept in this module. With the ahead-of-time module, it
is a small generated function that calls the module's export whose argument types are exactly
those of the call (pycc's exports do not check them), and numba's kernel for any other call (a
layout, dtype or scalar type the warm-up never compiled: numba compiles it, as before). Without
it (``KBS_JIT=1``, none built yet, no C compiler), the name is numba's kernel itself, and numba is
imported at that first use.

The results are the same either way (the same machine code; tested bit for bit on every kernel's
calls of real frames); a process that only calls exported signatures never imports numba, which
saves it about 0.6 s (:mod:`kbs.inference._aot`).
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np

_AOT: Any = False  # (module, exports) once looked for; None: not used


def _numba() -> Any:
    from kbs.inference import _numba_kernels

    return _numba_kernels


def _aot() -> Any:
    global _AOT
    if _AOT is False:
        _AOT = None
        from kbs.inference import _aot as aot

        if os.environ.get("KBS_JIT", "auto").strip().lower() not in ("0", "1") and aot.wanted():
            _AOT = aot.load()
    return _AOT


#: calls given to numba's kernel because no export had their types, by kernel (tests ask;
#: ``KBS_AOT_DEBUG=1`` prints each with its argument types on stderr)
FALLBACKS: dict[str, int] = {}

#: how an argument of each exported scalar type may be given (what numba types it as)
_SCALARS = {"float64": ("float", "np.float64"), "int64": ("int", "np.int64"), "bool": ("bool", "np.bool_")}


def _check(var: str, desc: list, consts: dict) -> str:
    """A Python test that ``var`` is exactly of the type ``desc`` (:func:`kbs.inference._aot._describe`)."""
    if desc[0] == "array":
        _, dt, ndim, layout, writeable, aligned = desc
        d = f"_d{len(consts)}"
        consts[d] = np.dtype(dt)
        tests = [f"isinstance({var}, _nd)", f"{var}.dtype == {d}", f"{var}.ndim == {ndim}"]
        flags = f"{var}.flags"
        if layout == "C":
            tests.append(f"{flags}.c_contiguous")
        elif layout == "F":
            tests.append(f"{flags}.f_contiguous and not {flags}.c_contiguous")
        else:
            tests.append(f"not {flags}.c_contiguous and not {flags}.f_contiguous")
        tests.append(f"{'' if writeable else 'not '}{flags}.writeable")
        tests.append(f"{'' if aligned else 'not '}{flags}.aligned")
        return " and ".join(tests)
    kinds = _SCALARS.get(desc[1], (f"np.{desc[1]}",))
    return "(" + " or ".join(f"type({var}) is {k}" for k in kinds) + ")"


def _dispatcher(name: str, module: Any, entries: list[dict]) -> Any:
    """The generated function for kernel ``name``: each export whose types the call has, in turn,
    else numba's kernel."""
    params = entries[0]["params"]
    defaults = entries[0]["defaults"]
    sig = ", ".join(f"{p}={defaults[p]!r}" if p in defaults else p for p in params)
    call = ", ".join(params)
    def _jit() -> Any:
        FALLBACKS[name] = FALLBACKS.get(name, 0) + 1
        if os.environ.get("KBS_AOT_DEBUG"):
            import inspect

            frame = inspect.currentframe().f_back  # type: ignore[union-attr]
            args = [frame.f_locals[p] for p in params]  # type: ignore[union-attr]
            import sys

            print("kbs: numba's kernel for", name, [(a.dtype.str, a.ndim, a.flags.c_contiguous, a.flags.writeable)
                                                    if isinstance(a, np.ndarray) else type(a).__name__ for a in args],
                  file=sys.stderr)
        return getattr(_numba(), name)

    consts: dict = {"_nd": np.ndarray, "np": np, "_jit": _jit}
    lines = [f"def {name}({sig}):"]
    for i, e in enumerate(entries):
        if e["params"] != params:
            continue
        fn = f"_aot{i}"
        consts[fn] = getattr(module, e["symbol"])
        test = " and ".join(_check(p, d, consts) for p, d in zip(params, e["args"]))
        lines.append(f"    if {test}:\n        return {fn}({call})")
    lines.append(f"    return _jit()({call})")
    exec("\n".join(lines), consts)  # noqa: S102 - generated from the module's own table
    fn = consts[name]
    fn.__doc__ = f"{name} of kbs.inference._numba_kernels, from its ahead-of-time build when the types match."
    return fn


def __getattr__(name: str) -> Any:
    if name.startswith("__"):
        raise AttributeError(name)
    aot = _aot()
    if aot is not None and name in aot[1]:
        fn = _dispatcher(name, aot[0], aot[1][name])
    else:
        fn = getattr(_numba(), name)
    globals()[name] = fn
    return fn
