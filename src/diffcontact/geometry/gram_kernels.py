"""Warp kernels of :func:`diffcontact.geometry.sparse_gram.sparse_gram`: the Gram matrix
``J J^T`` of Jacobian rows given as sparse entries, and its backward pass.

Row ``i`` of problem ``s`` has ``m`` entries: point ``points[s, i, a]`` and value
``values[s, i, a, :]`` (``dim`` numbers); entries of one row may repeat a point (they add
up) and unused entries have zero values. Then

    (J J^T)[s, i, j] = sum_a sum_b [points[s, i, a] == points[s, j, b]]
                       values[s, i, a, :] . values[s, j, b, :]

which needs no dense ``(R, P dim)`` rows. Two rows whose entries' point ranges
(:func:`row_ranges`) do not overlap share no point and are skipped after two
comparisons; a rope limit's row spans two or three adjacent points (its padded entries
repeat one of them, ``base._cat_rows``), so most pairs are. One thread per row ``(s, i)``,
forward and backward (a CPU launch calls the kernel once per thread: per entry of ``A``,
those calls cost more than the arithmetic); the forward thread computes ``j >= i`` and
writes both halves, so the result is exactly symmetric.

This module imports Warp at import time, and is a Warp module of its own: adding to it
does not change (and so does not recompile) the solver's kernels of
:mod:`diffcontact.contact.warp_kernels`.
"""

from __future__ import annotations

from typing import Any

import warp as wp

# forward only: the backward pass is the kernel below
wp.set_module_options({"enable_backward": False})


@wp.kernel
def row_ranges(
    points: wp.array3d(dtype=wp.int64),
    lo: wp.array2d(dtype=wp.int64),
    hi: wp.array2d(dtype=wp.int64),
):
    """The least and the largest point of row ``(s, i)``'s entries; threads ``(s, i)``."""
    s, i = wp.tid()
    m = points.shape[2]
    first = points[s, i, 0]
    last = first
    for a in range(1, m):
        p = points[s, i, a]
        first = wp.min(first, p)
        last = wp.max(last, p)
    lo[s, i] = first
    hi[s, i] = last


@wp.kernel
def gram(
    points: wp.array3d(dtype=wp.int64),
    values: wp.array4d(dtype=Any),
    lo: wp.array2d(dtype=wp.int64),
    hi: wp.array2d(dtype=wp.int64),
    out: wp.array3d(dtype=Any),
):
    """``out[s, i, j] = out[s, j, i] = (J J^T)[s, i, j]`` for ``j >= i``; threads ``(s, i)``.
    Pairs of rows whose point ranges (:func:`row_ranges`) do not overlap are skipped:
    ``out`` is zero on entry."""
    s, i = wp.tid()
    R = points.shape[1]
    m = points.shape[2]
    dim = values.shape[3]
    lo_i = lo[s, i]
    hi_i = hi[s, i]
    zero = type(values[s, i, 0, 0])(0.0)
    for j in range(i, R):
        if lo[s, j] <= hi_i and lo_i <= hi[s, j]:
            acc = zero
            for a in range(m):
                p = points[s, i, a]
                for b in range(m):
                    if points[s, j, b] == p:
                        for c in range(dim):
                            acc += values[s, i, a, c] * values[s, j, b, c]
            out[s, i, j] = acc
            out[s, j, i] = acc


@wp.kernel
def gram_backward(
    points: wp.array3d(dtype=wp.int64),
    values: wp.array4d(dtype=Any),
    lo: wp.array2d(dtype=wp.int64),
    hi: wp.array2d(dtype=wp.int64),
    grad_out: wp.array3d(dtype=Any),
    grad_values: wp.array4d(dtype=Any),
):
    """``grad_values[s, i, a, :] = sum_j (G[s, i, j] + G[s, j, i]) sum_b [points[s, i, a] ==
    points[s, j, b]] values[s, j, b, :]`` (``G = grad_out``; ``grad_values`` zero on entry);
    threads ``(s, i)``, rows ``j`` as in :func:`gram`."""
    s, i = wp.tid()
    R = points.shape[1]
    m = points.shape[2]
    dim = values.shape[3]
    lo_i = lo[s, i]
    hi_i = hi[s, i]
    for j in range(R):
        if lo[s, j] <= hi_i and lo_i <= hi[s, j]:
            g = grad_out[s, i, j] + grad_out[s, j, i]
            for a in range(m):
                p = points[s, i, a]
                for b in range(m):
                    if points[s, j, b] == p:
                        for c in range(dim):
                            grad_values[s, i, a, c] += g * values[s, j, b, c]
