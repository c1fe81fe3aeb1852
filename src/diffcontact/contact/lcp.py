"""The LCP contact model: Newton's restitution, a polyhedral friction cone, Lemke's method.

The standard velocity-level linear complementarity formulation of an impact
(Stewart and Trinkle 1996, Anitescu and Potra 1997; the formulation the paper's LCP
baseline used, appendix J), registered as ``"LCP"``. One impulse per contact, one phase.

Formulation
-----------

With ``A = J_C Mhat^-1 J_C^T`` and the pre-impact contact velocity
``v_C = J_C v = (v_n, v_t)`` per contact, the impulse of contact ``k`` is
``f_k = (p_k, D beta_k)``: a normal impulse ``p_k >= 0`` and a non-negative
combination of ``m`` unit tangent directions ``D = [d_1 ... d_m]`` (``(d-1, m)``).
The post-impact contact velocity is ``u = v_C + A f``. With a slack ``lambda_k >= 0``
(the sliding speed) the problem is, for every contact,

    0 <= p_k      _|_   u_n,k - s_n,k                  >= 0    (Newton's hypothesis)
    0 <= beta_k   _|_   D^T (u_t,k - s_t,k) + lambda_k 1 >= 0    (maximal dissipation)
    0 <= lambda_k _|_   mu_k p_k - 1^T beta_k           >= 0    (polyhedral Coulomb cone)

i.e. ``w = M z + q >= 0``, ``z >= 0``, ``z^T w = 0`` in ``z = (p, beta, lambda)`` per
contact, ``M = [[G^T A G, E], [mu e_n^T - E^T, 0]]``-style with ``G`` the map
``z -> f`` (:func:`lcp_matrices` builds it). The target velocity ``s``:

- Newton's hypothesis: ``s_n = -e v_n`` for an approaching contact (``v_n < 0``), 0
  otherwise. Contacts are detected by penetration, so a contact that already separates
  (``v_n > 0``) is in the set; with ``-e min(v_n, 0)`` it is only kept from
  approaching, as CM does (its compression impulse is then zero);
- penetration compensation (``v_C_star``, appendix G), as CM's restitution phase does
  it: there, the velocity after the impact is measured against ``v_C_star`` (``b =
  v_C_c - v_C^*`` in (7)), so the normal velocity ends at least at ``v_n^*`` and at
  least at Poisson's; here ``s_n = max(-e min(v_n, 0), v_n^*)`` and ``s_t = v_t^*``.
  For one frictionless contact both models give ``u_n = max(v_n, -e min(v_n, 0),
  v_n^*)``.

Friction cone: in 2D contact space (``d = 2``) the cone is exact, ``D = [t, -t]``; in
3D (``d = 3``) ``m`` directions (``LCP(directions=m)``, default 8) at angles
``2 pi j / m`` from the first tangent, a pyramid inscribed in Coulomb's cone: friction
is at worst ``cos(pi / m)`` of Coulomb's (92.4 % for 8, 98.1 % for 16) between two
directions and exact along them; each direction costs one LCP variable per contact
(``m + 2`` per contact). 8 is the compromise taken: the classic pyramid of 4
directions is up to 29 % short (``1 - cos(pi / 4)``), 16 directions take 18 variables
per contact instead of 10 to be at most 1.9 % short. ``d = 1`` (frictionless limits:
the rope's bending and stretch limits) has ``z = p`` only.

Solver: Lemke's complementary pivoting, batched
------------------------------------------------

Lemke's method is chosen over an interior point (what the paper's baseline used) or a
smoothed Fischer-Burmeister Newton because it ends on an exact *basis*: the set ``S``
of variables ``z_i`` that are basic, with ``w_S = 0`` and ``z_{not S} = 0``, so the
solution is ``z_S = -M_SS^-1 q_S`` exactly (re-solved from the data at the end, so
rounding in the tableau does not stay in the answer) and the piece of the piecewise
linear solution map that the backward pass differentiates is known. Lemke's method
solves this LCP (Stewart and Trinkle; Anitescu and Potra prove it processes the
velocity-level formulation with a PSD, possibly singular ``A``), and its basis matrix
is nonsingular at every pivot, also when ``A`` is singular (duplicate contacts,
equality constraints): the backward system never is. Interior points converge to the
analytic centre only approximately and stall exactly at the degenerate points below
(both complementary variables zero), which is where the paper's baseline returned NaN.

Batched: all problems of a batch pivot at once on a dense tableau ``(B, n, 2n + 2)``
(``[B^-1 | B^-1 (-M) | B^-1 (-c) | B^-1 q]``), one pivot per iteration of a loop whose
count is bounded by ``max_pivots``; problems leave the batch when they finish (the
artificial variable leaves the basis) and a problem with ``q >= 0`` is solved by
``z = 0`` without pivoting. Ties in the ratio test are broken lexicographically (rows
of ``(B^-1 q, B^-1) / column``; the first pivot takes the largest index among ties so
that the tableau starts lexico-positive), which prevents cycling on degenerate
problems (duplicate contacts always tie); where the artificial variable ties, it
leaves. Padded contacts (``active`` False) get an identity block, ``q = 1`` and a zero
covering entry: they never pivot and their impulse is exactly zero, and the tableau
entries of the real contacts are computed by the same element-wise operations whatever
the padding, so a state gets the same impulse in any batch (up to the final LU solve's
rounding). The data are scaled first by powers of two (exact): impulses by
``b / a``, velocities by ``b``, with ``a`` the largest diagonal entry of ``A`` and
``b`` the largest target-relative velocity of the real contacts. The solve runs in
float64 (``SolverSettings.compute_dtype``); results come back in the input dtype.

Backward: implicit differentiation on the final basis
-----------------------------------------------------

On the piece of the final basis, ``M_SS z_S + q_S = 0``, so for a loss gradient
``g = dL/dz``: ``y = -M_SS^-T g_S``, ``dL/dq = y`` and ``dL/dM = y z^T`` (zero outside
``S``), one LU solve with the forward's factorisation (a ``torch.autograd.Function``,
:func:`solve_lcp`). ``M`` and ``q`` are built from ``J_C``, ``Mhat_inv``, ``v``,
``mu`` and ``e`` by ordinary differentiable operations, so autograd carries the
gradient to all of them. Gradients are finite everywhere ``M_SS`` is (it is a basis
matrix, nonsingular by construction). At the degenerate points they are one-sided:

- *a contact exactly at the boundary of complementarity* (``z_i = w_i = 0``): the
  derivative of the piece of Lemke's final basis, i.e. with ``i`` in ``S`` if ``z_i``
  ended basic (at zero) and outside otherwise. It is the directional derivative for
  the perturbations that keep the degenerate basic variables non-negative (a
  one-sided derivative); no average of the two pieces is taken;
- *zero relative normal velocity* (``v_n = 0``): the contact is treated as separating,
  ``s_n = 0`` with zero derivative (the right derivative in ``v_n``); a problem whose
  ``q >= 0`` (every contact at rest or separating) has ``z = 0`` and ``S`` empty: zero
  gradients, the right derivatives;
- *duplicate contacts* (identical rows of ``J_C``, singular ``A``): the impulse is not
  unique (any split between the duplicates gives the same motion); Lemke's basis puts
  one of them in ``S`` (the first pivoted) and the other's ``w`` basic at zero, and
  the gradient is that of the split it returns. ``v_plus`` and its gradient do not
  depend on the split;
- *the penetration target*: at ``-e min(v_n, 0) = v_n^*`` the restitution branch is
  taken (gradient to ``e`` and ``v_n``, none to ``v_C_star``, which carries none
  anyway);
- *sticking*: a contact that presses (``p > 0``, ``mu > 0``) with zero tangential
  velocity (a body landing straight down, a disk rolling without slip) has its
  friction variables and their slacks all at zero, and Lemke's basis leaves the
  friction out: that piece (no friction) holds for no tangential perturbation (the
  derivative to ``v_t`` came out frictionless). The backward pass differentiates the
  sticking piece instead, the contact's first ``d - 1`` directions added to the basis
  (:func:`solve_lcp`'s ``stick``), which holds on both sides while friction is left
  (``mu p - 1^T beta > 0``), as CM's and Coulomb's derivatives do
  (``tests/contact/test_lcp.py``);
- ``mu = 0``: the derivative of the piece (the cone is linear in ``mu``), the right
  derivative.

Status and errors: a problem that ends by ray termination (no solution: an infeasible
frictionless problem with singular ``A``) or that did not finish within
``max_pivots`` or whose re-solved solution violates complementarity beyond ``tol``
raises :class:`LCPError` (a :class:`~diffcontact.contact.ConeQPError`, so
``System.simulate`` names the failing states), unless ``return_status=True``.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from diffcontact.contact.cone_qp import ConeQPError, SolverSettings, SolverStatus
from diffcontact.contact.first_order import first_order_only
from diffcontact.contact.impulse import (
    ImpulseResult,
    check_impulse_inputs,
    widened,
    wider_dtype,
)
from diffcontact.contact.models import ContactParams
from diffcontact.contact.operator import ContactOperator, as_operator
from diffcontact.fastops import lu_factor_ex
from diffcontact.shapes import broadcast_shapes, contact_dimension

__all__ = [
    "LCP",
    "LCPError",
    "NewtonLCP",
    "friction_directions",
    "lcp_impulse",
    "lcp_matrices",
    "solve_lcp",
]

DEFAULT_DIRECTIONS = 8


class LCPError(ConeQPError):
    """Raised when some LCPs of a batch end without a solution (see :func:`solve_lcp`)."""


# ----------------------------------------------------------------- the generic LCP solver
def _pow2(x: Tensor) -> Tensor:
    """The power of two at or below ``x > 0`` (exact scaling factors)."""
    _, exponent = torch.frexp(x)
    return torch.ldexp(torch.ones_like(x), exponent - 1)


def _pivot(T: Tensor, r: Tensor, e: Tensor) -> Tensor:
    """One pivot of every tableau of a batch: row ``r`` (B,), column ``e`` (B,)."""
    B = T.shape[0]
    idx = torch.arange(B, device=T.device)
    row = T[idx, r]  # (B, W)
    row = row / row[idx, e][:, None]
    col = T[idx, :, e]  # (B, n)
    T = T - col[:, :, None] * row[:, None, :]
    T[idx, r] = row
    # the entering column is a unit vector: set it exactly
    T[idx, :, e] = 0
    T[idx, r, e] = 1
    return T


def _lemke(M: Tensor, q: Tensor, active: Tensor, max_pivots: int, tol: float):
    """Lemke's method on a flat batch (compute dtype).

    Args:
        M: (B, n, n); q: (B, n); active: (B, n) bool (inactive rows are decoupled).
        max_pivots: cap on the pivots after the first.
        tol: relative tolerance of pivot elements and of ties in the ratio test.

    Returns:
        in_S (B, n) bool (``z_i`` basic at the end), finished (B,) bool (the artificial
        variable left the basis), ray (B,) bool (ray termination), pivots (B,).
    """
    B, n = q.shape
    dtype, device = q.dtype, q.device
    in_S = torch.zeros(B, n, dtype=torch.bool, device=device)
    finished = torch.ones(B, dtype=torch.bool, device=device)
    ray = torch.zeros(B, dtype=torch.bool, device=device)
    pivots = torch.zeros(B, dtype=torch.int64, device=device)
    # Lemke only identifies the basis (the solution is re-solved from the data): it runs
    # on q scaled to |q|_inf ~ 1 (exactly, by a power of two) with entries below ``tol``
    # set to zero, so that rounding noise (a tangential velocity of 1e-16) neither
    # starts pivoting nor makes a tie look like a strict order
    q_max = torch.where(active, q.abs(), 0).amax(-1, keepdim=True)
    q = q / _pow2(torch.where(q_max > 0, q_max, 1))
    q = torch.where(q.abs() <= tol, 0, q)
    need = (active & (q < 0)).any(-1)
    if not bool(need.any()):
        return in_S, finished, ray, pivots
    rows = need.nonzero().squeeze(-1)
    finished[rows] = False
    act = active[rows]
    Bn = rows.numel()
    eye = torch.eye(n, dtype=dtype, device=device)
    pair = act[:, :, None] & act[:, None, :]
    M_dec = torch.where(pair, M[rows], 0) + torch.where(act, 0.0, 1.0).to(dtype)[:, :, None] * eye
    q_dec = torch.where(act, q[rows], 1)
    cover = act.to(dtype)
    T = torch.cat([eye.expand(Bn, n, n), -M_dec, -cover[..., None], q_dec[..., None]], -1)
    basis = torch.arange(n, device=device).expand(Bn, n).clone()
    Z0, RHS = 2 * n, 2 * n + 1
    index = torch.arange(1, n + 1, device=device)

    # first pivot: the artificial variable enters, the most negative q_i leaves (ties:
    # the largest index, which leaves the tableau lexico-positive)
    neg = torch.where(act, -q_dec, -math.inf)
    top = neg.amax(-1, keepdim=True)
    tied = act & (neg >= top - tol * top.abs().clamp_min(1))
    r = (tied * index).argmax(-1)
    T = _pivot(T, r, torch.full_like(r, Z0))
    leaving = basis.gather(1, r[:, None]).squeeze(1)
    basis.scatter_(1, r[:, None], Z0)
    enter = leaving + n
    count = torch.ones(Bn, dtype=torch.int64, device=device)

    def retire(done: Tensor, solved: Tensor) -> None:
        """Write out the problems ``done`` (Bn,) of the working batch."""
        out = rows[done]
        bas = basis[done]
        is_z = (bas >= n) & (bas < 2 * n)
        j = torch.where(is_z, bas - n, 0)
        in_S[out] = torch.zeros_like(j).scatter_add(1, j, is_z.to(j.dtype)) > 0
        finished[out] = solved[done]
        ray[out] = ~solved[done]
        pivots[out] = count[done]

    for _ in range(max_pivots):
        col = T.gather(2, enter[:, None, None].expand(Bn, n, 1)).squeeze(-1)  # (Bn, n)
        rhs = T[..., RHS]
        scale = col.abs().amax(-1, keepdim=True).clamp_min(1)
        elig = act & (col > tol * scale)
        blocked = elig.any(-1)
        ratio = torch.where(elig, rhs / torch.where(elig, col, 1), math.inf)
        m0 = ratio.amin(-1, keepdim=True)
        cand = elig & (ratio <= m0 + tol * m0.abs().clamp_min(1))
        art = basis == Z0
        art_tied = (cand & art).any(-1, keepdim=True)
        cand = torch.where(art_tied, cand & art, cand)
        j = 0
        while j < n and bool((cand.sum(-1) > 1).any()):
            rj = torch.where(cand, T[..., j] / torch.where(cand, col, 1), math.inf)
            mj = rj.amin(-1, keepdim=True)
            cand = cand & (rj <= mj + tol * mj.abs().clamp_min(1))
            j += 1
        r = cand.to(torch.int8).argmax(-1)
        r = torch.where(blocked, r, 0)
        e_safe = torch.where(blocked, enter, Z0)
        # a problem without a blocking row (ray termination) keeps its tableau
        T_new = _pivot(T, r, e_safe)
        T = torch.where(blocked[:, None, None], T_new, T)
        T[..., RHS] = T[..., RHS].clamp_min(0)  # rounding (and ties within tol) only
        leaving = basis.gather(1, r[:, None]).squeeze(1)
        basis = torch.where(blocked[:, None], basis.scatter(1, r[:, None], enter[:, None]), basis)
        count = count + blocked.to(torch.int64)
        solved = blocked & (leaving == Z0)
        done = solved | ~blocked
        if bool(done.any()):
            retire(done, solved)
            keep = ~done
            rows, act, T, basis, count = rows[keep], act[keep], T[keep], basis[keep], count[keep]
            leaving, Bn = leaving[keep], int(keep.sum())
            if Bn == 0:
                break
        enter = torch.where(leaving < n, leaving + n, leaving - n)
    if Bn > 0 and rows.numel() > 0:  # out of pivots: unfinished
        pivots[rows] = count
    return in_S, finished, ray, pivots


def _refine(M: Tensor, q: Tensor, active: Tensor, in_S: Tensor):
    """The basis solution ``z_S = -M_SS^-1 q_S`` from the data, its LU and residual.

    Returns z (B, n) (clamped at 0), the LU factorisation and pivots of ``M_SS``
    bordered by the identity (B, n, n), and the residual ``max_i |min(z_i, w_i)|`` over
    the real rows divided by ``max(1, ||z||_inf)`` (B,).
    """
    n = q.shape[-1]
    eye = torch.eye(n, dtype=q.dtype, device=q.device)
    pair = in_S[:, :, None] & in_S[:, None, :]
    Mt = torch.where(pair, M, 0) + torch.where(in_S, 0.0, 1.0).to(q.dtype)[:, :, None] * eye
    LU, piv, info = lu_factor_ex(Mt)
    rhs = torch.where(in_S, -q, 0)
    z = torch.linalg.lu_solve(LU, piv, rhs.unsqueeze(-1)).squeeze(-1)
    z = torch.where(in_S & torch.isfinite(z), z, 0).clamp_min(0)
    w = torch.einsum("bij,bj->bi", torch.where(active[:, None, :], M, 0), z) + q
    nat = torch.where(active, torch.minimum(z, w).abs(), 0).amax(-1)
    res = nat / z.abs().amax(-1).clamp_min(1)
    res = torch.where(info == 0, res, math.inf)
    return z, LU, piv, res


class _LCPFunction(torch.autograd.Function):
    """Autograd wrapper of the batched Lemke solve: implicit backward on the basis."""

    @staticmethod
    def forward(M, q, active, max_pivots, tol, work, stick=None):
        Mw, qw = M.to(work), q.to(work)
        qw = torch.where(active, qw, 1)
        in_S, finished, ray, pivots = _lemke(Mw, qw, active, max_pivots, tol)
        z, LU, piv, res = _refine(Mw, qw, active, in_S)
        converged = finished & (res <= 1e3 * tol)
        if stick is not None:  # the backward's basis where sticking is degenerate
            LU, piv, in_S = _sticking_basis(Mw, qw, active, tol, z, LU, piv, in_S, res, stick)
        return z.to(q.dtype), converged, ray, pivots, res, (z, LU, piv, in_S)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.save_for_backward(*output[5])
        ctx.mark_non_differentiable(*output[1:5])

    @staticmethod
    @first_order_only
    def backward(ctx, grad_z, *_):
        z, LU, piv, in_S = ctx.saved_tensors
        g = torch.where(in_S, grad_z.to(z.dtype), 0)
        y = -torch.linalg.lu_solve(LU, piv, g.unsqueeze(-1), adjoint=True).squeeze(-1)
        y = torch.where(in_S, y, 0)
        grad_M = grad_q = None
        if ctx.needs_input_grad[0]:
            grad_M = (y.unsqueeze(-1) * z.unsqueeze(-2)).to(grad_z.dtype)
        if ctx.needs_input_grad[1]:
            grad_q = y.to(grad_z.dtype)
        return grad_M, grad_q, None, None, None, None, None


def _sticking_basis(M, q, active, tol, z, LU, piv, in_S, res, stick):
    """The basis the backward pass differentiates, with the ``stick`` variables added
    where they are degenerate (module docstring, "sticking"); ``LU, piv, in_S`` where
    nothing changes or the larger basis does not reproduce ``z``.

    ``stick = (variables, guards)``, each ``(n,)``: ``variables`` (bool) may join the
    basis where ``z_i = w_i = 0`` (within the tolerance) and ``w[guards_i] > 0`` (the
    contact's friction capacity ``mu p - 1^T beta`` left).
    """
    variables, guards = (t.to(z.device) for t in stick)
    w = torch.einsum("bij,bj->bi", torch.where(active[:, None, :], M, 0), z) + q
    small = 1e3 * tol * z.abs().amax(-1, keepdim=True).clamp_min(1)  # (B, 1)
    capacity = w.gather(-1, guards.expand_as(w)) > small
    join = variables & active & ~in_S & (z <= small) & (w.abs() <= small) & capacity
    if not bool(join.any()):
        return LU, piv, in_S
    wider = in_S | join
    z2, LU2, piv2, res2 = _refine(M, q, active, wider)
    same = (z2 - z).abs().amax(-1, keepdim=True) <= small
    use = join.any(-1, keepdim=True) & same & (res2 <= res.clamp_min(1e3 * tol))[:, None]
    return (
        torch.where(use[:, :, None], LU2, LU),
        torch.where(use, piv2, piv),
        torch.where(use, wider, in_S),
    )


def solve_lcp(
    M: Tensor,
    q: Tensor,
    active: Tensor | None = None,
    *,
    max_pivots: int | None = None,
    tol: float | None = None,
    compute_dtype: torch.dtype | None = torch.float64,
    return_status: bool = False,
    stick: tuple[Tensor, Tensor] | None = None,
) -> Tensor | tuple[Tensor, SolverStatus]:
    """Solve a batch of linear complementarity problems, differentiably.

    Find ``z >= 0`` with ``w = M z + q >= 0`` and ``z^T w = 0`` by Lemke's method
    (covering vector of ones, lexicographic ties), then re-solve the final basis from
    the data. The backward pass differentiates the final basis's piece (module
    docstring). ``M`` need not be symmetric; Lemke's method is guaranteed to find a
    solution for the contact LCPs of this module (and for copositive-plus ``M`` whose
    LCP is feasible); otherwise it may end on a ray (no solution found).

    Args:
        M: (..., n, n).
        q: (..., n).
        active: (..., n) bool; inactive rows and columns are dropped (their ``z`` is
            exactly 0 and their entries of ``M`` and ``q`` are not read). None: all.
        max_pivots: cap on the pivots per problem (default ``10 n + 50``).
        tol: relative tolerance of pivot elements and ties (default 1e-10 in float64,
            1e-5 in float32 compute dtype); a problem counts as solved when its
            re-solved residual ``|min(z, w)|_inf / max(1, |z|_inf)`` is within
            ``1e3 tol``.
        compute_dtype: precision of the solve (float64 by default; ``None``: the
            input's); the result comes back in the input dtype.
        return_status: also return a :class:`~diffcontact.contact.SolverStatus`
            (``unbounded`` marks ray terminations, ``iterations`` counts pivots).
        stick: ``(variables, guards)``, ``(n,)`` bool and long: variables that join
            the basis of the backward pass where they are degenerate (``z_i = w_i =
            0``) while ``w[guards_i] > 0`` (the contact LCP's sticking friction,
            :func:`lcp_impulse`); ``None``: Lemke's final basis.

    Returns:
        z: (..., n), dtype and device of ``M`` (and the status if asked).

    Raises:
        ValueError: bad shapes, dtypes, devices, options or non-finite inputs.
        LCPError: problems without a solution (unless ``return_status``).
    """
    for name, x in (("M", M), ("q", q)):
        if not isinstance(x, Tensor) or not x.is_floating_point():
            raise ValueError(f"solve_lcp: {name} must be a floating-point tensor")
    if M.dim() < 2 or M.shape[-1] != M.shape[-2] or M.shape[-1] == 0:
        raise ValueError(f"solve_lcp: M must have shape (..., n, n), got {tuple(M.shape)}")
    n = M.shape[-1]
    if q.dim() < 1 or q.shape[-1] != n:
        raise ValueError(f"solve_lcp: q must have shape (..., {n}), got {tuple(q.shape)}")
    if q.dtype != M.dtype or q.device != M.device:
        raise ValueError("solve_lcp: M and q must have the same dtype and device")
    if active is None:
        active = torch.ones(n, dtype=torch.bool, device=M.device)
    if not isinstance(active, Tensor) or active.dtype != torch.bool or active.shape[-1:] != (n,):
        raise ValueError(f"solve_lcp: active must be a bool tensor of shape (..., {n})")
    if active.device != M.device:
        raise ValueError(f"solve_lcp: active is on {active.device}, M is on {M.device}")
    if stick is not None:
        ok = (
            isinstance(stick, tuple)
            and len(stick) == 2
            and all(isinstance(t, Tensor) and t.shape == (n,) for t in stick)
        )
        if not ok or stick[0].dtype != torch.bool or stick[1].dtype != torch.long:
            raise ValueError(
                f"solve_lcp: stick must be (variables, guards): ({n},) bool and ({n},) long"
            )
        if bool(((stick[1] < 0) | (stick[1] >= n)).any()):
            raise ValueError(f"solve_lcp: stick's guards must be indices in [0, {n})")
    if max_pivots is not None and (
        isinstance(max_pivots, bool) or not isinstance(max_pivots, int) or max_pivots < 1
    ):
        raise ValueError(f"solve_lcp: max_pivots must be a positive integer, got {max_pivots!r}")
    if tol is not None and not (isinstance(tol, (int, float)) and 0 < tol < 1):
        raise ValueError(f"solve_lcp: tol must be a number in (0, 1), got {tol!r}")
    try:
        batch = broadcast_shapes(M.shape[:-2], q.shape[:-1], active.shape[:-1])
    except RuntimeError as err:
        raise ValueError(f"solve_lcp: batch dimensions do not broadcast: {err}") from None
    Mb = M.expand(*batch, n, n).reshape(-1, n, n)
    qb = q.expand(*batch, n).reshape(-1, n)
    ab = active.expand(*batch, n).reshape(-1, n)
    finite = torch.isfinite(torch.where(ab[:, :, None] & ab[:, None, :], Mb, 0)).all()
    if not bool(finite & torch.isfinite(torch.where(ab, qb, 0)).all()):
        raise ValueError("solve_lcp: M or q contains NaN or infinite values")
    work = compute_dtype or M.dtype
    if tol is None:
        tol = 1e-10 if work == torch.float64 else 1e-5
    if max_pivots is None:
        max_pivots = 10 * n + 50
    z, converged, ray, pivots, res, _ = _LCPFunction.apply(Mb, qb, ab, max_pivots, tol, work, stick)
    status = SolverStatus(
        converged=converged.reshape(batch),
        unbounded=ray.reshape(batch),
        iterations=pivots.reshape(batch),
        residual=res.to(M.dtype).reshape(batch),
    )
    z = z.reshape(*batch, n)
    if return_status:
        return z, status
    if not status.all_converged:
        n_ray = int(status.unbounded.sum())
        n_bad = int((~status.converged).sum()) - n_ray
        parts = []
        if n_ray:
            parts.append(f"{n_ray} of {z[..., 0].numel()} problems ended on a ray (no solution)")
        if n_bad:
            parts.append(
                f"{n_bad} of {z[..., 0].numel()} problems did not finish within {max_pivots} "
                "pivots or violate complementarity"
            )
        raise LCPError(
            "solve_lcp: " + "; ".join(parts) + ". Pass return_status=True to inspect them.",
            status,
        )
    return z


# ----------------------------------------------------------------- the contact LCP
def friction_directions(d: int, directions: int, *, dtype=None, device=None) -> Tensor:
    """Tangent directions of the polyhedral friction cone, ``(d - 1, m)``.

    ``d = 2``: ``[[1, -1]]`` (exact; ``directions`` is not used); ``d = 3``: ``m =
    directions`` unit vectors at angles ``2 pi j / m`` from the first tangent;
    ``d = 1``: ``(0, 0)``.
    """
    if d == 1:
        return torch.zeros(0, 0, dtype=dtype, device=device)
    if d == 2:
        return torch.tensor([[1.0, -1.0]], dtype=dtype, device=device)
    theta = 2 * math.pi * torch.arange(directions, dtype=torch.float64) / directions
    return torch.stack([theta.cos(), theta.sin()]).to(dtype=dtype, device=device)


def lcp_matrices(
    A: Tensor, q_C: Tensor, mu: Tensor, d: int, directions: int = DEFAULT_DIRECTIONS
) -> tuple[Tensor, Tensor, Tensor]:
    """The contact LCP ``(M, q)`` and the map ``G: z -> f`` (module docstring).

    Per contact the variables are ``(p, beta_1..beta_m, lambda)`` (``m + 2``; just
    ``p`` when ``d = 1``).

    Args:
        A: (B, C, C) Delassus matrix ``J_C Mhat^-1 J_C^T``, ``C = K d``.
        q_C: (B, C) contact velocity relative to the target, ``v_C - s``.
        mu: (B, K) friction coefficients.
        d: contact-space dimension.
        directions: tangent directions in 3D (``d = 3``).

    Returns:
        M: (B, n, n), q: (B, n), G: (C, n), ``n = K (m + 2)`` (``K`` when ``d = 1``).
    """
    K = mu.shape[-1]
    if d == 1:
        G = torch.eye(K, dtype=A.dtype, device=A.device)
        return A, q_C, G
    D = friction_directions(d, directions, dtype=A.dtype, device=A.device)
    m = D.shape[-1]
    w = m + 2
    Gk = A.new_zeros(d, w)
    Gk[0, 0] = 1
    Gk[1:, 1 : m + 1] = D
    eyeK = torch.eye(K, dtype=A.dtype, device=A.device)
    G = torch.kron(eyeK, Gk)  # (C, n)
    Lk = A.new_zeros(w, w)  # the constant part: beta rows + lambda, lambda row - 1^T beta
    Lk[1 : m + 1, m + 1] = 1
    Lk[m + 1, 1 : m + 1] = -1
    Mu = A.new_zeros(w, w)
    Mu[m + 1, 0] = 1  # mu_k p_k in the lambda row
    M = G.T @ A @ G + torch.kron(eyeK, Lk)
    M = M + torch.einsum("bk,kl,ij->bkilj", mu, eyeK, Mu).reshape(M.shape[0], K * w, K * w)
    q = (G.T @ q_C.unsqueeze(-1)).squeeze(-1)
    return M, q, G


def _sticking_variables(K: int, d: int, width: int, device: torch.device):
    """``(variables, guards)`` of :func:`solve_lcp`'s ``stick`` for the contact LCP of
    ``K`` contacts of ``width`` variables ``(p, beta_1..beta_m, lambda)``: each contact's
    first ``d - 1`` directions (independent: they span the tangent space), guarded by
    its ``lambda`` row (``w = mu p - 1^T beta``, the friction left); ``None`` for
    ``d = 1``."""
    if d == 1:
        return None
    j = torch.arange(K * width, device=device) % width
    variables = (j >= 1) & (j <= d - 1)
    guards = torch.arange(K * width, device=device) - j + (width - 1)
    return variables, guards


def lcp_impulse(
    J_C: Tensor | ContactOperator,
    Mhat_inv: Tensor | None,
    v: Tensor,
    mu: Tensor,
    cor: Tensor,
    active: Tensor,
    d: int,
    *,
    v_C_star: Tensor | None = None,
    directions: int = DEFAULT_DIRECTIONS,
    max_pivots: int | None = None,
    tol: float | None = None,
    compute_dtype: torch.dtype | None = torch.float64,
    return_status: bool = False,
    check_inputs: bool = True,
) -> ImpulseResult | tuple[ImpulseResult, SolverStatus]:
    """Resolve all active contacts of a batch of states with the Newton LCP.

    Args:
        J_C: (..., K*d, D) contact Jacobian, padded rows zero, or a
            :class:`~diffcontact.contact.ContactOperator` of ``J_C`` and ``Mhat^-1``.
        Mhat_inv: (..., D, D) constrained inverse inertia (S.12); ``None`` with an
            operator.
        v: (..., D) pre-impact velocities.
        mu: (..., K) friction coefficients >= 0 (unused when ``d = 1``).
        cor: (..., K) Newton's coefficients of restitution in [0, 1].
        active: (..., K) bool; inactive (padded) contacts get exactly zero impulse.
        d: contact-space dimension (1, 2 or 3).
        v_C_star: (..., K*d) penetration-compensation target, or None.
        directions: friction-cone directions when ``d = 3``.
        max_pivots, tol, compute_dtype, return_status: as in :func:`solve_lcp`.
        check_inputs: check ``cor`` in [0, 1] (a host read; off inside a simulation step,
            whose boundary checks once).

    Returns:
        :class:`~diffcontact.contact.ImpulseResult` with ``f_c`` the impulse ``(...,
        K*d)`` (normal then tangential per contact) and ``f_r`` zeros (one phase).

    States narrower than ``compute_dtype`` (float32 states, the default float64 solve)
    are resolved in ``compute_dtype`` from the rows on, as CM's
    (:func:`~diffcontact.contact.impulse.widened`): Lemke's pivots on ``A`` formed in
    float32 end at another solution where it is singular.
    """
    d = contact_dimension(d, "lcp_impulse")
    if check_inputs:
        check_impulse_inputs(
            cor, v, "lcp_impulse", J_C=J_C, Mhat_inv=Mhat_inv, mu=mu, active=active, d=d,
            v_C_star=v_C_star,
        )  # fmt: skip
    if not isinstance(active, Tensor) or active.dtype != torch.bool:
        raise ValueError("lcp_impulse: active must be a bool tensor")
    work = wider_dtype(v.dtype, compute_dtype)
    if work is not None:
        op, v_w, mu_w, cor_w, star_w = widened(work, J_C, Mhat_inv, v, mu, cor, v_C_star)
        out = lcp_impulse(
            op, None, v_w, mu_w, cor_w, active, d, v_C_star=star_w, directions=directions,
            max_pivots=max_pivots, tol=tol, compute_dtype=compute_dtype,
            return_status=return_status, check_inputs=False,
        )  # fmt: skip
        if return_status:
            return out[0].to(v.dtype), out[1]
        return out.to(v.dtype)
    op = as_operator(J_C, Mhat_inv)
    v_C = op.contact_velocity(v)
    batch = v_C.shape[:-1]
    C = v_C.shape[-1]
    K = C // d
    if C % d or active.shape[-1] != K or mu.shape[-1] != K or cor.shape[-1] != K:
        raise ValueError(
            f"lcp_impulse: J_C has {C} rows, not K*d for the K = {active.shape[-1]} contacts "
            f"of active (mu: {tuple(mu.shape)}, cor: {tuple(cor.shape)}) and d = {d}"
        )
    A = op.delassus()  # symmetric
    act = active.expand(*batch, K)
    v_k = v_C.reshape(*batch, K, d)
    v_n = v_k[..., 0]
    s_n = torch.where(v_n < 0, -cor * v_n, torch.zeros_like(v_n))
    if v_C_star is not None:
        star = v_C_star.reshape(*batch, K, d)
        s_n = torch.where(s_n >= star[..., 0], s_n, star[..., 0])
        s = torch.cat([s_n.unsqueeze(-1), star[..., 1:]], -1)
    else:
        s = torch.cat([s_n.unsqueeze(-1), torch.zeros_like(v_k[..., 1:])], -1)
    q_C = torch.where(act.unsqueeze(-1), v_k - s, 0).reshape(*batch, C)

    flat_A = A.reshape(-1, C, C)
    flat_q = q_C.reshape(-1, C)
    flat_act = act.reshape(-1, K)
    flat_mu = torch.where(flat_act, mu.expand(*batch, K).reshape(-1, K), 0)
    # exact (power-of-two) scales from the real contacts: impulses by b / a
    with torch.no_grad():
        act_c = flat_act.repeat_interleave(d, dim=-1)
        diag = torch.where(act_c, flat_A.diagonal(dim1=-2, dim2=-1).abs(), 0).amax(-1)
        a = _pow2(torch.where(diag > 0, diag, 1))
        vel = torch.where(act_c, flat_q.abs(), 0).amax(-1)
        b = _pow2(torch.where(vel > 0, vel, 1))
    M, q, G = lcp_matrices(flat_A / a[:, None, None], flat_q / b[:, None], flat_mu, d, directions)
    width = M.shape[-1] // K
    lcp_active = flat_act.repeat_interleave(width, dim=-1)
    z, status = solve_lcp(
        M,
        q,
        lcp_active,
        max_pivots=max_pivots,
        tol=tol,
        compute_dtype=compute_dtype,
        return_status=True,
        stick=_sticking_variables(K, d, width, M.device),
    )
    f = (b / a)[:, None] * (z @ G.T)
    f = torch.where(act_c, f, 0).reshape(*batch, C)
    v_plus = v + op.velocity_change(f)
    result = ImpulseResult(v_plus, f, torch.zeros_like(f))
    status = SolverStatus(*(x.reshape(batch) for x in (
        status.converged, status.unbounded, status.iterations, status.residual
    )))  # fmt: skip
    if return_status:
        return result, status
    if not status.all_converged:
        n_bad = int((~status.converged).sum())
        n_ray = int(status.unbounded.sum())
        parts = []
        if n_ray:  # Lemke's method is complete for these LCPs: a ray means no solution
            parts.append(f"{n_ray} have no solution (Lemke's method ended on a ray)")
        if n_bad > n_ray:
            parts.append(f"{n_bad - n_ray} did not finish within max_pivots (raise it)")
        raise LCPError(
            f"LCP contact model: {n_bad} of {status.converged.numel()} contact problems "
            f"failed: {'; '.join(parts)}",
            status,
        )
    return result


class NewtonLCP:
    """The LCP contact model (``"LCP"``): Newton's restitution, polyhedral friction.

    One-phase impulse of the standard velocity-level LCP, solved by batched Lemke
    pivoting with an implicit backward (module docstring of
    :mod:`diffcontact.contact.lcp`).

    Args:
        directions: friction-cone directions in 3D contact space (an integer >= 3;
            default 8). The 2D cone is exact (two directions) whatever this is.
        max_pivots: cap on Lemke pivots per problem (default ``10 n + 50`` for ``n``
            LCP variables).
        tol: pivot / tie tolerance (default 1e-10 in the float64 solve).

    It accepts a :class:`~diffcontact.contact.ContactOperator` in place of the dense
    ``J_C`` (``accepts_contact_operator``).
    """

    accepts_contact_operator = True

    def __init__(
        self,
        directions: int = DEFAULT_DIRECTIONS,
        max_pivots: int | None = None,
        tol: float | None = None,
    ) -> None:
        if isinstance(directions, bool) or not isinstance(directions, int) or directions < 3:
            raise ValueError(
                f"LCP: directions must be an integer >= 3 (friction-cone directions in 3D), "
                f"got {directions!r}"
            )
        if max_pivots is not None and (
            isinstance(max_pivots, bool) or not isinstance(max_pivots, int) or max_pivots < 1
        ):
            raise ValueError(f"LCP: max_pivots must be a positive integer, got {max_pivots!r}")
        if tol is not None and (
            isinstance(tol, bool) or not isinstance(tol, (int, float)) or not 0 < tol < 1e-2
        ):
            raise ValueError(f"LCP: tol must be a number in (0, 0.01), got {tol!r}")
        self.directions = directions
        self.max_pivots = max_pivots
        self.tol = tol

    def __repr__(self) -> str:
        return f"NewtonLCP(directions={self.directions})"

    def resolve(
        self,
        J_C: Tensor | ContactOperator,
        Mhat_inv: Tensor | None,
        v: Tensor,
        params: ContactParams,
        active: Tensor,
        d: int,
        *,
        v_C_star: Tensor | None = None,
        settings: SolverSettings | None = None,
    ) -> ImpulseResult:
        """:class:`~diffcontact.contact.ContactModel`'s ``resolve``; of ``settings``
        only ``compute_dtype`` is used."""
        compute_dtype = torch.float64 if settings is None else settings.compute_dtype
        return lcp_impulse(
            J_C,
            Mhat_inv,
            v,
            params.mu,
            params.cor,
            active,
            d,
            v_C_star=v_C_star,
            directions=self.directions,
            max_pivots=self.max_pivots,
            tol=self.tol,
            compute_dtype=compute_dtype,
            check_inputs=True if settings is None else settings.check_inputs,
        )


def LCP(
    directions: int = DEFAULT_DIRECTIONS, max_pivots: int | None = None, tol: float | None = None
) -> NewtonLCP:
    """Registry factory of ``"LCP"``: :class:`NewtonLCP` (``directions`` in 3D, default 8)."""
    return NewtonLCP(directions=directions, max_pivots=max_pivots, tol=tol)
