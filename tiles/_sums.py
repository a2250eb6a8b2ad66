"""Compiled sums of the output clusters' geometry over a tiled result's files, chunk by chunk.

They add, cluster by cluster and point by point in increasing index, exactly what
:func:`kbs.inference._compiled.geometry3` adds for one cluster's points (the same products in the
same order), so the descriptors are those of :func:`kbs.inference.cluster_geometry` on each
cluster's points, to the last bit; the tests compare them with it.
"""
from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True)
def centre_sums(X, cluster, u, den, mass, c):  # pragma: no cover - compiled
    """First pass over a chunk: per cluster, sum of u^2 (``den``), of u (``mass``), of u^2 x (``c``)."""
    for j in range(X.shape[0]):
        k = cluster[j]
        if k < 0:
            continue
        uj = u[j]
        wj = 1.0
        p = uj * uj * wj
        den[k] += p
        mass[k] += uj * wj
        c[k, 0] += p * X[j, 0]
        c[k, 1] += p * X[j, 1]
        c[k, 2] += p * X[j, 2]


@njit(cache=True, nogil=True)
def covariance_sums(X, cluster, u, centre, s):  # pragma: no cover - compiled
    """Second pass: per cluster, the sums u d_a d_b (d = x - centre) in the order 00 01 02 11 12 22."""
    for j in range(X.shape[0]):
        k = cluster[j]
        if k < 0:
            continue
        uw = u[j] * 1.0
        d0 = X[j, 0] - centre[k, 0]
        d1 = X[j, 1] - centre[k, 1]
        d2 = X[j, 2] - centre[k, 2]
        s[k, 0] += uw * d0 * d0
        s[k, 1] += uw * d0 * d1
        s[k, 2] += uw * d0 * d2
        s[k, 3] += uw * d1 * d1
        s[k, 4] += uw * d1 * d2
        s[k, 5] += uw * d2 * d2
