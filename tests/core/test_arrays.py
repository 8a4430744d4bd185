"""The fast array helpers give exactly numpy's answers (ties, NaN, 16-bit and wide keys)."""

import numpy as np

from omnid.core.arrays import kth_smallest, median, quartiles, stable_argsort


def test_stable_argsort_is_numpys_stable_order() -> None:
    rng = np.random.default_rng(5)
    for n in (0, 1, 2, 7, 300, 3000):
        cases = [
            rng.integers(0, 50, n),  # 16-bit, many ties
            rng.integers(0, 1 << 40, n),  # wide, no ties
            rng.integers(-5, 5, n),  # negative: not the radix path
            rng.random(n),
            np.round(rng.random(n), 2),  # real-valued with ties
            np.where(rng.random(n) < 0.1, np.nan, rng.random(n)),
        ]
        for keys in cases:
            want = np.argsort(keys, kind="stable")
            got = stable_argsort(keys)
            assert got.dtype == np.intp and np.array_equal(got, want)


def test_median_and_quartiles_are_numpys() -> None:
    rng = np.random.default_rng(6)
    for n in (1, 2, 3, 4, 10, 11, 999):
        for x in (rng.standard_normal(n), np.round(rng.standard_normal(n)).astype(np.float32)):
            assert median(x) == float(np.median(x))
            q = np.partition(x, (n // 4, n // 2))
            assert np.array_equal(quartiles(x), q[[n // 4, n // 2]])


def test_kth_smallest_and_long_quartiles_are_numpys_values() -> None:
    """Above 2048 values the rank is selected from a bracket; the value is numpy's to the bit
    (ties, NaN, signed zeros, sorted input)."""
    rng = np.random.default_rng(7)
    for n in (2047, 2048, 5411, 8639, 20000):
        x32 = rng.standard_normal(n).astype(np.float32)
        nan = x32.copy()
        nan[rng.random(n) < 0.05] = np.nan
        cases = [
            x32,
            rng.integers(-5, 5, n).astype(np.float32),  # ties
            rng.integers(-3, 3, n) * np.float32(0.0),  # only +0 and -0
            np.sort(x32),
            nan,
            rng.exponential(size=n),
        ]
        for x in cases:
            for k in (0, n // 4, n // 2, n - 1, int(rng.integers(0, n))):
                want = np.partition(x, k)[k]
                got = kth_smallest(x, k)
                assert got.dtype == x.dtype
                assert np.array_equal(want, got, equal_nan=True)
                assert np.signbit(want) == np.signbit(got)
            q = np.partition(x, n // 2)
            want_q = [np.partition(q[: n // 2], n // 4)[n // 4], q[n // 2]]
            got_q = quartiles(x)
            assert np.array_equal(got_q, np.array(want_q, x.dtype), equal_nan=True)
            assert np.array_equal(np.signbit(got_q), np.signbit(want_q))
