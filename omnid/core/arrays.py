"""Array helpers of the per-frame code: faster equivalents of numpy calls that are slow on the
~10³-element arrays of one frame (same results)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def stable_argsort(keys: NDArray) -> NDArray[np.intp]:
    """``np.argsort(keys, kind="stable")`` of a 1-D array, faster: numpy's stable sort of 32-
    and 64-bit keys (a merge sort) is ~5x slower than its quicksort on ~10³ shuffled keys,
    which gives the same order when no two keys tie (ties, rare for real-valued keys, take the
    stable sort); integer keys that fit 16 bits take its radix sort (~15x faster)."""
    n = len(keys)
    if n < 2:
        return np.arange(n, dtype=np.intp)
    if keys.dtype.kind in "iu" and int(keys.min()) >= 0 and int(keys.max()) < 1 << 16:
        return np.argsort(keys.astype(np.uint16), kind="stable").astype(np.intp, copy=False)
    order = np.argsort(keys)
    srt = keys[order]
    tie = bool(np.any(srt[1:] == srt[:-1])) or (srt.dtype.kind == "f" and bool(np.isnan(srt[-1])))
    if tie:
        order = np.argsort(keys, kind="stable")
    return order.astype(np.intp, copy=False)


def median(x: NDArray) -> float:
    """``np.median`` of a non-empty 1-D array, by partition (a few times faster on ~10³)."""
    n = len(x)
    lo, hi = (n - 1) // 2, n // 2
    q = np.partition(x, hi)
    return 0.5 * (float(q[:hi].max() if lo < hi else q[hi]) + float(q[hi]))


#: :func:`kth_smallest` selects from a bracket of this many samples' ranks either side (of
#: its ~256 samples) around the rank sought.
_BRACKET_SAMPLES = 8


def kth_smallest(x: NDArray, k: int) -> NDArray:
    """The value of rank ``k`` of a non-empty 1-D array, exactly ``np.partition(x, k)[k]``,
    ~3x faster on ~10⁴ values (see :func:`_bracketed`)."""
    value = _bracketed(x, k)
    return np.partition(x, k)[k] if value is None else value


def _bracketed(x: NDArray, k: int) -> NDArray | None:
    """The value of rank ``k`` of ``x`` from the values in a bracket [lo, hi] read off a sorted
    sample of ~256 of them, when the counts below and within say it holds that rank (only
    the few per cent within are partitioned); None when not, for a zero (whose sign the
    partition chooses) and for short arrays."""
    n = len(x)
    if n < 2048:
        return None
    sample = np.sort(x[:: n // 256])
    at = (k * len(sample)) // n
    lo = sample[max(at - _BRACKET_SAMPLES, 0)]
    hi = sample[min(at + _BRACKET_SAMPLES, len(sample) - 1)]
    below = int(np.count_nonzero(x < lo))
    within = np.flatnonzero((x >= lo) & (x <= hi))
    if not below <= k < below + len(within):
        return None
    value = np.partition(np.take(x, within), k - below)[k - below]
    return None if value == 0 else value


def quartiles(x: NDArray) -> NDArray:
    """The values of rank ``len(x) // 4`` and ``len(x) // 2`` of a non-empty 1-D array, in its
    dtype (what ``np.partition(x, (k25, k50))`` puts there, ~6x faster: numpy's partition at
    two ranks at once is slow; on ~10⁴ values each from a bracket, :func:`_bracketed`)."""
    k25, k50 = len(x) // 4, len(x) // 2
    low, mid = _bracketed(x, k25), _bracketed(x, k50)
    if low is None or mid is None:
        q = np.partition(x, k50)
        low = np.partition(q[:k50], k25)[k25] if k25 < k50 else q[k25]
        mid = q[k50]
    return np.array([low, mid], dtype=x.dtype)


def clip(x: NDArray, lo: float, hi: float) -> NDArray:
    """``np.clip(x, lo, hi)`` for ``lo <= hi`` as two ufuncs, without np.clip's Python layers
    (~4 us a call: it is called ~20 times a frame on small arrays)."""
    return np.minimum(np.maximum(x, lo), hi)
