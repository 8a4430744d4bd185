"""The fast array helpers give exactly numpy's answers (ties, NaN, 16-bit and wide keys)."""

import numpy as np

from omnid.core.arrays import median, quartiles, stable_argsort


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
