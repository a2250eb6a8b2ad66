"""Vectorised ray casting: pinhole rays, convex polyhedra, ellipsoids, rectangles, height fields.

Every ray starts at the sensor, the origin of the sensor frame (x forward along the horizontal
projection of the optical axis, y to the left, z up), and is given by its unit direction. Each
kernel returns, per ray, the distance ``t`` along the ray to the first surface it enters (``inf``
when it misses), so that occlusion is a minimum over the kernels' answers.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def pinhole_rays(
    shape: tuple[int, int],
    fov_deg: tuple[float, float],
    tilt_deg: float,
    *,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Unit directions of the rays of a pinhole sensor, one per pixel, in row-major order.

    Parameters
    ----------
    shape : (int, int)
        ``(rows, cols)`` of the image.
    fov_deg : (float, float)
        Vertical and horizontal fields of view, in degrees (each < 180).
    tilt_deg : float
        Depression of the optical axis below the horizontal, in degrees (positive: looking down).
    rng : numpy.random.Generator, optional
        When given, each ray goes through a uniformly random position inside its pixel instead of
        the pixel's centre (breaks the regular scan-line pattern of far ground points).

    Returns
    -------
    np.ndarray, shape (rows * cols, 3)
        Row 0 is the top of the image (farthest from the ground), column 0 its left (+y) side.
    """
    rows, cols = shape
    tilt = np.radians(tilt_deg)
    forward = np.array([np.cos(tilt), 0.0, -np.sin(tilt)])
    right = np.array([0.0, -1.0, 0.0])
    up = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
    r, c = np.meshgrid(np.arange(rows, dtype=np.float64), np.arange(cols, dtype=np.float64), indexing="ij")
    r, c = r.ravel(), c.ravel()
    if rng is None:
        r, c = r + 0.5, c + 0.5
    else:
        r, c = r + rng.uniform(size=r.size), c + rng.uniform(size=c.size)
    u = (2.0 * c / cols - 1.0) * np.tan(np.radians(fov_deg[1]) / 2.0)
    v = (1.0 - 2.0 * r / rows) * np.tan(np.radians(fov_deg[0]) / 2.0)
    d = forward + u[:, None] * right + v[:, None] * up
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def sphere_candidates(dirs: np.ndarray, center: np.ndarray, radius: float) -> np.ndarray:
    """Indices of the rays from the origin that pass within ``radius`` of ``center`` ahead of the
    origin (a cheap cull before an exact intersection test).

    Parameters
    ----------
    dirs : np.ndarray, shape (n, 3)
        Unit ray directions.
    center : np.ndarray, shape (3,)
    radius : float

    Returns
    -------
    np.ndarray, shape (m,), int64
    """
    along = dirs @ center
    across2 = float(center @ center) - along**2
    return np.flatnonzero((across2 <= radius**2) & (along > -radius))


def ray_plane(dirs: np.ndarray, normal: np.ndarray, offset: float) -> np.ndarray:
    """Distance along each ray from the origin to the plane ``normal . x = offset``, seen from the
    side the origin is on (rays parallel to it or going away: ``inf``).

    Parameters
    ----------
    dirs : np.ndarray, shape (n, 3)
        Unit ray directions.
    normal : np.ndarray, shape (3,)
    offset : float

    Returns
    -------
    np.ndarray, shape (n,)
    """
    denom = dirs @ np.asarray(normal, dtype=np.float64)
    t = np.full(len(dirs), np.inf)
    np.divide(offset, denom, out=t, where=denom != 0)
    t[~(t > 0)] = np.inf
    return t


def ray_convex(dirs: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry distance of rays from the origin into a convex polyhedron ``normals @ x <= offsets``.

    The slab method generalised: along the ray ``x = t u`` each half-space ``n . x <= d`` keeps
    ``t >= d / (n . u)`` when the ray enters it (``n . u < 0``) and ``t <= d / (n . u)`` when it
    leaves it (``n . u > 0``); the ray is inside on ``[max of the entries, min of the exits]``.
    The face hit is the entering plane with the largest entry.

    Parameters
    ----------
    dirs : np.ndarray, shape (n, 3)
        Unit ray directions.
    normals : np.ndarray, shape (k, 3)
        Outward unit normals of the faces.
    offsets : np.ndarray, shape (k,)
        Plane offsets; the origin must be outside the polyhedron.

    Returns
    -------
    t : np.ndarray, shape (n,)
        Entry distance, ``inf`` for a ray that misses.
    face : np.ndarray, shape (n,), int64
        Index of the face entered, -1 for a ray that misses.
    """
    denom = dirs @ normals.T  # (n, k)
    num = np.broadcast_to(np.asarray(offsets, dtype=np.float64), denom.shape)
    t = np.zeros_like(denom)
    np.divide(num, denom, out=t, where=denom != 0)
    entering, leaving = denom < 0, denom > 0
    t_in_all = np.where(entering, t, -np.inf)
    face = t_in_all.argmax(axis=1)
    t_in = np.take_along_axis(t_in_all, face[:, None], axis=1)[:, 0]
    t_out = np.where(leaving, t, np.inf).min(axis=1)
    # a ray parallel to a face and outside its half-space never enters
    parallel_out = (~entering & ~leaving & (num < 0)).any(axis=1)
    hit = np.isfinite(t_in) & (t_in > 0) & (t_in <= t_out) & ~parallel_out
    return np.where(hit, t_in, np.inf), np.where(hit, face, -1)


def ray_ellipsoid(dirs: np.ndarray, center: np.ndarray, axes: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Entry distance of rays from the origin into an ellipsoid.

    Parameters
    ----------
    dirs : np.ndarray, shape (n, 3)
        Unit ray directions.
    center : np.ndarray, shape (3,)
    axes : np.ndarray, shape (3, 3)
        Rows are the ellipsoid's orthonormal principal axes.
    radii : np.ndarray, shape (3,)
        Semi-axis lengths along ``axes``.

    Returns
    -------
    np.ndarray, shape (n,)
        Distance to the first intersection, ``inf`` for a miss (or a sensor inside).
    """
    o = (axes @ (-np.asarray(center, dtype=np.float64))) / radii  # origin in the unit-sphere frame
    u = (dirs @ axes.T) / radii
    a = np.einsum("ij,ij->i", u, u)
    b = 2.0 * (u @ o)
    c = float(o @ o) - 1.0
    disc = b * b - 4.0 * a * c
    t = np.full(len(dirs), np.inf)
    ok = disc >= 0
    t[ok] = (-b[ok] - np.sqrt(disc[ok])) / (2.0 * a[ok])
    t[~(t > 0)] = np.inf
    return t


def ray_rectangle(
    dirs: np.ndarray, center: np.ndarray, axis_u: np.ndarray, axis_v: np.ndarray, half_u: float, half_v: float
) -> np.ndarray:
    """Distance along rays from the origin to a two-sided rectangle (``inf`` for a miss).

    Parameters
    ----------
    dirs : np.ndarray, shape (n, 3)
        Unit ray directions.
    center : np.ndarray, shape (3,)
    axis_u, axis_v : np.ndarray, shape (3,)
        Orthonormal in-plane axes.
    half_u, half_v : float
        Half extents along ``axis_u`` and ``axis_v``.

    Returns
    -------
    np.ndarray, shape (n,)
    """
    normal = np.cross(axis_u, axis_v)
    offset = float(normal @ center)
    denom = dirs @ normal
    t = np.full(len(dirs), np.inf)
    np.divide(offset, denom, out=t, where=denom != 0)
    t[~(t > 0)] = np.inf
    finite = np.isfinite(t)
    p = dirs[finite] * t[finite, None] - center
    inside = (np.abs(p @ axis_u) <= half_u) & (np.abs(p @ axis_v) <= half_v)
    t[np.flatnonzero(finite)[~inside]] = np.inf
    return t


@dataclass(frozen=True, eq=False)
class HeightField:
    """A smooth terrain ``z = base + sum_k a_k sin(w_k . (x, y) + phase_k)`` (metres).

    Attributes
    ----------
    base : float
        Mean height.
    amplitudes : np.ndarray, shape (k,)
    wavevectors : np.ndarray, shape (k, 2)
        Angular wave vectors, rad/m.
    phases : np.ndarray, shape (k,)
    """

    base: float
    amplitudes: np.ndarray
    wavevectors: np.ndarray
    phases: np.ndarray

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height at ``(x, y)`` (arrays of any one shape)."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        z = np.full(np.broadcast(x, y).shape, self.base)
        for a, (wx, wy), ph in zip(self.amplitudes, self.wavevectors, self.phases):
            z += a * np.sin(wx * x + wy * y + ph)
        return z

    @property
    def bounds(self) -> tuple[float, float]:
        """Lowest and highest heights the field can take."""
        spread = float(np.abs(self.amplitudes).sum())
        return self.base - spread, self.base + spread

    @property
    def max_slope(self) -> float:
        """An upper bound of the gradient's norm (rise per metre)."""
        return float((np.abs(self.amplitudes) * np.linalg.norm(self.wavevectors, axis=1)).sum())


def ray_heightfield(
    dirs: np.ndarray,
    field: HeightField,
    t_max: float | np.ndarray,
    *,
    step: float = 0.2,
    tol: float = 1e-6,
) -> np.ndarray:
    """Distance along rays from the origin (above the terrain) to their first terrain crossing.

    A ray can only meet the terrain where its height lies within the field's bounds; each ray
    marches that interval (clipped at ``t_max``) in steps of ``step`` until its first sample
    below the surface (all rays at once, each leaving the active set when it is done), then the
    crossing is refined by bisection to ``tol``. A crossing that enters and leaves the terrain
    within one step (much shorter than the terrain's wavelengths) could be missed.

    Parameters
    ----------
    dirs : np.ndarray, shape (n, 3)
        Unit ray directions.
    field : HeightField
        The terrain; its highest point must be below the origin.
    t_max : float or np.ndarray of shape (n,)
        Rays that do not meet the terrain within this distance miss.
    step : float
        Marching step along the ray, metres.
    tol : float
        Width of the final bracket of each crossing, metres.

    Returns
    -------
    np.ndarray, shape (n,)
        Distance to the crossing, ``inf`` for a miss.
    """
    z_lo, z_hi = field.bounds
    if z_hi >= 0:
        raise ValueError("the sensor must be above the terrain")
    n = len(dirs)
    uz = dirs[:, 2]
    t = np.full(n, np.inf)
    down = uz < 0
    t_a = np.full(n, np.inf)
    t_b = np.full(n, np.inf)
    t_a[down] = z_hi / uz[down]
    t_b[down] = np.minimum(z_lo / uz[down], t_max if np.ndim(t_max) == 0 else np.asarray(t_max)[down])
    active = np.flatnonzero(down & (t_a <= t_b))
    lo_all, hi_all = np.full(n, np.nan), np.full(n, np.nan)

    def below(idx: np.ndarray, tt: np.ndarray) -> np.ndarray:
        d = dirs[idx]
        return tt * d[:, 2] <= field(tt * d[:, 0], tt * d[:, 1])

    prev = t_a[active]  # above (or on) the terrain by construction
    while active.size:
        cur = np.minimum(prev + step, t_b[active])
        under = below(active, cur)
        lo_all[active[under]], hi_all[active[under]] = prev[under], cur[under]
        going = ~under & (cur < t_b[active])
        active, prev = active[going], cur[going]
    found = np.flatnonzero(np.isfinite(hi_all))
    lo, hi = lo_all[found], hi_all[found]
    for _ in range(max(0, int(np.ceil(np.log2(step / tol))))):
        mid = 0.5 * (lo + hi)
        under = below(found, mid)
        hi = np.where(under, mid, hi)
        lo = np.where(under, lo, mid)
    t[found] = hi
    return t
