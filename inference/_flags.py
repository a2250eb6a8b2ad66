"""Whether the compiled kernels (:mod:`kbs.inference._compiled`, numba) are used.

Read once from the environment when kbs is imported: ``KBS_JIT=0`` runs the plain-numpy
reference of every kernel instead (same iterations, same results up to rounding; the tests
compare the two). Tests switch it with ``monkeypatch.setattr(kbs.inference._flags, "JIT", False)``.
"""
from __future__ import annotations

import os

JIT: bool = os.environ.get("KBS_JIT", "1") != "0"
