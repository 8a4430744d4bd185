"""A slow, direct, loop-by-loop transcription of the thesis's dot detector (chapter 5).

It follows the text step by step with plain Python loops over pixels and windows, and shares
no code with ``omnid.core.detect`` (ring membership is recomputed here from the rule "city-block
distance from the window centre"), so the vectorised detector can be checked against it. Like
the vectorised one it holds the smoothed image as 3x3 sums and writes each test on integer
sums with the same formula, so both give bit-identical decisions.

Input: 2-D integer gray images (lists or arrays). Output: list of (row, col, strength).
"""

from __future__ import annotations

import numpy as np


def oracle_detect(mask, base, *, block_px, block_coefficient, min_peak_gray, e1, e2, e3, e4):
    m = np.asarray(mask).astype(int).tolist()
    b = np.asarray(base).astype(int).tolist()
    h, w = len(m), len(m[0])

    # 5.1: subtracted = base - mask, negatives set to 0.
    sub = [[max(b[r][c] - m[r][c], 0) for c in range(w)] for r in range(h)]

    # 5.1: 3x3 mean smoothing (kept as the 3x3 sum; outside the image counts as 0).
    s9 = [[0] * w for _ in range(h)]
    for r in range(h):
        for c in range(w):
            total = 0
            for rr in range(r - 1, r + 2):
                for cc in range(c - 1, c + 2):
                    if 0 <= rr < h and 0 <= cc < w:
                        total += sub[rr][cc]
            s9[r][c] = total

    # 5.1: 21x21 window stepped by 21 px; below coefficient * window mean -> 0.
    enh = [row[:] for row in s9]
    for r0 in range(0, h, block_px):
        for c0 in range(0, w, block_px):
            rows = range(r0, min(r0 + block_px, h))
            cols = range(c0, min(c0 + block_px, w))
            tile_sum = 0
            n = 0
            for r in rows:
                for c in cols:
                    tile_sum += s9[r][c]
                    n += 1
            threshold = block_coefficient * float(tile_sum)
            for r in rows:
                for c in cols:
                    if not float(s9[r][c] * n) >= threshold:
                        enh[r][c] = 0

    # 5.3: circular neighbourhoods of the 8x8 window, by city-block distance from (3.5, 3.5).
    rings = {1: [], 2: [], 3: [], 4: []}
    for i in range(8):
        for j in range(8):
            d = abs(i - 3.5) + abs(j - 3.5)
            if d in (1.0, 2.0, 3.0, 4.0):
                rings[int(d)].append((i, j))
    assert [len(rings[k]) for k in (1, 2, 3, 4)] == [4, 8, 12, 16]

    # 5.4: scan the 8x8 window by 1 px (top-left origin (r0, c0)); the 12x12 square (window
    # grown by 2 px on every side) must lie in the image.
    found = []
    for r0 in range(2, h - 8 - 2 + 1):
        for c0 in range(2, w - 8 - 2 + 1):
            # brightest pixel of the window: the first maximum in row-major scan order
            best = -1
            best_at = None
            for i in range(8):
                for j in range(8):
                    v = enh[r0 + i][c0 + j]
                    if v > best:
                        best = v
                        best_at = (i, j)
            if best_at != (3, 3):
                continue
            if not best > 9.0 * min_peak_gray:
                continue
            avg = {}
            for k in (1, 2, 3, 4):
                total = 0
                for i, j in rings[k]:
                    total += enh[r0 + i][c0 + j]
                avg[k] = total / float(len(rings[k]))
            a4, a8, a12, a16 = avg[1], avg[2], avg[3], avg[4]
            if not (a12 - a16) / 9.0 >= e1:
                continue
            if not (a8 - a12) / 9.0 >= e2:
                continue
            if not (a4 - a8) / 9.0 >= e3:
                continue
            sq_total = 0
            for i in range(-2, 10):
                for j in range(-2, 10):
                    sq_total += enh[r0 + i][c0 + j]
            square_avg = sq_total / 144.0
            circular_avg = (a4 + a8 + a12 + a16) / 4.0
            if not (circular_avg - square_avg) / 9.0 >= e4:
                continue
            found.append((r0 + 3, c0 + 3, enh[r0 + 3][c0 + 3] / 9.0))
    return found
