"""Compiled kernels of the two iteration layers for 3D points (numba, cached on disk).

These are the iterations of :func:`kbs.inference.engine.fcm_fit` and
:func:`kbs.inference.engine.gg_fit` (the plain-numpy reference, which the tests compare them
with), with the whole iteration loop (stopping test, SQUAREM extrapolation) compiled, so that a
fit never returns to Python between updates. On the small fitting sets of a split tree (hundreds
to a few thousand samples, K <= 10) numpy's per-call overhead, not arithmetic, dominated: about
60 numpy calls per Gath-Geva update.

Every loop runs along contiguous rows of length n (structure of arrays: ``XT`` (3, n), moments
(10, n), memberships (K, n)) so that the compiler vectorises it; reductions are written with
``fastmath`` (their summation order differs from numpy's BLAS by rounding only). The exponential
of the memberships is :func:`_exp_row`, a vectorisable exp (Cody-Waite reduction and a
degree-13 Taylor polynomial, relative error below 1e-15 on the range used), because the scalar
libm ``exp`` numba calls cost five times numpy's vectorised one here.

A cluster that dies (effective size below the minimum) is not handled here: the kernel stops
and says so (``status`` 1) and the caller reruns the reference from the same start, which records
the drop exactly as before. Drops are rare (a new prototype that finds no points).

Shapes: ``XT`` (3, n) centred points, ``w`` (n,) weights, ``R`` (10, n) the moments
``[w, w x, w y, w z, w xx + s_xx, w xy + s_xy, w xz + s_xz, w yy + s_yy, w yz + s_yz, w zz + s_zz]``
(``s`` the within-voxel scatter), memberships ``u`` (K, n).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

TINY = float(np.finfo(np.float64).tiny)
_LN2_HI = 6.93147180369123816490e-01
_LN2_LO = 1.90821492927058770002e-10
_LOG2E = 1.44269504088896338700e00
#: 1 / k! for k = 0 .. 13
_INV_FACT = tuple(1.0 / math.factorial(k) for k in range(14))
_C2, _C3, _C4, _C5, _C6, _C7, _C8, _C9, _C10, _C11, _C12, _C13 = _INV_FACT[2:]
_FAST = {"nnan", "ninf", "nsz", "arcp", "contract", "afn", "reassoc"}
_VEC = {"contract"}  # loops without reductions: fused multiply-adds only


@njit(nogil=True, fastmath=_VEC)
def _exp_row(x, ibuf, out):
    """``out[j] = exp(x[j])`` for ``x[j] <= 0`` (values below -708 give 0, as they would
    underflow to subnormals): vectorisable."""
    n = x.shape[0]
    fbuf = ibuf.view(np.float64)
    for j in range(n):
        v = x[j]
        if v < -708.0:
            v = -708.0
        k = math.floor(v * _LOG2E + 0.5)
        r = (v - k * _LN2_HI) - k * _LN2_LO
        p = _C13
        p = p * r + _C12
        p = p * r + _C11
        p = p * r + _C10
        p = p * r + _C9
        p = p * r + _C8
        p = p * r + _C7
        p = p * r + _C6
        p = p * r + _C5
        p = p * r + _C4
        p = p * r + _C3
        p = p * r + _C2
        p = p * r + 1.0
        p = p * r + 1.0
        out[j] = p
        ibuf[j] = (np.int64(k) + 1023) << 52
    for j in range(n):
        out[j] = out[j] * fbuf[j] if x[j] >= -708.0 else 0.0


@njit(nogil=True, fastmath=_FAST)
def _dot(a, b):
    s = 0.0
    for j in range(a.shape[0]):
        s += a[j] * b[j]
    return s


@njit(nogil=True, fastmath=_VEC)
def _power_row(u, power, out):
    n = u.shape[0]
    if power == 2.0:
        for j in range(n):
            out[j] = u[j] * u[j]
    elif power == 1.0:
        for j in range(n):
            out[j] = u[j]
    else:
        for j in range(n):
            out[j] = u[j] ** power


@njit(nogil=True)
def _centers(u, R, power, tmp):
    """Centres (K, 3) ``sum w u^p x / sum w u^p``."""
    K = u.shape[0]
    centers = np.empty((K, 3))
    for k in range(K):
        _power_row(u[k], power, tmp)
        den = max(_dot(tmp, R[0]), TINY)
        for d in range(3):
            centers[k, d] = _dot(tmp, R[1 + d]) / den
    return centers


@njit(nogil=True, fastmath=_FAST)
def _max_abs_diff(a, b):
    K, n = a.shape
    delta = 0.0
    for k in range(K):
        ak = a[k]
        bk = b[k]
        for j in range(n):
            delta = max(delta, abs(ak[j] - bk[j]))
    return delta


# -- fuzzy c-means ---------------------------------------------------------------------------


@njit(nogil=True, fastmath=_VEC)
def _fcm_memberships(XT, centers, m, d2, dmin, tot, u_new):
    """Memberships from squared Euclidean distances, as
    :func:`~kbs.inference.kernels.memberships_from_sq_dist`; ``d2``, ``dmin``, ``tot`` are
    work buffers (K, n), (n,), (n,)."""
    K = centers.shape[0]
    n = XT.shape[1]
    x0 = XT[0]
    x1 = XT[1]
    x2 = XT[2]
    for j in range(n):
        dmin[j] = np.inf
        tot[j] = 0.0
    for k in range(K):
        c0 = centers[k, 0]
        c1 = centers[k, 1]
        c2 = centers[k, 2]
        dk = d2[k]
        for j in range(n):
            t0 = x0[j] - c0
            t1 = x1[j] - c1
            t2 = x2[j] - c2
            s = t0 * t0 + t1 * t1 + t2 * t2
            s = max(s, TINY)
            dk[j] = s
            dmin[j] = min(dmin[j], s)
    inv = 1.0 / (m - 1.0)
    for k in range(K):
        dk = d2[k]
        uk = u_new[k]
        if m == 2.0:
            for j in range(n):
                r = dmin[j] / dk[j]
                uk[j] = r
                tot[j] += r
        else:
            for j in range(n):
                r = (dmin[j] / dk[j]) ** inv
                uk[j] = r
                tot[j] += r
    for k in range(K):
        uk = u_new[k]
        for j in range(n):
            uk[j] = uk[j] / tot[j]


@njit(cache=True, nogil=True)
def new_prototype_u2(XT, centers, d0):
    """:func:`kbs.inference.engine.new_prototype_memberships` for m = 2 and 3 coordinates: the
    squared distances ``(t0^2 + t1^2) + t2^2`` to the K centres and ``d0`` to the new one, floored
    at TINY, then ``u_k = (d_min / d_k) / sum_k (d_min / d_k)``. Each operation rounded alone, in
    numpy's order (no fused multiply-adds): the very memberships numpy computes."""
    K = centers.shape[0]
    n = XT.shape[1]
    r = np.empty((K + 1, n))
    for j in range(n):
        x0 = XT[0, j]
        x1 = XT[1, j]
        x2 = XT[2, j]
        for k in range(K):
            t0 = x0 - centers[k, 0]
            t1 = x1 - centers[k, 1]
            t2 = x2 - centers[k, 2]
            r[k, j] = max((t0 * t0 + t1 * t1) + t2 * t2, TINY)
        r[K, j] = max(d0, TINY)
        dmin = r[0, j]
        for k in range(1, K + 1):
            dmin = min(dmin, r[k, j])
        tot = 0.0
        for k in range(K + 1):
            v = dmin / r[k, j]
            r[k, j] = v
            tot += v
        for k in range(K + 1):
            r[k, j] = r[k, j] / tot
    return r


@njit(cache=True, nogil=True)
def fcm_run(XT, w, R, u0, m, tol, max_iter, min_mass):
    """Fuzzy c-means from ``u0`` (K, n). Returns ``(centers, u, n_iter, converged, status)``;
    ``status`` 1 means a cluster died in update ``n_iter``: ``u`` are then that update's new
    memberships (their effective sizes say which)."""
    K, n = u0.shape
    u = u0.copy()
    un = np.empty_like(u)
    d2 = np.empty_like(u)
    dmin = np.empty(n)
    tot = np.empty(n)
    tmp = np.empty(n)
    centers = np.zeros((K, 3))
    it = 0
    while it < max_iter:
        it += 1
        centers = _centers(u, R, m, tmp)
        _fcm_memberships(XT, centers, m, d2, dmin, tot, un)
        for k in range(K):
            if _dot(un[k], w) < min_mass:
                return centers, un, it, False, 1
        delta = _max_abs_diff(un, u)
        u, un = un, u
        if delta < tol:
            return centers, u, it, True, 0
    return centers, u, it, False, 0


# -- Gath-Geva -------------------------------------------------------------------------------


@njit(nogil=True, fastmath=_FAST)
def _gg_sums(uk, R, power, S):
    """One pass over the points for one cluster: ``S[0:4] = sum u^p [w, w x]`` (the centre) and
    ``S[4:14] = sum u R`` (mass, first and second moments)."""
    n = uk.shape[0]
    a0 = a1 = a2 = a3 = 0.0
    b0 = b1 = b2 = b3 = b4 = b5 = b6 = b7 = b8 = b9 = 0.0
    r0 = R[0]
    r1 = R[1]
    r2 = R[2]
    r3 = R[3]
    r4 = R[4]
    r5 = R[5]
    r6 = R[6]
    r7 = R[7]
    r8 = R[8]
    r9 = R[9]
    for j in range(n):
        u = uk[j]
        if power == 2.0:
            p = u * u
        elif power == 1.0:
            p = u
        else:
            p = u ** power
        a0 += p * r0[j]
        a1 += p * r1[j]
        a2 += p * r2[j]
        a3 += p * r3[j]
        b0 += u * r0[j]
        b1 += u * r1[j]
        b2 += u * r2[j]
        b3 += u * r3[j]
        b4 += u * r4[j]
        b5 += u * r5[j]
        b6 += u * r6[j]
        b7 += u * r7[j]
        b8 += u * r8[j]
        b9 += u * r9[j]
    S[0] = a0
    S[1] = a1
    S[2] = a2
    S[3] = a3
    S[4] = b0
    S[5] = b1
    S[6] = b2
    S[7] = b3
    S[8] = b4
    S[9] = b5
    S[10] = b6
    S[11] = b7
    S[12] = b8
    S[13] = b9


@njit(nogil=True)
def _jacobi(a, v, vectors):
    """The cyclic Jacobi rotations of :func:`_eigh3` on the symmetric 3 x 3 ``a`` (both triangles
    set), in place, until it is diagonal: its diagonal then holds the eigenvalues (unsorted);
    with ``vectors``, the rotations are also applied to ``v`` (the identity at the start: the
    eigenvectors, columns). The eigenvalues do not depend on ``vectors`` (the same rotations):
    a caller that needs the values only (:func:`ball_thickness`) skips the vectors, and the
    arrays of a call (it allocates none)."""
    for sweep in range(64):
        if a[0, 1] == 0.0 and a[0, 2] == 0.0 and a[1, 2] == 0.0:
            break
        for pq in range(3):
            p = 0 if pq < 2 else 1
            q = 1 if pq == 0 else 2
            apq = a[p, q]
            if apq == 0.0:
                continue
            g = 100.0 * abs(apq)
            app = a[p, p]
            aqq = a[q, q]
            if sweep > 2 and abs(app) + g == abs(app) and abs(aqq) + g == abs(aqq):
                a[p, q] = 0.0
                a[q, p] = 0.0
                continue
            h = aqq - app
            if abs(h) + g == abs(h):
                t = apq / h
            else:
                theta = 0.5 * h / apq
                t = 1.0 / (abs(theta) + math.sqrt(1.0 + theta * theta))
                if theta < 0.0:
                    t = -t
            c = 1.0 / math.sqrt(1.0 + t * t)
            s = t * c
            tau = s / (1.0 + c)
            a[p, p] = app - t * apq
            a[q, q] = aqq + t * apq
            a[p, q] = 0.0
            a[q, p] = 0.0
            r = 3 - p - q
            arp = a[r, p]
            arq = a[r, q]
            a[r, p] = a[p, r] = arp - s * (arq + arp * tau)
            a[r, q] = a[q, r] = arq + s * (arp - arq * tau)
            if vectors:
                for j in range(3):
                    vjp = v[j, p]
                    vjq = v[j, q]
                    v[j, p] = vjp - s * (vjq + vjp * tau)
                    v[j, q] = vjq + s * (vjp - vjq * tau)


@njit(nogil=True)
def _eigh3(A):
    """Eigenvalues (3,), ascending, and unit eigenvectors (3, 3), columns, of the symmetric 3 x 3
    matrix ``A``, of which the lower triangle is read (as ``np.linalg.eigh``, whose results these
    equal to rounding): cyclic Jacobi rotations (Rutishauser's formulation, Golub and Van Loan
    section 8.5), each of which sets one off-diagonal element to zero, until all three are zero.

    Why not ``np.linalg.eigh``: in numba it calls LAPACK through ``scipy.linalg.cython_lapack``,
    whose import costs a ``kbs run`` process about 0.1 s; and in one scratch loop over 20,000
    covariance-like matrices a call took 1.1-1.6 us here against 4.4-4.6 us there. Jacobi's
    method is the accurate one for small symmetric matrices (small eigenvalues to a high relative
    accuracy, orthogonal eigenvectors), and converges quadratically: 3 to 5 sweeps of three
    rotations. An element is also set to zero once it is too small to change
    either diagonal element it rotates (after three sweeps, as in Numerical Recipes' ``jacobi``),
    so that the loop ends on any finite matrix. A non-finite matrix raises ``LinAlgError``, as
    numba's ``np.linalg.eigh`` does."""
    a = np.empty((3, 3))
    for i in range(3):
        for j in range(i + 1):
            x = A[i, j]
            if not np.isfinite(x):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
            a[i, j] = x
            a[j, i] = x
    v = np.eye(3)
    _jacobi(a, v, True)
    # ascending, ties in their order (a stable sort of three)
    o0, o1, o2 = 0, 1, 2
    if a[o1, o1] < a[o0, o0]:
        o0, o1 = o1, o0
    if a[o2, o2] < a[o1, o1]:
        o1, o2 = o2, o1
        if a[o1, o1] < a[o0, o0]:
            o0, o1 = o1, o0
    lam = np.empty(3)
    vec = np.empty((3, 3))
    order = (o0, o1, o2)
    for k in range(3):
        o = order[k]
        lam[k] = a[o, o]
        for j in range(3):
            vec[j, k] = v[j, o]
    return lam, vec


@njit(nogil=True)
def _gg_params(u, R, power, total, min_variance, max_condition, min_mass, tmp):
    """Centres, floored Gaussians and priors from memberships ``u`` (K, n): one Gath-Geva
    update's parameters. ``status`` 1 when a cluster dies."""
    K = u.shape[0]
    centers = np.empty((K, 3))
    SS = np.empty((K, 14))
    for k in range(K):
        _gg_sums(u[k], R, power, SS[k])
        den = max(SS[k, 0], TINY)
        for d in range(3):
            centers[k, d] = SS[k, 1 + d] / den
    lam_all = np.empty((K, 3))
    vec_all = np.empty((K, 3, 3))
    whit = np.empty((K, 3, 3))
    logdet = np.empty(K)
    priors = np.empty(K)
    cov = np.empty((3, 3))
    for k in range(K):
        S = SS[k, 4:]
        mass = S[0]
        if mass < min_mass:
            return centers, lam_all, vec_all, whit, logdet, priors, 1
        den = max(mass, TINY)
        v0 = centers[k, 0]
        v1 = centers[k, 1]
        v2 = centers[k, 2]
        s1 = (S[1], S[2], S[3])
        v = (v0, v1, v2)
        # second moments (row-major index into S for (a, b), a <= b)
        idx = ((4, 5, 6), (5, 7, 8), (6, 8, 9))
        for a in range(3):
            for b in range(3):
                cov[a, b] = (S[idx[a][b]] - v[a] * s1[b] - s1[a] * v[b] + mass * v[a] * v[b]) / den
        lam, vec = _eigh3(cov)
        floor = max(min_variance, lam[2] / max_condition)
        ld = 0.0
        for d in range(3):
            if lam[d] < floor:
                lam[d] = floor
            ld += math.log(lam[d])
        for a in range(3):
            for b in range(3):
                vec_all[k, a, b] = vec[a, b]
                whit[k, a, b] = vec[a, b] / math.sqrt(lam[b])
            lam_all[k, a] = lam[a]
        logdet[k] = ld
        priors[k] = mass / total
    return centers, lam_all, vec_all, whit, logdet, priors, 0


@njit(nogil=True, fastmath=_VEC)
def _gg_z(XT, centers, whit, logdet, priors, m, maha, z, zmax):
    """Squared Mahalanobis distances into ``maha`` (K, n), the softmax arguments
    ``-log d_e2 / (m - 1)`` into ``z`` (K, n) and their maximum over clusters into ``zmax``."""
    K = centers.shape[0]
    n = XT.shape[1]
    x0 = XT[0]
    x1 = XT[1]
    x2 = XT[2]
    a = -0.5 / (m - 1.0)
    for j in range(n):
        zmax[j] = -np.inf
    for k in range(K):
        ck = (0.5 * logdet[k] - math.log(priors[k])) / (m - 1.0)
        w00 = whit[k, 0, 0]
        w01 = whit[k, 0, 1]
        w02 = whit[k, 0, 2]
        w10 = whit[k, 1, 0]
        w11 = whit[k, 1, 1]
        w12 = whit[k, 1, 2]
        w20 = whit[k, 2, 0]
        w21 = whit[k, 2, 1]
        w22 = whit[k, 2, 2]
        v0 = centers[k, 0]
        v1 = centers[k, 1]
        v2 = centers[k, 2]
        mk = maha[k]
        zk = z[k]
        for j in range(n):
            d0 = x0[j] - v0
            d1 = x1[j] - v1
            d2 = x2[j] - v2
            y0 = w00 * d0 + w10 * d1 + w20 * d2
            y1 = w01 * d0 + w11 * d1 + w21 * d2
            y2 = w02 * d0 + w12 * d1 + w22 * d2
            s = y0 * y0 + y1 * y1 + y2 * y2
            mk[j] = s
            t = s * a - ck
            zk[j] = t
            zmax[j] = max(zmax[j], t)


@njit(nogil=True, fastmath=_VEC)
def _softmax(z, zmax, tot, ibuf, u_new):
    """``u_new[k] = exp(z[k] - zmax) / sum_k exp(z[k] - zmax)``; ``z`` is overwritten.

    One cluster (the K = 1 fit of every sweep): where ``z - zmax`` is 0 (``z`` finite) the
    general path computes ``exp(0) = 1`` (``k = 0``, ``r = 0``, ``p = 1``, scale ``2^0``),
    ``tot = 1 / 1`` and ``1 * 1``: 1.0 exactly, which is written without the exponential; any
    other value (a non-finite ``z``) takes the general path."""
    K, n = z.shape
    if K == 1:
        zk = z[0]
        ones = True
        for j in range(n):
            if zk[j] - zmax[j] != 0.0:
                ones = False
                break
        if ones:
            uk = u_new[0]
            for j in range(n):
                zk[j] = 0.0
                uk[j] = 1.0
            return
    for j in range(n):
        tot[j] = 0.0
    for k in range(K):
        zk = z[k]
        for j in range(n):
            zk[j] = zk[j] - zmax[j]
        uk = u_new[k]
        _exp_row(zk, ibuf, uk)
        for j in range(n):
            tot[j] += uk[j]
    for j in range(n):
        tot[j] = 1.0 / tot[j]
    for k in range(K):
        uk = u_new[k]
        for j in range(n):
            uk[j] = uk[j] * tot[j]


@njit(nogil=True)
def _gg_memberships(XT, centers, whit, logdet, priors, m, u_new, maha, z, zmax, tot, ibuf):
    _gg_z(XT, centers, whit, logdet, priors, m, maha, z, zmax)
    _softmax(z, zmax, tot, ibuf, u_new)


@njit(cache=True, nogil=True)
def gg_predict(XT, centers, whit, logdet, priors, m):
    """Memberships (K, n) of points ``XT`` (3, n, centred) under fixed parameters."""
    K = centers.shape[0]
    n = XT.shape[1]
    u = np.empty((K, n))
    maha = np.empty((K, n))
    z = np.empty((K, n))
    _gg_memberships(XT, centers, whit, logdet, priors, m, u, maha, z, np.empty(n), np.empty(n),
                    np.empty(n, dtype=np.int64))
    return u


@njit(cache=True, nogil=True)
def gg_predict_rows(X, offset, centers, whit, logdet, priors, m, chunk):
    """Memberships (n, K) of points ``X`` (n, 3, input coordinates) under fixed parameters
    (``centers`` centred on ``offset``): :func:`gg_predict` of each chunk of ``chunk`` rows
    centred ``X - offset``, as :func:`kbs.inference.engine.memberships_in_chunks` computes them,
    without its transposed copies. The same compiled memberships on the same centred
    coordinates: identical values."""
    n = X.shape[0]
    K = centers.shape[0]
    out = np.empty((n, K))
    for s in range(0, n, chunk):
        c = min(chunk, n - s)
        XT = np.empty((3, c))
        for j in range(c):
            for a in range(3):
                XT[a, j] = X[s + j, a] - offset[a]
        u = np.empty((K, c))
        _gg_memberships(XT, centers, whit, logdet, priors, m, u, np.empty((K, c)), np.empty((K, c)),
                        np.empty(c), np.empty(c), np.empty(c, dtype=np.int64))
        for j in range(c):
            for k in range(K):
                out[s + j, k] = u[k, j]
    return out


@njit(nogil=True, fastmath=_FAST)
def _squarem_norms(u, s1, s2, w):
    K, n = u.shape
    nr = 0.0
    nv = 0.0
    for k in range(K):
        uk = u[k]
        ak = s1[k]
        bk = s2[k]
        for j in range(n):
            r = ak[j] - uk[j]
            v = bk[j] - 2.0 * ak[j] + uk[j]
            nr += r * r * w[j]
            nv += v * v * w[j]
    return nr, nv


@njit(nogil=True, fastmath=_VEC)
def _extrapolate(u, s1, s2, alpha, tot, out):
    """``out = u - 2 alpha r + alpha^2 v`` (r = s1 - u, v = s2 - 2 s1 + u), clipped to [0, 1]
    and renormalised over clusters."""
    K, n = u.shape
    for j in range(n):
        tot[j] = 0.0
    for k in range(K):
        uk = u[k]
        ak = s1[k]
        bk = s2[k]
        ok = out[k]
        for j in range(n):
            r = ak[j] - uk[j]
            v = bk[j] - 2.0 * ak[j] + uk[j]
            x = uk[j] - 2.0 * alpha * r + alpha * alpha * v
            x = min(max(x, 0.0), 1.0)
            ok[j] = x
            tot[j] += x
    for j in range(n):
        tot[j] = max(tot[j], TINY)
    for k in range(K):
        ok = out[k]
        for j in range(n):
            ok[j] = ok[j] / tot[j]


@njit(cache=True, nogil=True)
def gg_run(XT, w, R, u0, m, power, tol, max_iter, min_variance, max_condition, min_mass, accelerate):
    """Gath-Geva iterations from ``u0`` (K, n), with the stopping test and the SQUAREM
    extrapolation of :func:`kbs.inference.engine._iterate`.

    Returns ``(centers, eigenvalues, eigenvectors, whitening, logdet, priors, u, maha, n_iter,
    converged, status)``; the memberships were computed from the returned parameters. With
    ``status`` 1 (a cluster died in update ``n_iter``), ``u`` are the memberships that update
    started from (their effective sizes say which clusters died).
    """
    K, n = u0.shape
    total = 0.0
    for j in range(n):
        total += w[j]
    u = u0.copy()
    s1u = np.empty_like(u)
    s2u = np.empty_like(u)
    ua = np.empty_like(u)
    maha = np.empty_like(u)
    z = np.empty_like(u)
    zmax = np.empty(n)
    tot = np.empty(n)
    tmp = np.empty(n)
    ibuf = np.empty(n, dtype=np.int64)
    it = 0
    converged = False
    centers, lam, vec, whit, logdet, priors, status = _gg_params(u, R, power, total, min_variance, max_condition,
                                                                  min_mass, tmp)
    while it < max_iter:
        it += 1
        if it > 1:
            centers, lam, vec, whit, logdet, priors, status = _gg_params(u, R, power, total, min_variance,
                                                                          max_condition, min_mass, tmp)
        if status:
            return centers, lam, vec, whit, logdet, priors, u, maha, it, False, 1
        _gg_memberships(XT, centers, whit, logdet, priors, m, s1u, maha, z, zmax, tot, ibuf)
        delta = _max_abs_diff(s1u, u)
        if delta < tol:
            return centers, lam, vec, whit, logdet, priors, s1u, maha, it, True, 0
        if not accelerate or it + 2 > max_iter:
            u, s1u = s1u, u
            continue
        it += 1
        centers, lam, vec, whit, logdet, priors, status = _gg_params(s1u, R, power, total, min_variance,
                                                                      max_condition, min_mass, tmp)
        if status:
            return centers, lam, vec, whit, logdet, priors, s1u, maha, it, False, 1
        _gg_memberships(XT, centers, whit, logdet, priors, m, s2u, maha, z, zmax, tot, ibuf)
        nr, nv = _squarem_norms(u, s1u, s2u, w)
        nv = math.sqrt(nv)
        alpha = -math.sqrt(nr) / nv if nv > 0 else -1.0
        if alpha >= -1.0:
            u, s2u = s2u, u
            continue
        _extrapolate(u, s1u, s2u, alpha, tot, ua)
        it += 1
        centers, lam, vec, whit, logdet, priors, status = _gg_params(ua, R, power, total, min_variance,
                                                                      max_condition, min_mass, tmp)
        if status:
            return centers, lam, vec, whit, logdet, priors, ua, maha, it, False, 1
        _gg_memberships(XT, centers, whit, logdet, priors, m, s2u, maha, z, zmax, tot, ibuf)
        delta = _max_abs_diff(s2u, ua)
        u, s2u = s2u, u
        if delta < tol:
            converged = True
            break
    return centers, lam, vec, whit, logdet, priors, u, maha, it, converged, 0


# -- voxel grids: distinct int64 keys by open addressing (O(n), no sort of the points) ---------
#
# The tables start small and double when half full, so that counting a few thousand distinct
# cells among 10^5 points stays in the cache.

_EMPTY = np.int64(-1)  # keys are non-negative
_START_SIZE = 1024
_START_SHIFT = 64 - 10  # 64 - log2(_START_SIZE); one less each time the table doubles
_PRESIZE = 1 << 17  # a table starts large enough for this many distinct keys (4 MB), then grows


@njit(nogil=True)
def _slot(key, shift):
    """Fibonacci hashing: the top ``64 - shift`` bits of the key times 2^64 / golden ratio."""
    return np.int64((np.uint64(key) * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(shift))


@njit(nogil=True)
def _new_table(expect):
    """An empty table (keys, groups) of at least twice ``expect`` slots (at least the start size),
    and its shift."""
    size = _START_SIZE
    shift = _START_SHIFT
    while size < 2 * expect:
        size *= 2
        shift -= 1
    return np.full(size, _EMPTY), np.empty(size, dtype=np.int64), shift


@njit(nogil=True)
def _grow(table, group, shift):
    """The table twice as large (its shift is ``shift - 1``), every key moved."""
    size = table.shape[0] * 2
    mask = size - 1
    t2 = np.full(size, _EMPTY)
    g2 = np.empty(size, dtype=np.int64)
    for i in range(table.shape[0]):
        key = table[i]
        if key != _EMPTY:
            s = _slot(key, shift - 1)
            while t2[s] != _EMPTY:
                s = (s + 1) & mask
            t2[s] = key
            g2[s] = group[i]
    return t2, g2


@njit(nogil=True)
def _insert(table, group, key, m, shift):
    """Find or insert ``key``; returns its group (``m`` when new) and whether it was new."""
    mask = table.shape[0] - 1
    s = _slot(key, shift)
    while True:
        t = table[s]
        if t == key:
            return group[s], False
        if t == _EMPTY:
            table[s] = key
            group[s] = m
            return m, True
        s = (s + 1) & mask


@njit(nogil=True)
def _first_appearance(keys, want_inverse, expect):
    """The distinct keys (non-negative int64) in order of first appearance, by a hash table, and
    (when ``want_inverse``, else an empty array) each key's group: its distinct key's position.
    The table starts sized for ``expect`` distinct keys (a negative ``expect``: as many as keys,
    up to ``_PRESIZE``) and doubles when half full: the answer does not depend on it."""
    n = keys.shape[0]
    # most keys are distinct in the fine grids: sized for them, the table seldom grows
    table, group, shift = _new_table(min(n, _PRESIZE) if expect < 0 else min(n, expect))
    first_keys = np.empty(n, dtype=np.int64)
    inv = np.empty(n if want_inverse else 0, dtype=np.int64)
    m = 0
    for j in range(n):
        g, new = _insert(table, group, keys[j], m, shift)
        if want_inverse:
            inv[j] = g
        if new:
            first_keys[m] = keys[j]
            m += 1
            if 2 * m > table.shape[0]:
                table, group = _grow(table, group, shift)
                shift -= 1
    return first_keys[:m].copy(), inv


@njit(cache=True, nogil=True)
def unique_inverse(keys, expect=-1):
    """``(distinct keys sorted, inverse)`` as ``np.unique(keys, return_inverse=True)`` for
    non-negative int64 keys: a hash table gives each key a group in order of first appearance,
    then only the distinct keys are sorted. ``expect``: about how many distinct keys there are
    (-1: as many as keys); a table sized for the few voxels of a fitting set stays in cache."""
    distinct, inv = _first_appearance(keys, True, expect)
    m = distinct.shape[0]
    order = np.argsort(distinct)
    rank = np.empty(m, dtype=np.int64)
    for i in range(m):
        rank[order[i]] = i
    for j in range(inv.shape[0]):
        inv[j] = rank[inv[j]]
    return distinct[order], inv


@njit(cache=True, nogil=True)
def distinct_keys(keys):
    """The distinct keys (non-negative int64) in order of first appearance, as
    :func:`_first_appearance` gives them, by a hash table that writes no groups (2.9 -> 2.0 ms on
    the 86,402 distinct fine cells of SemanticKITTI 000001; 5.1 -> 2.2 ms with each key three
    times), started and grown as that one is; no sort."""
    n = keys.shape[0]
    table, group, shift = _new_table(min(n, _PRESIZE))
    mask = table.shape[0] - 1
    out = np.empty(n, dtype=np.int64)
    m = 0
    for j in range(n):
        key = keys[j]
        s = _slot(key, shift)
        while True:
            t = table[s]
            if t == key:
                break
            if t == _EMPTY:
                table[s] = key
                out[m] = key
                m += 1
                if 2 * m > table.shape[0]:
                    table, group = _grow(table, group, shift)
                    shift -= 1
                    mask = table.shape[0] - 1
                break
            s = (s + 1) & mask
    return out[:m].copy()


@njit(cache=True, nogil=True)
def cell_keys(X, origin, size):
    """The 20-bit-per-axis int64 key of each point's cell ``floor((x - origin) / size)`` (the
    cells non-negative and below 2^20 on each axis), as :func:`kbs.inference.voxel._keys` of
    :func:`kbs.inference.voxel._cells`, without their (n, D) temporaries."""
    n, D = X.shape
    keys = np.empty(n, dtype=np.int64)
    for j in range(n):
        key = np.int64(0)
        for a in range(D):
            key = (key << 20) | np.int64(math.floor((X[j, a] - origin[a]) / size))
        keys[j] = key
    return keys


@njit(cache=True, nogil=True)
def voxel_sums(X, origin, size, inv, w, M):
    """The per-voxel sums of :func:`kbs.inference.voxel.voxel_reduce` in one pass: weights
    ``sum w``, first moments ``sum w l`` and second moments ``sum (w l_a) l_b`` of the coordinates
    ``l`` local to each point's voxel corner ``origin + floor((x - origin) / size) size``, and each
    voxel's first member. The same operations in the same order as numpy's ``bincount``
    (sequential, in point order): identical sums."""
    n, D = X.shape
    weights = np.zeros(M)
    s1 = np.zeros((M, D))
    s2 = np.zeros((M, D, D))
    first = np.full(M, n, dtype=np.int64)
    la = np.empty(D)
    for j in range(n):
        g = inv[j]
        wj = w[j]
        first[g] = min(first[g], j)
        for a in range(D):
            c = np.int64(math.floor((X[j, a] - origin[a]) / size))
            la[a] = X[j, a] - (origin[a] + c * size)
        weights[g] += wj
        for a in range(D):
            wa = wj * la[a]
            s1[g, a] += wa
            for b in range(a, D):
                s2[g, a, b] += wa * la[b]
    return weights, s1, s2, first


@njit(cache=True, nogil=True)
def voxel_finish(X, origin, size, weights, s1, s2, first):
    """The end of :func:`kbs.inference.voxel.voxel_reduce` from :func:`voxel_sums`'s sums, for
    the voxels of positive weight: centroid ``corner + s1 / w`` (corner ``origin + c size``, ``c``
    the first member's cell) and scatter ``s2_ab - (w m_a) m_b`` (``m = s1 / w``). The same
    operations in the same order as numpy's there, each rounded alone: identical arrays."""
    M, D = s1.shape
    keep = 0
    for g in range(M):
        if weights[g] > 0:
            keep += 1
    cent = np.empty((keep, D))
    wout = np.empty(keep)
    scat = np.empty((keep, D, D))
    mean = np.empty(D)
    i = 0
    for g in range(M):
        wg = weights[g]
        if not wg > 0:
            continue
        wout[i] = wg
        j = first[g]
        for a in range(D):
            mean[a] = s1[g, a] / wg
            c = np.int64(math.floor((X[j, a] - origin[a]) / size))
            cent[i, a] = (origin[a] + c * size) + mean[a]
        for a in range(D):
            for b in range(a, D):
                v = s2[g, a, b] - wg * mean[a] * mean[b]
                scat[i, a, b] = v
                scat[i, b, a] = v
        i += 1
    return cent, wout, scat


@njit(cache=True, nogil=True)
def count_coarse_keys(keys, D, factor):
    """Number of distinct rows of ``floor(cells / factor)``, the cells (non-negative) those of the
    distinct 20-bit-per-axis ``keys`` of :mod:`kbs.inference.voxel` (D <= 3 axes), read from the
    keys themselves: no decoded (n, D) array. Each axis's ``floor(c / factor)`` is computed once
    per cell index into a table (the indices run to the fine grid's 4,096 or so), and the set of
    coarse keys is a hash table of keys alone, sized once for the most there can be (n, or the
    coarse grid's size when smaller): it never grows, and stays in cache for the coarse grids.
    The 21 searches of a SemanticKITTI 000001 frame: 178 -> 91 ms (docs/PERFORMANCE.md, session 11)."""
    n = keys.shape[0]
    mask = np.int64((1 << 20) - 1)
    top = np.zeros(3, dtype=np.int64)
    for j in range(n):
        key = keys[j]
        for d in range(D):
            c = (key >> np.int64(20 * (D - 1 - d))) & mask
            if c > top[d]:
                top[d] = c
    width = max(top[0], max(top[1], top[2])) + 1
    coarse = np.empty((D, width), dtype=np.int64)
    for d in range(D):
        for c in range(top[d] + 1):
            coarse[d, c] = np.int64(math.floor(np.int64(c) / factor))
    # at most n coarse cells, and at most the coarse grid's own size: a table sized for that
    # bound never grows, and stays small (in cache) for the coarse grids of a search
    bound = np.int64(1)
    for d in range(D):
        bound *= coarse[d, top[d]] + 1
        if bound >= n:
            break
    table, _group, shift = _new_table(max(1, min(n, bound)))
    tmask = table.shape[0] - 1
    m = 0
    for j in range(n):
        fkey = keys[j]
        key = np.int64(0)
        for d in range(D):
            key = (key << 20) | coarse[d, (fkey >> np.int64(20 * (D - 1 - d))) & mask]
        s = _slot(key, shift)
        while True:
            t = table[s]
            if t == key:
                break
            if t == _EMPTY:
                table[s] = key
                m += 1
                if 2 * m > table.shape[0]:
                    table, _group = _grow(table, _group, shift)
                    shift -= 1
                    tmask = table.shape[0] - 1
                break
            s = (s + 1) & tmask
    return m


@njit(cache=True, nogil=True)
def turn_to_frame(X, origin, c, s):
    """:meth:`kbs.inference.voxel.HorizontalFrame.to_frame` in one pass: ``y = x - origin``, then
    ``(y0 c + y1 s, y1 c - y0 s)`` in the first two columns. The same operations, each rounded as
    numpy rounds them (no fused multiply-adds): identical coordinates, no temporaries."""
    n, D = X.shape
    Y = np.empty((n, D))
    for j in range(n):
        for a in range(D):
            Y[j, a] = X[j, a] - origin[a]
        if D >= 2:
            y0 = Y[j, 0]
            y1 = Y[j, 1]
            Y[j, 0] = y0 * c + y1 * s
            Y[j, 1] = y1 * c - y0 * s
    return Y


@njit(nogil=True)
def _lex_less(X, a, b, D):
    for d in range(D):
        if X[a, d] < X[b, d]:
            return True
        if X[a, d] > X[b, d]:
            return False
    return False


@njit(cache=True, nogil=True)
def lex_order(X):
    """``np.lexsort(X.T[::-1])`` for finite ``X`` (n, D): the rows in order of the first column,
    then the second, ..., ties in input order. A stable order is unique, so this bottom-up merge
    sort (a right row goes first only when strictly less) gives numpy's permutation exactly,
    without its D passes of indirect sorts (runs of 16 by insertion first)."""
    n, D = X.shape
    src = np.arange(n)
    dst = np.empty(n, dtype=np.int64)
    run = 16
    for lo in range(0, n, run):  # stable insertion sort of each run
        hi = min(lo + run, n)
        for i in range(lo + 1, hi):
            v = src[i]
            j = i - 1
            while j >= lo and _lex_less(X, v, src[j], D):
                src[j + 1] = src[j]
                j -= 1
            src[j + 1] = v
    width = run
    while width < n:
        for lo in range(0, n, 2 * width):
            mid = min(lo + width, n)
            hi = min(lo + 2 * width, n)
            i = lo
            j = mid
            k = lo
            while i < mid and j < hi:
                if _lex_less(X, src[j], src[i], D):
                    dst[k] = src[j]
                    j += 1
                else:
                    dst[k] = src[i]
                    i += 1
                k += 1
            while i < mid:
                dst[k] = src[i]
                i += 1
                k += 1
            while j < hi:
                dst[k] = src[j]
                j += 1
                k += 1
        src, dst = dst, src
        width *= 2
    return src


@njit(cache=True, nogil=True)
def bounds(X):
    """Per-column minimum and maximum of ``X`` (n, D) in one pass."""
    n, D = X.shape
    lo = X[0].copy()
    hi = X[0].copy()
    for j in range(1, n):
        for d in range(D):
            v = X[j, d]
            if v < lo[d]:
                lo[d] = v
            if v > hi[d]:
                hi[d] = v
    return lo, hi


# -- criteria and cluster geometry ----------------------------------------------------------


@njit(cache=True, nogil=True, fastmath=_FAST)
def central_sums(u, w, maha):
    """``S_i = sum_j w_j u_ij [maha_ij < 1]`` (K,): the weighted memberships of each cluster's
    central members (Gath-Geva's validity criteria)."""
    K, n = u.shape
    out = np.zeros(K)
    for k in range(K):
        uk = u[k]
        mk = maha[k]
        s = 0.0
        for j in range(n):
            if mk[j] < 1.0:
                s += uk[j] * w[j]
        out[k] = s
    return out


@njit(cache=True, nogil=True)
def geometry3(X, u, w, power):
    """Fuzzy centre (3,) (weights ``w u^power``), fuzzy covariance (3, 3) (weights ``w u``, two
    passes), its eigenvalues (ascending) and eigenvectors, and the effective size, of points
    ``X`` (n, 3). An empty ``u`` or ``w`` stands for all ones. When the effective size or the
    centre's total weight is not positive, the size alone is meaningful (the rest is zeros)."""
    n = X.shape[0]
    has_u = u.shape[0] > 0
    has_w = w.shape[0] > 0
    c0 = c1 = c2 = 0.0
    den = 0.0
    mass = 0.0
    for j in range(n):
        uj = u[j] if has_u else 1.0
        wj = w[j] if has_w else 1.0
        p = (uj * uj if power == 2.0 else uj ** power) * wj
        den += p
        mass += uj * wj
        c0 += p * X[j, 0]
        c1 += p * X[j, 1]
        c2 += p * X[j, 2]
    center = np.zeros(3)
    cov = np.zeros((3, 3))
    if not (den > 0.0 and mass > 0.0):
        return center, cov, np.zeros(3), np.eye(3), mass
    c0 /= den
    c1 /= den
    c2 /= den
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    for j in range(n):
        uw = (u[j] if has_u else 1.0) * (w[j] if has_w else 1.0)
        d0 = X[j, 0] - c0
        d1 = X[j, 1] - c1
        d2 = X[j, 2] - c2
        s00 += uw * d0 * d0
        s01 += uw * d0 * d1
        s02 += uw * d0 * d2
        s11 += uw * d1 * d1
        s12 += uw * d1 * d2
        s22 += uw * d2 * d2
    cov[0, 0] = s00 / mass
    cov[0, 1] = cov[1, 0] = s01 / mass
    cov[0, 2] = cov[2, 0] = s02 / mass
    cov[1, 1] = s11 / mass
    cov[1, 2] = cov[2, 1] = s12 / mass
    cov[2, 2] = s22 / mass
    lam, vec = _eigh3(cov)
    center[0] = c0
    center[1] = c1
    center[2] = c2
    return center, cov, lam, vec, mass


@njit(cache=True, nogil=True)
def covariance_eigen(s, mass, ok):
    """From per-cluster sums ``s`` (k, 6) of ``u d_a d_b`` (the order 00 01 02 11 12 22) and masses
    (k,): the covariances (k, 3, 3), their eigenvalues (clipped at 0) and eigenvectors, as
    :func:`geometry3` makes them from the same sums (zeros and the identity for a cluster that is
    not ``ok``). The streamed tiles' descriptors (:mod:`kbs.tiles.streamed`), summed over files in
    chunks, end here, so that they are an in-memory run's to the last bit."""
    k = s.shape[0]
    covs = np.zeros((k, 3, 3))
    lams = np.zeros((k, 3))
    vecs = np.zeros((k, 3, 3))
    for i in range(k):
        if not ok[i]:
            vecs[i] = np.eye(3)
            continue
        m = mass[i]
        cov = np.zeros((3, 3))
        cov[0, 0] = s[i, 0] / m
        cov[0, 1] = cov[1, 0] = s[i, 1] / m
        cov[0, 2] = cov[2, 0] = s[i, 2] / m
        cov[1, 1] = s[i, 3] / m
        cov[1, 2] = cov[2, 1] = s[i, 4] / m
        cov[2, 2] = s[i, 5] / m
        lam, vec = _eigh3(cov)
        covs[i] = cov
        lams[i] = np.maximum(lam, 0.0)
        vecs[i] = vec
    return covs, lams, vecs


@njit(cache=True, nogil=True)
def local_medians(d, idx, heights, owners, own, neighbours, quantile):
    """For each row of a k-nearest query (``d``, ``idx`` (q, k), nearest first, ``inf`` / ``m``
    where fewer were found): the median height (``quantile`` 0.5; another: that quantile, see
    :func:`sorted_quantile`) of the first ``neighbours`` found points whose owner is not ``own``
    (-1: any), NaN when none, and the position of the first of them (-1)."""
    q, k = d.shape
    ground = np.full(q, np.nan)
    nearest = np.full(q, -1, dtype=np.int64)
    buf = np.empty(max(neighbours, 1))
    for r in range(q):
        m = 0
        for c in range(k):
            if m >= neighbours:
                break
            if not np.isfinite(d[r, c]):
                continue
            i = idx[r, c]
            if own >= 0 and owners[i] == own:
                continue
            if m == 0:
                nearest[r] = i
            buf[m] = heights[i]
            m += 1
        if m:
            s = np.sort(buf[:m])
            ground[r] = sorted_quantile(s, m, quantile)
    return ground, nearest


@njit(cache=True, nogil=True)
def sorted_quantile(s, m, quantile):
    """The ``quantile`` of the first ``m`` (> 0) values of ``s``, sorted: at 0.5 the median
    (``0.5 (a + b)`` of the middle two, as before quantiles were asked), otherwise the linear
    interpolation between the values at ranks ``floor((m - 1) q)`` and the next, ``a + (b - a) t``,
    kept within ``[a, b]`` (so that the value lies between the heights it came from in floating
    point too, as :meth:`LocalGround.height_bounds` assumes)."""
    if quantile == 0.5:
        return 0.5 * (s[(m - 1) // 2] + s[m // 2])
    pos = (m - 1) * quantile
    lo = int(np.floor(pos))
    hi = min(lo + 1, m - 1)
    a = s[lo]
    b = s[hi]
    v = a + (b - a) * (pos - lo)
    return min(max(v, a), b)


# -- connexity (CAh) on the projected points -----------------------------------------------------
#
# The graph of :mod:`kbs.geometry.connexity` links distinct positions at most ``r`` apart. With
# square cells of side ``r``, two linked points lie in the same or 8-adjacent cells, so each pair
# is met once by visiting, for every cell, itself and four of its neighbours. Distances are
# compared as scipy's k-d tree compares them (``dx*dx + dy*dy <= r*r`` for the degrees and the
# components, ``sqrt(dx*dx + dy*dy) <= r`` for the dilation's nearest-point test), so the results
# are those of the k-d tree version, which remains for clouds whose extent is absurd for ``r``.

_HALF = ((0, 0), (1, -1), (1, 0), (1, 1), (0, 1))


@njit(nogil=True)
def _grid_extent(U, side):
    """The lower corner ``(lo0, lo1)`` of points (m > 0, 2) and their extent in cells of ``side``
    along each axis, ``(fx, fy)`` (not rounded)."""
    lo0 = hi0 = U[0, 0]
    lo1 = hi1 = U[0, 1]
    for i in range(1, U.shape[0]):
        lo0 = min(lo0, U[i, 0])
        hi0 = max(hi0, U[i, 0])
        lo1 = min(lo1, U[i, 1])
        hi1 = max(hi1, U[i, 1])
    return lo0, lo1, (hi0 - lo0) / side, (hi1 - lo1) / side


@njit(nogil=True)
def _cell_grid(U, side, max_cells):
    """Points (m, 2) in square cells of ``side``: ``(ny, start, order, ix, iy)`` with the points
    of cell ``c = ix * ny + iy`` at ``order[start[c]:start[c + 1]]``; ``ny = -1`` when the grid
    would have more than ``max_cells`` cells."""
    m = U.shape[0]
    lo0, lo1, fx, fy = _grid_extent(U, side)
    empty = np.zeros(0, dtype=np.int64)
    if not (fx < 1e9 and fy < 1e9) or (fx + 1.0) * (fy + 1.0) > max_cells:
        return -1, empty, empty, empty, empty
    nx = int(fx) + 1
    ny = int(fy) + 1
    ix = np.empty(m, dtype=np.int64)
    iy = np.empty(m, dtype=np.int64)
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for i in range(m):
        a = min(int(math.floor((U[i, 0] - lo0) / side)), nx - 1)
        b = min(int(math.floor((U[i, 1] - lo1) / side)), ny - 1)
        ix[i] = a
        iy[i] = b
        start[a * ny + b + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    order = np.empty(m, dtype=np.int64)
    for i in range(m):
        c = ix[i] * ny + iy[i]
        order[fill[c]] = i
        fill[c] += 1
    return ny, start, order, ix, iy


_NINE = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 0), (0, 1), (1, -1), (1, 0), (1, 1))
#: the positions in :data:`_NINE` of the offsets of :data:`_HALF`
_HALF_IN_NINE = (4, 6, 7, 8, 5)


@njit(nogil=True)
def _occupied_cells(U, side, max_cells):
    """Points (m, 2) in square cells of ``side``, the occupied cells only: ``(ok, start, order,
    cell, nbr)`` with the points of occupied cell ``c`` at ``order[start[c]:start[c + 1]]``, ``cell``
    (m,) each point's cell and ``nbr`` (cells, 9) the cell at each offset of :data:`_NINE` (-1:
    none occupied). The cells are those of :func:`_cell_grid` (cell ``(a, b)``: ``floor((u -
    lo) / side)``); a grid of more than ``max_cells`` cells is not laid out but its occupied cells
    found by sorting, so that an extent absurd for ``side`` costs no more than a compact one.
    ``ok`` False only when a grid axis would have 1e9 cells or more."""
    m = U.shape[0]
    empty = np.zeros(0, dtype=np.int64)
    ny, start, order, ix, iy = _cell_grid(U, side, max_cells)
    if ny >= 0:  # the dense grid: its non-empty cells
        nx = (start.shape[0] - 1) // ny
        idof = np.full(nx * ny, -1, dtype=np.int64)
        k = 0
        for c in range(nx * ny):
            if start[c + 1] > start[c]:
                idof[c] = k
                k += 1
        cstart = np.empty(k + 1, dtype=np.int64)
        nbr = np.full((k, 9), -1, dtype=np.int64)
        cstart[k] = m
        for c in range(nx * ny):
            o = idof[c]
            if o < 0:
                continue
            cstart[o] = start[c]
            a = c // ny
            b = c - a * ny
            for t in range(9):
                a2 = a + _NINE[t][0]
                b2 = b + _NINE[t][1]
                if 0 <= a2 < nx and 0 <= b2 < ny:
                    nbr[o, t] = idof[a2 * ny + b2]
        cell = np.empty(m, dtype=np.int64)
        for i in range(m):
            cell[i] = idof[ix[i] * ny + iy[i]]
        return True, cstart, order, cell, nbr
    lo0, lo1, fx, fy = _grid_extent(U, side)
    if not (fx < 1e9 and fy < 1e9):
        return False, empty, empty, empty, np.zeros((0, 9), dtype=np.int64)
    nx = int(fx) + 1
    ny = int(fy) + 1
    key = np.empty(m, dtype=np.int64)
    for i in range(m):
        a = min(int(math.floor((U[i, 0] - lo0) / side)), nx - 1)
        b = min(int(math.floor((U[i, 1] - lo1) / side)), ny - 1)
        key[i] = a * ny + b
    order = np.argsort(key, kind="mergesort")
    cell = np.empty(m, dtype=np.int64)
    keys = np.empty(m, dtype=np.int64)
    cstart = np.empty(m + 1, dtype=np.int64)
    k = -1
    for p in range(m):
        i = order[p]
        if k < 0 or key[i] != keys[k]:
            k += 1
            keys[k] = key[i]
            cstart[k] = p
        cell[i] = k
    k += 1
    cstart[k] = m
    keys = keys[:k]
    nbr = np.full((k, 9), -1, dtype=np.int64)
    for o in range(k):
        a = keys[o] // ny
        b = keys[o] - a * ny
        for t in range(9):
            a2 = a + _NINE[t][0]
            b2 = b + _NINE[t][1]
            if 0 <= a2 < nx and 0 <= b2 < ny:
                want = a2 * ny + b2
                j = np.searchsorted(keys, want)
                if j < k and keys[j] == want:
                    nbr[o, t] = j
    return True, cstart[:k + 1].copy(), order, cell, nbr


@njit(cache=True, nogil=True)
def connexity_degrees(U, mult, r, max_cells):
    """Degree (m,) of each distinct position (``mult`` input points at each): the number of other
    input points within ``r``; an empty array when a grid axis would have 1e9 cells or more (see
    :func:`_occupied_cells`: beyond ``max_cells`` cells only the occupied ones are kept)."""
    ok, start, order, cell, nbr = _occupied_cells(U, r, max_cells)
    if not ok:
        return np.zeros(0, dtype=np.int64)
    r2 = r * r
    deg = mult - 1
    for c in range(start.shape[0] - 1):
        for t in range(5):
            c2 = nbr[c, _HALF_IN_NINE[t]]
            if c2 < 0:
                continue
            for p in range(start[c], start[c + 1]):
                i = order[p]
                q0 = start[c2] if t else p + 1
                for q in range(q0, start[c2 + 1]):
                    j = order[q]
                    dx = U[i, 0] - U[j, 0]
                    dy = U[i, 1] - U[j, 1]
                    if dx * dx + dy * dy <= r2:
                        deg[i] += mult[j]
                        deg[j] += mult[i]
    return deg


@njit(nogil=True)
def _root(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(nogil=True)
def _union(parent, i, j):
    """Join the sets of ``i`` and ``j``; the smaller root stays the root."""
    ri = _root(parent, i)
    rj = _root(parent, j)
    if ri < rj:
        parent[rj] = ri
    elif rj < ri:
        parent[ri] = rj


@njit(nogil=True)
def _first_appearance_labels(parent, keep):
    """Each kept element's set, numbered in order of first appearance (-1 elsewhere), and how
    many sets."""
    m = parent.shape[0]
    label = np.full(m, -1, dtype=np.int64)
    comp = np.full(m, -1, dtype=np.int64)
    n = 0
    for i in range(m):
        if not keep[i]:
            continue
        ri = _root(parent, i)
        if label[ri] < 0:
            label[ri] = n
            n += 1
        comp[i] = label[ri]
    return comp, n


@njit(cache=True, nogil=True)
def connexity_components(U, kept, r, dilate, max_cells):
    """The dilation of ``kept`` (m,) bool (when ``dilate``: a removed position comes back when a
    kept one lies within ``r``) and the connected components of the graph ``|p - q| <= r`` on the
    positions kept after it. Returns ``(kept, comp, n_comp)``, ``comp`` (m,) the component of
    each kept position (numbered in order of first appearance) and -1 elsewhere; ``n_comp`` -1
    when a grid axis would have 1e9 cells or more (see :func:`_occupied_cells`)."""
    m = U.shape[0]
    ok, start, order, cell, nbr = _occupied_cells(U, r, max_cells)
    if not ok:
        return kept, np.full(m, -1, dtype=np.int64), -1
    r2 = r * r
    out = kept.copy()
    if dilate:
        for i in range(m):
            if kept[i]:
                continue
            found = False
            for t in range(9):
                c = nbr[cell[i], t]
                if c < 0:
                    continue
                for q in range(start[c], start[c + 1]):
                    j = order[q]
                    if kept[j]:
                        dx = U[i, 0] - U[j, 0]
                        dy = U[i, 1] - U[j, 1]
                        if math.sqrt(dx * dx + dy * dy) <= r:
                            found = True
                            break
                if found:
                    break
            out[i] = found
    parent = np.arange(m)
    for c in range(start.shape[0] - 1):
        for t in range(5):
            c2 = nbr[c, _HALF_IN_NINE[t]]
            if c2 < 0:
                continue
            for p in range(start[c], start[c + 1]):
                i = order[p]
                if not out[i]:
                    continue
                q0 = start[c2] if t else p + 1
                for q in range(q0, start[c2 + 1]):
                    j = order[q]
                    if not out[j]:
                        continue
                    dx = U[i, 0] - U[j, 0]
                    dy = U[i, 1] - U[j, 1]
                    if dx * dx + dy * dy <= r2:
                        _union(parent, i, j)
    comp, n_comp = _first_appearance_labels(parent, out)
    return out, comp, n_comp


@njit(cache=True, nogil=True)
def graph_labels(n, i, j):
    """Connected components of the undirected graph on ``n`` nodes with the edges ``(i[e], j[e])``:
    ``(n_components, labels)``, the components numbered in order of their lowest node, as scipy's
    ``connected_components(..., directed=False)`` numbers them."""
    parent = np.arange(n)
    for e in range(i.shape[0]):
        _union(parent, i[e], j[e])
    comp, n_comp = _first_appearance_labels(parent, np.ones(n, dtype=np.bool_))
    return n_comp, comp


# -- robust planes ----------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def plane_inlier_counts(S, a, nrm, dist):
    """For each hypothesis ``h`` (a plane through ``a[h]`` with unit normal ``nrm[h]``), the
    number of points of ``S`` (n, 3) with ``|(s - a[h]) . nrm[h]| <= dist``: the operations of
    ``np.einsum("kij,kj->ki", S - a, nrm)`` in the same order (no fused multiply-add), without
    its (k, n, 3) temporary."""
    k = a.shape[0]
    n = S.shape[0]
    counts = np.zeros(k, dtype=np.int64)
    for h in range(k):
        a0, a1, a2 = a[h, 0], a[h, 1], a[h, 2]
        n0, n1, n2 = nrm[h, 0], nrm[h, 1], nrm[h, 2]
        c = 0
        for j in range(n):
            v = (S[j, 0] - a0) * n0
            v = v + (S[j, 1] - a1) * n1
            v = v + (S[j, 2] - a2) * n2
            if abs(v) <= dist:
                c += 1
        counts[h] = c
    return counts


# -- the slope surface (height_above_slope_surface) -------------------------------------------


@njit(cache=True, nogil=True)
def surface_grid(T, side, max_cells):
    """The points ``T`` (m, 2) in square cells of ``side`` (see :func:`_cell_grid`): ``(ny,
    start, order, lo)`` with ``lo`` (2,) the grid's lower corner; ``ny = -1`` when the grid would
    have more than ``max_cells`` cells."""
    ny, start, order, _ix, _iy = _cell_grid(T, side, max_cells)
    lo = np.empty(2)
    lo[0] = T[0, 0]
    lo[1] = T[0, 1]
    for i in range(1, T.shape[0]):
        lo[0] = min(lo[0], T[i, 0])
        lo[1] = min(lo[1], T[i, 1])
    return ny, start, order, lo


@njit(nogil=True)
def _block3(x, y, lo, side, nx, ny):
    """The 3 x 3 block of cells (of ``side``, ``nx`` x ``ny`` from ``lo``) around the point ``(x,
    y)``'s cell, clipped to the grid: ``(inside, a0, a1, b0, b1)``, ``inside`` False when no cell of
    the block is in the grid (the point lies a cell or more outside it)."""
    fa = math.floor((x - lo[0]) / side)
    fb = math.floor((y - lo[1]) / side)
    if not (fa >= -1.0 and fa <= nx and fb >= -1.0 and fb <= ny):
        return False, 0, -1, 0, -1
    return True, max(int(fa) - 1, 0), min(int(fa) + 1, nx - 1), max(int(fb) - 1, 0), min(int(fb) + 1, ny - 1)


@njit(cache=True, nogil=True)
def slope_lowest(Q, T, heights, owners, own, ny, start, order, lo, side, rise, r2):
    """For each query ``Q[k]`` (q, 2): ``min_j heights[j] + rise * sqrt(d2)`` over the points
    ``T[j]`` with ``d2 = dx*dx + dy*dy <= r2`` (as scipy's ``query_ball_point`` compares them)
    whose owner is not ``own`` (-1: any); +inf where none. The grid (``surface_grid`` of side at
    least ``sqrt(r2)``) holds every such point in the 3 x 3 block of cells around the query's cell.
    The value of each point is computed as ``heights[j] + rise * np.sqrt(((T[j] - Q[k]) **
    2).sum())`` computes it (no fused multiply-add), so the minimum is numpy's."""
    q = Q.shape[0]
    nx = (start.shape[0] - 1) // ny
    out = np.full(q, np.inf)
    for k in range(q):
        inside, a0, a1, b0, b1 = _block3(Q[k, 0], Q[k, 1], lo, side, nx, ny)
        if not inside:
            continue
        best = np.inf
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                c = a * ny + b
                for p in range(start[c], start[c + 1]):
                    j = order[p]
                    if own >= 0 and owners[j] == own:
                        continue
                    dx = T[j, 0] - Q[k, 0]
                    dy = T[j, 1] - Q[k, 1]
                    d2 = dx * dx + dy * dy
                    if d2 <= r2:
                        v = heights[j] + rise * math.sqrt(d2)
                        if v < best:
                            best = v
        out[k] = best
    return out


@njit(cache=True, nogil=True)
def ball_thickness(Q, hq, S, ny, start, lo, side, reach, r2, min_points):
    """For each query ``Q[k]`` (q, 2) at height ``hq[k]``: the thickness of the surface points
    ``S[p]`` (m, 3: plane coordinates and height, in the order of their cells: those of cell ``c``
    at ``start[c]:start[c + 1]``, cells ``c = a * ny + b`` of ``side`` from ``lo``, as
    :func:`surface_grid` lays them out) with ``d2 = dx*dx + dy*dy <= r2`` (as scipy's
    ``query_ball_point`` compares them), the square root of the smallest eigenvalue of the
    covariance of their positions (plane coordinates and height, each taken from the query's);
    NaN where fewer than ``min_points`` lie there. ``reach * side`` must be at least
    ``sqrt(r2)``: the cells within ``reach`` of the query's hold every such point, and of them
    only those whose rectangle comes within the radius are read (with cells a third of the radius
    wide, about half the points of a 3 x 3 block of cells as wide as the radius; the points of a
    cell lie in one run of ``S``: no gather). Non-finite sums raise ``LinAlgError``, as
    :func:`_eigh3` does."""
    q = Q.shape[0]
    nx = (start.shape[0] - 1) // ny
    out = np.full(q, np.nan)
    a = np.empty((3, 3))
    # a cell is skipped when its rectangle lies beyond the radius by more than the rounding of
    # the cell's bounds (a point's cell is floor((x - lo) / side), computed in floating point)
    slack = r2 + 1e-9 * (r2 + side * side)
    for k in range(q):
        x = Q[k, 0]
        y = Q[k, 1]
        fa = math.floor((x - lo[0]) / side)
        fb = math.floor((y - lo[1]) / side)
        if not (fa >= -reach and fa < nx + reach and fb >= -reach and fb < ny + reach):
            continue  # no cell within reach (NaN coordinates too)
        a0 = max(int(fa) - reach, 0)
        a1 = min(int(fa) + reach, nx - 1)
        b0 = max(int(fb) - reach, 0)
        b1 = min(int(fb) + reach, ny - 1)
        n = 0
        s0 = s1 = s2 = 0.0
        s00 = s01 = s02 = s11 = s12 = s22 = 0.0
        for ca in range(a0, a1 + 1):
            x0 = lo[0] + ca * side
            ex = x0 - x if x < x0 else (x - x0 - side if x > x0 + side else 0.0)
            if ex * ex > slack:
                continue
            for cb in range(b0, b1 + 1):
                y0 = lo[1] + cb * side
                ey = y0 - y if y < y0 else (y - y0 - side if y > y0 + side else 0.0)
                if ex * ex + ey * ey > slack:
                    continue
                c = ca * ny + cb
                for p in range(start[c], start[c + 1]):
                    dx = S[p, 0] - x
                    dy = S[p, 1] - y
                    if dx * dx + dy * dy <= r2:
                        dz = S[p, 2] - hq[k]
                        n += 1
                        s0 += dx
                        s1 += dy
                        s2 += dz
                        s00 += dx * dx
                        s01 += dx * dy
                        s02 += dx * dz
                        s11 += dy * dy
                        s12 += dy * dz
                        s22 += dz * dz
        if n < min_points:
            continue
        m0 = s0 / n
        m1 = s1 / n
        m2 = s2 / n
        a[0, 0] = s00 / n - m0 * m0
        a[1, 0] = a[0, 1] = s01 / n - m0 * m1
        a[2, 0] = a[0, 2] = s02 / n - m0 * m2
        a[1, 1] = s11 / n - m1 * m1
        a[2, 1] = a[1, 2] = s12 / n - m1 * m2
        a[2, 2] = s22 / n - m2 * m2
        for i in range(3):
            for j in range(i + 1):
                if not np.isfinite(a[i, j]):
                    raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
        _jacobi(a, a, False)  # the eigenvalues only (the second argument is not read)
        out[k] = math.sqrt(max(min(a[0, 0], min(a[1, 1], a[2, 2])), 0.0))
    return out


@njit(cache=True, nogil=True)
def slope_cells(T, heights, side, max_cells):
    """The points ``T`` (m, 2) in square cells of ``side`` for :func:`slope_lowest_pruned`:
    ``(ny, start, order, lo, hmin, box)`` as :func:`surface_grid`, with per cell the lowest of its
    points' ``heights`` (-inf when one is NaN) and its points' bounding box ``box`` (cells, 4):
    ``x0, x1, y0, y1`` (empty cells: +inf, -inf); ``ny = -1`` when the grid would have more than
    ``max_cells`` cells."""
    ny, start, order, lo = surface_grid(T, side, max_cells)
    if ny < 0:
        return ny, start, order, lo, np.zeros(0), np.zeros((0, 4))
    n = start.shape[0] - 1
    hmin = np.full(n, np.inf)
    box = np.empty((n, 4))
    for c in range(n):
        box[c, 0] = np.inf
        box[c, 1] = -np.inf
        box[c, 2] = np.inf
        box[c, 3] = -np.inf
        for p in range(start[c], start[c + 1]):
            j = order[p]
            h = heights[j]
            if math.isnan(h):
                hmin[c] = -np.inf
            elif h < hmin[c]:
                hmin[c] = h
            box[c, 0] = min(box[c, 0], T[j, 0])
            box[c, 1] = max(box[c, 1], T[j, 0])
            box[c, 2] = min(box[c, 2], T[j, 1])
            box[c, 3] = max(box[c, 3], T[j, 1])
    return ny, start, order, lo, hmin, box


@njit(cache=True, nogil=True)
def slope_lowest_pruned(Q, T, heights, owners, own, ny, start, order, lo, side, hmin, box, rise, r, r2):
    """:func:`slope_lowest` on the finer cells of :func:`slope_cells`, with the same outputs, bit
    for bit, visiting fewer points: the cells that may hold a point within ``r`` of a query are
    visited lowest bound first, and the visit stops at the first cell whose bound exceeds the
    lowest value found. A cell's bound is ``hmin + rise * sqrt(ex * ex + ey * ey)``, ``ex``/``ey``
    the query's distances to the cell's bounding box along each axis: computed with the same
    rounded operations as a point's value, each monotone, it is at most the value of any point of
    the cell, so a skipped cell holds no point whose value is at most the minimum (and a cell whose
    box is farther than ``r`` holds no point within it). The minimum is the same value whatever
    the order of the visit: a value ``h + rise * sqrt(d2)`` is never -0.0, so equal values are
    equal bit for bit."""
    q = Q.shape[0]
    n = start.shape[0] - 1
    nx = n // ny
    out = np.full(q, np.inf)
    reach = int(math.ceil(r / side)) + 1
    w = 2 * reach + 1
    lbs = np.empty(w * w)
    cells = np.empty(w * w, dtype=np.int64)
    for k in range(q):
        qx = Q[k, 0]
        qy = Q[k, 1]
        if not (math.isfinite(qx) and math.isfinite(qy)):
            continue
        fa = math.floor((qx - lo[0]) / side)
        fb = math.floor((qy - lo[1]) / side)
        if not (fa >= -reach - 1.0 and fa <= nx + reach and fb >= -reach - 1.0 and fb <= ny + reach):
            continue
        a0 = max(int(fa) - reach, 0)
        a1 = min(int(fa) + reach, nx - 1)
        b0 = max(int(fb) - reach, 0)
        b1 = min(int(fb) + reach, ny - 1)
        m = 0
        for a in range(a0, a1 + 1):
            for b in range(b0, b1 + 1):
                c = a * ny + b
                if start[c] == start[c + 1]:
                    continue
                ex = 0.0
                if qx < box[c, 0]:
                    ex = box[c, 0] - qx
                elif qx > box[c, 1]:
                    ex = qx - box[c, 1]
                ey = 0.0
                if qy < box[c, 2]:
                    ey = box[c, 2] - qy
                elif qy > box[c, 3]:
                    ey = qy - box[c, 3]
                d2 = ex * ex + ey * ey
                if d2 > r2:
                    continue
                lb = hmin[c] + rise * math.sqrt(d2)
                i = m
                while i > 0 and lbs[i - 1] > lb:
                    lbs[i] = lbs[i - 1]
                    cells[i] = cells[i - 1]
                    i -= 1
                lbs[i] = lb
                cells[i] = c
                m += 1
        best = np.inf
        for t in range(m):
            if lbs[t] > best:
                break
            c = cells[t]
            for p in range(start[c], start[c + 1]):
                j = order[p]
                if own >= 0 and owners[j] == own:
                    continue
                dx = T[j, 0] - qx
                dy = T[j, 1] - qy
                d2 = dx * dx + dy * dy
                if d2 <= r2:
                    v = heights[j] + rise * math.sqrt(d2)
                    if v < best:
                        best = v
        out[k] = best
    return out


# -- order statistics of a cluster's heights (the predicates' p90, p10, median) ---------------


@njit(cache=True, nogil=True)
def quantile_linear(h, q, median):
    """``np.percentile(h, 100 q)`` (method 'linear') or, with ``median``, ``np.median(h)``, of a
    1D float64 array, bit for bit, without numpy's per-call overhead: ``(value, ok)``. The two
    order statistics are taken from a sorted copy (they are unique bit for bit, as numpy's
    partition finds them, unless they are zeros of either sign) and combined with numpy's
    operations in its order (the interpolation of ``_lerp``: ``a + (b - a) t``, or ``b - (b - a)
    (1 - t)`` for ``t >= 0.5``; the median: ``(a + b) / 2`` or the middle value). ``ok`` is False,
    and the value to be ignored, when the array is empty, holds a NaN, or a picked value is a
    zero (whose sign the partition decides): the caller asks numpy then."""
    n = h.shape[0]
    if n == 0:
        return np.nan, False
    s = np.empty(n)
    for i in range(n):
        if math.isnan(h[i]):
            return np.nan, False
        s[i] = h[i]
    s.sort()
    if median:
        if n % 2 == 1:
            a = s[(n - 1) // 2]
            return a / 1.0, a != 0.0
        a = s[n // 2 - 1]
        b = s[n // 2]
        return (a + b) / 2.0, a != 0.0 and b != 0.0
    vi = (n - 1) * q
    if vi >= n - 1:  # numpy takes the last value at both ends (index -1), gamma = vi + 1
        a = s[n - 1]
        b = a
        t = vi - (-1.0)
    else:
        lo = math.floor(vi)
        a = s[int(lo)]
        b = s[int(lo) + 1]
        t = vi - lo
    diff = b - a
    if t >= 0.5:
        v = b - diff * (1.0 - t)
    else:
        v = a + diff * t
    return v, a != 0.0 and b != 0.0


# -- the local ground surface's medians, without a sort per row ---------------------------------


@njit(cache=True, nogil=True)
def local_medians_fast(d, idx, heights, owners, own, neighbours, quantile):
    """:func:`local_medians` with the same outputs, without an array allocated per row: the kept
    heights are insertion-sorted in one buffer as they are found. Sorted values are unique bit for
    bit except for +0.0 and -0.0 (equal, of another sign) and NaN (unordered): a row that keeps a
    zero or a NaN is done again with ``np.sort`` of the heights in found order, as
    :func:`local_medians` does, so every output is bit for bit its."""
    q, k = d.shape
    ground = np.full(q, np.nan)
    nearest = np.full(q, -1, dtype=np.int64)
    buf = np.empty(max(neighbours, 1))
    for r in range(q):
        m = 0
        odd = False  # a zero or a NaN kept
        for c in range(k):
            if m >= neighbours:
                break
            if not np.isfinite(d[r, c]):
                continue
            i = idx[r, c]
            if own >= 0 and owners[i] == own:
                continue
            if m == 0:
                nearest[r] = i
            v = heights[i]
            if not (v < 0.0 or v > 0.0):
                odd = True
            j = m
            while j > 0 and buf[j - 1] > v:  # insertion: the buffer stays sorted
                buf[j] = buf[j - 1]
                j -= 1
            buf[j] = v
            m += 1
        if m:
            if odd:  # numpy's sort of the found order decides where each zero (or NaN) goes
                n = 0
                for c in range(k):
                    if n >= m:
                        break
                    if np.isfinite(d[r, c]) and not (own >= 0 and owners[idx[r, c]] == own):
                        buf[n] = heights[idx[r, c]]
                        n += 1
                ground[r] = sorted_quantile(np.sort(buf[:m]), m, quantile)
            else:
                ground[r] = sorted_quantile(buf, m, quantile)
    return ground, nearest


# -- the bounds of the local ground surface (``LocalGround.height_bounds``) ---------------------


@njit(nogil=True)
def _block_reduce(A, reach, op):
    """``op`` (0 minimum, 1 maximum, 2 sum) of ``A`` (nx, ny) over the (2 reach + 1)^2 block of
    cells around each cell (cells beyond the edges do not count), one axis after the other."""
    nx, ny = A.shape
    B = A.copy()
    for a in range(nx):  # along the first axis: rows of cells at once
        for x in range(max(a - reach, 0), min(a + reach, nx - 1) + 1):
            if x != a:
                _fold_row(B[a], A[x], op)
    C = B.copy()
    for a in range(nx):  # along the second axis: within each row, shifted by d both ways
        for d in range(1, min(reach, ny - 1) + 1):
            _fold_row(C[a, :ny - d], B[a, d:], op)
            _fold_row(C[a, d:], B[a, :ny - d], op)
    return C


@njit(nogil=True, inline="always")
def _fold_row(dst, src, op):
    if op == 0:
        for j in range(dst.shape[0]):
            if src[j] < dst[j]:
                dst[j] = src[j]
    elif op == 1:
        for j in range(dst.shape[0]):
            if src[j] > dst[j]:
                dst[j] = src[j]
    else:
        for j in range(dst.shape[0]):
            dst[j] += src[j]


@njit(cache=True, nogil=True)
def surface_blocks(T, heights, origin, side, nx, ny, reach):
    """The block grid of the local ground surface's bounds: points ``T`` (m, 2) with ``heights``
    (m,) in cells ``floor((T - origin) / side)`` of an (nx, ny) grid that holds them all; per
    cell, the lowest and highest height over the (2 reach + 1)^2 block around it (+inf / -inf
    where empty) and the number of points of its 3 x 3 block (as floats). The same arrays as the
    numpy reference (``LocalGround._block_grid``): minima, maxima and sums of whole numbers do not
    depend on the order they are taken in."""
    lo = np.full((nx, ny), np.inf)
    hi = np.full((nx, ny), -np.inf)
    n = np.zeros((nx, ny))
    for i in range(T.shape[0]):
        a = int(math.floor((T[i, 0] - origin[0]) / side))
        b = int(math.floor((T[i, 1] - origin[1]) / side))
        h = heights[i]
        if h < lo[a, b]:
            lo[a, b] = h
        if h > hi[a, b]:
            hi[a, b] = h
        n[a, b] += 1.0
    return _block_reduce(lo, reach, 0), _block_reduce(hi, reach, 1), _block_reduce(n, 1, 2)


@njit(cache=True, nogil=True)
def block_plane_spread(T, heights, origin, side, nx, ny):
    """Per cell of an (nx, ny) grid of ``side`` from ``origin`` holding the points ``T`` (m, 2) at
    ``heights`` (m,): how far apart the points of its 3 x 3 block of cells lie across the block's
    least-squares plane ``h = h0 + b x + c y``, highest residual less lowest (-inf where the block
    is empty). The thickness of any of those points (the square root of the smallest eigenvalue of
    their covariance) is at most half of it: the variance along any direction bounds the smallest
    eigenvalue, and the residual of a plane is the projection on its normal scaled by at least 1.
    A tilted smooth road measures its noise, where the spread of its heights measures its slope.
    Any plane gives a bound: the fit only makes it tight (a block of fewer than 3 points, or a
    degenerate one, is measured across the horizontal)."""
    m = T.shape[0]
    S = np.zeros((nx, ny, 9))  # per block: n, sx, sy, sz, sxx, sxy, syy, sxz, syz (block-local x, y)
    ca = np.empty(m, dtype=np.int64)
    cb = np.empty(m, dtype=np.int64)
    zref = 0.0
    for i in range(m):
        zref += heights[i]
    zref = zref / m if m else 0.0
    for i in range(m):
        a = int(math.floor((T[i, 0] - origin[0]) / side))
        b = int(math.floor((T[i, 1] - origin[1]) / side))
        ca[i] = a
        cb[i] = b
        z = heights[i] - zref
        for u in range(max(a - 1, 0), min(a + 1, nx - 1) + 1):
            x = T[i, 0] - (origin[0] + u * side)
            for v in range(max(b - 1, 0), min(b + 1, ny - 1) + 1):
                y = T[i, 1] - (origin[1] + v * side)
                S[u, v, 0] += 1.0
                S[u, v, 1] += x
                S[u, v, 2] += y
                S[u, v, 3] += z
                S[u, v, 4] += x * x
                S[u, v, 5] += x * y
                S[u, v, 6] += y * y
                S[u, v, 7] += x * z
                S[u, v, 8] += y * z
    P = np.zeros((nx, ny, 5))  # per block: mean x, y, z and the slopes b, c
    for u in range(nx):
        for v in range(ny):
            n = S[u, v, 0]
            if n == 0.0:
                continue
            mx = S[u, v, 1] / n
            my = S[u, v, 2] / n
            mz = S[u, v, 3] / n
            P[u, v, 0] = mx
            P[u, v, 1] = my
            P[u, v, 2] = mz
            if n < 3.0:
                continue
            cxx = S[u, v, 4] / n - mx * mx
            cxy = S[u, v, 5] / n - mx * my
            cyy = S[u, v, 6] / n - my * my
            cxz = S[u, v, 7] / n - mx * mz
            cyz = S[u, v, 8] / n - my * mz
            det = cxx * cyy - cxy * cxy
            if det > 1e-9 * (cxx + cyy) * (cxx + cyy) and det > 0.0:
                P[u, v, 3] = (cxz * cyy - cyz * cxy) / det
                P[u, v, 4] = (cyz * cxx - cxz * cxy) / det
    lo = np.full((nx, ny), np.inf)
    hi = np.full((nx, ny), -np.inf)
    for i in range(m):
        a = ca[i]
        b = cb[i]
        z = heights[i] - zref
        for u in range(max(a - 1, 0), min(a + 1, nx - 1) + 1):
            x = T[i, 0] - (origin[0] + u * side)
            for v in range(max(b - 1, 0), min(b + 1, ny - 1) + 1):
                y = T[i, 1] - (origin[1] + v * side)
                r = z - (P[u, v, 2] + P[u, v, 3] * (x - P[u, v, 0]) + P[u, v, 4] * (y - P[u, v, 1]))
                if r < lo[u, v]:
                    lo[u, v] = r
                if r > hi[u, v]:
                    hi[u, v] = r
    return hi - lo


@njit(cache=True, nogil=True)
def surface_bounds(Q, lo, hi, origin, side, lo_b, hi_b, n3, need, narrow):
    """Write the bounds of one block grid (see :func:`surface_blocks`) for the plane points ``Q``
    (q, 2) into ``lo``, ``hi`` (q,): the block's lowest and highest height where the point's cell
    ``floor((Q - origin) / side)`` is inside the grid; with ``narrow`` (the fine grid), only where
    the 3 x 3 block holds at least ``need`` points, and only to narrow the bounds already there."""
    nx, ny = lo_b.shape
    for k in range(Q.shape[0]):
        fa = math.floor((Q[k, 0] - origin[0]) / side)
        fb = math.floor((Q[k, 1] - origin[1]) / side)
        if not (fa >= 0.0 and fb >= 0.0 and fa < nx and fb < ny):  # NaN fails too
            continue
        a = int(fa)
        b = int(fb)
        if not narrow:
            lo[k] = lo_b[a, b]
            hi[k] = hi_b[a, b]
        elif n3[a, b] >= need:
            lo[k] = max(lo[k], lo_b[a, b])
            hi[k] = min(hi[k], hi_b[a, b])


# -- the distance from each point of a plane to its nearest other point (connexity's spacing) ----


@njit(nogil=True)
def _sqdist(Q, j, T, i):
    """scipy's squared Euclidean distance ``((0 + d0 d0) + d1 d1) + ...``, ``d = query - data``."""
    s = 0.0
    for a in range(Q.shape[1]):
        d = Q[j, a] - T[i, a]
        s += d * d
    return s


@njit(nogil=True)
def _point_grid(S, lo0, lo1, side, nx, ny):
    """Cells (nx, ny) of ``side`` from (lo0, lo1) over the first two columns of ``S`` (n, D >= 2): each row's cell
    (cx, cy) and the rows cell by cell (``member[start[c]:start[c + 1]]``, cell c = cx ny + cy)."""
    n = S.shape[0]
    cx = np.empty(n, dtype=np.int64)
    cy = np.empty(n, dtype=np.int64)
    start = np.zeros(nx * ny + 1, dtype=np.int64)
    for j in range(n):
        a = min(max(int(math.floor((S[j, 0] - lo0) / side)), 0), nx - 1)
        b = min(max(int(math.floor((S[j, 1] - lo1) / side)), 0), ny - 1)
        cx[j] = a
        cy[j] = b
        start[a * ny + b + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    member = np.empty(n, dtype=np.int64)
    for j in range(n):
        c = cx[j] * ny + cy[j]
        member[fill[c]] = j
        fill[c] += 1
    return cx, cy, start, member


@njit(cache=True, nogil=True)
def nearest_other_distances(S, side):
    """For each row of ``S`` (n, D >= 2), the distance to its nearest other row: what
    ``cKDTree(S).query(S, k=2)[0][:, 1]`` gives, bit for bit (scipy's squared distance
    ``((0 + d0 d0) + d1 d1) + ...`` with ``d = query - data``, then its square root), by a grid
    over the first two columns searched ring by ring around each point until no cell beyond the
    searched block can hold a nearer point (its border farther than the best distance, less a
    margin of 1e-6 cell; the other columns only add to a distance).

    The cells: ``side`` shrunk to about one point per occupied cell of a first grid of ``side``
    (the points of a cluster fill a part of their bounding box). Returns ``(d, ok)``; ``ok`` False
    (``d`` then unset) when ``side`` is not positive and finite or the first grid would have more
    than ``8 n + 64`` cells: the caller asks its k-d tree."""
    n = S.shape[0]
    d = np.empty(n)
    if not (side > 0.0 and side < np.inf) or n < 2:
        return d, False
    lo0 = S[0, 0]
    lo1 = S[0, 1]
    hi0 = lo0
    hi1 = lo1
    for j in range(n):
        lo0 = min(lo0, S[j, 0])
        lo1 = min(lo1, S[j, 1])
        hi0 = max(hi0, S[j, 0])
        hi1 = max(hi1, S[j, 1])
    limit = 8.0 * n + 64.0
    fx = math.floor((hi0 - lo0) / side) + 1.0
    fy = math.floor((hi1 - lo1) / side) + 1.0
    if not (fx * fy <= limit):
        return d, False
    nx = int(fx)
    ny = int(fy)
    cx, cy, start, member = _point_grid(S, lo0, lo1, side, nx, ny)
    occupied = 0
    for c in range(nx * ny):
        if start[c + 1] > start[c]:
            occupied += 1
    fine = side * math.sqrt(occupied / n)
    gx = math.floor((hi0 - lo0) / fine) + 1.0
    gy = math.floor((hi1 - lo1) / fine) + 1.0
    if fine > 0.0 and gx * gy <= limit:
        side = fine
        nx = int(gx)
        ny = int(gy)
        cx, cy, start, member = _point_grid(S, lo0, lo1, side, nx, ny)
    margin = 1e-6 * side
    for j in range(n):
        q0 = S[j, 0]
        q1 = S[j, 1]
        a = cx[j]
        b = cy[j]
        best = np.inf
        r = 0
        while True:
            for ia in range(max(a - r, 0), min(a + r, nx - 1) + 1):
                ring_row = ia == a - r or ia == a + r
                for ib in range(max(b - r, 0), min(b + r, ny - 1) + 1):
                    if not ring_row and ib != b - r and ib != b + r:
                        continue
                    c = ia * ny + ib
                    for t in range(start[c], start[c + 1]):
                        i = member[t]
                        if i == j:
                            continue
                        s = _sqdist(S, j, S, i)
                        if s < best:
                            best = s
            # the nearest a cell outside the searched block can be (none beyond the grid's edge)
            border = np.inf
            if a - r > 0:
                border = min(border, q0 - (lo0 + (a - r) * side))
            if a + r < nx - 1:
                border = min(border, (lo0 + (a + r + 1) * side) - q0)
            if b - r > 0:
                border = min(border, q1 - (lo1 + (b - r) * side))
            if b + r < ny - 1:
                border = min(border, (lo1 + (b + r + 1) * side) - q1)
            if border == np.inf:
                break
            border -= margin
            if border > 0.0 and best <= border * border:
                break
            r += 1
        d[j] = math.sqrt(best)
    return d, True


# -- the nearest point: a k-d tree (scipy's ``cKDTree.query(k=1)`` answers) -------------------

_LEAF = 12


@njit(nogil=True)
def _select(T, perm, lo, hi, k, axis):
    """Reorder ``perm[lo:hi + 1]`` so that the row at ``k`` has the rank it would have sorted by
    ``T[:, axis]``, rows at most it before, rows at least it after (Hoare's selection)."""
    while hi > lo:
        pivot = T[perm[(lo + hi) // 2], axis]
        i = lo
        j = hi
        while i <= j:
            while T[perm[i], axis] < pivot:
                i += 1
            while T[perm[j], axis] > pivot:
                j -= 1
            if i <= j:
                t = perm[i]
                perm[i] = perm[j]
                perm[j] = t
                i += 1
                j -= 1
        if k <= j:
            hi = j
        elif k >= i:
            lo = i
        else:
            return


@njit(cache=True, nogil=True)
def kdtree_build(T):
    """A k-d tree over the rows of ``T`` (m > 0, D): ``(perm, start, stop, left, right, lo, hi)``,
    node ``v`` holding the rows ``perm[start[v]:stop[v]]`` within the box ``lo[v]``..``hi[v]``
    (the points' bounds at the root, a child's the parent's cut at the median row), its children ``left[v]``, ``right[v]`` (-1 for a leaf of at most 8 rows). A
    node splits at the median along its widest side (a selection, no sort)."""
    m, D = T.shape
    cap = 2 * (m // _LEAF + 1) * 2 + 1
    perm = np.arange(m)
    start = np.empty(cap, dtype=np.int64)
    stop = np.empty(cap, dtype=np.int64)
    left = np.full(cap, -1, dtype=np.int64)
    right = np.full(cap, -1, dtype=np.int64)
    lo = np.empty((cap, D))
    hi = np.empty((cap, D))
    stack = np.empty(cap, dtype=np.int64)
    start[0] = 0
    stop[0] = m
    n = 1
    top = 0
    stack[top] = 0
    top += 1
    for a in range(D):  # the root's box: the bounds of the points
        lo[0, a] = T[0, a]
        hi[0, a] = T[0, a]
    for p in range(1, m):
        for a in range(D):
            lo[0, a] = min(lo[0, a], T[p, a])
            hi[0, a] = max(hi[0, a], T[p, a])
    while top > 0:
        top -= 1
        v = stack[top]
        s0 = start[v]
        s1 = stop[v]
        if s1 - s0 <= _LEAF:
            continue
        axis = 0
        for a in range(1, D):
            if hi[v, a] - lo[v, a] > hi[v, axis] - lo[v, axis]:
                axis = a
        if not hi[v, axis] > lo[v, axis]:
            continue  # every row at one position: a leaf
        mid = s0 + (s1 - s0) // 2
        _select(T, perm, s0, s1 - 1, mid, axis)
        cut = T[perm[mid], axis]
        for a in range(D):  # the children's boxes: the node's, cut at the median row
            lo[n, a] = lo[v, a]
            hi[n, a] = hi[v, a]
            lo[n + 1, a] = lo[v, a]
            hi[n + 1, a] = hi[v, a]
        hi[n, axis] = cut
        lo[n + 1, axis] = cut
        left[v] = n
        start[n] = s0
        stop[n] = mid
        right[v] = n + 1
        start[n + 1] = mid
        stop[n + 1] = s1
        stack[top] = n
        stack[top + 1] = n + 1
        top += 2
        n += 2
    return perm, start[:n].copy(), stop[:n].copy(), left[:n].copy(), right[:n].copy(), lo[:n].copy(), hi[:n].copy()


@njit(nogil=True)
def _box_sqdist(Q, j, lo, hi, v):
    """A lower bound of :func:`_sqdist` from ``Q[j]`` to any point of box ``v``: the same sum, in the
    same order, of gaps no larger than the coordinates' differences (rounding keeps the order)."""
    s = 0.0
    for a in range(Q.shape[1]):
        x = Q[j, a]
        g = 0.0
        if x < lo[v, a]:
            g = lo[v, a] - x
        elif x > hi[v, a]:
            g = x - hi[v, a]
        s += g * g
    return s


@njit(cache=True, nogil=True)
def kdtree_nearest(Q, T, perm, start, stop, left, right, lo, hi, labels):
    """For each row of ``Q`` (q, D), its nearest row of ``T`` by the tree of :func:`kdtree_build`:
    ``(d, idx, ok)``, ``d`` the distance as ``cKDTree(T).query(Q, k=1)`` computes it
    (:func:`_sqdist`, then its square root), bit for bit. Every point at the nearest distance is
    seen (a box is left out only when it lies strictly farther); a row is ``ok`` when its answer is
    the k-d tree's whatever the order of equal distances: with ``labels`` (m,) (empty: none), no
    point of another label lies at the nearest distance; without, always."""
    q = Q.shape[0]
    m = T.shape[0]
    d = np.full(q, np.inf)
    idx = np.full(q, m, dtype=np.int64)
    ok = np.ones(q, dtype=np.bool_)
    use_labels = labels.shape[0] > 0
    stack = np.empty(start.shape[0] + 1, dtype=np.int64)
    near = np.empty(start.shape[0] + 1)  # each stacked box's lower bound
    for j in range(q):
        best = np.inf
        bi = -1
        tie = False
        stack[0] = 0
        near[0] = 0.0
        top = 1
        while top > 0:
            top -= 1
            v = stack[top]
            if near[top] > best:
                continue
            if left[v] < 0:
                for p in range(start[v], stop[v]):
                    i = perm[p]
                    s = _sqdist(Q, j, T, i)
                    if s < best:
                        best = s
                        bi = i
                        tie = False
                    elif s == best and use_labels and labels[i] != labels[bi]:
                        tie = True
                continue
            a = left[v]
            b = right[v]
            da = _box_sqdist(Q, j, lo, hi, a)
            db = _box_sqdist(Q, j, lo, hi, b)
            if da > db:  # the nearer child last on the stack: searched first
                a, b = b, a
                da, db = db, da
            if db <= best:
                stack[top] = b
                near[top] = db
                top += 1
            if da <= best:
                stack[top] = a
                near[top] = da
                top += 1
        d[j] = math.sqrt(best)
        idx[j] = bi
        ok[j] = not tie
    return d, idx, ok


# -- the k nearest surface points within a radius (the local ground surface's queries) ---------


@njit(cache=True, nogil=True)
def plane_grid(T, side, per_cell=4.0, max_dup=0.01):
    """A grid over the rows of ``T`` (m, 2) for :func:`grid_knn`: cells of about ``side``, shrunk
    to about ``per_cell`` points per occupied cell. Returns ``(lo0, lo1, side, nx, ny, start,
    member, ok)``; ``ok`` False when no grid of at most ``8 m + 64`` cells fits, or when more than
    ``max_dup`` of the rows repeat an earlier row's position (their distances tie, and rows with
    ties in the wrong places go to the k-d tree: a third of a GndNet scan's points are
    duplicated)."""
    m = T.shape[0]
    e = np.zeros(0, dtype=np.int64)
    if m < 1 or not (side > 0.0 and side < np.inf):
        return 0.0, 0.0, 0.0, 0, 0, e, e, False
    lo0 = T[0, 0]
    lo1 = T[0, 1]
    hi0 = lo0
    hi1 = lo1
    for j in range(m):
        lo0 = min(lo0, T[j, 0])
        lo1 = min(lo1, T[j, 1])
        hi0 = max(hi0, T[j, 0])
        hi1 = max(hi1, T[j, 1])
    limit = 8.0 * m + 64.0
    fx = math.floor((hi0 - lo0) / side) + 1.0
    fy = math.floor((hi1 - lo1) / side) + 1.0
    if not (fx * fy <= limit):
        return 0.0, 0.0, 0.0, 0, 0, e, e, False
    nx = int(fx)
    ny = int(fy)
    cx, cy, start, member = _point_grid(T, lo0, lo1, side, nx, ny)
    occupied = 0
    for c in range(nx * ny):
        if start[c + 1] > start[c]:
            occupied += 1
    fine = side * math.sqrt(per_cell * occupied / m)
    gx = math.floor((hi0 - lo0) / fine) + 1.0
    gy = math.floor((hi1 - lo1) / fine) + 1.0
    if fine > 0.0 and gx * gy <= limit:
        side = fine
        nx = int(gx)
        ny = int(gy)
        cx, cy, start, member = _point_grid(T, lo0, lo1, side, nx, ny)
    dup = 0  # rows at the plane position of an earlier row: their distances tie, the k-d tree answers them
    for c in range(nx * ny):
        for t in range(start[c] + 1, start[c + 1]):
            i = member[t]
            for u in range(start[c], t):
                if T[member[u], 0] == T[i, 0] and T[member[u], 1] == T[i, 1]:
                    dup += 1
                    break
    if dup > max_dup * m:
        return 0.0, 0.0, 0.0, 0, 0, e, e, False
    return lo0, lo1, side, nx, ny, start, member, True


@njit(nogil=True)
def _near(a, b):
    return b - a <= 1e-12 * b


@njit(nogil=True)
def _knn_ambiguous(bs, bi, cnt, k, near_r2, far_r2, heights, owners, own, neighbours, first):
    """Whether the k-d tree's order of equal distances could change a row's outputs (see
    :func:`grid_knn`); ``bs``/``bi`` the ``cnt`` (at most k + 1) nearest, sorted."""
    for p in range(cnt):
        if near_r2 <= bs[p] < far_r2:
            return True
    if cnt == k + 1 and _near(bs[k - 1], bs[k]):
        return True
    n = min(cnt, k)
    kept = 0
    f = -1
    first_open = False  # still in the group of the first kept point
    odd = False  # a kept height is zero or NaN
    two = False  # a group holds two kept points
    g_kept = 0  # kept points in the current group
    for p in range(n):
        if p > 0 and not _near(bs[p - 1], bs[p]):
            g_kept = 0
            first_open = False
        if own >= 0 and owners[bi[p]] == own:
            continue
        if kept >= neighbours:  # the next one not of own: open only if it shares a kept one's group
            if g_kept > 0:
                return True
            break
        if kept == 0:
            first_open = True
            f = bi[p]
        elif first_open and (first == 0 or (first == 1 and owners[bi[p]] != owners[f])):
            return True  # two candidates for the first kept point (of two owners)
        v = heights[bi[p]]
        if not (v < 0.0 or v > 0.0):
            odd = True
        kept += 1
        g_kept += 1
        if g_kept > 1:
            two = True
    return odd and two


@njit(cache=True, nogil=True)
def grid_knn(Q, T, lo0, lo1, side, nx, ny, start, member, k, radius, heights, owners, own, neighbours, first):
    """``cKDTree(T).query(Q, k, distance_upper_bound=radius)`` over the grid of
    :func:`plane_grid`: ``(d, i, ok)`` with ``d`` (q, k) the distances nearest first (scipy's
    ``sqrt((0 + d0 d0) + d1 d1)``, ``d = query - data``), inf and ``m`` where fewer than k points
    lie nearer than ``radius``. A row is ``ok`` when :func:`local_medians_fast` (``heights``,
    ``owners``, ``own``, ``neighbours``) gives it the k-d tree's outputs whatever the order of
    equal distances: the k nearest are one set (the k-th and the next not within 1e-12 of each
    other, relative, squared), none lies within 1e-9 of the radius, the kept points (the first
    ``neighbours`` not of ``own``) are one set whatever the order within a group of near-equal
    distances, and so is the first of them (``first`` 0: one point; 1: its owner, ``owners``, one
    cluster; 2: not asked), and no group holds two kept points when a kept height is zero or NaN
    (their order then decides the sort). The caller asks its k-d tree for the other rows."""
    q = Q.shape[0]
    m = T.shape[0]
    d = np.full((q, k), np.inf)
    idx = np.full((q, k), m, dtype=np.int64)
    ok = np.ones(q, dtype=np.bool_)
    r2 = radius * radius
    near_r2 = r2 * (1.0 - 1e-9)
    far_r2 = r2 * (1.0 + 1e-9)
    margin = 1e-6 * side
    kk = k + 1
    bs = np.empty(kk)
    bi = np.empty(kk, dtype=np.int64)
    for j in range(q):
        q0 = Q[j, 0]
        q1 = Q[j, 1]
        fa = math.floor((q0 - lo0) / side)
        fb = math.floor((q1 - lo1) / side)
        if not (abs(fa) < 1e15 and abs(fb) < 1e15):
            ok[j] = False
            continue
        a = int(fa)
        b = int(fb)
        cnt = 0  # the kk best so far, sorted by squared distance
        r = 0
        while True:
            a0 = max(a - r, 0)
            a1 = min(a + r, nx - 1)
            b0 = max(b - r, 0)
            b1 = min(b + r, ny - 1)
            for ia in range(a0, a1 + 1):
                ring_row = ia == a - r or ia == a + r
                ib = b0
                while ib <= b1:
                    if not ring_row and ib != b - r and ib != b + r:
                        ib = b + r if b + r <= b1 else b1 + 1  # the row's inner cells were searched
                        continue
                    c = ia * ny + ib
                    for t in range(start[c], start[c + 1]):
                        i = member[t]
                        d0 = q0 - T[i, 0]
                        d1 = q1 - T[i, 1]
                        s = (0.0 + d0 * d0) + d1 * d1
                        if s >= far_r2:
                            continue
                        if cnt == kk and s >= bs[kk - 1]:
                            continue
                        p = cnt if cnt < kk else kk - 1
                        while p > 0 and bs[p - 1] > s:
                            bs[p] = bs[p - 1]
                            bi[p] = bi[p - 1]
                            p -= 1
                        bs[p] = s
                        bi[p] = i
                        if cnt < kk:
                            cnt += 1
                    ib += 1
            # the nearest a point outside the searched block can be (none beyond the grid's edge)
            border = np.inf
            if a - r > 0:
                border = min(border, q0 - (lo0 + (a - r) * side))
            if a + r < nx - 1:
                border = min(border, (lo0 + (a + r + 1) * side) - q0)
            if b - r > 0:
                border = min(border, q1 - (lo1 + (b - r) * side))
            if b + r < ny - 1:
                border = min(border, (lo1 + (b + r + 1) * side) - q1)
            if border == np.inf:
                break
            border -= margin
            if border > 0.0:
                b2 = border * border
                if b2 >= far_r2:
                    break
                if cnt == kk and bs[kk - 1] <= b2:
                    break
            r += 1
        if _knn_ambiguous(bs, bi, cnt, k, near_r2, far_r2, heights, owners, own, neighbours, first):
            ok[j] = False
            continue
        for p in range(min(cnt, k)):
            if bs[p] < r2:
                d[j, p] = math.sqrt(bs[p])
                idx[j, p] = bi[p]
    return d, idx, ok
