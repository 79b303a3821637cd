"""numba kernel of :meth:`riskflow_env.maps.DrivableMap.crop` for float32 queries (the
learned policies' map crops, every agent every planning cycle).

It repeats :func:`~riskflow_env.maps.sampling.crop_points` and
:func:`~riskflow_env.maps.sampling.interpolate_flat` point by point in float32, op for op
as numpy evaluates them (Python floats taken as float32, NEP 50), so it gives numpy's
values bit for bit; the cosines and sines come from numpy (its float32 ``cos`` is not the C
library's). The numpy functions stay the reference and the path of every other query.
"""

from __future__ import annotations

import math

import numba
import numpy as np

_jit = numba.njit(cache=True, nogil=True)


@_jit
def crop(table, origin_x, origin_y, resolution, extend, xy, cos, sin, offsets, out):
    """``out`` (N, S, S) float32: the raster ``table`` (H, W) float32 sampled bilinearly at
    the crop points of agents ``xy`` (N, 2) with headings' ``cos``, ``sin`` (N,) and pixel
    ``offsets`` (S,) [m] (all float32); ``extend`` as ``interpolate_flat``'s."""
    height, width = table.shape
    ox, oy, res = np.float32(origin_x), np.float32(origin_y), np.float32(resolution)
    half, one, zero = np.float32(0.5), np.float32(1.0), np.float32(0.0)
    last_col, last_row = np.float32(width - 1), np.float32(height - 1)
    for n in range(xy.shape[0]):
        c, s = cos[n], sin[n]
        for r in range(offsets.shape[0]):
            left = offsets[r]
            for k in range(offsets.shape[0]):
                forward = offsets[k]
                x = xy[n, 0] + forward * c - left * s
                y = xy[n, 1] + forward * s + left * c
                col = (x - ox) / res - half
                row = (y - oy) / res - half
                col_c = min(max(col, zero), last_col)
                row_c = min(max(row, zero), last_row)
                col0 = max(min(int(col_c), width - 2), 0)
                row0 = max(min(int(row_c), height - 2), 0)
                fc = col_c - np.float32(col0)
                fr = row_c - np.float32(row0)
                gc, gr = one - fc, one - fr
                top = table[row0, col0] * gc + table[row0, col0 + 1] * fc
                bottom = table[row0 + 1, col0] * gc + table[row0 + 1, col0 + 1] * fc
                value = top * gr + bottom * fr
                if extend:
                    off_c, off_r = col - col_c, row - row_c
                    distance = np.float32(math.sqrt(off_c * off_c + off_r * off_r))
                    value = value + (distance if value > zero else zero) * res
                out[n, r, k] = value
