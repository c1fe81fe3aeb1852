"""Warp kernel of the fused friction-cone QP solver: one thread per problem.

The thread runs, for its problem, the same algorithm as the reference solver:

1. the primal-dual interior point of :func:`diffcontact.contact.interior_point.
   interior_point_solve` (initial point, Nesterov-Todd scaling, Mehrotra
   predictor-corrector with the ``plain_only`` fallback, the stopping tests
   ``solved / diverged / stalled / stuck``, padded contacts held at ``f = 0``);
2. the natural-map Newton polish of :func:`diffcontact.contact.cone_qp._polish`
   (backtracking line search on the residual; where the Jacobian is nearly singular the
   step with its component along the null space of ``A`` removed is tried first);
3. the natural map, the projection's derivatives and the factorisation of ``dF/df`` at
   the final point, which the implicit backward pass reuses.

The Newton systems are solved reduced (:func:`_reduced_factor`): in per-contact bases of
the range and null space of ``dPi/dz``, ``dF/df`` is block triangular with an identity
block, so only the range block is factorised (LU in LAPACK's ``getrf`` layout: packed
``L \\ U`` and 1-based row interchanges; for ``d <= 2`` the block is symmetric positive
definite and gets a Cholesky factorisation instead). Separating and padded contacts drop
out, and for ``d <= 2`` so does the normal of each sliding contact's ray. The test-only
kernels (``fused_solve``, ``fused_polish``) still return the full LU factorisation, for
the reference's backward.

Dense linear algebra (Cholesky, LU with partial pivoting, and for the null space of ``A``
a pivoted Cholesky factorisation with Gram-Schmidt in place of the reference's
eigendecomposition, twenty to fifty times cheaper per thread) runs in per-thread scratch
arrays. The Cholesky factorisation and its triangular solves are written in C++
(``wp.func_native``, one overload per float type) over raw pointers: Warp's own indexing
checks every index for a negative value, which made them up to 5x slower. Every array is
generic in its float type (float32 or float64); scalars of that type are passed typed.
Contact blocks are handled as 3-vectors padded with zeros (exact for ``d = 2``: the padded
components stay zero), so one kernel serves ``d = 1, 2, 3``.

Shapes (``n`` threads, ``B`` problems in the inputs, ``K`` contacts, ``C = K d``): inputs
are indexed by ``rows[t]``, outputs and scratch by the thread ``t``. The scratch arrays
may be strided (on CUDA the thread index is the fastest-varying one, so that the threads
of a warp read adjacent words).

This module imports Warp at import time; :mod:`diffcontact.contact.fused` imports it
lazily, on the first solve that uses the Warp backend.
"""

from __future__ import annotations

from typing import Any

import warp as wp

# forward only: gradients come from the implicit backward pass in torch (this also
# halves the compile time)
wp.set_module_options({"enable_backward": False})

# rows of the vector scratch ``vec`` (n, N_SLOTS, C); contact-indexed quantities use the
# first K entries of their row, per-contact d x d blocks use d rows (row i of block k at
# index k d + j)
F_ = wp.constant(0)  # iterate f (scaled in the interior point, then unscaled)
SL = wp.constant(1)  # orthant slack s_l (K)
ZL = wp.constant(2)  # orthant dual z_l (K)
SQ = wp.constant(3)  # cone slack s_q (C)
ZQ = wp.constant(4)  # cone dual z_q (C)
RX = wp.constant(5)  # dual residual r_x (C)
RZL = wp.constant(6)  # primal residual, orthant (K)
RZQ = wp.constant(7)  # primal residual, cone (C)
WL = wp.constant(8)  # orthant scaling w_l (K)
LAML = wp.constant(9)  # orthant scaled point lambda_l (K)
LAMQ = wp.constant(10)  # cone scaled point lambda_q (C)
W0 = wp.constant(11)  # NT scaling W, 3 rows
WI0 = wp.constant(14)  # W^-1, 3 rows
WII0 = wp.constant(17)  # W^-2, 3 rows
R3L = wp.constant(20)  # right-hand side r3 (orthant, K), then the plain one
R3Q = wp.constant(21)  # right-hand side r3 (cone, C)
R3LC = wp.constant(22)  # corrected r3 (Mehrotra)
R3QC = wp.constant(23)
DIR_A = wp.constant(24)  # direction (df, dsl, dsq, dzl, dzq): predictor, then plain
DIR_B = wp.constant(29)  # direction: Mehrotra
# polish (reuses the interior point's rows from 1 on)
FN = wp.constant(1)  # trial point
RES = wp.constant(2)  # natural map F at f
RESN = wp.constant(3)  # F at the trial point
DMU = wp.constant(4)  # dPi/dmu at f
DMUN = wp.constant(5)
DL = wp.constant(6)  # dPi/dl at f
DLN = wp.constant(7)
P0 = wp.constant(8)  # dPi/dz at f, 3 rows
PN0 = wp.constant(11)  # dPi/dz at the trial point, 3 rows
DELTA = wp.constant(14)  # Newton step
DFLAT = wp.constant(15)  # Newton step without its null-space component
RHS = wp.constant(16)  # the reduced Newton system's right-hand side, then solution
QU0 = wp.constant(17)  # per contact: the bases Q of the reduced Newton system (u0, K)
QU1 = wp.constant(18)  # (u1, K)
DK = wp.constant(19)  # per contact: how many leading columns of Q are in the system (K)
PF0 = wp.constant(21)  # dPi/dz of the reduced factorisation in M, 3 rows
AF = wp.constant(24)  # A f of the natural map's point (the interior point's DIR_A row)
N_SLOTS = 34

# constants that are not exact in float32, typed float64 (Warp before 1.10 emits float
# literals in kernels as float32); ``type(x)(C)`` rounds them to the kernel's type
STEP_BACK = wp.constant(wp.float64(0.99))  # fraction of the largest step taken
JITTER = wp.constant(wp.float64(1e-12))  # relative diagonal jitter of a failed Cholesky
FLAT = wp.constant(wp.float64(1e-6))  # |U_jj| below which dF/df counts as singular
# the shift, relative to max |A_ij|, that A's active block must be positive definite with
# to count as positive semi-definite (fused.SEMIDEFINITE_TOL, which must equal it)
SEMIDEFINITE = wp.constant(wp.float64(3e-4))


# --- small helpers ---------------------------------------------------------------------


@wp.func
def _pick(cond: bool, a: Any, b: Any):
    """``a`` if ``cond`` else ``b``."""
    if cond:
        return a
    return b


@wp.func
def _load(vec: wp.array3d(dtype=Any), t: int, slot: int, k: int, d: int):
    """Block k of a vector row as a 3-vector padded with zeros."""
    i = k * d
    x0 = vec[t, slot, i]
    x1 = type(x0)(0.0)
    x2 = type(x0)(0.0)
    if d > 1:
        x1 = vec[t, slot, i + 1]
    if d > 2:
        x2 = vec[t, slot, i + 2]
    return wp.vector(x0, x1, x2)


@wp.func
def _store(vec: wp.array3d(dtype=Any), t: int, slot: int, k: int, d: int, x: Any):
    i = k * d
    for j in range(d):
        vec[t, slot, i + j] = x[j]


@wp.func
def _load_block(vec: wp.array3d(dtype=Any), t: int, slot: int, k: int, d: int):
    """Per-contact d x d block (rows in ``slot``, ``slot + 1``, ...) as a padded 3x3."""
    r0 = _load(vec, t, slot, k, d)
    zero = type(r0[0])(0.0)
    r1 = wp.vector(zero, zero, zero)
    r2 = r1
    if d > 1:
        r1 = _load(vec, t, slot + 1, k, d)
    if d > 2:
        r2 = _load(vec, t, slot + 2, k, d)
    return wp.matrix(r0[0], r0[1], r0[2], r1[0], r1[1], r1[2], r2[0], r2[1], r2[2], shape=(3, 3))


@wp.func
def _store_block(vec: wp.array3d(dtype=Any), t: int, slot: int, k: int, d: int, M: Any):
    for i in range(d):
        for j in range(d):
            vec[t, slot + i, k * d + j] = M[i, j]


@wp.func
def _square(M: Any):
    """M M for a 3x3 matrix, summed explicitly (Warp 1.5's float64 matrix product is not
    accurate to rounding)."""
    r0 = wp.vector(M[0, 0], M[0, 1], M[0, 2])
    r1 = wp.vector(M[1, 0], M[1, 1], M[1, 2])
    r2 = wp.vector(M[2, 0], M[2, 1], M[2, 2])
    c0 = wp.vector(M[0, 0], M[1, 0], M[2, 0])
    c1 = wp.vector(M[0, 1], M[1, 1], M[2, 1])
    c2 = wp.vector(M[0, 2], M[1, 2], M[2, 2])
    return wp.matrix(
        wp.dot(r0, c0), wp.dot(r0, c1), wp.dot(r0, c2),
        wp.dot(r1, c0), wp.dot(r1, c1), wp.dot(r1, c2),
        wp.dot(r2, c0), wp.dot(r2, c1), wp.dot(r2, c2),
        shape=(3, 3),
    )  # fmt: skip


@wp.func
def _cone_G(x: Any, mu: Any):
    """Cone block of G x for one contact: -(mu x_n, x_t)."""
    return wp.vector(-(mu * x[0]), -x[1], -x[2])


@wp.func
def _cone_GT(zl: Any, zq: Any, mu: Any, d: int):
    """G^T z for one contact: -(z_l + mu z_q0, z_qt) (d > 1), -z_l (d = 1)."""
    if d == 1:
        return wp.vector(-zl, type(zl)(0.0), type(zl)(0.0))
    return wp.vector(-(zl + mu * zq[0]), -zq[1], -zq[2])


@wp.func
def _soc_det(x: Any):
    return x[0] * x[0] - (x[1] * x[1] + x[2] * x[2])


@wp.func
def _soc_prod(x: Any, y: Any):
    """Jordan product (x.y, x0 y_t + y0 x_t)."""
    return wp.vector(
        wp.dot(x, y),
        x[0] * y[1] + y[0] * x[1],
        x[0] * y[2] + y[0] * x[2],
    )


@wp.func
def _soc_div(x: Any, y: Any):
    """u with x o u = y (x inside the cone)."""
    u0 = (x[0] * y[0] - (x[1] * y[1] + x[2] * y[2])) / _soc_det(x)
    return wp.vector(u0, (y[1] - x[1] * u0) / x[0], (y[2] - x[2] * u0) / x[0])


@wp.func
def _orth_max_step(x: Any, dx: Any, inf: Any):
    if dx < type(x)(0.0):
        return -x / dx
    return inf


@wp.func
def _soc_max_step(x: Any, dx: Any, inf: Any):
    """Largest alpha with x + alpha dx in the cone (x interior), as the reference."""
    zero = type(inf)(0.0)
    c = _soc_det(x)
    bq = x[0] * dx[0] - (x[1] * dx[1] + x[2] * dx[2])
    a = _soc_det(dx)
    disc = bq * bq - a * c
    sq = wp.sqrt(wp.max(disc, zero))
    q = -(bq + _pick(bq >= zero, sq, -sq))
    r1 = q / a
    r2 = c / q
    if not (r1 > zero):
        r1 = inf
    if not (r2 > zero):
        r2 = inf
    roots = wp.min(r1, r2)
    if disc < zero:
        roots = inf
    return wp.min(roots, _orth_max_step(x[0], dx[0], inf))


# --- dense linear algebra on one thread's matrix ---------------------------------------


# The Cholesky factorisation is the one cubic cost of a Newton step (n^3 / 6 multiply-adds;
# n = 60 for 30 sticking contacts). Warp's array indexing handles negative indices with a
# branch per index, which keeps LLVM from turning the inner loop into pointer steps: about
# 2 ns per multiply-add. The same loops in C++ over raw pointers are up to 5x faster at
# n = 60, with bitwise the same result (``python benchmarks/run.py kernels``). ``strides``
# are in bytes; along a row the step is 1 element on the CPU, where the scratch arrays are
# contiguous, and larger on CUDA, where the thread index is the fastest-varying one.
_CHOLESKY_CPP = r"""
auto* a = (decltype(M.data))((char*)M.data + (long long)t * M.strides[0]);
const long long s1 = M.strides[1] / (long long)sizeof(*a);
const long long s2 = M.strides[2] / (long long)sizeof(*a);
#define DC_CHOLESKY(S2)                                                  \
    for (int j = 0; j < n; ++j) {                                        \
        auto* rj = a + j * s1;                                           \
        auto s = rj[j * (S2)];                                           \
        if (!(s > 0)) return false;                                      \
        auto ljj = wp::sqrt(s);                                          \
        rj[j * (S2)] = ljj;                                              \
        for (int i = j + 1; i < n; ++i) {                                \
            auto l = a[i * s1 + j * (S2)] / ljj;                         \
            a[i * s1 + j * (S2)] = l;                                    \
            rj[i * (S2)] = l;                                            \
        }                                                                \
        for (int i = j + 1; i < n; ++i) {                                \
            auto* ri = a + i * s1;                                       \
            const auto l = rj[i * (S2)];                                 \
            for (int k = j + 1; k <= i; ++k) ri[k * (S2)] -= l * rj[k * (S2)]; \
        }                                                                \
    }
if (s2 == 1) {
    DC_CHOLESKY(1)
} else {
    DC_CHOLESKY(s2)
}
#undef DC_CHOLESKY
return true;
"""


@wp.func_native(_CHOLESKY_CPP)
def _cholesky_cpp(M: wp.array3d(dtype=wp.float64), t: int, n: int) -> bool: ...


@wp.func_native(_CHOLESKY_CPP)
def _cholesky_cpp(M: wp.array3d(dtype=wp.float32), t: int, n: int) -> bool: ...


@wp.func
def _cholesky(M: wp.array3d(dtype=Any), t: int, n: int):
    """In-place lower Cholesky factor of M[t] (lower triangle read); False on failure.

    Right-looking (:data:`_CHOLESKY_CPP`): column j of L is finished, then subtracted from
    the trailing lower triangle. The updates are independent of each other, where the
    dot-product form's running sums make one dependency chain per entry. Each entry takes
    its subtractions in the order of j, so padded contacts (zero rows) leave it bitwise
    unchanged. The upper triangle is overwritten with L^T (a row-contiguous copy of the
    column being applied)."""
    return _cholesky_cpp(M, t, n)


_CHOLESKY_SOLVE_CPP = r"""
auto* a = (decltype(M.data))((char*)M.data + (long long)t * M.strides[0]);
const long long s1 = M.strides[1] / (long long)sizeof(*a);
const long long s2 = M.strides[2] / (long long)sizeof(*a);
auto* v = (decltype(vec.data))((char*)vec.data + (long long)t * vec.strides[0]
                                + (long long)slot * vec.strides[1]);
const long long v2 = vec.strides[2] / (long long)sizeof(*v);
#define DC_CHOLESKY_SOLVE(S2, V2)                                         \
    for (int i = 0; i < n; ++i) {                                        \
        const auto* ri = a + i * s1;                                     \
        auto s = *ri;                                                    \
        s = 0;                                                           \
        for (int k = 0; k < i; ++k) s = s + ri[k * (S2)] * v[k * (V2)];  \
        v[i * (V2)] = (v[i * (V2)] - s) / ri[i * (S2)];                  \
    }                                                                    \
    for (int i = n - 1; i >= 0; --i) {                                   \
        const auto* ri = a + i * s1;                                     \
        const auto xi = v[i * (V2)] / ri[i * (S2)];                      \
        v[i * (V2)] = xi;                                                \
        for (int k = 0; k < i; ++k) v[k * (V2)] = v[k * (V2)] - ri[k * (S2)] * xi; \
    }
if (s2 == 1 && v2 == 1) {
    DC_CHOLESKY_SOLVE(1, 1)
} else {
    DC_CHOLESKY_SOLVE(s2, v2)
}
#undef DC_CHOLESKY_SOLVE
"""


@wp.func_native(_CHOLESKY_SOLVE_CPP)
def _cholesky_solve_cpp(
    M: wp.array3d(dtype=wp.float64), t: int, n: int, vec: wp.array3d(dtype=wp.float64), slot: int
): ...


@wp.func_native(_CHOLESKY_SOLVE_CPP)
def _cholesky_solve_cpp(
    M: wp.array3d(dtype=wp.float32), t: int, n: int, vec: wp.array3d(dtype=wp.float32), slot: int
): ...


@wp.func
def _cholesky_solve(
    M: wp.array3d(dtype=Any), t: int, n: int, vec: wp.array3d(dtype=Any), slot: int
):
    """Solve L L^T x = vec[t, slot] in place (L in M[t]'s lower triangle, read by rows;
    :data:`_CHOLESKY_SOLVE_CPP`): forward substitution with each row's sum in order (as
    :func:`_dot`), then back substitution by columns."""
    _cholesky_solve_cpp(M, t, n, vec, slot)


@wp.func
def _dot(
    X: wp.array3d(dtype=Any), x0: int, x1: int, Y: wp.array3d(dtype=Any), y0: int, y1: int, n: int
):
    """Sum of X[x0, x1, k] Y[y0, y1, k] over k < n, in order. One running sum, so that the
    entries of padded contacts (zeros) leave it bitwise unchanged wherever they sit: a
    problem's result does not depend on its padding (partial sums would be faster)."""
    s = type(X[x0, x1, 0])(0.0)
    for k in range(n):
        s = s + X[x0, x1, k] * Y[y0, y1, k]
    return s


@wp.func
def _lu_factor(M: wp.array3d(dtype=Any), piv: wp.array2d(dtype=wp.int32), t: int, n: int):
    """In-place LU with partial pivoting (LAPACK getrf layout); returns min |U_jj|."""
    zero = type(M[t, 0, 0])(0.0)
    umin = wp.abs(M[t, 0, 0])
    for j in range(n):
        p = j
        amax = wp.abs(M[t, j, j])
        for i in range(j + 1, n):
            if wp.abs(M[t, i, j]) > amax:
                amax = wp.abs(M[t, i, j])
                p = i
        piv[t, j] = p + 1
        if p != j:
            for k in range(n):
                tmp = M[t, j, k]
                M[t, j, k] = M[t, p, k]
                M[t, p, k] = tmp
        ajj = M[t, j, j]
        umin = _pick(j == 0, wp.abs(ajj), wp.min(umin, wp.abs(ajj)))
        if ajj != zero:
            for i in range(j + 1, n):
                M[t, i, j] = M[t, i, j] / ajj
        for i in range(j + 1, n):
            lij = M[t, i, j]
            for k in range(j + 1, n):
                M[t, i, k] = M[t, i, k] - lij * M[t, j, k]
    return umin


@wp.func
def _lu_solve(
    M: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
    t: int,
    n: int,
    vec: wp.array3d(dtype=Any),
    slot: int,
):
    """Solve (P L U) x = vec[t, slot] in place."""
    for j in range(n):
        p = piv[t, j] - 1
        if p != j:
            tmp = vec[t, slot, j]
            vec[t, slot, j] = vec[t, slot, p]
            vec[t, slot, p] = tmp
    for i in range(n):
        s = vec[t, slot, i]
        for k in range(i):
            s = s - M[t, i, k] * vec[t, slot, k]
        vec[t, slot, i] = s
    for ii in range(n):
        i = n - 1 - ii
        s = vec[t, slot, i]
        for k in range(i + 1, n):
            s = s - M[t, i, k] * vec[t, slot, k]
        vec[t, slot, i] = s / M[t, i, i]


@wp.func
def _range_basis(
    A: wp.array3d(dtype=Any),
    r: int,
    t: int,
    n: int,
    M: wp.array3d(dtype=Any),
    perm: wp.array2d(dtype=wp.int32),
    Q: wp.array3d(dtype=Any),
    eps: Any,
):
    """Orthonormal basis of the range of A[r] (PSD) in the first columns of Q[t]; returns
    their number (the numerical rank).

    A Cholesky factorisation with diagonal pivoting, stopped where the largest remaining
    pivot is at most ``1e3 eps n max_i A_ii`` (the reference's threshold on the
    eigenvalues of ``A``, with the largest diagonal entry for the largest eigenvalue),
    gives ``A ~ L L^T`` with L of rank r; its columns are orthonormalised by Gram-Schmidt,
    twice. The null-space projector is then ``I - Q Q^T``. M[t] and perm[t] are
    overwritten."""
    zero = type(eps)(0.0)
    top = zero
    for i in range(n):
        perm[t, i] = i
        top = wp.max(top, A[r, i, i])
        for j in range(n):
            M[t, i, j] = A[r, i, j]
    threshold = type(eps)(1e3) * eps * type(eps)(n) * top
    rank = int(0)
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if M[t, i, i] > M[t, p, p]:
                p = i
        if not (M[t, p, p] > threshold):
            break
        if p != k:  # symmetric interchange of k and p
            for j in range(n):
                tmp = M[t, k, j]
                M[t, k, j] = M[t, p, j]
                M[t, p, j] = tmp
            for i in range(n):
                tmp = M[t, i, k]
                M[t, i, k] = M[t, i, p]
                M[t, i, p] = tmp
            q = perm[t, k]
            perm[t, k] = perm[t, p]
            perm[t, p] = q
        lkk = wp.sqrt(M[t, k, k])
        for i in range(k, n):
            M[t, i, k] = M[t, i, k] / lkk
        for i in range(k + 1, n):
            for j in range(k + 1, n):
                M[t, i, j] = M[t, i, j] - M[t, i, k] * M[t, j, k]
        rank += 1
    for k in range(rank):
        for i in range(n):
            Q[t, i, k] = zero
        for i in range(k, n):
            Q[t, perm[t, i], k] = M[t, i, k]
        for _pass in range(2):
            for j in range(k):
                dot = zero
                for i in range(n):
                    dot = dot + Q[t, i, j] * Q[t, i, k]
                for i in range(n):
                    Q[t, i, k] = Q[t, i, k] - dot * Q[t, i, j]
        norm = zero
        for i in range(n):
            norm = norm + Q[t, i, k] * Q[t, i, k]
        norm = wp.sqrt(norm)
        for i in range(n):
            Q[t, i, k] = Q[t, i, k] / norm
    return rank


# --- the interior point ----------------------------------------------------------------


@wp.func
def _nt_scaling(vec: wp.array3d(dtype=Any), t: int, k: int, d: int, tiny: Any):
    """Nesterov-Todd scaling of cone k: stores W, W^-1, W^-2 and lambda_q = W z_q."""
    one = type(tiny)(1.0)
    two = type(tiny)(2.0)
    s = _load(vec, t, SQ, k, d)
    z = _load(vec, t, ZQ, k, d)
    sJs = wp.max(_soc_det(s), tiny)
    zJz = wp.max(_soc_det(z), tiny)
    sb = s / wp.sqrt(sJs)
    zb = z / wp.sqrt(zJz)
    gamma = wp.sqrt(wp.max((one + wp.dot(sb, zb)) / two, type(tiny)(0.0)))
    Jzb = wp.vector(zb[0], -zb[1], -zb[2])
    wbar = (sb + Jzb) / (two * gamma)
    v = wp.vector(wbar[0] + one, wbar[1], wbar[2]) / wp.sqrt(two * (wbar[0] + one))
    eta = wp.pow(sJs / zJz, type(tiny)(0.25))
    J = wp.diag(wp.vector(one, -one, -one))
    W = eta * (two * wp.outer(v, v) - J)
    Jv = wp.vector(v[0], -v[1], -v[2])
    Wi = (two * wp.outer(Jv, Jv) - J) / eta
    _store_block(vec, t, W0, k, d, W)
    _store_block(vec, t, WI0, k, d, Wi)
    _store_block(vec, t, WII0, k, d, _square(Wi))
    _store(vec, t, LAMQ, k, d, W * z)


@wp.func
def _build_kkt(
    A: wp.array3d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    r: int,
    t: int,
    d: int,
    K: int,
    jitter: Any,
    vec: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
):
    """Lower triangle of A + blockdiag(D) + jitter I into M[t], D = G^T W^-2 G per contact;
    returns max |D|."""
    n = K * d
    one = type(jitter)(1.0)
    dmax = type(jitter)(0.0)
    for i in range(n):
        for j in range(i + 1):
            M[t, i, j] = A[r, i, j]
    for k in range(K):
        i0 = k * d
        wl = vec[t, WL, k]
        d00 = one / (wl * wl)
        if d == 1:
            M[t, i0, i0] = M[t, i0, i0] + d00
            dmax = wp.max(dmax, wp.abs(d00))
        else:
            Wii = _load_block(vec, t, WII0, k, d)
            m = mu[r, k]
            for i in range(d):
                for j in range(d):
                    si = _pick(i == 0, m, one)
                    sj = _pick(j == 0, m, one)
                    dij = si * Wii[i, j] * sj
                    if i == 0 and j == 0:
                        dij = d00 + dij
                    dmax = wp.max(dmax, wp.abs(dij))
                    if j <= i:
                        M[t, i0 + i, i0 + j] = M[t, i0 + i, i0 + j] + dij
    if jitter != type(jitter)(0.0):
        for i in range(n):
            M[t, i, i] = M[t, i, i] + jitter
    return dmax


@wp.func
def _direction(
    mu: wp.array2d(dtype=Any),
    r: int,
    t: int,
    d: int,
    K: int,
    vec: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
    r3l: int,
    r3q: int,
    out: int,
):
    """Newton direction (df, dsl, dsq, dzl, dzq) into rows out .. out + 4 for the
    complementarity right-hand side r3 (rows r3l, r3q), on the factor in M[t]."""
    for k in range(K):
        wl = vec[t, WL, k]
        ul = vec[t, r3l, k] / vec[t, LAML, k]
        vl = (-vec[t, RZL, k]) / (wl * wl) - ul / wl
        vq = wp.vector(type(vl)(0.0), type(vl)(0.0), type(vl)(0.0))
        if d > 1:
            uq = _soc_div(_load(vec, t, LAMQ, k, d), _load(vec, t, r3q, k, d))
            rzq = _load(vec, t, RZQ, k, d)
            vq = _load_block(vec, t, WII0, k, d) * (-rzq) - _load_block(vec, t, WI0, k, d) * uq
        rhs = -_load(vec, t, RX, k, d) + _cone_GT(vl, vq, mu[r, k], d)
        _store(vec, t, out, k, d, rhs)
    _cholesky_solve(M, t, K * d, vec, out)
    for k in range(K):
        wl = vec[t, WL, k]
        ul = vec[t, r3l, k] / vec[t, LAML, k]
        df = _load(vec, t, out, k, d)
        gl = -df[0]
        vec[t, out + 3, k] = (gl + vec[t, RZL, k]) / (wl * wl) + ul / wl
        vec[t, out + 1, k] = -(gl + vec[t, RZL, k])
        if d > 1:
            uq = _soc_div(_load(vec, t, LAMQ, k, d), _load(vec, t, r3q, k, d))
            gq = _cone_G(df, mu[r, k]) + _load(vec, t, RZQ, k, d)
            dzq = _load_block(vec, t, WII0, k, d) * gq + _load_block(vec, t, WI0, k, d) * uq
            _store(vec, t, out + 4, k, d, dzq)
            _store(vec, t, out + 2, k, d, -gq)


@wp.func
def _max_step(
    active: wp.array2d(dtype=wp.bool),
    r: int,
    t: int,
    d: int,
    K: int,
    vec: wp.array3d(dtype=Any),
    out: int,
    inf: Any,
):
    """Largest step keeping the active contacts' s and z inside their cones."""
    a = inf
    for k in range(K):
        if active[r, k]:
            a = wp.min(a, _orth_max_step(vec[t, SL, k], vec[t, out + 1, k], inf))
            a = wp.min(a, _orth_max_step(vec[t, ZL, k], vec[t, out + 3, k], inf))
            if d > 1:
                sq = _load(vec, t, SQ, k, d)
                zq = _load(vec, t, ZQ, k, d)
                a = wp.min(a, _soc_max_step(sq, _load(vec, t, out + 2, k, d), inf))
                a = wp.min(a, _soc_max_step(zq, _load(vec, t, out + 4, k, d), inf))
    return a


@wp.func
def _gap_after(
    active: wp.array2d(dtype=wp.bool),
    r: int,
    t: int,
    d: int,
    K: int,
    vec: wp.array3d(dtype=Any),
    out: int,
    inf: Any,
):
    """Step length 0.99 x the largest (at most 1) along a direction and the gap there."""
    largest = _max_step(active, r, t, d, K, vec, out, inf)
    alpha = wp.min(type(inf)(STEP_BACK) * largest, type(inf)(1.0))
    gl = type(inf)(0.0)
    gq = type(inf)(0.0)
    for k in range(K):
        if active[r, k]:
            sl = vec[t, SL, k] + alpha * vec[t, out + 1, k]
            zl = vec[t, ZL, k] + alpha * vec[t, out + 3, k]
            gl = gl + sl * zl
            if d > 1:
                sq = _load(vec, t, SQ, k, d) + alpha * _load(vec, t, out + 2, k, d)
                zq = _load(vec, t, ZQ, k, d) + alpha * _load(vec, t, out + 4, k, d)
                gq = gq + wp.dot(sq, zq)
    return gl + gq, alpha


@wp.func
def _shift(x0: Any, worst: Any):
    """x0 + (1 + worst) if the worst violation is >= 0, as the reference's shift."""
    if worst >= type(x0)(0.0):
        return x0 + (type(x0)(1.0) + worst)
    return x0


@wp.func
def _interior_point(
    A: wp.array3d(dtype=Any),
    b: wp.array2d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    lower: wp.array2d(dtype=Any),
    apex: wp.array2d(dtype=Any),
    active: wp.array2d(dtype=wp.bool),
    r: int,
    t: int,
    d: int,
    K: int,
    tol: Any,
    max_iter: int,
    blowup: Any,
    tiny: Any,
    inf: Any,
    vec: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
):
    """The reference's interior point on problem r (scaled data); f into vec[t, F_].

    Returns (solved, unbounded, iterations)."""
    n = K * d
    zero = type(tol)(0.0)
    one = type(tol)(1.0)
    n_valid = int(0)
    for k in range(K):
        if active[r, k]:
            n_valid += 1
    per_contact = _pick(d > 1, 2, 1)
    n_cones = type(tol)(wp.max(n_valid * per_contact, 1))

    # initial point: minimise 0.5 f'Af + b'f + 0.5 ||G f - h||^2, z = G f - h, s = -z
    for i in range(n):
        for j in range(i + 1):
            M[t, i, j] = A[r, i, j]
    for k in range(K):
        i0 = k * d
        m = mu[r, k]
        hl = -lower[r, k]
        if d == 1:
            M[t, i0, i0] = M[t, i0, i0] + one
            vec[t, F_, i0] = -b[r, i0] + (-hl)
        else:
            M[t, i0, i0] = M[t, i0, i0] + (one + m * m)
            vec[t, F_, i0] = -b[r, i0] + (-(hl + m * apex[r, k]))
            for j in range(1, d):
                M[t, i0 + j, i0 + j] = M[t, i0 + j, i0 + j] + one
                vec[t, F_, i0 + j] = -b[r, i0 + j]
    if not _cholesky(M, t, n):
        for i in range(n):
            vec[t, F_, i] = zero
        return False, False, 0
    _cholesky_solve(M, t, n, vec, F_)
    worst_s = -inf
    worst_z = -inf
    for k in range(K):
        f = _load(vec, t, F_, k, d)
        zl = -f[0] - (-lower[r, k])
        vec[t, ZL, k] = zl
        vec[t, SL, k] = -zl
        if d > 1:
            zq = _cone_G(f, mu[r, k]) - wp.vector(apex[r, k], zero, zero)
            _store(vec, t, ZQ, k, d, zq)
            _store(vec, t, SQ, k, d, -zq)
        if active[r, k]:
            worst_s = wp.max(worst_s, zl)
            worst_z = wp.max(worst_z, -zl)
            if d > 1:
                zq = _load(vec, t, ZQ, k, d)
                nt = wp.sqrt(zq[1] * zq[1] + zq[2] * zq[2])
                worst_s = wp.max(worst_s, nt + zq[0])
                worst_z = wp.max(worst_z, nt - zq[0])
    for k in range(K):
        if active[r, k]:
            vec[t, SL, k] = _shift(vec[t, SL, k], worst_s)
            vec[t, ZL, k] = _shift(vec[t, ZL, k], worst_z)
            if d > 1:
                vec[t, SQ, k * d] = _shift(vec[t, SQ, k * d], worst_s)
                vec[t, ZQ, k * d] = _shift(vec[t, ZQ, k * d], worst_z)
        else:  # held at f = 0, s = z = e
            vec[t, SL, k] = one
            vec[t, ZL, k] = one
            for j in range(d):
                vec[t, F_, k * d + j] = zero
                if d > 1:
                    vec[t, SQ, k * d + j] = _pick(j == 0, one, zero)
                    vec[t, ZQ, k * d + j] = _pick(j == 0, one, zero)

    stalled = bool(False)
    plain_only = bool(False)
    prev_res = inf
    prev_size = inf
    for it in range(max_iter):
        # residuals and gap
        gap_l = zero
        gap_q = zero
        res = zero
        size = zero
        for i in range(n):
            size = wp.max(size, wp.abs(vec[t, F_, i]))
        for k in range(K):
            m = mu[r, k]
            zq = _load(vec, t, ZQ, k, d)
            gt = _cone_GT(vec[t, ZL, k], zq, m, d)
            for j in range(d):
                i = k * d + j
                rx = (_dot(A, r, i, vec, t, F_, n) + b[r, i]) + gt[j]
                vec[t, RX, i] = rx
                if active[r, k]:
                    res = wp.max(res, wp.abs(rx))
            f = _load(vec, t, F_, k, d)
            rzl = -f[0] + vec[t, SL, k] + lower[r, k]
            vec[t, RZL, k] = rzl
            if active[r, k]:
                res = wp.max(res, wp.abs(rzl))
                gap_l = gap_l + vec[t, SL, k] * vec[t, ZL, k]
            if d > 1:
                sq = _load(vec, t, SQ, k, d)
                rzq = _cone_G(f, m) + sq - wp.vector(apex[r, k], zero, zero)
                _store(vec, t, RZQ, k, d, rzq)
                if active[r, k]:
                    gap_q = gap_q + wp.dot(sq, zq)
                    res = wp.max(
                        res, wp.max(wp.abs(rzq[0]), wp.max(wp.abs(rzq[1]), wp.abs(rzq[2])))
                    )
        gap = gap_l + gap_q
        small_gap = gap <= tol * n_cones
        solved = small_gap and res <= tol
        diverged = size > blowup
        stuck = small_gap and res > type(tol)(0.5) * prev_res and size <= type(tol)(1.5) * prev_size
        prev_res = res
        prev_size = size
        if solved or diverged or stalled or stuck:
            return solved, diverged and not solved, it
        mu_gap = gap / n_cones

        # Nesterov-Todd scaling and the factorisation of A + G^T W^-2 G
        for k in range(K):
            sl = vec[t, SL, k]
            zl = vec[t, ZL, k]
            vec[t, WL, k] = wp.sqrt(sl / zl)
            vec[t, LAML, k] = wp.sqrt(sl * zl)
            if d > 1:
                _nt_scaling(vec, t, k, d, tiny)
        dmax = _build_kkt(A, mu, r, t, d, K, zero, vec, M)
        if not _cholesky(M, t, n):
            jitter = type(tol)(JITTER) * (one + dmax)
            _build_kkt(A, mu, r, t, d, K, jitter, vec, M)
            _cholesky(M, t, n)

        # predictor
        for k in range(K):
            laml = vec[t, LAML, k]
            vec[t, R3L, k] = -laml * laml
            if d > 1:
                lamq = _load(vec, t, LAMQ, k, d)
                _store(vec, t, R3Q, k, d, -_soc_prod(lamq, lamq))
        _direction(mu, r, t, d, K, vec, M, R3L, R3Q, DIR_A)
        alpha = wp.min(_max_step(active, r, t, d, K, vec, DIR_A, inf), one)
        sigma = (one - alpha) * (one - alpha) * (one - alpha)
        # corrector: r3 = -lam o lam + sigma mu e - (W^-1 ds_a) o (W dz_a); a problem whose
        # gap grows under Mehrotra's term drops it from then on (plain_only)
        centre = sigma * mu_gap
        for k in range(K):
            r3l = vec[t, R3L, k] + centre
            vec[t, R3L, k] = r3l
            corr = vec[t, DIR_A + 1, k] * vec[t, DIR_A + 3, k]
            if plain_only:
                corr = zero
            vec[t, R3LC, k] = r3l - corr
            if d > 1:
                r3q = _load(vec, t, R3Q, k, d)
                r3q = wp.vector(r3q[0] + centre, r3q[1], r3q[2])
                _store(vec, t, R3Q, k, d, r3q)
                a_s = _load_block(vec, t, WI0, k, d) * _load(vec, t, DIR_A + 2, k, d)
                a_z = _load_block(vec, t, W0, k, d) * _load(vec, t, DIR_A + 4, k, d)
                corr_q = _soc_prod(a_s, a_z)
                if plain_only:
                    corr_q = wp.vector(zero, zero, zero)
                _store(vec, t, R3QC, k, d, r3q - corr_q)
        _direction(mu, r, t, d, K, vec, M, R3LC, R3QC, DIR_B)
        gap_m, alpha = _gap_after(active, r, t, d, K, vec, DIR_B, inf)
        direction = DIR_B
        if gap_m > gap and not plain_only:
            _direction(mu, r, t, d, K, vec, M, R3L, R3Q, DIR_A)
            _gap, alpha_p = _gap_after(active, r, t, d, K, vec, DIR_A, inf)
            alpha = alpha_p
            plain_only = True
            direction = DIR_A

        # step; a problem whose step breaks down keeps its iterate (stalled)
        ok = bool(True)
        for k in range(K):
            if active[r, k]:
                for j in range(d):
                    i = k * d + j
                    ok = ok and wp.isfinite(vec[t, F_, i] + alpha * vec[t, direction, i])
                sl = vec[t, SL, k] + alpha * vec[t, direction + 1, k]
                zl = vec[t, ZL, k] + alpha * vec[t, direction + 3, k]
                ok = ok and wp.isfinite(sl * zl) and sl > zero and zl > zero
                if d > 1:
                    sq = _load(vec, t, SQ, k, d) + alpha * _load(vec, t, direction + 2, k, d)
                    zq = _load(vec, t, ZQ, k, d) + alpha * _load(vec, t, direction + 4, k, d)
                    for j in range(d):
                        ok = ok and wp.isfinite(sq[j] * zq[j])
                    ok = ok and _soc_det(sq) > zero and _soc_det(zq) > zero
        if ok:
            for k in range(K):
                if active[r, k]:
                    for j in range(d):
                        i = k * d + j
                        vec[t, F_, i] = vec[t, F_, i] + alpha * vec[t, direction, i]
                        if d > 1:
                            vec[t, SQ, i] = vec[t, SQ, i] + alpha * vec[t, direction + 2, i]
                            vec[t, ZQ, i] = vec[t, ZQ, i] + alpha * vec[t, direction + 4, i]
                    vec[t, SL, k] = vec[t, SL, k] + alpha * vec[t, direction + 1, k]
                    vec[t, ZL, k] = vec[t, ZL, k] + alpha * vec[t, direction + 3, k]
        else:
            stalled = True
    return False, False, max_iter


# --- the polish ------------------------------------------------------------------------


@wp.func
def _project(z: Any, mu: Any, lower: Any, d: int):
    """Projection of one contact block onto {f_n >= l, ||f_t|| <= mu f_n} with dPi/dz,
    dPi/dmu and dPi/dl (the regions and one-sided choices of
    :func:`diffcontact.contact.cone.project_contact_set`); padded 3-vectors / 3x3."""
    zero = type(mu)(0.0)
    one = type(mu)(1.0)
    zv = wp.vector(zero, zero, zero)
    zm = wp.outer(zv, zv)
    zn = z[0]
    if d == 1:
        if zn < lower:
            return wp.vector(lower, zero, zero), zm, zv, wp.vector(one, zero, zero)
        return wp.vector(zn, zero, zero), wp.diag(wp.vector(one, zero, zero)), zv, zv
    s = wp.sqrt(z[1] * z[1] + z[2] * z[2])
    s_safe = _pick(s > zero, s, one)
    u = zv
    if s > zero:
        u = wp.vector(zero, z[1] / s_safe, z[2] / s_safe)
    uu = wp.outer(u, u)
    eye_t = wp.diag(wp.vector(zero, one, one))
    mu2 = mu * mu
    inside = mu > zero and s <= mu * zn
    polar = (not inside) and mu * s <= -zn
    c = (zn + mu * s) / (one + mu2)
    cone_n = c
    if inside:
        cone_n = zn
    elif polar:
        cone_n = zero
    use_disk = cone_n < lower or (polar and cone_n <= lower)
    if use_disk:  # f_n = l, f_t clipped to the radius mu l
        radius = mu * lower
        e0 = wp.vector(one, zero, zero)
        if s > radius or radius <= zero:
            P = (radius / s_safe) * (eye_t - uu)
            return lower * e0 + radius * u, P, lower * u, e0 + mu * u
        return wp.vector(lower, z[1], z[2]), eye_t, zv, e0
    if inside:
        return z, wp.diag(wp.vector(one, one, one)), zv, zv
    if polar:
        return zv, zm, zv, zv
    # the cone's surface (sliding)
    e0 = wp.vector(one, zero, zero)
    a = mu / (one + mu2)
    P = wp.outer(e0, e0) / (one + mu2) + a * (wp.outer(e0, u) + wp.outer(u, e0))
    P = P + (mu2 / (one + mu2)) * uu + (c * mu / s_safe) * (eye_t - uu)
    dc = (s - type(mu)(2.0) * mu * c) / (one + mu2)
    return c * e0 + (c * mu) * u, P, dc * e0 + (dc * mu + c) * u, zv


# The natural map's product A f and the reduced Newton system's rows are the other
# quadratic loops of a Newton step (about n^2 and m n d entries of A), in C++ over raw
# pointers for the same reason as the Cholesky routines. Each product is a separate
# statement from its sum, as in Warp's generated code, so that no multiply-add is fused
# and the results are bitwise those of the Warp loops they replace.
_MATVEC_CPP = r"""
auto* a = (decltype(A.data))((char*)A.data + (long long)r * A.strides[0]);
const long long a1 = A.strides[1] / (long long)sizeof(*a);
const long long a2 = A.strides[2] / (long long)sizeof(*a);
auto* v = (decltype(vec.data))((char*)vec.data + (long long)t * vec.strides[0]);
const long long v1 = vec.strides[1] / (long long)sizeof(*v);
const long long v2 = vec.strides[2] / (long long)sizeof(*v);
const auto* x = v + (long long)src * v1;
auto* y = v + (long long)dst * v1;
auto zero = x[0];
zero = 0;
const int n = K * d;
// four rows at a time: four independent running sums, each over the columns in order
int i = 0;
for (; i + 4 <= n; i += 4) {
    const auto* r0 = a + i * a1;
    auto s0 = zero, s1 = zero, s2 = zero, s3 = zero;
    for (int k = 0; k < K; ++k) {
        bool nonzero = false;
        for (int q = 0; q < d; ++q) nonzero = nonzero || x[(k * d + q) * v2] != zero;
        if (!nonzero) continue;
        for (int q = 0; q < d; ++q) {
            const int j = k * d + q;
            const auto xj = x[j * v2];
            const long long o = j * a2;
            const auto p0 = r0[o] * xj;
            const auto p1 = r0[a1 + o] * xj;
            const auto p2 = r0[2 * a1 + o] * xj;
            const auto p3 = r0[3 * a1 + o] * xj;
            s0 = s0 + p0;
            s1 = s1 + p1;
            s2 = s2 + p2;
            s3 = s3 + p3;
        }
    }
    y[i * v2] = s0;
    y[(i + 1) * v2] = s1;
    y[(i + 2) * v2] = s2;
    y[(i + 3) * v2] = s3;
}
for (; i < n; ++i) {
    const auto* ai = a + i * a1;
    auto s = zero;
    for (int k = 0; k < K; ++k) {
        bool nonzero = false;
        for (int q = 0; q < d; ++q) nonzero = nonzero || x[(k * d + q) * v2] != zero;
        if (!nonzero) continue;
        for (int q = 0; q < d; ++q) {
            const int j = k * d + q;
            const auto p = ai[j * a2] * x[j * v2];
            s = s + p;
        }
    }
    y[i * v2] = s;
}
"""


@wp.func_native(_MATVEC_CPP)
def _matvec_cpp(
    A: wp.array3d(dtype=wp.float64),
    r: int,
    vec: wp.array3d(dtype=wp.float64),
    t: int,
    src: int,
    dst: int,
    K: int,
    d: int,
): ...


@wp.func_native(_MATVEC_CPP)
def _matvec_cpp(
    A: wp.array3d(dtype=wp.float32),
    r: int,
    vec: wp.array3d(dtype=wp.float32),
    t: int,
    src: int,
    dst: int,
    K: int,
    d: int,
): ...


@wp.func
def _matvec(
    A: wp.array3d(dtype=Any),
    r: int,
    vec: wp.array3d(dtype=Any),
    t: int,
    src: int,
    dst: int,
    K: int,
    d: int,
):
    """vec[t, dst] = A[r] vec[t, src] (:data:`_MATVEC_CPP`). Each row's sum runs over the
    columns in order, as :func:`_dot`; blocks of the vector that are zero (the separating
    and padded contacts) are skipped, which leaves every sum bitwise the same (a sum that
    starts at +0 never becomes -0)."""
    _matvec_cpp(A, r, vec, t, src, dst, K, d)


@wp.func
def _z_block(
    b: wp.array2d(dtype=Any),
    r: int,
    t: int,
    d: int,
    k: int,
    rho: Any,
    vec: wp.array3d(dtype=Any),
    f: int,
):
    """Block k of z = f - rho (A f + b), f in row ``f`` and A f in row AF (:func:`_matvec`),
    as a padded 3-vector."""
    zero = type(rho)(0.0)
    i = k * d
    s = _load(vec, t, AF, k, d)
    fk = _load(vec, t, f, k, d)
    z0 = fk[0] - rho * (s[0] + b[r, i])
    z1 = zero
    z2 = zero
    if d > 1:
        z1 = fk[1] - rho * (s[1] + b[r, i + 1])
    if d > 2:
        z2 = fk[2] - rho * (s[2] + b[r, i + 2])
    return wp.vector(z0, z1, z2)


@wp.func
def _natural_map(
    A: wp.array3d(dtype=Any),
    b: wp.array2d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    lower: wp.array2d(dtype=Any),
    r: int,
    t: int,
    d: int,
    K: int,
    rho: Any,
    c: Any,
    vec: wp.array3d(dtype=Any),
    f: int,
    res: int,
    P: int,
    dmu: int,
    dl: int,
):
    """F(f) = f - Pi(f - rho (A f + b)) and the projection's derivatives at the point in
    row f, into rows res, P (3 rows), dmu, dl; returns ||F||_inf / max(c, ||f||_inf)."""
    zero = type(rho)(0.0)
    fmax = zero
    Fmax = zero
    _matvec(A, r, vec, t, f, AF, K, d)
    for k in range(K):
        zk = _z_block(b, r, t, d, k, rho, vec, f)
        proj, Pk, dmuk, dlk = _project(zk, mu[r, k], lower[r, k], d)
        fk = _load(vec, t, f, k, d)
        Fk = fk - proj
        _store(vec, t, res, k, d, Fk)
        _store_block(vec, t, P, k, d, Pk)
        _store(vec, t, dmu, k, d, dmuk)
        _store(vec, t, dl, k, d, dlk)
        for j in range(d):
            fmax = wp.max(fmax, wp.abs(fk[j]))
            Fmax = wp.max(Fmax, wp.abs(Fk[j]))
    return Fmax / wp.max(c, fmax)


@wp.func
def _jacobian(
    A: wp.array3d(dtype=Any),
    r: int,
    t: int,
    d: int,
    K: int,
    rho: Any,
    reg: Any,
    vec: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
):
    """dF/df = I - P + rho P (A + reg I) into M[t] (P: rows P0.., per-contact blocks)."""
    n = K * d
    zero = type(rho)(0.0)
    one = type(rho)(1.0)
    for k in range(K):
        Pk = _load_block(vec, t, P0, k, d)
        for i in range(d):
            row = k * d + i
            for col in range(n):
                s = zero
                for m in range(d):
                    a = A[r, k * d + m, col]
                    if k * d + m == col:
                        a = a + reg
                    s = s + Pk[i, m] * a
                value = _pick(row == col, one, zero) + rho * s
                if col >= k * d and col < k * d + d:
                    value = value - Pk[i, col - k * d]
                M[t, row, col] = value


@wp.func
def _block_basis(P: Any, d: int):
    """The reduced Newton system's basis of one contact block: ``(u0, u1, dk)`` for the
    orthonormal ``Q = [(u0, u1, 0), (-u1, u0, 0), (0, 0, 1)]`` (its first d rows and
    columns; :func:`_basis_column`) whose first dk columns span the range of the block P
    of dPi/dz and whose others span its null space.

    For d <= 2 the contact set's faces are flat (the apex, two rays, the interior), so P
    is an orthogonal projector: 0, I or u u^T with u along the ray; its rank is its trace.
    For d = 3 the cone's surface is curved and P is no projector: dk is 0 where P = 0 and
    d elsewhere, with Q = I."""
    zero = type(P[0, 0])(0.0)
    one = type(P[0, 0])(1.0)
    if d == 3:
        dk = int(0)
        for i in range(3):
            for j in range(3):
                if P[i, j] != zero:
                    dk = 3
        return one, zero, dk
    trace = P[0, 0] + P[1, 1]
    if trace > type(one)(1.5):
        return one, zero, d
    if not (trace > type(one)(0.5)):
        return one, zero, 0
    if d == 1:
        return one, zero, 1
    j = _pick(P[0, 0] >= P[1, 1], 0, 1)
    u0 = P[0, j]
    u1 = P[1, j]
    norm = wp.sqrt(u0 * u0 + u1 * u1)
    return u0 / norm, u1 / norm, 1


@wp.func
def _basis_column(u0: Any, u1: Any, j: int):
    """Column j of the basis Q of :func:`_block_basis`, as a 3-vector."""
    zero = type(u0)(0.0)
    if j == 0:
        return wp.vector(u0, u1, zero)
    if j == 1:
        return wp.vector(-u1, u0, zero)
    return wp.vector(zero, zero, type(u0)(1.0))


_REDUCED_ROWS_CPP = r"""
auto* a = (decltype(A.data))((char*)A.data + (long long)r * A.strides[0]);
const long long a1 = A.strides[1] / (long long)sizeof(*a);
const long long a2 = A.strides[2] / (long long)sizeof(*a);
auto* v = (decltype(vec.data))((char*)vec.data + (long long)t * vec.strides[0]);
const long long v1 = vec.strides[1] / (long long)sizeof(*v);
const long long v2 = vec.strides[2] / (long long)sizeof(*v);
auto* h = (decltype(M.data))((char*)M.data + (long long)t * M.strides[0]);
const long long h1 = M.strides[1] / (long long)sizeof(*h);
const long long h2 = M.strides[2] / (long long)sizeof(*h);
const auto* qu0 = v + (long long)qu0_row * v1;
const auto* qu1 = v + (long long)qu1_row * v1;
const auto* dks = v + (long long)dk_row * v1;
auto* y = v + (long long)y_row * v1;
const int n = K * d;
auto zero = rho;
zero = 0;
const auto one = zero + 1;
int row = 0;
for (int k = 0; k < K; ++k) {
    const int dk = (int)dks[k * v2];
    if (dk <= 0) continue;
    // the padded 3x3 block P_k of dPi/dz (rows p_row.., columns k d ..)
    decltype(zero) P[3][3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            P[i][j] = (i < d && j < d) ? v[(long long)(p_row + i) * v1 + (k * d + j) * v2] : zero;
    const auto uk0 = qu0[k * v2];
    const auto uk1 = qu1[k * v2];
    for (int i = 0; i < dk; ++i) {
        // column i of Q_k, and w = P_k^T u
        decltype(zero) u[3];
        u[0] = i == 0 ? uk0 : (i == 1 ? -uk1 : zero);
        u[1] = i == 0 ? uk1 : (i == 1 ? uk0 : zero);
        u[2] = i == 2 ? one : zero;
        decltype(zero) w[3];
        for (int j = 0; j < 3; ++j) w[j] = u[0] * P[0][j] + u[1] * P[1][j] + u[2] * P[2][j];
        // y = sum_p w_p A[k d + p, :] over the nonzero w_p, in order (row y_row)
        for (int j = 0; j < n; ++j) y[j * v2] = zero;
        for (int p = 0; p < d; ++p) {
            if (w[p] == zero) continue;
            const auto wp_ = w[p];
            const auto* ap = a + (k * d + p) * a1;
            for (int j = 0; j < n; ++j) {
                const auto prod = wp_ * ap[j * a2];
                y[j * v2] = y[j * v2] + prod;
            }
        }
        int cu = 0;
        int cv = m;
        auto* hrow = h + (long long)row * h1;
        for (int l = 0; l < K; ++l) {
            const int dl = (int)dks[l * v2];
            // block l of the row rho w^T (A + reg I) (+ (u - w)^T on block k)
            decltype(zero) x[3];
            for (int c = 0; c < 3; ++c) x[c] = rho * (c < d ? y[(l * d + c) * v2] : zero);
            if (l == k) {
                for (int c = 0; c < 3; ++c) {
                    const auto rw = reg * w[c];
                    const auto rrw = rho * rw;
                    x[c] = x[c] + rrw;
                }
                for (int c = 0; c < 3; ++c) {
                    const auto uw = u[c] - w[c];
                    x[c] = x[c] + uw;
                }
            }
            const auto ul0 = qu0[l * v2];
            const auto ul1 = qu1[l * v2];
            for (int j = 0; j < d; ++j) {
                const auto b0 = j == 0 ? ul0 : (j == 1 ? -ul1 : zero);
                const auto b1 = j == 0 ? ul1 : (j == 1 ? ul0 : zero);
                const auto b2 = j == 2 ? one : zero;
                const auto value = x[0] * b0 + x[1] * b1 + x[2] * b2;
                if (j < dl) {
                    hrow[cu * h2] = value;
                    cu += 1;
                } else {
                    hrow[cv * h2] = value;
                    cv += 1;
                }
            }
        }
        row += 1;
    }
}
"""


@wp.func_native(_REDUCED_ROWS_CPP)
def _reduced_rows_cpp(
    A: wp.array3d(dtype=wp.float64),
    r: int,
    t: int,
    d: int,
    K: int,
    m: int,
    rho: wp.float64,
    reg: wp.float64,
    vec: wp.array3d(dtype=wp.float64),
    qu0_row: int,
    qu1_row: int,
    dk_row: int,
    p_row: int,
    y_row: int,
    M: wp.array3d(dtype=wp.float64),
): ...


@wp.func_native(_REDUCED_ROWS_CPP)
def _reduced_rows_cpp(
    A: wp.array3d(dtype=wp.float32),
    r: int,
    t: int,
    d: int,
    K: int,
    m: int,
    rho: wp.float32,
    reg: wp.float32,
    vec: wp.array3d(dtype=wp.float32),
    qu0_row: int,
    qu1_row: int,
    dk_row: int,
    p_row: int,
    y_row: int,
    M: wp.array3d(dtype=wp.float32),
): ...


@wp.func
def _reduced_build(
    A: wp.array3d(dtype=Any),
    r: int,
    t: int,
    d: int,
    K: int,
    rho: Any,
    reg: Any,
    vec: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
):
    """The blocks H (M[t, :m, :m]) and G (M[t, :m, m:n]) of :func:`_reduced_factor`, the
    bases (rows QU0, QU1, DK) and the copy of P it depends on (rows PF0..); returns m.

    Row a of [H G] (range column i of contact k, u its basis column, w = P_k^T u) is
    ``rho w^T (A + reg I) + (u - w)^T`` on block k, times each contact's Q
    (:data:`_REDUCED_ROWS_CPP`: ``w_p A`` over the nonzero ``w_p`` in order, each
    column of Q applied as ``wp.dot``)."""
    n = K * d
    m = int(0)
    for k in range(K):
        u0, u1, dk = _block_basis(_load_block(vec, t, P0, k, d), d)
        vec[t, QU0, k] = u0
        vec[t, QU1, k] = u1
        vec[t, DK, k] = type(rho)(dk)
        m += dk
    _reduced_rows_cpp(A, r, t, d, K, m, rho, reg, vec, QU0, QU1, DK, P0, AF + 1, M)
    for a2 in range(d):  # what the factorisation depends on besides A (_same_P)
        for i in range(n):
            vec[t, PF0 + a2, i] = vec[t, P0 + a2, i]
    return m


@wp.func
def _reduced_factor(
    A: wp.array3d(dtype=Any),
    r: int,
    t: int,
    d: int,
    K: int,
    rho: Any,
    reg: Any,
    vec: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
):
    """dF/df = I - P + rho P (A + reg I) at the point whose P is in rows P0.., reduced.

    In the per-contact bases Q of :func:`_block_basis` (range coordinates U first,
    contact by contact, then the null-space ones V), ``Q^T dF/df Q = [[H, G], [0, I]]``:
    a null-space row of dF/df is a row of the identity (V^T P = 0), and a range row is
    ``u^T (I - P)`` on its own block plus ``rho u^T P (A + reg I)``. Only the m x m block
    H is factorised, in place in M[t, :m, :m]; G stays in M[t, :m, m:n]. Separating and
    padded contacts (P = 0) and, for d <= 2, the normal of each sliding contact's ray drop
    out, so the factorisation costs m^3, not n^3.

    For d <= 2, P is a projector (u = P^T u), so H = rho U^T (A + reg I) U is symmetric
    positive definite: Cholesky (lower factor in M, ``piv[t, 0] = 0`` marks it). Where
    that fails (rounding, A singular) and for d = 3 (H is not symmetric): LU with partial
    pivoting (LAPACK's layout, pivots in piv[t], 1-based). Writes the bases into rows QU0,
    QU1 and DK (per contact); returns (m, the smallest pivot of dF/df: min L_jj^2 or
    min |U_jj|, 1 where m = 0)."""
    m = _reduced_build(A, r, t, d, K, rho, reg, vec, M)
    umin = type(rho)(1.0)
    if m > 0:
        chol = bool(False)
        if d <= 2:
            chol = _cholesky(M, t, m)
            if chol:
                piv[t, 0] = 0
                for j in range(m):
                    pivot = M[t, j, j] * M[t, j, j]
                    umin = _pick(j == 0, pivot, wp.min(umin, pivot))
            else:
                _reduced_build(A, r, t, d, K, rho, reg, vec, M)  # (the failed one overwrote H)
        if not chol:
            umin = _lu_factor(M, piv, t, m)
    return m, umin


@wp.func
def _same_P(vec: wp.array3d(dtype=Any), t: int, n: int, d: int):
    """Whether dPi/dz (rows P0..) is bitwise the one of the factorisation in M (rows
    PF0..): dF/df depends on the point only through it, so the factorisation is reused
    (for d <= 2, P takes few values: 0, I, the rays' projectors)."""
    for a in range(d):
        for i in range(n):
            if vec[t, P0 + a, i] != vec[t, PF0 + a, i]:
                return False
    return True


@wp.func
def _reduced_solve(
    vec: wp.array3d(dtype=Any),
    t: int,
    d: int,
    K: int,
    m: int,
    M: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
    slot: int,
):
    """Solve dF/df x = vec[t, slot] in place, with the factorisation of
    :func:`_reduced_factor`: y = Q^T x, y_V as given, H y_U = y_U - G y_V, x = Q y."""
    n = K * d
    cu = int(0)
    cv = m
    for k in range(K):
        dk = int(vec[t, DK, k])
        u0 = vec[t, QU0, k]
        u1 = vec[t, QU1, k]
        x = _load(vec, t, slot, k, d)
        for j in range(d):
            y = wp.dot(x, _basis_column(u0, u1, j))
            if j < dk:
                vec[t, RHS, cu] = y
                cu += 1
            else:
                vec[t, RHS, cv] = y
                cv += 1
    for a in range(m):
        s = vec[t, RHS, a]
        for b in range(m, n):
            s = s - M[t, a, b] * vec[t, RHS, b]
        vec[t, RHS, a] = s
    if m > 0:
        if piv[t, 0] == 0:  # Cholesky (see _reduced_factor)
            _cholesky_solve(M, t, m, vec, RHS)
        else:
            _lu_solve(M, piv, t, m, vec, RHS)
    cu = int(0)
    cv = m
    for k in range(K):
        dk = int(vec[t, DK, k])
        u0 = vec[t, QU0, k]
        u1 = vec[t, QU1, k]
        zero = type(u0)(0.0)
        x = wp.vector(zero, zero, zero)
        for j in range(d):
            y = zero
            if j < dk:
                y = vec[t, RHS, cu]
                cu += 1
            else:
                y = vec[t, RHS, cv]
                cv += 1
            x = x + y * _basis_column(u0, u1, j)
        _store(vec, t, slot, k, d, x)


@wp.func
def _accept(vec: wp.array3d(dtype=Any), t: int, n: int):
    """The trial point (rows FN, RESN, PN0.., DMUN, DLN) becomes the current one."""
    for i in range(n):
        vec[t, F_, i] = vec[t, FN, i]
        vec[t, RES, i] = vec[t, RESN, i]
        vec[t, DMU, i] = vec[t, DMUN, i]
        vec[t, DL, i] = vec[t, DLN, i]
        for j in range(3):
            vec[t, P0 + j, i] = vec[t, PN0 + j, i]


@wp.func
def _try_steps(
    A: wp.array3d(dtype=Any),
    b: wp.array2d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    lower: wp.array2d(dtype=Any),
    r: int,
    t: int,
    d: int,
    K: int,
    rho: Any,
    c: Any,
    res: Any,
    vec: wp.array3d(dtype=Any),
    step: int,
):
    """Backtracking along row ``step`` (full, 1/2, 1/4, 1/8): the first step that lowers
    the residual is taken; returns the residual (unchanged if none)."""
    n = K * d
    alpha = type(rho)(1.0)
    for _ in range(4):
        for i in range(n):
            vec[t, FN, i] = vec[t, F_, i] + alpha * vec[t, step, i]
        res_new = _natural_map(A, b, mu, lower, r, t, d, K, rho, c, vec, FN, RESN, PN0, DMUN, DLN)
        if res_new < res:
            _accept(vec, t, n)
            return res_new
        alpha = alpha * type(rho)(0.5)
    return res


@wp.func
def _polish(
    A: wp.array3d(dtype=Any),
    b: wp.array2d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    lower: wp.array2d(dtype=Any),
    r: int,
    t: int,
    d: int,
    K: int,
    rho: Any,
    reg: Any,
    c: Any,
    target: Any,
    steps: int,
    eps: Any,
    vec: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
    V: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
):
    """Newton steps on the natural map from vec[t, F_] as the reference's ``_polish``
    (the same steps, solved in the reduced form of :func:`_reduced_factor`). Leaves F, P,
    dmu, dl at the final point in their rows and the reduced factorisation of dF/df there
    in M[t], piv[t] and rows QU0, QU1, DK; returns (residual, m, smallest pivot)."""
    n = K * d
    zero = type(rho)(0.0)
    res = _natural_map(A, b, mu, lower, r, t, d, K, rho, c, vec, F_, RES, P0, DMU, DL)
    flat = bool(False)
    rank = int(0)
    have = bool(False)  # M holds the factorisation for the P in rows PF0..
    m = int(0)
    umin = type(rho)(1.0)
    for step in range(steps):
        if res <= target:
            break
        if not (have and _same_P(vec, t, n, d)):
            m, umin = _reduced_factor(A, r, t, d, K, rho, reg, vec, M, piv)
            have = True
        for i in range(n):
            vec[t, DELTA, i] = -vec[t, RES, i]
        _reduced_solve(vec, t, d, K, m, M, piv, DELTA)
        for i in range(n):
            if not wp.isfinite(vec[t, DELTA, i]):
                vec[t, DELTA, i] = zero
        if step == 0 and umin <= type(rho)(FLAT):
            # nearly singular: the minimiser may not be unique; try the step without
            # its component along the null space of A first (no move by rounding)
            flat = True
            rank = _range_basis(A, r, t, n, M, piv, V, eps)  # (M, piv: its scratch)
            have = False
        new_res = res
        if flat:  # the step projected onto the range of A
            for i in range(n):
                vec[t, DFLAT, i] = zero
            for e in range(rank):
                proj = zero
                for i in range(n):
                    proj = proj + V[t, i, e] * vec[t, DELTA, i]
                for i in range(n):
                    vec[t, DFLAT, i] = vec[t, DFLAT, i] + V[t, i, e] * proj
            new_res = _try_steps(A, b, mu, lower, r, t, d, K, rho, c, res, vec, DFLAT)
        if not (new_res < res):
            new_res = _try_steps(A, b, mu, lower, r, t, d, K, rho, c, res, vec, DELTA)
        if not (new_res < res):
            break  # the same point would give the same steps again
        res = new_res
    if not (have and _same_P(vec, t, n, d)):
        m, umin = _reduced_factor(A, r, t, d, K, rho, reg, vec, M, piv)
    return res, m, umin


# --- the kernel ------------------------------------------------------------------------


@wp.func
def _polish_into(
    A: wp.array3d(dtype=Any),
    b: wp.array2d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    lower: wp.array2d(dtype=Any),
    rho: Any,
    reg: Any,
    c: Any,
    r: int,
    t: int,
    d: int,
    K: int,
    target: Any,
    polish_steps: int,
    eps: Any,
    vec: wp.array3d(dtype=Any),
    V: wp.array3d(dtype=Any),
    f_out: wp.array2d(dtype=Any),
    res_out: wp.array(dtype=Any),
    P_out: wp.array3d(dtype=Any),
    dmu_out: wp.array2d(dtype=Any),
    dl_out: wp.array2d(dtype=Any),
    LU: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
):
    """Polish from vec[t, F_] and write f, the residual, dPi/dz (blocks (C, d)), dPi/dmu,
    dPi/dl and the LU factorisation of dF/df (in place in LU, piv) for thread t."""
    n = K * d
    res, _m, _umin = _polish(
        A, b, mu, lower, r, t, d, K, rho, reg, c, target, polish_steps, eps, vec, LU, V, piv
    )
    res_out[t] = res
    # the reference's full factorisation, for its backward pass
    _jacobian(A, r, t, d, K, rho, reg, vec, LU)
    _lu_factor(LU, piv, t, n)
    for i in range(n):
        f_out[t, i] = vec[t, F_, i]
        dmu_out[t, i] = vec[t, DMU, i]
        dl_out[t, i] = vec[t, DL, i]
    for k in range(K):
        for a in range(d):
            for j in range(d):
                P_out[t, k * d + a, j] = vec[t, P0 + a, k * d + j]


@wp.kernel
def fused_solve(
    rows: wp.array(dtype=wp.int32),
    A_ipm: wp.array3d(dtype=Any),
    b_ipm: wp.array2d(dtype=Any),
    mu_ipm: wp.array2d(dtype=Any),
    lower_ipm: wp.array2d(dtype=Any),
    apex: wp.array2d(dtype=Any),
    active: wp.array2d(dtype=wp.bool),
    A: wp.array3d(dtype=Any),
    b: wp.array2d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    lower: wp.array2d(dtype=Any),
    rho: wp.array(dtype=Any),
    reg: wp.array(dtype=Any),
    c: wp.array(dtype=Any),
    d: int,
    K: int,
    gap: Any,
    max_iter: int,
    target: Any,
    polish_steps: int,
    blowup: Any,
    eps: Any,
    tiny: Any,
    inf: Any,
    vec: wp.array3d(dtype=Any),
    V: wp.array3d(dtype=Any),
    f_ipm: wp.array2d(dtype=Any),
    f_out: wp.array2d(dtype=Any),
    res_out: wp.array(dtype=Any),
    P_out: wp.array3d(dtype=Any),
    dmu_out: wp.array2d(dtype=Any),
    dl_out: wp.array2d(dtype=Any),
    LU: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
    iterations: wp.array(dtype=wp.int64),
    solved: wp.array(dtype=wp.bool),
    unbounded: wp.array(dtype=wp.bool),
):
    """Interior point, polish and the backward pass's factorisation for problem rows[t].

    Inputs: the scaled problem of the interior point (``A_ipm`` (B, C, C), ``b_ipm``
    (B, C), ``mu_ipm``, ``lower_ipm``, ``apex``, ``active`` (B, K)) and the problem of the
    polish (``A``, ``b``, ``mu``, ``lower``; ``rho``, ``reg`` and the impulse scale ``c``
    (B,)). Outputs per thread: the interior point's (scaled) iterate and f (n, C), the
    scaled residual (n,), dPi/dz (n, C, d), dPi/dmu and dPi/dl (n, C), the LU
    factorisation of dF/df (n, C, C) with its pivots (n, C), the interior point's
    iterations, solved and unbounded flags (n,).
    """
    t = wp.tid()
    r = int(rows[t])
    n = K * d
    ok, diverged, it = _interior_point(
        A_ipm,
        b_ipm,
        mu_ipm,
        lower_ipm,
        apex,
        active,
        r,
        t,
        d,
        K,
        gap,
        max_iter,
        blowup,
        tiny,
        inf,
        vec,
        LU,
    )
    iterations[t] = wp.int64(it)
    solved[t] = ok
    unbounded[t] = diverged
    for i in range(n):
        f_ipm[t, i] = vec[t, F_, i]
        vec[t, F_, i] = vec[t, F_, i] * c[r]
    _polish_into(
        A, b, mu, lower, rho[r], reg[r], c[r], r, t, d, K, target, polish_steps, eps, vec, V,
        f_out, res_out, P_out, dmu_out, dl_out, LU, piv,
    )  # fmt: skip


@wp.kernel
def fused_polish(
    rows: wp.array(dtype=wp.int32),
    f0: wp.array2d(dtype=Any),
    A: wp.array3d(dtype=Any),
    b: wp.array2d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    lower: wp.array2d(dtype=Any),
    rho: wp.array(dtype=Any),
    reg: wp.array(dtype=Any),
    c: wp.array(dtype=Any),
    d: int,
    K: int,
    target: Any,
    polish_steps: int,
    eps: Any,
    vec: wp.array3d(dtype=Any),
    V: wp.array3d(dtype=Any),
    f_out: wp.array2d(dtype=Any),
    res_out: wp.array(dtype=Any),
    P_out: wp.array3d(dtype=Any),
    dmu_out: wp.array2d(dtype=Any),
    dl_out: wp.array2d(dtype=Any),
    LU: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
):
    """The polish alone, from the point f0[t] (n, C), for problem rows[t]: the fast paths'
    guesses and warm starts. Inputs and outputs as :func:`fused_solve`'s."""
    t = wp.tid()
    r = int(rows[t])
    for i in range(K * d):
        vec[t, F_, i] = f0[t, i]
    _polish_into(
        A, b, mu, lower, rho[r], reg[r], c[r], r, t, d, K, target, polish_steps, eps, vec, V,
        f_out, res_out, P_out, dmu_out, dl_out, LU, piv,
    )  # fmt: skip


# --- the whole forward pass and the backward pass, one thread per problem ---------------
#
# ``fused_forward`` runs for its problem everything that :func:`diffcontact.contact.
# cone_qp.solve_cone_qp` and ``_forward`` do on the reference backend after the batch is
# flattened: the per-contact equilibration (``_contact_scales``) and the symmetrisation of
# ``A``, the scaling and decoupling of inactive contacts, the fast paths' guesses
# (:mod:`diffcontact.contact.closed_form`, the caller's warm start) and their polish, the
# interior point with its retries, the unboundedness certificate with its Tikhonov re-solve
# (:func:`diffcontact.contact.cone_qp._unbounded`), and the status. ``fused_backward`` is
# the implicit backward pass of ``_ConeQPFunction`` with the chain rule of the scaling.
#
# Workspace rows: pass 0 (the problem) uses row t, pass 1 (the Tikhonov re-solve of the
# certificate, run only where it is needed) row n + t of every workspace array.

SC_AS = wp.constant(0)  # columns of the per-row scalars ``sc``: a_s, b_s, c, rho, reg
SC_BS = wp.constant(1)
SC_C = wp.constant(2)
SC_RHO = wp.constant(3)
SC_REG = wp.constant(4)
N_SC = 5
# rows of the saved array ``sv`` (n, N_SV, C) that the backward pass reads
SV_F = wp.constant(0)  # the scaled solution f' (inactive entries zero)
SV_DMU = wp.constant(1)  # dPi/dmu
SV_DL = wp.constant(2)  # dPi/dl
SV_S = wp.constant(3)  # contact scales s (per component)
SV_ACT = wp.constant(4)  # 1 on active components, 0 elsewhere
SV_RHO = wp.constant(5)  # rho in entry 0
SV_P = wp.constant(6)  # dPi/dz, d rows (row a of block k at index k d + j)
TINY_DET = wp.constant(wp.float64(1e-8))  # relative determinant of the closed form
HUNDREDTH = wp.constant(wp.float64(0.01))  # the retries' gap factor


@wp.func
def _trimmed(act: wp.array2d(dtype=wp.bool), t: int, K: int):
    """The number of contacts up to problem t's last active one (at least 1)."""
    last = int(0)
    for k in range(K):
        if act[t, k]:
            last = k + 1
    return wp.max(last, 1)


@wp.func
def _equilibrate(
    A_in: wp.array3d(dtype=Any),
    b_in: wp.array2d(dtype=Any),
    lower_in: wp.array2d(dtype=Any),
    mu_in: wp.array2d(dtype=Any),
    active_in: wp.array2d(dtype=wp.bool),
    t: int,
    d: int,
    K: int,
    spread: Any,
    diag0: wp.array2d(dtype=Any),
    b0: wp.array2d(dtype=Any),
    mu0: wp.array2d(dtype=Any),
    lower0: wp.array2d(dtype=Any),
    act: wp.array2d(dtype=wp.bool),
    row1: int,
    sv: wp.array3d(dtype=Any),
):
    """``_contact_scales`` and the diagonal of ``S sym(A) S``, ``S b``, ``lower / s`` into
    row t of the workspace (the scales into sv[t, SV_S], the active mask into
    sv[t, SV_ACT] and rows t, row1 of ``act``); b and the diagonal only up to the last
    active contact (``_trimmed``). The whole matrix is built by :func:`_masked_matrix`."""
    zero = type(spread)(0.0)
    one = type(spread)(1.0)
    top = zero
    low = zero
    any_ok = bool(False)
    for k in range(K):
        a = A_in[t, k * d, k * d]
        if active_in[t, k] and a > zero:
            top = _pick(any_ok, wp.max(top, a), a)
            low = _pick(any_ok, wp.min(low, a), a)
            any_ok = True
    wide = any_ok and top > spread * low
    for k in range(K):
        a = A_in[t, k * d, k * d]
        on = active_in[t, k]
        act[t, k] = on
        act[row1, k] = on
        s = one
        if wide and on and a > zero:
            s = wp.sqrt(top / a)
        for j in range(d):
            sv[t, SV_S, k * d + j] = s
            sv[t, SV_ACT, k * d + j] = _pick(on, one, zero)
        lower0[t, k] = lower_in[t, k] / s
        mu0[t, k] = mu_in[t, k]
    n = _trimmed(act, t, K) * d  # (the solve's contacts)
    for i in range(n):
        si = sv[t, SV_S, i]
        b0[t, i] = b_in[t, i] * si
        diag0[t, i] = type(spread)(0.5) * (A_in[t, i, i] * (si * si) + A_in[t, i, i] * (si * si))


@wp.func
def _prepare(
    diag0: wp.array2d(dtype=Any),
    b0: wp.array2d(dtype=Any),
    mu0: wp.array2d(dtype=Any),
    lower0: wp.array2d(dtype=Any),
    act: wp.array2d(dtype=wp.bool),
    r: int,
    d: int,
    K: int,
    kkt_reg: Any,
    tiny: Any,
    bm: wp.array2d(dtype=Any),
    mum: wp.array2d(dtype=Any),
    lowerm: wp.array2d(dtype=Any),
    bipm: wp.array2d(dtype=Any),
    muipm: wp.array2d(dtype=Any),
    loweripm: wp.array2d(dtype=Any),
    apex: wp.array2d(dtype=Any),
    sc: wp.array2d(dtype=Any),
):
    """The scaled, decoupled problems of ``_forward`` (the polish's ``data`` and the
    interior point's ``ipm_data``) of workspace row r, but for their matrices
    (:func:`_masked_matrix`, :func:`_ipm_matrix`); reads the diagonal ``diag0`` of the
    equilibrated matrix only."""
    zero = type(tiny)(0.0)
    one = type(tiny)(1.0)
    n_act = int(0)
    sdiag = zero
    lmax = zero
    bmax = zero
    for k in range(K):
        if act[r, k]:
            n_act += d
            lmax = wp.max(lmax, lower0[r, k])
            for j in range(d):
                i = k * d + j
                sdiag = sdiag + diag0[r, i]
                bmax = wp.max(bmax, wp.abs(b0[r, i]))
    a_s = wp.max(sdiag / type(tiny)(wp.max(n_act, 1)), tiny)
    if not (a_s > type(tiny)(1e3) * tiny):
        a_s = one
    b_s = wp.max(bmax, a_s * lmax)
    if not (b_s > zero):
        b_s = a_s
    c = b_s / a_s
    sc[r, SC_AS] = a_s
    sc[r, SC_BS] = b_s
    sc[r, SC_C] = c
    sc[r, SC_RHO] = one / a_s
    sc[r, SC_REG] = kkt_reg * a_s
    for k in range(K):
        on = act[r, k]
        lm = _pick(on, lower0[r, k], zero)
        m = one
        if d > 1 and on:
            m = mu0[r, k]
        lowerm[r, k] = lm
        mum[r, k] = m
        if d > 1:
            muipm[r, k] = _pick(m > zero, m, one)
            apex[r, k] = _pick(m == zero, one, zero)
            loweripm[r, k] = _pick(m > zero and lm == zero, -one, lm / c)
        else:
            muipm[r, k] = m
            apex[r, k] = zero
            loweripm[r, k] = lm / c
    for k in range(K):
        for a in range(d):
            i = k * d + a
            on_i = act[r, k]
            free_i = d > 1 and a > 0 and mum[r, k] == zero
            bi = b0[r, i]
            if not on_i:
                bi = _pick(a == 0, b_s, zero)
            bm[r, i] = bi
            bipm[r, i] = _pick(free_i, zero, bi) / b_s


_MASKED_MATRIX_CPP = r"""
auto* a = (decltype(A_in.data))((char*)A_in.data + (long long)t * A_in.strides[0]);
const long long a1 = A_in.strides[1] / (long long)sizeof(*a);
const long long a2 = A_in.strides[2] / (long long)sizeof(*a);
const auto* s = (decltype(sv.data))((char*)sv.data + (long long)t * sv.strides[0]
                                     + (long long)s_row * sv.strides[1]);
const long long s2 = sv.strides[2] / (long long)sizeof(*s);
const char* on = (const char*)act.data + (long long)r * act.strides[0];
const long long o1 = act.strides[1];
auto* am = (decltype(Am.data))((char*)Am.data + (long long)r * Am.strides[0]);
const long long m1 = Am.strides[1] / (long long)sizeof(*am);
const long long m2 = Am.strides[2] / (long long)sizeof(*am);
auto zero = a_s;
zero = 0;
const auto half = zero + 0.5f;
bool nonfinite = false;
bool asym = false;
const int n = K * d;
for (int i = 0; i < n; ++i) {
    const bool on_k = *(const bool*)(on + (long long)(i / d) * o1);
    const auto si = s[i * s2];
    const auto* ai = a + i * a1;
    for (int j = i; j < n; ++j) {
        const auto x = ai[j * a2];
        const auto x_t = a[j * a1 + i * a2];
        if (!(wp::isfinite(x) && wp::isfinite(x_t))) nonfinite = true;
        if (check != 0) {
            const auto diff = x - x_t;
            if (wp::abs(diff) > asym_tol) asym = true;
        }
        auto v = zero;
        if (on_k && *(const bool*)(on + (long long)(j / d) * o1)) {
            const auto sj = s[j * s2];
            const auto p1 = si * sj;
            const auto q1 = x * p1;
            const auto p2 = sj * si;
            const auto q2 = x_t * p2;
            const auto sum = q1 + q2;
            v = half * sum;
        } else if (!on_k && i == j) {
            v = a_s;
        }
        am[i * m1 + j * m2] = v;
        am[j * m1 + i * m2] = v;
    }
}
if (nonfinite) *(int*)((char*)flags.data) = 1;
if (asym) *(int*)((char*)flags.data + 8 * flags.strides[0]) = 1;
"""


@wp.func_native(_MASKED_MATRIX_CPP)
def _masked_matrix_cpp(
    A_in: wp.array3d(dtype=wp.float64),
    sv: wp.array3d(dtype=wp.float64),
    s_row: int,
    act: wp.array2d(dtype=wp.bool),
    t: int,
    r: int,
    d: int,
    K: int,
    a_s: wp.float64,
    check: int,
    asym_tol: wp.float64,
    flags: wp.array(dtype=wp.int32),
    Am: wp.array3d(dtype=wp.float64),
): ...


@wp.func_native(_MASKED_MATRIX_CPP)
def _masked_matrix_cpp(
    A_in: wp.array3d(dtype=wp.float32),
    sv: wp.array3d(dtype=wp.float32),
    s_row: int,
    act: wp.array2d(dtype=wp.bool),
    t: int,
    r: int,
    d: int,
    K: int,
    a_s: wp.float32,
    check: int,
    asym_tol: wp.float32,
    flags: wp.array(dtype=wp.int32),
    Am: wp.array3d(dtype=wp.float32),
): ...


@wp.func
def _masked_matrix(
    A_in: wp.array3d(dtype=Any),
    sv: wp.array3d(dtype=Any),
    sc: wp.array2d(dtype=Any),
    act: wp.array2d(dtype=wp.bool),
    t: int,
    r: int,
    d: int,
    K: int,
    tikhonov: bool,
    delta: Any,
    check: int,
    asym_tol: Any,
    flags: wp.array(dtype=wp.int32),
    Am: wp.array3d(dtype=Any),
):
    """The polish's matrix ``A_m`` of workspace row r: on the active contacts ``S sym(A)
    S`` (from the input A_in[t] and the scales sv[t, SV_S]), or for the certificate's
    Tikhonov problem (``tikhonov``, r = row1) ``A_m[t] / a_s + delta I``; inactive
    contacts decoupled (``a_s`` on their diagonal). From the input, one pass over the
    pairs (i, j >= i), which also makes :func:`_flag_finite`'s tests of this block
    (finiteness, and where ``check`` symmetry to ``asym_tol``)."""
    a_s = sc[r, SC_AS]
    zero = type(a_s)(0.0)
    n = K * d
    if tikhonov:
        a_t = sc[t, SC_AS]
        for i in range(n):
            on_i = act[r, i // d]
            for j in range(n):
                v = zero
                if on_i and act[r, j // d]:
                    v = Am[t, i, j] / a_t + _pick(i == j, delta, zero)
                elif (not on_i) and i == j:
                    v = a_s
                Am[r, i, j] = v
        return
    _masked_matrix_cpp(A_in, sv, SV_S, act, t, r, d, K, a_s, check, asym_tol, flags, Am)


@wp.func
def _ipm_matrix(
    Am: wp.array3d(dtype=Any),
    mum: wp.array2d(dtype=Any),
    sc: wp.array2d(dtype=Any),
    r: int,
    d: int,
    K: int,
    Aipm: wp.array3d(dtype=Any),
):
    """The interior point's matrix of workspace row r (``_prepare``'s ``A_m / a_s`` with
    the tangential components of frictionless contacts decoupled), built only for the
    problems that need the interior point."""
    a_s = sc[r, SC_AS]
    zero = type(a_s)(0.0)
    for k in range(K):
        for a in range(d):
            i = k * d + a
            free_i = d > 1 and a > 0 and mum[r, k] == zero
            for k2 in range(K):
                for a2 in range(d):
                    j = k2 * d + a2
                    free_j = d > 1 and a2 > 0 and mum[r, k2] == zero
                    w = zero
                    if not (free_i or free_j):
                        w = Am[r, i, j]
                    if free_i and i == j:
                        w = a_s
                    Aipm[r, i, j] = w / a_s


@wp.func
def _quad2(A: wp.array3d(dtype=Any), b: wp.array2d(dtype=Any), r: int, i0: int, f0: Any, f1: Any):
    """0.5 f^T A f + b^T f for the 2-vector f on block i0 of row r (as ``_objective``)."""
    half = type(f0)(0.5)
    af0 = A[r, i0, i0] * f0 + A[r, i0, i0 + 1] * f1
    af1 = A[r, i0 + 1, i0] * f0 + A[r, i0 + 1, i0 + 1] * f1
    return (half * (f0 * af0) + b[r, i0] * f0) + (half * (f1 * af1) + b[r, i0 + 1] * f1)


@wp.func
def _guess(
    Am: wp.array3d(dtype=Any),
    bm: wp.array2d(dtype=Any),
    mum: wp.array2d(dtype=Any),
    lowerm: wp.array2d(dtype=Any),
    act: wp.array2d(dtype=wp.bool),
    r: int,
    d: int,
    K: int,
    tiny: Any,
    inf: Any,
    vec: wp.array3d(dtype=Any),
):
    """The fast paths' starting point (``separating_guess``, ``single_contact_minimiser``)
    into vec[r, F_]; returns whether one applies."""
    n = K * d
    zero = type(tiny)(0.0)
    for i in range(n):
        vec[r, F_, i] = zero
    separating = bool(True)
    n_on = int(0)
    kk = int(0)
    for k in range(K):
        if lowerm[r, k] != zero:
            separating = False
        if act[r, k]:
            n_on += 1
            kk = k
            bn = bm[r, k * d]
            if d == 1:
                if not (bn >= zero):
                    separating = False
            else:
                bt = bm[r, k * d + 1]
                bt2 = zero
                if d > 2:
                    bt2 = bm[r, k * d + 2]
                if not (mum[r, k] * wp.sqrt(bt * bt + bt2 * bt2) <= bn):
                    separating = False
    if separating:
        return True
    if n_on != 1 or d > 2:
        return False
    i0 = kk * d
    a_nn = Am[r, i0, i0]
    l_k = lowerm[r, kk]
    b_n = bm[r, i0]
    if d == 1:
        if not (a_nn > tiny):
            return False
        vec[r, F_, i0] = wp.max(l_k, -b_n / a_nn)
        return True
    a_nt = Am[r, i0, i0 + 1]
    a_tn = Am[r, i0 + 1, i0]
    a_tt = Am[r, i0 + 1, i0 + 1]
    b_t = bm[r, i0 + 1]
    m = mum[r, kk]
    det = a_nn * a_tt - a_nt * a_nt
    if not (a_nn > tiny and a_tt > tiny and det > type(tiny)(TINY_DET) * a_nn * a_tt):
        return False
    one = type(tiny)(1.0)
    # candidates as single_contact_minimiser: the rays t (1, +-mu), the segment, the free one
    best_n = zero
    best_t = zero
    best_q = inf
    for c in range(4):
        fn = zero
        ft = zero
        if c < 2:
            sgn = _pick(c == 0, one, -one)
            r1 = m * sgn
            # r^T A r summed as einsum's bni,bij,bnj (row by row)
            rar = (one * (a_nn * one) + one * (a_nt * r1)) + (r1 * (a_tn * one) + r1 * (a_tt * r1))
            tt = -(one * b_n + r1 * b_t) / rar
            tt = wp.max(tt, l_k)
            fn = tt * one
            ft = tt * r1
        elif c == 2:
            cap = m * l_k
            fn = l_k
            ft = wp.clamp(-(b_t + a_nt * l_k) / a_tt, -cap, cap)
        else:
            fn = -(a_tt * b_n - a_nt * b_t) / det
            ft = -(a_nn * b_t - a_nt * b_n) / det
        q = _quad2(Am, bm, r, i0, fn, ft)
        if c == 3 and not (fn >= l_k and wp.abs(ft) <= m * fn):
            q = inf
        if q < best_q or c == 0:
            best_q = q
            best_n = fn
            best_t = ft
    vec[r, F_, i0] = best_n
    vec[r, F_, i0 + 1] = best_t
    return True


@wp.func
def _at_a_kink(
    A: wp.array3d(dtype=Any),
    b: wp.array2d(dtype=Any),
    mu: wp.array2d(dtype=Any),
    lower: wp.array2d(dtype=Any),
    act: wp.array2d(dtype=wp.bool),
    r: int,
    t: int,
    d: int,
    K: int,
    rho: Any,
    c: Any,
    vec: wp.array3d(dtype=Any),
):
    """Whether the natural map is not differentiable at the point in row F_: for an active
    contact, ``z = f - rho (A f + b)`` lies (to ``FLAT`` relative to the largest ``|z|``) on
    a boundary between the projection's pieces of :func:`_project`: the cone's surface
    (``||z_t|| = mu z_n``), the polar cone's (``mu ||z_t|| = -z_n``) or the lower bound
    (``z_n = l``). There strict complementarity fails, and a regular dF/df (of one piece)
    does not make the minimiser unique: e.g. a disk in a corner, a singular A, Newton from
    zero ending at the end of the optimal segment where one contact just reaches the
    cone's surface with no sliding velocity. Writes A f into row AF."""
    zero = type(rho)(0.0)
    one = type(rho)(1.0)
    _matvec(A, r, vec, t, F_, AF, K, d)
    zmax = c
    for k in range(K):
        if act[r, k]:
            zk = _z_block(b, r, t, d, k, rho, vec, F_)
            for j in range(d):
                zmax = wp.max(zmax, wp.abs(zk[j]))
    tol = type(rho)(FLAT) * zmax
    kink = bool(False)
    for k in range(K):
        if act[r, k]:
            zk = _z_block(b, r, t, d, k, rho, vec, F_)
            zn = zk[0]
            m = mu[r, k]
            if d == 1 or lower[r, k] > zero:
                if wp.abs(zn - lower[r, k]) <= tol:
                    kink = True
            if d > 1:
                s = wp.sqrt(zk[1] * zk[1] + zk[2] * zk[2])
                norm = wp.sqrt(one + m * m)
                if wp.abs(zn + m * s) <= tol * norm:  # the polar cone's surface (mu = 0: z_n = 0)
                    kink = True
                if m > zero and wp.abs(m * zn - s) <= tol * norm:  # the cone's surface
                    kink = True
    return kink


@wp.func
def _solve_row(
    Am: wp.array3d(dtype=Any),
    bm: wp.array2d(dtype=Any),
    mum: wp.array2d(dtype=Any),
    lowerm: wp.array2d(dtype=Any),
    Aipm: wp.array3d(dtype=Any),
    bipm: wp.array2d(dtype=Any),
    muipm: wp.array2d(dtype=Any),
    loweripm: wp.array2d(dtype=Any),
    apex: wp.array2d(dtype=Any),
    act: wp.array2d(dtype=wp.bool),
    sc: wp.array2d(dtype=Any),
    r: int,
    d: int,
    K: int,
    guessed: bool,
    gap: Any,
    max_iter: int,
    retries: int,
    target: Any,
    tol: Any,
    polish_steps: int,
    first_steps: int,
    canonical: int,
    blowup: Any,
    eps: Any,
    tiny: Any,
    inf: Any,
    vec: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
    V: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
):
    """The solve of ``_forward`` for workspace row r: polish of the guess in vec[r, F_]
    (if ``guessed``), else ``first_steps`` Newton steps from zero (kept at a kink of the
    natural map only where ``canonical`` is 0: ``SolverSettings.canonical``); where that
    does not finish, interior point and polish with retries. Leaves the polished
    point (f, F, P, dmu, dl in their rows of vec; the reduced factorisation of dF/df of
    :func:`_reduced_factor` in M[r], piv[r]); returns (residual, interior-point
    iterations, interior point diverged, the size m of the factorised block)."""
    rho = sc[r, SC_RHO]
    reg = sc[r, SC_REG]
    c = sc[r, SC_C]
    n = K * d
    iterations = int(0)
    diverged = bool(False)
    res = inf
    kept = bool(False)
    m = int(0)
    if guessed:
        res, m, _umin = _polish(
            Am, bm, mum, lowerm, r, r, d, K, rho, reg, c, target, polish_steps, eps, vec, M, V,
            piv,
        )  # fmt: skip
        kept = res <= target
    else:
        # Newton from zero first: kept where it converges to a point where the natural map
        # is differentiable (strict complementarity) with a regular dF/df, an isolated and
        # so (convex problem) the unique minimiser, the one the interior point would have
        # found; else (a minimiser that may not be unique, which the interior point's
        # central path picks) the interior point
        for i in range(n):
            vec[r, F_, i] = type(gap)(0.0)
        res, m, umin = _polish(
            Am, bm, mum, lowerm, r, r, d, K, rho, reg, c, target, first_steps, eps, vec, M, V,
            piv,
        )  # fmt: skip
        kept = res <= target and umin > type(gap)(FLAT)
        if kept and canonical != 0:  # and not at a kink of the natural map, where
            # regular is not unique (the caller asks for the canonical minimiser)
            kept = not _at_a_kink(Am, bm, mum, lowerm, act, r, r, d, K, rho, c, vec)
    if not kept:
        _ipm_matrix(Am, mum, sc, r, d, K, Aipm)
        g = gap
        for _attempt in range(retries + 1):
            _ok, div, it = _interior_point(
                Aipm, bipm, muipm, loweripm, apex, act, r, r, d, K, g, max_iter, blowup, tiny,
                inf, vec, M,
            )  # fmt: skip
            iterations += it
            diverged = div
            for i in range(n):
                vec[r, F_, i] = vec[r, F_, i] * c
            res, m, _umin = _polish(
                Am, bm, mum, lowerm, r, r, d, K, rho, reg, c, target, polish_steps, eps, vec, M,
                V, piv,
            )  # fmt: skip
            if not (res > tol and not div):
                break
            g = g * type(gap)(HUNDREDTH)
    for k in range(K):
        if not act[r, k]:
            for j in range(d):
                vec[r, F_, k * d + j] = type(gap)(0.0)
    return res, iterations, diverged, m


@wp.func
def _certifies(
    Am: wp.array3d(dtype=Any),
    bm: wp.array2d(dtype=Any),
    mum: wp.array2d(dtype=Any),
    act: wp.array2d(dtype=wp.bool),
    sc: wp.array2d(dtype=Any),
    t: int,
    d: int,
    K: int,
    g: wp.array3d(dtype=Any),
    gr: int,
    gs: int,
    g_scale: Any,
    f: wp.array3d(dtype=Any),
    fr: int,
    fs: int,
    f_scale: Any,
    slope_max: Any,
    sqrt_eps: Any,
    eps: Any,
    u: wp.array3d(dtype=Any),
    ur: int,
    us: int,
):
    """``_certifies_unbounded`` of problem t (scaled data A_m / a_s, b_m / b_s) for the
    direction g[gr, gs] / g_scale at the solver's point f[fr, fs] / f_scale; u[ur, us] is
    scratch."""
    n = K * d
    zero = type(slope_max)(0.0)
    a_s = sc[t, SC_AS]
    b_s = sc[t, SC_BS]
    scale = zero
    for k in range(K):
        gk = _load(g, gr, gs, k, d) / g_scale
        uk, _P, _dm, _dl = _project(gk, mum[t, k], zero, d)
        if not act[t, k]:
            uk = wp.vector(zero, zero, zero)
        _store(u, ur, us, k, d, uk)
        for j in range(d):
            scale = wp.max(scale, wp.abs(uk[j]))
    if not (scale > zero):
        scale = type(slope_max)(1.0)
    slope = zero
    curv = zero
    slope_f = zero  # (A f + b)^T u: the slope along u at the solver's point
    a_max = zero
    f_max = zero
    for i in range(n):
        u[ur, us, i] = u[ur, us, i] / scale
    for i in range(n):
        bi = bm[t, i] / b_s
        slope = slope + bi * u[ur, us, i]
        Au = zero
        Af = zero
        for j in range(n):
            a = Am[t, i, j] / a_s
            fj = f[fr, fs, j] / f_scale
            Au = Au + a * u[ur, us, j]
            Af = Af + a * fj
            a_max = wp.max(a_max, wp.abs(a))
            f_max = wp.max(f_max, wp.abs(fj))
        curv = curv + u[ur, us, i] * Au
        slope_f = slope_f + (Af + bi) * u[ur, us, i]
    # the test of the slope at f, where its rounding error is below a quarter of the slope
    noise = eps * type(slope)(n) * a_max * f_max
    still_falls = slope_f <= type(slope)(0.5) * slope or type(slope)(4.0) * noise >= -slope
    return slope <= slope_max and curv <= sqrt_eps * slope * slope and still_falls


@wp.func
def _flag_finite(
    A_in: wp.array3d(dtype=Any),
    b_in: wp.array2d(dtype=Any),
    mu_in: wp.array2d(dtype=Any),
    lower_in: wp.array2d(dtype=Any),
    warm_in: wp.array2d(dtype=Any),
    t: int,
    n: int,
    K: int,
    n_skip: int,
    has_warm: int,
    check: int,
    flags: wp.array(dtype=wp.int32),
):
    """flags[0..4] = 1 where problem t's A, b, mu, lower or warm start is not finite, and
    where ``check``, flags[6..8] = 1 where mu < 0, lower < 0 or A is not symmetric (to
    ``1e-6 max_i |A_ii| + 1e-12``), tests of ``solve_cone_qp``'s ``check_inputs`` (every
    thread that finds one writes the same value; flags[9], semi-definiteness, is
    :func:`_semidefinite`'s). The leading n_skip x n_skip block of A is left to
    :func:`_masked_matrix`, which reads it anyway; returns the symmetry tolerance."""
    scale = wp.abs(A_in[t, 0, 0])
    if check != 0:
        for i in range(n):
            scale = wp.max(scale, wp.abs(A_in[t, i, i]))
        for k in range(K):
            if mu_in[t, k] < type(scale)(0.0):
                flags[6] = 1
            if lower_in[t, k] < type(scale)(0.0):
                flags[7] = 1
    asym_tol = type(scale)(1e-6) * scale + type(scale)(1e-12)
    for i in range(n):  # one pass over the pairs (i, j >= i) outside the leading block
        for j in range(wp.max(i, n_skip), n):
            a = A_in[t, i, j]
            a_t = A_in[t, j, i]
            if not (wp.isfinite(a) and wp.isfinite(a_t)):
                flags[0] = 1
            if check != 0 and wp.abs(a - a_t) > asym_tol:
                flags[8] = 1
    for i in range(n):
        if not wp.isfinite(b_in[t, i]):
            flags[1] = 1
        if has_warm != 0:
            if not wp.isfinite(warm_in[t, i]):
                flags[4] = 1
    for k in range(K):
        if not wp.isfinite(mu_in[t, k]):
            flags[2] = 1
        if not wp.isfinite(lower_in[t, k]):
            flags[3] = 1
    return asym_tol


@wp.func
def _semidefinite(
    A_in: wp.array3d(dtype=Any),
    active_in: wp.array2d(dtype=wp.bool),
    t: int,
    d: int,
    K: int,
    M: wp.array3d(dtype=Any),
):
    """Whether problem t's A, on its active contacts among the first K, is positive
    semi-definite to the tolerance of ``fused.SEMIDEFINITE_TOL``: the Cholesky
    factorisation of that block plus ``SEMIDEFINITE max |A_ij| I`` succeeds (rounding-level
    negative eigenvalues of a singular A pass, an indefinite A fails). Uses ``M[t]`` as
    scratch; reads the lower triangle (symmetry is checked apart)."""
    n = K * d
    zero = type(A_in[t, 0, 0])(0.0)
    scale = zero
    for i in range(n):  # one pass: the masked lower triangle and its largest entry
        on = active_in[t, i // d]
        for j in range(i + 1):
            a = _pick(on and active_in[t, j // d], A_in[t, i, j], zero)
            M[t, i, j] = a
            scale = wp.max(scale, wp.abs(a))
    if scale == zero:
        return True  # (a zero block is semi-definite)
    shift = type(scale)(SEMIDEFINITE) * scale
    for i in range(n):
        M[t, i, i] = _pick(active_in[t, i // d], M[t, i, i] + shift, scale)
    return _cholesky(M, t, n)


@wp.kernel
def fused_forward(
    A_in: wp.array3d(dtype=Any),
    b_in: wp.array2d(dtype=Any),
    mu_in: wp.array2d(dtype=Any),
    lower_in: wp.array2d(dtype=Any),
    active_in: wp.array2d(dtype=wp.bool),
    warm_in: wp.array2d(dtype=Any),
    n_total: int,
    first: int,
    d: int,
    K_all: int,
    has_warm: int,
    check: int,
    passes: int,
    retries: int,
    max_iter: int,
    polish_steps: int,
    first_steps: int,
    canonical: int,
    gap: Any,
    target: Any,
    tol: Any,
    kkt_reg: Any,
    blowup: Any,
    eps: Any,
    tiny: Any,
    inf: Any,
    spread: Any,
    delta: Any,
    size_check: Any,
    size_again: Any,
    slope_max: Any,
    sqrt_eps: Any,
    diag0: wp.array2d(dtype=Any),
    Am: wp.array3d(dtype=Any),
    Aipm: wp.array3d(dtype=Any),
    M: wp.array3d(dtype=Any),
    V: wp.array3d(dtype=Any),
    vec: wp.array3d(dtype=Any),
    b0: wp.array2d(dtype=Any),
    bm: wp.array2d(dtype=Any),
    bipm: wp.array2d(dtype=Any),
    mu0: wp.array2d(dtype=Any),
    lower0: wp.array2d(dtype=Any),
    mum: wp.array2d(dtype=Any),
    lowerm: wp.array2d(dtype=Any),
    muipm: wp.array2d(dtype=Any),
    loweripm: wp.array2d(dtype=Any),
    apex: wp.array2d(dtype=Any),
    sc: wp.array2d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
    act: wp.array2d(dtype=wp.bool),
    f_out: wp.array2d(dtype=Any),
    res_out: wp.array(dtype=Any),
    it_out: wp.array(dtype=wp.int64),
    conv_out: wp.array(dtype=wp.bool),
    unb_out: wp.array(dtype=wp.bool),
    sv: wp.array3d(dtype=Any),
    LU_out: wp.array3d(dtype=Any),
    piv_out: wp.array2d(dtype=wp.int32),
    flags: wp.array(dtype=wp.int32),
):
    """``solve_cone_qp``'s whole forward pass for problem t of n_total (flat inputs in the
    compute dtype: ``A_in`` (n, C, C), ``b_in`` (n, C), ``mu_in``, ``lower_in``,
    ``active_in`` (n, K), ``warm_in`` (n, C) where ``has_warm``). Writes f (n, C) in the
    caller's scale, the status (n,), and for the backward pass f', dPi/dz, dPi/dmu, dPi/dl,
    the scales, the mask and rho into ``sv`` (n, N_SV, C) and the reduced factorisation of
    dF/df (:func:`_reduced_factor`) into ``LU_out``, ``piv_out``. Workspace arrays have
    2 n rows (see above). Sets
    ``flags[0..4]`` to 1 where A, b, mu, lower, warm_in hold non-finite values and
    ``flags[5]`` where the problem did not converge, ``flags[6..8]`` where ``check`` finds
    bad input (see ``_flag_finite``; zeros on entry) and ``flags[9]`` where it finds A
    not positive semi-definite on the active contacts (:func:`_semidefinite`). Thread i
    solves problem t = first + i (a launch may cover a range of the problems)."""
    t = wp.tid() + first
    zero = type(tol)(0.0)
    # the trailing inactive contacts are decoupled (identity rows, zero impulse): the solve
    # runs on the contacts up to the last active one (callers pad at the end); its leading
    # block of A is checked where _masked_matrix reads it
    K = _trimmed(active_in, t, K_all)
    n = K * d
    asym_tol = _flag_finite(
        A_in, b_in, mu_in, lower_in, warm_in, t, K_all * d, K_all, n, has_warm, check, flags
    )
    if check != 0:
        if not _semidefinite(A_in, active_in, t, d, K, M):
            flags[9] = 1
    row1 = n_total + t
    _equilibrate(
        A_in, b_in, lower_in, mu_in, active_in, t, d, K_all, spread, diag0, b0, mu0, lower0, act,
        row1, sv,
    )  # fmt: skip
    again = bool(False)
    cert = bool(False)
    res0 = zero
    for p in range(passes):
        r = t
        if p == 1:
            if not again:
                break
            r = row1
            # the Tikhonov problem A_hat + delta I, b_hat, mu_m, lower 0 of ``_unbounded``
            a_s = sc[t, SC_AS]
            b_s = sc[t, SC_BS]
            for i in range(n):
                b0[r, i] = bm[t, i] / b_s
                diag0[r, i] = Am[t, i, i] / a_s + delta  # (_prepare's a_s)
            for k in range(K):
                mu0[r, k] = mum[t, k]
                lower0[r, k] = zero
        _prepare(
            diag0, b0, mu0, lower0, act, r, d, K, kkt_reg, tiny, bm, mum, lowerm, bipm, muipm,
            loweripm, apex, sc,
        )  # fmt: skip
        _masked_matrix(A_in, sv, sc, act, t, r, d, K, p == 1, delta, check, asym_tol, flags, Am)
        guessed = _guess(Am, bm, mum, lowerm, act, r, d, K, tiny, inf, vec)
        if p == 0 and has_warm != 0 and not guessed:
            for k in range(K):
                for j in range(d):
                    i = k * d + j
                    vec[r, F_, i] = _pick(act[r, k], warm_in[t, i] / sv[t, SV_S, i], zero)
            guessed = True
        res, iterations, _div, m = _solve_row(
            Am, bm, mum, lowerm, Aipm, bipm, muipm, loweripm, apex, act, sc, r, d, K, guessed,
            gap, max_iter, retries, target, tol, polish_steps, first_steps, canonical, blowup, eps,
            tiny, inf, vec, M, V, piv,
        )  # fmt: skip
        if p == 0:
            res0 = res
            res_out[t] = res
            it_out[t] = wp.int64(iterations)
            c = sc[t, SC_C]
            size = zero
            any_on = bool(False)
            for k in range(K):
                any_on = any_on or act[t, k]
            for i in range(n):
                fi = vec[t, F_, i]
                sv[t, SV_F, i] = fi
                sv[t, SV_DMU, i] = vec[t, DMU, i]
                sv[t, SV_DL, i] = vec[t, DL, i]
                f_out[t, i] = fi * sv[t, SV_S, i]
                size = wp.max(size, wp.abs(fi / c))
                piv_out[t, i] = piv[t, i]
                if i < m:  # (rows m.. of the reduced factorisation are not used)
                    for j in range(n):
                        LU_out[t, i, j] = M[t, i, j]
                for a in range(d):
                    sv[t, SV_P + a, i] = vec[t, P0 + a, i]
            for i in range(n, K_all * d):  # the trimmed contacts: zero impulse
                sv[t, SV_F, i] = zero
                sv[t, SV_DMU, i] = zero
                sv[t, SV_DL, i] = zero
                f_out[t, i] = zero
                for a in range(d):
                    sv[t, SV_P + a, i] = zero
            sv[t, SV_RHO, 0] = sc[t, SC_RHO]
            unconverged = res > tol
            if any_on and (unconverged or size > size_check):
                cert = _certifies(
                    Am, bm, mum, act, sc, t, d, K, sv, t, SV_F, c, sv, t, SV_F, c, slope_max,
                    sqrt_eps, eps, vec, t, FN,
                )  # fmt: skip
                again = (not cert) and (unconverged or size > size_again)
        else:
            one = type(tol)(1.0)
            cert = _certifies(
                Am, bm, mum, act, sc, t, d, K, vec, r, F_, one, sv, t, SV_F, sc[t, SC_C],
                slope_max, sqrt_eps, eps, vec, t, FN,
            )  # fmt: skip
    unb_out[t] = cert
    converged = res0 <= tol and not cert
    conv_out[t] = converged
    if not converged:
        flags[5] = 1


@wp.kernel
def fused_backward(
    grad_f: wp.array2d(dtype=Any),
    sv: wp.array3d(dtype=Any),
    LU: wp.array3d(dtype=Any),
    piv: wp.array2d(dtype=wp.int32),
    d: int,
    K_all: int,
    want_A: int,
    want_mu: int,
    first: int,
    vec: wp.array3d(dtype=Any),
    grad_A: wp.array3d(dtype=Any),
    grad_b: wp.array2d(dtype=Any),
    grad_mu: wp.array2d(dtype=Any),
    grad_l: wp.array2d(dtype=Any),
):
    """The implicit backward pass of problem t, with the chain rule of ``S sym(A) S``,
    ``S b``, ``lower / s`` and ``f = S f'``: v = dF/df^-T g (g = s grad_f on active
    components), then gradients to A, b, mu and lower as ``_ConeQPFunction.backward``.
    ``vec`` (n, 2, C) is scratch. Thread i handles problem t = first + i."""
    t = wp.tid() + first
    zero = type(grad_f[t, 0])(0.0)
    C = K_all * d
    K = int(0)  # as the forward pass: the contacts up to the last active one
    for k in range(K_all):
        if sv[t, SV_ACT, k * d] != zero:
            K = k + 1
    K = wp.max(K, 1)
    n = K * d
    for i in range(n, C):  # the trimmed contacts: no gradient
        grad_b[t, i] = zero
    for k in range(K, K_all):
        if want_mu != 0:
            grad_mu[t, k] = zero
        grad_l[t, k] = zero
    if want_A != 0:
        for i in range(C):
            for j in range(C):
                if i >= n or j >= n:
                    grad_A[t, i, j] = zero
    rho = sv[t, SV_RHO, 0]
    for i in range(n):
        g = grad_f[t, i] * sv[t, SV_S, i]
        vec[t, 0, i] = _pick(sv[t, SV_ACT, i] != zero, g, zero)
    # v = dF/df^-T g with the forward's reduced factorisation (``_reduced_factor``; its
    # per-contact bases again from P): Q^T dF/df Q = [[H, G], [0, I]], so with y = Q^T g
    # (range coordinates first, into row 1): H^T y_U = y_U, y_V = y_V - G^T y_U, v = Q y
    m = int(0)
    for k in range(K):
        _u0, _u1, dk = _block_basis(_load_block(sv, t, SV_P, k, d), d)
        m += dk
    cu = int(0)
    cv = m
    for k in range(K):
        u0, u1, dk = _block_basis(_load_block(sv, t, SV_P, k, d), d)
        x = _load(vec, t, 0, k, d)
        for j in range(d):
            y = wp.dot(x, _basis_column(u0, u1, j))
            if j < dk:
                vec[t, 1, cu] = y
                cu += 1
            else:
                vec[t, 1, cv] = y
                cv += 1
    if m > 0 and piv[t, 0] == 0:  # H = L L^T (see _reduced_factor)
        _cholesky_solve(LU, t, m, vec, 1)
    else:  # H = P L U (LAPACK pivots): U^T y = g, L^T w = y, y = P w
        for i in range(m):
            s = vec[t, 1, i]
            for k in range(i):
                s = s - LU[t, k, i] * vec[t, 1, k]
            vec[t, 1, i] = s / LU[t, i, i]
        for ii in range(m):
            i = m - 1 - ii
            s = vec[t, 1, i]
            for k in range(i + 1, m):
                s = s - LU[t, k, i] * vec[t, 1, k]
            vec[t, 1, i] = s
        for jj in range(m):
            j = m - 1 - jj
            p = piv[t, j] - 1
            if p != j:
                tmp = vec[t, 1, j]
                vec[t, 1, j] = vec[t, 1, p]
                vec[t, 1, p] = tmp
    for j in range(m, n):
        s = vec[t, 1, j]
        for i in range(m):
            s = s - LU[t, i, j] * vec[t, 1, i]
        vec[t, 1, j] = s
    cu = int(0)
    cv = m
    for k in range(K):
        u0, u1, dk = _block_basis(_load_block(sv, t, SV_P, k, d), d)
        x = wp.vector(zero, zero, zero)
        for j in range(d):
            y = zero
            if j < dk:
                y = vec[t, 1, cu]
                cu += 1
            else:
                y = vec[t, 1, cv]
                cv += 1
            x = x + y * _basis_column(u0, u1, j)
        _store(vec, t, 0, k, d, x)
    # P^T v per block, into row 1
    for k in range(K):
        for i in range(d):
            s = zero
            for j in range(d):
                s = s + sv[t, SV_P + j, k * d + i] * vec[t, 0, k * d + j]
            vec[t, 1, k * d + i] = s
    for k in range(K):
        on = sv[t, SV_ACT, k * d] != zero
        gm = zero
        gl = zero
        for j in range(d):
            gm = gm + sv[t, SV_DMU, k * d + j] * vec[t, 0, k * d + j]
            gl = gl + sv[t, SV_DL, k * d + j] * vec[t, 0, k * d + j]
        if want_mu != 0:
            grad_mu[t, k] = _pick(on and d > 1, gm, zero)
        grad_l[t, k] = _pick(on, gl, zero) / sv[t, SV_S, k * d]
    for i in range(n):
        si = sv[t, SV_S, i]
        Pv_i = (-rho) * vec[t, 1, i]
        grad_b[t, i] = _pick(sv[t, SV_ACT, i] != zero, Pv_i, zero) * si
        if want_A != 0:
            for j in range(n):
                Pv_j = (-rho) * vec[t, 1, j]
                G = type(rho)(0.5) * (Pv_i * sv[t, SV_F, j] + Pv_j * sv[t, SV_F, i])
                grad_A[t, i, j] = G * (si * sv[t, SV_S, j])
