"""Pure geometry of point sets, below the knowledge layer: the principal components and plane
basis of a point set (:mod:`~kbs.geometry.pca`), the alpha-complex connexity and alpha opening
(:mod:`~kbs.geometry.connexity`), the robust plane of a ground candidate
(:mod:`~kbs.geometry.groundplane`), the local ground surface (:mod:`~kbs.geometry.groundmodel`) and
the nearest point (:mod:`~kbs.geometry.nearest`: scipy's k-d tree answers, compiled).

Arrays in, arrays out: no rules, no files. It uses numpy, scipy and the compiled kernels of
:mod:`kbs.inference._compiled` (one numba module, one warm-up; switched by ``KBS_JIT``), so it sits
just above the inference motor: ``inference < geometry < knowledge`` (``tests/test_layers.py``).

The engine's fuzzy cluster descriptor, :func:`kbs.inference.cluster_geometry` (membership-weighted
covariance, best approximating plane, with a compiled twin), stays in the inference motor: it is
part of the motor's public API, the tiles' streamed sums reproduce it to the last bit, and a motor
that imported this folder would make the layers circular.
"""
from __future__ import annotations
