"""kbs.arrays.rows: the same array as numpy's advanced indexing along the first axis."""
from __future__ import annotations

import numpy as np
import pytest

from kbs.arrays import rows


@pytest.mark.parametrize("make", [
    lambda rng, n: rng.integers(0, n, 50),                       # repeats, any order
    lambda rng, n: np.sort(rng.choice(n, 40, replace=False)),    # a cluster's sorted rows
    lambda rng, n: -rng.integers(1, n + 1, 10),                  # negative, as Python counts them
    lambda rng, n: rng.random(n) > 0.5,                          # a mask
    lambda rng, n: np.zeros(0, dtype=np.int64),                  # none
    lambda rng, n: np.zeros(n, dtype=bool),                      # a mask of none
    lambda rng, n: rng.integers(0, n, 7).astype(np.int32),       # another integer type
])
@pytest.mark.parametrize("layout", ["C", "F", "strided", "1-D", "3-D"])
def test_rows_is_numpy_s_indexing(make, layout):
    rng = np.random.default_rng(1)
    base = rng.normal(size=(200, 3))
    a = {"C": base, "F": np.asfortranarray(base), "strided": rng.normal(size=(200, 6))[:, ::2],
         "1-D": base[:, 0].copy(), "3-D": rng.normal(size=(200, 3, 3))}[layout]
    index = make(rng, a.shape[0])
    want, got = a[index], rows(a, index)
    assert got.dtype == want.dtype and got.shape == want.shape
    assert np.array_equal(got, want)
    assert got.flags.c_contiguous == want.flags.c_contiguous
    got[...] = 0.0  # a new array, as indexing gives: the source is untouched
    assert np.array_equal(a[index], want)


@pytest.mark.parametrize("index", [np.array([0, 200]), np.array([-201]), np.ones(199, dtype=bool),
                                   np.array([0.0, 1.0])])
def test_rows_raises_what_numpy_raises(index):
    a = np.zeros((200, 3))
    with pytest.raises(IndexError):
        a[index]
    with pytest.raises(IndexError):
        rows(a, index)


@pytest.mark.parametrize("n", [0, 5, 999, 1000, 5000])
@pytest.mark.parametrize("layout", ["C", "F", "strided"])
def test_minus_is_numpy_s_subtraction(n, layout):
    from kbs.arrays import minus

    rng = np.random.default_rng(n)
    base = rng.normal(size=(n, 3)) * 1e3
    a = {"C": base, "F": np.asfortranarray(base), "strided": np.repeat(base, 2, axis=1)[:, ::2]}[layout]
    v = rng.normal(size=3)
    want, got = a - v, minus(a, v)
    assert got.shape == want.shape and got.dtype == want.dtype
    assert np.array_equal(got, want)  # the same floats, bit for bit
    assert np.array_equal(minus(a.astype(np.float32), v), a.astype(np.float32) - v)  # other types: numpy's own


@pytest.mark.parametrize("bad", [[], [(3, 0)], [(0, 2), (4000, 1)], [(n, 0) for n in range(0, 5000, 7)]])
def test_finite_rows_is_numpy_s(bad):
    from kbs.arrays import finite_rows

    a = np.random.default_rng(2).normal(size=(5000, 3))
    for row, col in bad:
        a[row, col] = np.nan if row % 2 else np.inf
    assert np.array_equal(finite_rows(a), np.isfinite(a).all(axis=1))
    assert finite_rows(a).dtype == bool
