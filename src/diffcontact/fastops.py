"""Tensor operations cheap enough for the per-step hot paths.

Two patterns that torch 2.13 runs far below the hardware's speed on the CPU, and their
replacements (``python benchmarks/run.py fastops`` times each pair):

- sums over a short last dimension: ``torch.sum(x, -1)`` over 2 or 3 numbers runs a
  cascade sum per row, about 13 ns per row (270 us for 1024 x 10 contact vectors in
  float64); a product with a vector of ones computes the same sums in a tenth of the
  time (:func:`sum_last`, :func:`dot_last`). For two numbers the result is bitwise the
  same (one addition); for three or more the order of the additions may differ.
- an unbatched matrix applied to a batch, ``G @ X`` with ``G: (R, P)`` and
  ``X: (..., P, k)``: broadcasting runs one tiny product per batch element;
  :func:`left_matmul` runs one matrix product over the whole batch (on BD5's mass matrix
  times constraint rows, 200 x 15 x 15 x 2 in float64: 3.6x faster forward, 1.4x forward
  + backward).

And two linear solves that a CUDA graph can capture (``System.simulate(cuda_graph=...)``):
torch runs a batched ``cholesky_solve`` on CUDA through MAGMA, which fails inside a capture
("operation not permitted when stream is capturing"), and ``torch.linalg.solve`` reads the
device to check for singular matrices. :func:`cholesky_solve` runs two batched triangular
solves (cuBLAS) there instead; :func:`spd_solve` factorises without a check.

And one workaround: :func:`lu_factor_ex` factorises a CPU batch of large matrices on one
thread, where torch 2.13's multi-threaded LU returned wrong factors.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from diffcontact.shapes import broadcast_shapes

# above this many numbers per row torch's own sum is as fast
_SHORT = 8
# a product's backward pass (an outer product) costs more than a sum's (a broadcast): below
# this many numbers the gain of the forward pass does not pay for it
_SMALL_GRAD = 1 << 12
# left_matmul: from this many numbers in X one product over the whole batch pays off
_MANY = 1 << 14
# times_matrix: from this size a diagonal matrix is worth checking for
_DIAGONAL_MIN = 64
# spd_solve on the CPU: systems of at most this size, in batches of at least this many
# (twice as many without a gradient), are solved by the written-out factorisation; below,
# LAPACK's per-matrix calls cost less than its few dozen operations. LAPACK's time over the
# written-out one's for 3 x 3 systems (`python benchmarks/run.py fastops`, float64, one
# thread): forward 0.4x at 256 systems, 0.7x at 512, 1.1x at 1000, 1.8x at 2000; forward and
# backward 1.2x, 2.0x, 2.5x, 3.6x
_UNROLL = 3
_UNROLL_BATCH = 512


@functools.lru_cache(maxsize=64)
def _ones(size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    with torch.inference_mode(False):  # usable in autograd even if first made in inference
        return torch.ones(size, dtype=dtype, device=device)


def sum_last(x: Tensor) -> Tensor:
    """``x.sum(-1)``: ``(..., m) -> (...)``, differentiable; fast for small ``m``."""
    m = x.shape[-1]
    if m > _SHORT or m == 0 or not x.is_floating_point() or x.dim() < 2:
        return x.sum(-1)
    if x.requires_grad and x.numel() < _SMALL_GRAD:
        return x.sum(-1)
    return x @ _ones(m, x.dtype, x.device)


def dot_last(a: Tensor, b: Tensor) -> Tensor:
    """``(a * b).sum(-1)`` with broadcasting: ``(..., m), (..., m) -> (...)``."""
    return sum_last(a * b)


def left_matmul(G: Tensor, X: Tensor) -> Tensor:
    """``G @ X`` for ``G: (R, P)`` (or batched ``(..., R, P)``) and ``X: (..., P, k)``.

    An unbatched ``G`` applied to a large ``X`` (at least 16384 numbers) is one matrix
    product over the whole batch (``einsum``); otherwise ``@`` (broadcast, where fewer
    tiny products cost less than the einsum's reshapes). Differentiable in both.
    """
    if G.dim() == 2 and X.dim() > 2 and X.numel() >= _MANY:
        return torch.einsum("rp,...pk->...rk", G, X)
    return G @ X


def times_matrix(X: Tensor, M: Tensor) -> Tensor:
    """``X @ M`` for ``X: (..., r, D)`` and ``M: (..., D, D)``, one product where ``M`` is one
    matrix broadcast over a batch (:func:`shared`).

    On the CPU, where that one matrix is large (``D >= 64``), needs no gradient and is
    diagonal (checked: the constrained inverse inertia of point masses without equality
    constraints, a rope's), ``X`` times its diagonal instead: ``D`` times fewer operations
    (a 200-point rope's ``(n K d, 400) @ (400, 400)`` product took a fifth of its
    read-free step at 48823df: ``python benchmarks/run.py profile_step --tasks Rope-D400
    --scenes 128 --steps 3``). Elsewhere (and on CUDA, where the check would read the
    device) the product."""
    M = shared(M)
    if (
        M.dim() == 2
        and M.shape[-1] >= _DIAGONAL_MIN
        and M.device.type == "cpu"
        and not (M.requires_grad and torch.is_grad_enabled())
    ):
        diagonal = M.diagonal()
        if torch.equal(M, torch.diag(diagonal)):
            return X * diagonal
    return X @ M


def shared(T: Tensor) -> Tensor:
    """``T: (..., m, k)`` without its broadcast leading dimensions: where ``T`` is one
    ``(m, k)`` matrix expanded over a batch (stride 0), that matrix, so that ``X @ T`` is
    one matrix product instead of a batch of tiny ones; else ``T`` itself."""
    if T.dim() > 2 and all(s == 0 for s in T.stride()[:-2]):
        return T[(0,) * (T.dim() - 2)]
    return T


# torch 2.13's CPU LU factorisation (oneMKL) returns garbage for a batch of two or more
# matrices of about 150 rows or more when torch runs on several threads: pivots of 0 and
# "Intel oneMKL ERROR: Parameter 6 was incorrect on entry to DLASWP", and wrong factors
# (found 2026-11-27 with the torch reference solver's polish of 193-row rope projection
# problems; every batch of 3 random 193 x 193 matrices on 2 threads, none on 1). From this
# size lu_factor_ex() factorises on one thread.
_LU_ONE_THREAD_FROM = 128


def lu_factor_ex(M: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """``torch.linalg.lu_factor_ex(M)`` (``LU, pivots, info``) for ``M: (..., n, n)``; a CPU
    batch of large matrices is factorised on one torch thread (:data:`_LU_ONE_THREAD_FROM`:
    the multi-threaded path of torch 2.13's LAPACK returned wrong factors there)."""
    threads = torch.get_num_threads()
    if (
        M.device.type == "cpu"
        and threads > 1
        and M.shape[-1] >= _LU_ONE_THREAD_FROM
        and math.prod(M.shape[:-2]) > 1
    ):
        torch.set_num_threads(1)
        try:
            return torch.linalg.lu_factor_ex(M)
        finally:
            torch.set_num_threads(threads)
    return torch.linalg.lu_factor_ex(M)


def cholesky_solve(B: Tensor, L: Tensor) -> Tensor:
    """``torch.cholesky_solve(B, L)``: ``X`` with ``L L^T X = B`` for lower-triangular ``L:
    (..., n, n)`` and ``B: (..., n, k)``. On CUDA two batched triangular solves (which a CUDA
    graph can capture; torch's own goes through MAGMA there), elsewhere LAPACK's.
    Differentiable."""
    if L.device.type != "cuda":
        return torch.cholesky_solve(B, L)
    Y = torch.linalg.solve_triangular(L, B, upper=False)
    return torch.linalg.solve_triangular(L.mT, Y, upper=True)


def spd_solve(A: Tensor, B: Tensor) -> Tensor:
    """Solve ``A X = B`` for symmetric positive definite ``A: (..., n, n)``, ``B: (..., n, k)``
    (batch dimensions broadcast), by a Cholesky factorisation.

    A batch element whose ``A`` is not positive definite (e.g. a constraint system that
    became singular: the state left its constraint manifold) gets NaN, without a host
    synchronisation (``torch.linalg.solve`` reads the device to raise instead);
    ``System.simulate`` reports non-finite states by index at the end. Differentiable."""
    batch = broadcast_shapes(A.shape[:-2], B.shape[:-2])
    n = A.shape[-1]
    grad = torch.is_grad_enabled() and (A.requires_grad or B.requires_grad)
    least = _UNROLL_BATCH if grad else 2 * _UNROLL_BATCH
    if A.device.type == "cpu" and 0 < n <= _UNROLL and math.prod(batch) >= least:
        return _unrolled_spd_solve(A.expand(*batch, n, n), B.expand(*batch, *B.shape[-2:]))
    L, info = torch.linalg.cholesky_ex(A.expand(*batch, *A.shape[-2:]))
    X = cholesky_solve(B.expand(*batch, *B.shape[-2:]), L)
    return torch.where((info > 0)[..., None, None], torch.nan, X)


def _unrolled_spd_solve(A: Tensor, B: Tensor) -> Tensor:
    """:func:`spd_solve` for ``n <= 3``, the Cholesky factorisation and the two triangular
    solves written out entry by entry: a few dozen operations on ``(...)``-shaped entries
    whatever the batch, where LAPACK makes one call per matrix (1000 bodies' 3 x 3
    constraint systems of BD5, 200 states x 5 bodies; ``python benchmarks/run.py fastops``).
    NaN where a pivot is not positive, as LAPACK's. ``A: (..., n, n)`` (its lower triangle is
    read), ``B: (..., n, k)`` with the same batch shape. The backward pass is one more solve
    with the same factor, ``grad_B = A^-1 grad_X`` and ``grad_A = -sym(grad_B X^T)``
    (symmetric, as the LAPACK path's; a custom function: two nodes instead of the sixty of
    the written-out operations), itself differentiable (``create_graph``)."""
    return _SmallSPDSolve.apply(A, B)


def _factor(A: Tensor) -> tuple[list[list[Tensor]], Tensor]:
    """The Cholesky factor of ``A: (..., n, n)`` as entries ``L[i][j]`` (``j <= i``), each
    ``(..., 1)``, and ``(...)``: 0 where every pivot is positive, NaN elsewhere."""
    n = A.shape[-1]
    a = A.flatten(-2).unbind(-1)  # the entries (...), row-major
    L: list[list[Tensor]] = [[] for _ in range(n)]
    pivots = []
    for j in range(n):
        d = a[j * n + j]
        for k in range(j):
            d = d - L[j][k] * L[j][k]
        pivots.append(d)
        ljj = d.sqrt()
        L[j].append(ljj)
        for i in range(j + 1, n):
            e = a[i * n + j]
            for k in range(j):
                e = e - L[i][k] * L[j][k]
            L[i].append(e / ljj)
    smallest = torch.stack(pivots, -1).amin(-1)  # NaN propagates: NaN > 0 is false
    nan = torch.where(smallest > 0, 0.0, torch.nan).to(A.dtype)
    return [[t.unsqueeze(-1) for t in row] for row in L], nan


def _substitute(L: list[list[Tensor]], B: Tensor) -> Tensor:
    """``X`` with ``L L^T X = B`` for ``B: (..., n, k)`` and the entries of :func:`_factor`."""
    n = len(L)
    b = B.unbind(-2)  # the rows (..., k)
    y: list[Tensor] = []
    for i in range(n):  # L y = B
        r = b[i]
        for k in range(i):
            r = r - L[i][k] * y[k]
        y.append(r / L[i][i])
    x: list[Tensor] = [y[0]] * n
    for i in reversed(range(n)):  # L^T x = y
        r = y[i]
        for k in range(i + 1, n):
            r = r - L[k][i] * x[k]
        x[i] = r / L[i][i]
    return torch.stack(x, -2)


class _SmallSPDSolve(torch.autograd.Function):
    """``X = A^-1 B`` by :func:`_factor` and :func:`_substitute`, implicit backward pass."""

    @staticmethod
    def forward(ctx, A: Tensor, B: Tensor) -> Tensor:
        L, nan = _factor(A)
        X = _substitute(L, B) + nan[..., None, None]
        ctx.factor = L
        ctx.save_for_backward(A, X)
        return X

    @staticmethod
    def backward(ctx, grad_X: Tensor) -> tuple[Tensor, Tensor]:
        A, X = ctx.saved_tensors
        if torch.is_grad_enabled():  # create_graph: a backward pass that is differentiable
            grad_B = _SmallSPDSolve.apply(A, grad_X)
        else:  # the kept factor
            grad_B = _substitute(ctx.factor, grad_X)
        grad_A = grad_B @ X.mT
        return -0.5 * (grad_A + grad_A.mT), grad_B  # symmetric, as LAPACK's path gives
