"""Batched, differentiable friction-cone QP: ``solve_cone_qp``.

For every problem of a batch, with contact blocks ``f_k = (f_n, f_t)`` of
``d`` numbers,

    minimize_f  0.5 f^T A f + b^T f
    subject to  f_n,k >= l_k  and  ||f_t,k|| <= mu_k f_n,k      for each contact k.

This is the compression (5) and restitution (7) problem of the paper, with
``A = J_C Mhat^-1 J_C^T`` positive *semi*-definite.

How it is solved (all problems of the batch at once, no Python loop over
problems or contacts):

1. Inactive contacts are decoupled (identity block, a separating velocity) so
   their impulse is exactly zero and they do not touch the others; ``mu = 0``
   tangential components are decoupled for the interior-point phase.
2. A problem whose contacts differ in scale by more than 1e3 (masses orders of
   magnitude apart) is first equilibrated contact by contact (``S A S``; the cones
   are invariant; :func:`_contact_scales`). The problem is scaled (diag(A) ~ 1,
   |b| ~ 1) and a primal-dual interior-point
   method (Mehrotra predictor-corrector, Nesterov-Todd scaling;
   :mod:`diffcontact.contact.interior_point`) approaches the solution to ``gap``;
   problems leave the batch as they finish. Problems the polish cannot finish are
   solved again with a tighter gap (``retries``).
3. A Newton polish on the natural map ``F(f) = f - Pi_C(f - rho (A f + b)) = 0``
   (:mod:`diffcontact.contact.cone`), whose zeros are exactly the minimisers,
   identifies the active constraints and drives ``F`` to rounding level
   (~1e-12 in float64). Steps that do not reduce ``||F||`` are rejected.
   Steps 2 and 3 run on the backend of ``SolverSettings.backend``: batched torch
   operations (the reference), or NVIDIA Warp (:mod:`diffcontact.contact.fused`), where
   one kernel, one thread per problem, runs the whole call (the scaling of step 1-2, the
   fast paths, the solve, the certificate of step 4, the status and the input checks)
   and a second one the backward pass of step 5: a call is a dozen torch operations.
4. Unboundedness (``SolverStatus.unbounded``) is decided by a certificate checked
   on the data, a direction ``u`` in the friction cones with ``A u = 0`` and
   ``b^T u < 0`` (to relative accuracy ``sqrt(eps)``; :func:`_certifies_unbounded`),
   along which the objective still falls at the solver's point (so that a bounded
   problem whose far-out minimiser the solver reached is not called unbounded),
   found from the solver's runaway iterate or, failing that, from one re-solve with a
   small Tikhonov term. It is never inferred from the residual, which is relative to
   ``|f|`` and which a runaway iterate passes: such a problem is reported unbounded
   (with a certificate) or unconverged, never converged.
5. The backward pass differentiates ``F(f; A, b, mu, l) = 0`` implicitly, reusing
   the LU factorisation of ``dF/df = I - P + rho P (A + delta I)`` from the
   polish: one transposed solve per batch. ``delta`` (``SolverSettings.kkt_reg``,
   relative to diag(A)) keeps it invertible when the minimiser is not unique
   (singular ``A`` with a free direction inside the cones), and gradients
   along the free directions are not meaningful (the velocity change
   ``Mhat^-1 J_C^T f`` does not depend on them).

Which minimiser when it is not unique (several contacts on one body; it matters:
the compression impulse feeds Poisson's bound of the restitution phase): the limit
of the interior point's central path, which lies near the analytic centre of the
optimal set (the relative interior point that maximises the barrier), reached to
the interior-point gap. It is a function of the problem alone: padded contacts take
no part in the iterations (:func:`interior_point_solve`'s ``active``) and the polish
does not move along null directions of ``A`` (:func:`_polish`), so a state gets the
same impulse whichever states share its batch (to rounding: LAPACK factorises a
padded matrix with another blocking; ``tests/systems/test_batch_invariance.py``).
The Warp backend's Newton steps from zero (``SolverSettings.polish_steps``) keep their
result only where they end at a point where the natural map is differentiable (strict
complementarity: no contact's ``f - rho (A f + b)`` on a boundary of the projection's
pieces) with a regular Jacobian, an isolated and so (convex problem) the unique
minimiser: where the minimiser may not be unique, the interior point picks it as above.
(A regular Jacobian alone does not suffice: with a disk in a corner, Newton ended at the
end of the optimal segment, where one contact just reaches its cone's surface.)
A minimum-norm choice (a Tikhonov term ``tau I``) was not taken: in floating point it
fixes the free components only to ``eps / tau`` and would bias every solution by
``tau``.

Gradients at degenerate points follow the one-sided choices documented in
:mod:`diffcontact.contact.cone` (right derivatives at ``mu = 0`` and ``l = 0``).
"""

from __future__ import annotations

import contextlib
import functools
import math
import numbers
import threading
from collections.abc import Iterator
from dataclasses import dataclass

import torch
from torch import Tensor

from diffcontact.contact import fused
from diffcontact.contact.closed_form import separating_guess, single_contact_minimiser
from diffcontact.contact.cone import project_contact_set
from diffcontact.contact.first_order import first_order_only
from diffcontact.contact.interior_point import add_block_diag, interior_point_solve
from diffcontact.fastops import lu_factor_ex
from diffcontact.shapes import broadcast_shapes, contact_dimension


class ConeQPError(RuntimeError):
    """Raised when some problems of a batch are unbounded or did not converge.

    Attributes:
        status: the :class:`SolverStatus` of the batch (which problems failed), or None.
        states: indices of the simulated states whose problems failed, where a
            simulator filled them in (:meth:`diffcontact.systems.System.simulate`).
    """

    def __init__(self, message: str, status: SolverStatus | None = None):
        super().__init__(message)
        self.status = status
        self.states: list[int] | None = None


def _is_real(value: object) -> bool:
    """A real number that is not a bool (``numbers.Real``: floats, ints, numpy scalars)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_int(value: object) -> bool:
    """An integer that is not a bool (``numbers.Integral``)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


@dataclass(frozen=True)
class SolverSettings:
    """Tolerances and caps of :func:`solve_cone_qp`. ``None`` picks a dtype default.

    Attributes:
        tol: accepted natural-map residual ``||F||_inf / max(1, ||f||_inf)`` after
            scaling (float64: 1e-7, float32: 1e-4). Problems above it are re-solved and
            then reported; near-degenerate ones (many weakly active rope limits) can end
            between 1e-9 and 1e-7.
        polish_tol: the polish goes on while it makes progress until the residual is
            below this (float64: 1e-13, i.e. rounding level; float32: 1e-6).
        gap: interior-point target for the complementarity gap per cone and the
            residuals (scaled), before polishing (float64: 1e-9, float32: 1e-4).
        max_iter: interior-point iteration cap.
        polish_steps: Newton steps on the natural map. The Warp backend first tries twice
            as many from zero on a problem without a fast path (several contacts) and
            keeps the result where it converges to a regular point (a unique minimiser);
            the interior point solves the others.
        retries: re-solves, each with a 100x tighter interior-point gap, of the
            problems the polish could not finish.
        kkt_reg: relative regularisation ``delta`` of ``A`` in the polish and
            backward Jacobian (float64: 1e-12, float32: 1e-7).
        check_inputs: validate shapes, signs, finiteness, symmetry and that ``A`` is
            positive semi-definite on the active contacts (to
            :data:`fused.SEMIDEFINITE_TOL`; a Cholesky factorisation per problem).
        compute_dtype: precision of the internal solve (float64 by default; the
            result and gradients come back in the input dtype). ``None`` solves in
            the input dtype: faster, but a float32 interior point cannot reach the gap
            that identifies the active set of every problem, and some problems then
            end unconverged (``test_leading_batch_dims_and_float32`` runs this mode).
        canonical: where the minimiser is not unique (a singular ``A``), return the
            canonical one, the interior point's (default; the impulses of a state then do
            not depend on its batch). ``False``: any minimiser, for callers that use only
            ``A f`` (the position projection, whose step ``M^-1 J^T lambda`` is the same for
            every minimiser): the Warp backend then keeps its Newton steps from zero at
            kinks of the natural map too, where it would otherwise run the interior point.
            The torch backend runs the interior point always.
        backend: ``"auto"`` (default), ``"torch"`` or ``"warp"``: the reference solver of
            batched torch operations, or the same algorithm fused into one NVIDIA Warp
            kernel per call (one thread per problem; ``pip install diffcontact[warp]``).
            ``"auto"`` takes the environment variable ``DIFFCONTACT_SOLVER`` if set, else
            Warp where it is installed (:mod:`diffcontact.contact.fused`).
    """

    tol: float | None = None
    polish_tol: float | None = None
    gap: float | None = None
    max_iter: int = 100
    polish_steps: int = 4
    retries: int = 3
    kkt_reg: float | None = None
    check_inputs: bool = True
    compute_dtype: torch.dtype | None = torch.float64
    backend: str = "auto"
    canonical: bool = True

    def __post_init__(self) -> None:
        # (a negative tol ended every solve "unconverged", max_iter=-5 ran none silently, a
        # string reached a comparison deep inside the solve)
        for name, low, strict in (("tol", 0.0, True), ("polish_tol", 0.0, True),
                                  ("gap", 0.0, True), ("kkt_reg", 0.0, False)):  # fmt: skip
            value = getattr(self, name)
            if value is None:
                continue
            if (
                not _is_real(value)
                or not math.isfinite(value)
                or not (value > low if strict else value >= low)
            ):
                bound = "a finite number > 0" if strict else "a finite number >= 0"
                raise ValueError(f"SolverSettings.{name} must be {bound} or None, got {value!r}")
        for name, low in (("max_iter", 1), ("polish_steps", 0), ("retries", 0)):
            value = getattr(self, name)
            if not _is_int(value) or value < low:
                raise ValueError(
                    f"SolverSettings.{name} must be an integer >= {low}, got {value!r}"
                )
        if not isinstance(self.check_inputs, bool):
            raise ValueError(
                f"SolverSettings.check_inputs must be a bool, got {self.check_inputs!r}"
            )
        cd = self.compute_dtype
        if cd is not None and not (isinstance(cd, torch.dtype) and cd.is_floating_point):
            # ("float64", a string, failed as a device; an integer dtype in torch.finfo)
            raise ValueError(
                "SolverSettings.compute_dtype must be a floating torch.dtype (torch.float64, "
                f"torch.float32) or None (the inputs' dtype), got {cd!r}"
            )
        if not isinstance(self.canonical, bool):
            raise ValueError(f"SolverSettings.canonical must be a bool, got {self.canonical!r}")
        if self.backend not in fused.BACKENDS:
            raise ValueError(
                f"SolverSettings.backend must be one of {', '.join(fused.BACKENDS)}, "
                f"got {self.backend!r}"
            )

    def resolved(self, dtype: torch.dtype, device: torch.device | None = None) -> SolverSettings:
        dtype = self.compute_dtype or dtype
        double = dtype == torch.float64
        return SolverSettings(
            tol=self.tol if self.tol is not None else (1e-7 if double else 1e-4),
            polish_tol=self.polish_tol
            if self.polish_tol is not None
            else (1e-13 if double else 1e-6),
            gap=self.gap if self.gap is not None else (1e-9 if double else 1e-4),
            max_iter=self.max_iter,
            polish_steps=self.polish_steps,
            retries=self.retries,
            kkt_reg=self.kkt_reg if self.kkt_reg is not None else (1e-12 if double else 1e-7),
            check_inputs=self.check_inputs,
            compute_dtype=dtype,
            backend=fused.resolve_backend(self.backend, dtype, device),
            canonical=self.canonical,
        )


def settings_or_default(settings: object, what: str) -> SolverSettings:
    """``settings``, or the defaults for ``None``; a ``ValueError`` naming ``what`` for
    anything else (a dict had given an ``AttributeError`` inside, and ``{}``, being falsy,
    had been taken for the defaults)."""
    if settings is None:
        return SolverSettings()
    if not isinstance(settings, SolverSettings):
        raise ValueError(
            f"{what} must be a SolverSettings, got {type(settings).__name__} "
            "(e.g. SolverSettings(backend='torch'))"
        )
    return settings


@dataclass
class SolverStatus:
    """Per-problem outcome, shaped like the batch dims of the call.

    Attributes:
        converged: bool, the residual is within ``tol``.
        unbounded: bool, the objective is unbounded below (no minimiser): a
            certificate, a descent direction of zero curvature inside the friction
            cones, was found (to relative accuracy ``sqrt(eps)``: a minimiser farther
            than ``1 / sqrt(eps)`` natural impulse scales that the solver did not
            reach counts as none). An unbounded problem is never ``converged``.
        iterations: int64, interior-point iterations used.
        residual: scaled natural-map residual ``||F||_inf / max(1, ||f||_inf)``.
    """

    converged: Tensor
    unbounded: Tensor
    iterations: Tensor
    residual: Tensor

    @property
    def all_converged(self) -> bool:
        return bool(self.converged.all())


def _blockwise(P: Tensor, x: Tensor) -> Tensor:
    """Apply per-contact blocks. P: (B, K, d, d), x: (B, K*d, ...) -> (B, K*d, ...)."""
    B, K, d, _ = P.shape
    xs = x.reshape(B, K, d, -1)
    return torch.einsum("bkij,bkjm->bkim", P, xs).reshape(x.shape)


def _natural_map(A: Tensor, b: Tensor, mu: Tensor, lower: Tensor, f: Tensor, rho: Tensor):
    """Residual F(f) (B, C) and the projection's derivatives at z = f - rho (A f + b)."""
    B, C = f.shape
    K = mu.shape[-1]
    d = C // K
    r = torch.einsum("bij,bj->bi", A, f) + b
    z = (f - rho[:, None] * r).reshape(B, K, d)
    proj, P, dmu, dl = project_contact_set(z, mu, lower)
    return f - proj.reshape(B, C), P, dmu, dl


def _scaled_residual(F: Tensor, f: Tensor, c: Tensor) -> Tensor:
    return F.abs().amax(-1) / torch.maximum(c, f.abs().amax(-1))


def _jacobian(A: Tensor, P: Tensor, rho: Tensor, reg: Tensor) -> Tensor:
    """dF/df = I - P + rho P (A + reg I), (B, C, C)."""
    C = A.shape[-1]
    eye = torch.eye(C, dtype=A.dtype, device=A.device)
    A_reg = A + reg[:, None, None] * eye
    return add_block_diag(eye + rho[:, None, None] * _blockwise(P, A_reg), -P)


def _forward(
    A,
    b,
    mu,
    lower,
    active,
    d: int,
    settings: SolverSettings,
    certify: bool = True,
    warm_start: Tensor | None = None,
):
    """Solve a flat batch. Shapes: A (B,C,C), b (B,C), mu/lower/active (B,K).

    ``certify=False`` skips the test for unboundedness (used by that test itself, on
    problems that are bounded by construction)."""
    C = b.shape[-1]
    dtype, device = A.dtype, A.device
    act_c = active.repeat_interleave(d, dim=-1)  # (B, C)
    pair = act_c[:, :, None] & act_c[:, None, :]

    # scales from the active part
    diag = A.diagonal(dim1=-2, dim2=-1)
    n_act = act_c.sum(-1).clamp_min(1)
    a_s = (torch.where(act_c, diag, 0).sum(-1) / n_act).clamp_min(torch.finfo(dtype).tiny)
    a_s = torch.where(a_s > 1e3 * torch.finfo(dtype).tiny, a_s, torch.ones_like(a_s))
    lower_m = torch.where(active, lower, 0)
    b_s = torch.where(act_c, b.abs(), 0).amax(-1)
    b_s = torch.maximum(b_s, a_s * lower_m.amax(-1))
    b_s = torch.where(b_s > 0, b_s, a_s)
    c = b_s / a_s  # impulse scale

    eye = torch.eye(C, dtype=dtype, device=device)
    is_normal = torch.zeros(C, dtype=torch.bool, device=device)
    is_normal[::d] = True
    # decouple inactive contacts: identity block, separating velocity
    A_m = torch.where(pair, A, 0) + torch.where(~act_c, a_s[:, None], 0)[:, :, None] * eye
    b_m = torch.where(act_c, b, torch.where(is_normal, b_s[:, None], 0))
    mu_m = torch.where(active, mu, 1) if d > 1 else torch.ones_like(mu)

    # interior point on the scaled problem. Redundant constraints are switched off so
    # that no contact has two constraints active at the cone's tip (a degenerate point
    # where interior-point steps stall): mu = 0 tangents are decoupled (their optimum is
    # f_t = 0) and their dummy cone's apex moved out of the way; where the cone already
    # implies f_n >= 0 (mu > 0, lower = 0) the orthant bound is relaxed to -1.
    apex = None
    if d > 1:
        free_t = (mu_m == 0).repeat_interleave(d, dim=-1) & ~is_normal
        keep = ~free_t
        A_ipm = torch.where(keep[:, :, None] & keep[:, None, :], A_m, 0)
        A_ipm = A_ipm + torch.where(free_t, a_s[:, None], 0)[:, :, None] * eye
        b_ipm = torch.where(free_t, 0, b_m)
        mu_ipm = torch.where(mu_m > 0, mu_m, 1)
        apex = (mu_m == 0).to(dtype)
        lower_ipm = torch.where((mu_m > 0) & (lower_m == 0), -1.0, lower_m / c[:, None])
    else:
        A_ipm, b_ipm, mu_ipm = A_m, b_m, mu_m
        lower_ipm = lower_m / c[:, None]
    rho = 1 / a_s
    reg = settings.kkt_reg * a_s
    A_ipm = A_ipm / a_s[:, None, None]
    b_ipm = b_ipm / b_s[:, None]
    apex = torch.zeros_like(lower_ipm) if apex is None else apex
    data = (A_m, b_m, mu_m, lower_m, rho, reg, c)

    # A problem the polish cannot finish (the interior point stopped too early to
    # identify its active set: rare, near-degenerate) is solved again with a tighter gap.
    rows = torch.arange(b.shape[0], device=device)
    fresh = True  # no problem has a result yet
    # Fast paths (:mod:`diffcontact.contact.closed_form`): problems with a starting
    # point that is often already a minimiser skip the interior point when the polish
    # from it reaches the tolerance: f = 0 for separating problems (exact; derivatives
    # those of the natural map at 0: zero inside the dual cone, the one-sided choices
    # of cone.py on its boundary), the closed form of one active contact (d <= 2), and
    # the caller's warm start. Each guess depends on its problem alone.
    separating = separating_guess(b_m, mu_m, lower_m, active, d)
    guess, single = single_contact_minimiser(A_m, b_m, mu_m, lower_m, active, d)
    guess = torch.where(separating[:, None], 0, guess)
    guessed = separating | single
    if warm_start is not None:
        guess = torch.where(guessed[:, None], guess, torch.where(act_c, warm_start, 0))
        guessed = torch.ones_like(guessed)
    if bool(guessed.any()):
        g_rows = rows[guessed]
        polished = _polish_rows(guess[g_rows], g_rows, data, settings)
        # kept only at the polish's own target (rounding level), not at ``tol``: a guess
        # must not end less accurate than the interior point and polish would
        kept = polished[1] <= min(settings.polish_tol, settings.tol)
        f, res, P, dmu, dl, LU, piv = (
            x.new_zeros(b.shape[0], *x.shape[1:]).index_put_((g_rows,), x) for x in polished
        )
        iterations = torch.zeros_like(res, dtype=torch.int64)
        done = torch.zeros_like(guessed).index_put_((g_rows,), kept)
        rows, fresh = rows[~done], False
    gap = settings.gap
    for _attempt in range(settings.retries + 1):
        if rows.numel() == 0:
            break
        ipm, polished = _solve(
            rows, (A_ipm, b_ipm, mu_ipm, lower_ipm, apex, active), data, d, gap, settings
        )
        if fresh:
            f, res, P, dmu, dl, LU, piv = polished
            iterations, fresh = ipm.iterations, False
        else:
            for full, part in zip((f, res, P, dmu, dl, LU, piv), polished, strict=True):
                full[rows] = part
            iterations[rows] += ipm.iterations
        retry = (polished[1] > settings.tol) & ~ipm.unbounded
        if not bool(retry.any()):
            break
        rows, gap = rows[retry], gap * 1e-2

    f = torch.where(act_c, f, 0)
    # Unboundedness is decided by a certificate checked on the data, never by the
    # residual (it is scaled by |f|, so a runaway iterate passes it); the interior
    # point's divergence test (``ipm.unbounded``) only stops it and skips the retries.
    unbounded = torch.zeros_like(res, dtype=torch.bool)
    if certify:
        A_hat, b_hat = A_m / a_s[:, None, None], b_m / b_s[:, None]
        unbounded = _unbounded(A_hat, b_hat, mu_m, active, d, f / c[:, None], res, settings)
    converged = (res <= settings.tol) & ~unbounded
    status = SolverStatus(
        converged=converged, unbounded=unbounded, iterations=iterations, residual=res
    )
    saved = (f, P, dmu, dl, rho, LU, piv, act_c, active)
    return f, status, saved


def _solve(rows: Tensor, ipm_data, data, d: int, gap: float, settings: SolverSettings):
    """Interior point, then polish, of the problems ``rows`` (B,) of a batch, on the
    backend of ``settings`` (one fused Warp kernel, or the torch reference).

    ``ipm_data``: the scaled problem of :func:`interior_point_solve` (``A, b, mu, lower,
    apex, active``), ``data``: that of :func:`_polish`, both for the whole batch. Returns
    the :class:`~diffcontact.contact.interior_point.InteriorPointResult` and what
    :func:`_polish` returns, for the rows."""
    if settings.backend == "warp":
        return fused.solve(rows, ipm_data, data, d, gap, settings)
    A_ipm, b_ipm, mu_ipm, lower_ipm, apex, active = (x[rows] for x in ipm_data)
    ipm = interior_point_solve(
        A_ipm,
        b_ipm,
        mu_ipm,
        lower_ipm,
        d,
        tol=gap,
        max_iter=settings.max_iter,
        apex=apex,
        active=active,
    )
    c = data[-1]
    return ipm, _polish_rows(ipm.f * c[rows, None], rows, data, settings)


def _polish_rows(f: Tensor, rows: Tensor, data, settings: SolverSettings):
    """:func:`_polish` of the problems ``rows`` (n,) of a batch from ``f`` (n, C), on the
    backend of ``settings`` (``data`` for the whole batch)."""
    if settings.backend == "warp":
        return fused.polish(f, rows, data, settings)
    return _polish(f, [x[rows] for x in data], settings)


def flatten_batch(
    batch: tuple[int, ...], A: Tensor, b: Tensor, mu: Tensor, lower: Tensor, active: Tensor,
    warm_start: Tensor | None = None,
) -> tuple[tuple[Tensor, Tensor, Tensor, Tensor, Tensor], Tensor | None]:  # fmt: skip
    """Broadcast a contact problem to ``batch`` and flatten it to one batch dimension.

    Returns ``((A (n,C,C), b (n,C), mu (n,K), lower (n,K), active (n,K)), warm_start
    (n,C) or None)`` with ``n = prod(batch)``; shared by the solvers that take
    ``solve_cone_qp``'s arguments (the Coulomb solver too).
    """
    C, K = b.shape[-1], mu.shape[-1]
    n = 1
    for s in batch:
        n *= s

    def flat_view(x: Tensor, *tail: int) -> Tensor:
        if x.shape == (n, *tail) and len(batch) == 1:  # already flat: no view op
            return x
        return x.expand(*batch, *tail).reshape(n, *tail)

    flat = (
        flat_view(A, C, C),
        flat_view(b, C),
        flat_view(mu, K),
        flat_view(lower, K),
        flat_view(active, K),
    )
    if warm_start is not None:
        warm_start = flat_view(warm_start, C)
    return flat, warm_start


# contacts whose blocks of A differ in scale by more than this factor are equilibrated
_EQUILIBRATE_ABOVE = 1e3


def _contact_scales(A: Tensor, active: Tensor, d: int) -> Tensor:
    """Per-contact scales that equilibrate badly scaled problems, (B, C) detached.

    A problem whose contacts' normal diagonals ``A_nn,k`` differ by more than
    :data:`_EQUILIBRATE_ABOVE` (bodies whose masses differ by orders of magnitude)
    is solved as ``A' = S A S``, ``b' = S b``, ``lower' = lower / s``, ``f = S f'``
    with ``s_k = (max_j A_nn,j / A_nn,k)^(1/2)`` on every component of contact ``k``:
    the friction cone is invariant under a positive scale of a contact's impulse, so
    the problems are the same, but the scaled one has unit-order curvature in every
    contact, which the solver's single scale per problem and its unboundedness
    certificate (relative to the largest curvature) need. Other problems keep
    ``s = 1`` exactly. The scales are constants of the transformation, so gradients
    flow through ``S A S`` and ``S f'`` unchanged.
    """
    with torch.no_grad():
        a = A.diagonal(dim1=-2, dim2=-1)[:, ::d]  # (B, K) normal diagonals
        ok = active & (a > 0)
        top = torch.where(ok, a, 0).amax(-1, keepdim=True)
        low = torch.where(ok, a, torch.inf).amin(-1, keepdim=True)
        spread = ok.any(-1, keepdim=True) & (top > _EQUILIBRATE_ABOVE * low)
        s = torch.where(ok & spread, (top / torch.where(ok, a, 1)).sqrt(), 1.0)
        return s.repeat_interleave(d, dim=-1)


def _certifies_unbounded(
    A: Tensor, b: Tensor, mu: Tensor, active: Tensor, d: int, g: Tensor, f: Tensor
) -> Tensor:
    """Whether the direction of ``g`` is a certificate of unboundedness, (B,) bool.

    The objective is unbounded below exactly when a recession direction of the feasible
    set (``u`` in the friction cones, ``||u_t,k|| <= mu_k u_n,k``; the lower bounds do
    not change them) has zero curvature and descends: ``A u = 0`` and ``b^T u < 0``
    (then ``f + t u`` lowers the objective by ``t |b^T u|`` for every ``t``). ``u`` is
    ``g`` projected onto the cones (exactly, so it is a recession direction) and
    normalised to ``||u||_inf = 1``; it is accepted when

        b^T u <= -1e3 eps C,     u^T A u <= sqrt(eps) (b^T u)^2,
        and     (A f + b)^T u <= (b^T u) / 2

    (``eps`` of the dtype, data scaled so that diag(A) ~ 1 and ``|b|_inf <= 1``): along
    ``u`` the objective then falls by at least ``(b^T u)^2 / (2 u^T A u) >=
    1 / (2 sqrt(eps))`` natural units, so a minimiser, if any, lies beyond
    ``1 / sqrt(eps)`` (1.5e8 in float64) natural impulse scales; and it still falls along
    ``u`` at the solver's point ``f`` (where that slope's rounding error, about ``eps C
    max|A| |f|_inf``, is below a quarter of ``|b^T u|``; beyond, as at a runaway iterate
    of 1e15 scales, this test is not applied). Along a direction of zero curvature the
    slope is the same everywhere (``A u = 0``), so the last condition costs a true
    certificate nothing; it keeps a bounded problem whose minimiser lies that far out,
    and which the solver found (the slope there is zero to rounding), from being called
    unbounded. A body of mass 1e-6 wedged between a wall and one of mass 1e3 is such a
    problem (condition 4e9, its minimiser about 2e9 scales out:
    ``tests/contact/test_cone_qp.py``, ``_wedged_light_body``). A bounded problem that
    badly scaled whose minimiser the solver did not reach is still reported unbounded.

    Args:
        A: (B, C, C) scaled ``A`` with inactive contacts decoupled.
        b: (B, C) scaled ``b``.
        mu: (B, K) friction coefficients (inactive entries arbitrary).
        active: (B, K) bool.
        d: contact dimension.
        g: (B, C) candidate direction, any length.
        f: (B, C) the solver's (scaled) point.
    """
    B, C = g.shape
    eps = torch.finfo(g.dtype).eps
    act_c = active.repeat_interleave(d, dim=-1)
    u = project_contact_set(g.reshape(B, -1, d), mu, torch.zeros_like(mu))[0].reshape(B, C)
    u = torch.where(act_c, u, 0)
    scale = u.abs().amax(-1, keepdim=True)
    u = u / torch.where(scale > 0, scale, 1)
    slope = (b * u).sum(-1)
    curv = (u * torch.einsum("bij,bj->bi", A, u)).sum(-1)
    slope_f = ((torch.einsum("bij,bj->bi", A, f) + b) * u).sum(-1)  # the slope at f
    # its rounding error, about eps C max|A| |f|_inf: beyond a quarter of the slope (a
    # runaway iterate of 1e15 scales) the test says nothing and is not applied
    noise = eps * C * A.abs().amax((-1, -2)) * f.abs().amax(-1)
    still_falls = (slope_f <= slope / 2) | (4 * noise >= -slope)
    return (slope <= -1e3 * eps * C) & (curv <= eps**0.5 * slope * slope) & still_falls


def _unbounded(A, b, mu, active, d, g, res, settings: SolverSettings) -> Tensor:
    """Problems with a certificate of unboundedness (:func:`_certifies_unbounded`), (B,).

    Scaled data as there; ``g`` is the solver's iterate and ``res`` its residual.

    Only problems that may be unbounded are examined: unconverged ones, and those whose
    iterate lies beyond 100 natural impulse scales (the residual is relative to
    ``max(1, ||g||)``, so a runaway iterate can pass it; a converged bounded problem
    nearer than that cannot pass the certificate). The iterate's own direction is tried
    first: on an unbounded problem it runs off along a certificate, exactly when
    ``A = 0``. Where it is not one yet (a runaway along a null direction of a singular
    ``A`` still carries its bounded offset) and the problem is unconverged or beyond
    ``1e-2 / tol`` scales, the problem is solved once more with a Tikhonov term,
    ``A + delta I`` (``delta = eps^(3/8)``, 1.4e-6 in float64), which is bounded: its
    minimiser is ``w / delta + O(1)`` with ``w`` the projection of ``-b`` onto the
    directions of the cones in the null space of ``A``, a certificate whenever one
    exists with ``||w|| >~ eps^(1/8)`` (0.01 in float64). The default path (every
    problem converged within 100 scales) costs one host synchronisation.
    """
    found = torch.zeros_like(res, dtype=torch.bool)
    size = g.abs().amax(-1)
    unconverged = res > settings.tol
    todo = active.any(-1) & (unconverged | (size > 1e2))
    if not bool(todo.any()):
        return found
    rows = todo.nonzero().squeeze(-1)
    A, b, mu, active, g = A[rows], b[rows], mu[rows], active[rows], g[rows]
    cert = _certifies_unbounded(A, b, mu, active, d, g, g)
    again = ~cert & (unconverged[rows] | (size[rows] > 1e-2 / settings.tol))
    if bool(again.any()):
        sub = again.nonzero().squeeze(-1)
        A_s, b_s, mu_s, act_s = A[sub], b[sub], mu[sub], active[sub]
        delta = torch.finfo(A.dtype).eps ** 0.375
        eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
        g_s, _, _ = _forward(
            A_s + delta * eye, b_s, mu_s, torch.zeros_like(mu_s), act_s, d, settings, certify=False
        )
        cert_s = _certifies_unbounded(A_s, b_s, mu_s, act_s, d, g_s, g[sub])
        cert = cert.index_put((sub,), cert_s)
    return found.index_put((rows,), cert)


def _flat_projector(A: Tensor, LU: Tensor) -> Tensor | None:
    """Projector onto the null space of ``A`` (B, C, C) for problems whose Jacobian is
    (nearly) singular, i.e. that may have directions of zero curvature; zeros for the
    others; ``None`` when no problem has one (no eigendecomposition is made)."""
    B, C, _ = A.shape
    flat = LU.diagonal(dim1=-2, dim2=-1).abs().amin(-1) <= 1e-6
    if not bool(flat.any()):
        return None
    rows = flat.nonzero().squeeze(-1)
    evals, V = torch.linalg.eigh(A[rows])
    top = evals.abs().amax(-1, keepdim=True)
    keep = evals <= 1e3 * torch.finfo(A.dtype).eps * C * top
    N = V * keep[:, None, :]
    return A.new_zeros(B, C, C).index_put((rows,), N @ N.transpose(-1, -2))


def _polish(f: Tensor, data, settings: SolverSettings):
    """Newton steps on the natural map from ``f`` (B, C), with a backtracking line
    search on the residual (full, 1/2, 1/4 and 1/8 steps; a problem keeps its point if
    none lowers the residual: near-degenerate contacts can make full steps switch
    branches back and forth). Returns the point, its residual, the projection's
    derivatives and the LU factorisation of dF/df there (reused by the backward pass).

    Where ``A`` is singular, the minimiser may not be unique: the natural map is flat
    along null directions of ``A`` inside the cones, and the Newton step (regularised
    by ``kkt_reg`` there) would move along them by rounding noise / ``kkt_reg`` (1e-4
    relative in float64), i.e. pick a minimiser by rounding. So the step with its
    null-space component removed is tried first, and the full step only where that one
    does not lower the residual (a null direction that the constraints need): the
    minimiser returned is then the interior point's, the limit of its central path
    (near the analytic centre of the optimal set), which depends on the problem alone,
    not on the batch it is solved in.
    """
    A, b, mu, lower, rho, reg, c = data
    F, P, dmu, dl = _natural_map(A, b, mu, lower, f, rho)
    res = _scaled_residual(F, f, c)
    target = min(settings.polish_tol, settings.tol)  # ``tol`` is what is accepted
    flat = None
    for step in range(settings.polish_steps + 1):
        LU, piv, _ = lu_factor_ex(_jacobian(A, P, rho, reg))
        if step == settings.polish_steps or bool((res <= target).all()):
            break
        delta = -torch.linalg.lu_solve(LU, piv, F.unsqueeze(-1)).squeeze(-1)
        delta = torch.nan_to_num(delta, nan=0.0, posinf=0.0, neginf=0.0)
        if step == 0:
            flat = _flat_projector(A, LU)
        steps = [delta]
        if flat is not None:
            steps.insert(0, delta - torch.einsum("bij,bj->bi", flat, delta))
        todo = res > target
        for direction in steps:
            for alpha in (1.0, 0.5, 0.25, 0.125):
                f_new = f + alpha * direction
                F_new, P_new, dmu_new, dl_new = _natural_map(A, b, mu, lower, f_new, rho)
                res_new = _scaled_residual(F_new, f_new, c)
                better = todo & (res_new < res)
                f = torch.where(better[:, None], f_new, f)
                F = torch.where(better[:, None], F_new, F)
                P = torch.where(better[:, None, None, None], P_new, P)
                dmu = torch.where(better[:, None, None], dmu_new, dmu)
                dl = torch.where(better[:, None, None], dl_new, dl)
                res = torch.where(better, res_new, res)
                todo = todo & ~better
                if not bool(todo.any()):
                    break
            if not bool(todo.any()):
                break
    return f, res, P, dmu, dl, LU, piv


class _ConeQPFunction(torch.autograd.Function):
    """Autograd wrapper: forward solve + implicit-differentiation backward."""

    @staticmethod
    def forward(A, b, mu, lower, active, d, settings, warm_start):
        work = settings.compute_dtype
        A = 0.5 * (A + A.transpose(-1, -2))
        if warm_start is not None:
            warm_start = warm_start.detach().to(work)
        f, status, saved = _forward(
            A.to(work),
            b.to(work),
            mu.to(work),
            lower.to(work),
            active,
            d,
            settings,
            warm_start=warm_start,
        )
        return (
            f.to(A.dtype),
            status.converged,
            status.unbounded,
            status.iterations,
            status.residual,
            saved,
        )

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.d = inputs[5]
        # The solve's intermediates go through save_for_backward, never as attributes of
        # ctx: ``f`` may be the very tensor returned (same dtype), and a tensor attribute
        # that is an output makes a cycle (output -> grad_fn -> ctx -> output) through
        # C++ references that the garbage collector cannot see, keeping every solve's
        # factorisations alive (tests/contact/test_cone_qp.py checks no node survives).
        ctx.save_for_backward(*output[5])
        ctx.mark_non_differentiable(*output[1:5])

    @staticmethod
    @first_order_only
    def backward(ctx, grad_f, *_):
        f, P, dmu, dl, rho, LU, piv, act_c, active = ctx.saved_tensors
        d = ctx.d
        B = f.shape[0]
        out_dtype = grad_f.dtype
        g = torch.where(act_c, grad_f.to(f.dtype), 0)
        v = torch.linalg.lu_solve(LU, piv, g.unsqueeze(-1), adjoint=True).squeeze(-1)
        Pv = _blockwise(P.transpose(-1, -2), v.unsqueeze(-1)).squeeze(-1)
        grad_b = grad_A = grad_mu = grad_l = None
        if ctx.needs_input_grad[1]:
            grad_b = torch.where(act_c, -rho[:, None] * Pv, 0)
        if ctx.needs_input_grad[0]:
            G = -rho[:, None, None] * Pv.unsqueeze(-1) * f.unsqueeze(-2)
            grad_A = 0.5 * (G + G.transpose(-1, -2))
        vk = v.reshape(B, -1, d)
        if ctx.needs_input_grad[2]:
            grad_mu = torch.where(active, (dmu * vk).sum(-1), 0)
            if d == 1:
                grad_mu = torch.zeros_like(grad_mu)
        if ctx.needs_input_grad[3]:
            grad_l = torch.where(active, (dl * vk).sum(-1), 0)
        grads = [None if x is None else x.to(out_dtype) for x in (grad_A, grad_b, grad_mu, grad_l)]
        return *grads, None, None, None, None


@functools.lru_cache(maxsize=64)
def _no_lower(K: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """(K,) zeros, the default ``lower`` (read only: shared by the calls)."""
    return torch.zeros((), dtype=dtype, device=device).expand(K)


@functools.lru_cache(maxsize=64)
def _all_active(K: int, device: torch.device) -> Tensor:
    """(K,) True, the default ``active`` (read only: shared by the calls)."""
    return torch.ones((), dtype=torch.bool, device=device).expand(K)


_DEFERRED = threading.local()


@contextlib.contextmanager
def deferred_checks(flags: Tensor) -> Iterator[Tensor]:
    """Fused (Warp) solves inside do not read their status from the device.

    Each Warp-backend call of :func:`solve_cone_qp` in this thread ORs its error flags
    (with ``return_status``, only the input errors: the caller handles failures) into
    ``flags`` (``(len(fused.FLAGS),)`` int32 on the solve's device, in place) and
    returns its impulses without raising, instead of reading the flags (a host
    synchronisation; none of them can happen inside a captured CUDA graph). The caller
    reads ``flags`` once afterwards (:func:`deferred_error`) and must treat the results
    as garbage where it is not None. Calls on the torch backend check as usual (they
    synchronise anyway)."""
    if flags.dtype != torch.int32 or flags.shape != (len(fused.FLAGS),):
        raise ValueError(f"deferred_checks: flags must be ({len(fused.FLAGS)},) int32")
    outer = getattr(_DEFERRED, "flags", None)
    _DEFERRED.flags = flags
    try:
        yield flags
    finally:
        _DEFERRED.flags = outer


@functools.lru_cache(maxsize=8)
def _input_flags(device: torch.device) -> Tensor:
    """``(len(fused.FLAGS),)`` int32: 1 at the input-error flags, 0 at the failure flag."""
    mask = torch.ones(len(fused.FLAGS), dtype=torch.int32, device=device)  # (no copy from
    mask[fused.FLAGS.index(None)] = 0  # the host: capturable in a CUDA graph)
    return mask


def deferred_error(flags: Tensor) -> str | None:
    """What the solves of a :func:`deferred_checks` block reported: None where every
    problem converged with valid inputs, else the message (one host read)."""
    values = flags.tolist()
    error = fused.input_error(values)
    if error is None and values[5]:
        error = "solve_cone_qp: some problems were unbounded or did not converge"
    return error


def _semidefinite(A: Tensor, active: Tensor, d: int) -> bool:
    """Whether every A (..., C, C) is positive semi-definite on its active contacts (...,
    K), to :data:`fused.SEMIDEFINITE_TOL`: the Cholesky factorisation of that block plus
    ``SEMIDEFINITE_TOL max |A_ij| I`` succeeds (the lower triangles; the Warp kernel's
    ``_semidefinite``, per problem, in the same compute dtype). The tolerance is relative
    to the block's largest entry: a negative eigenvalue above ``-SEMIDEFINITE_TOL max
    |A_ij|`` passes, that of a singular A rounded in float32 included (and an indefinite
    coupling among entries that much smaller than the largest)."""
    if A.dtype not in (torch.float32, torch.float64):  # (no Cholesky in half precision)
        A = A.float()
    keep = active.repeat_interleave(d, dim=-1)  # (..., C)
    block = torch.where(keep.unsqueeze(-1) & keep.unsqueeze(-2), A, 0.0)
    scale = block.abs().amax((-2, -1)).unsqueeze(-1)  # (..., 1)
    shift = torch.where(keep, fused.SEMIDEFINITE_TOL * scale, scale)
    shift = torch.where(scale > 0, shift, 1.0)  # (a zero block is semi-definite)
    info = torch.linalg.cholesky_ex(block + torch.diag_embed(shift)).info
    return not bool((info > 0).any())


def check_dense(caller: str, name: str, x: Tensor) -> None:
    """``ValueError`` naming ``caller`` and ``name`` unless ``x`` is a dense tensor with
    values: a sparse one (which the solver's kernels cannot read) or one on the meta
    device (shapes only) is refused before any arithmetic."""
    if x.layout != torch.strided:
        raise ValueError(
            f"{caller}: {name} must be a dense tensor, got layout {x.layout} (call .to_dense())"
        )
    if x.device.type == "meta":
        raise ValueError(f"{caller}: {name} is on the meta device, which holds no values")


def _check(name: str, x: Tensor, finite: bool = True) -> None:
    """Type check, and unless ``finite`` is False (the Warp backend checks finiteness in its
    kernel, without a host synchronisation per tensor), a finiteness check."""
    if not isinstance(x, Tensor):
        raise ValueError(f"solve_cone_qp: {name} must be a torch.Tensor, got {type(x).__name__}")
    check_dense("solve_cone_qp", name, x)
    if finite and not bool(torch.isfinite(x).all()):
        raise ValueError(f"solve_cone_qp: {name} contains NaN or infinite values")


def solve_cone_qp(
    A: Tensor,
    b: Tensor,
    mu: Tensor,
    d: int,
    lower: Tensor | None = None,
    active: Tensor | None = None,
    *,
    settings: SolverSettings | None = None,
    return_status: bool = False,
    warm_start: Tensor | None = None,
) -> Tensor | tuple[Tensor, SolverStatus]:
    """Solve a batch of friction-cone QPs, differentiably.

    ``minimize 0.5 f^T A f + b^T f`` s.t. ``f_n,k >= lower_k`` and
    ``||f_t,k|| <= mu_k f_n,k`` for every contact ``k``, block
    ``f[..., k*d:(k+1)*d] = (f_n, f_t)``.

    Args:
        A: (..., C, C) symmetric positive semi-definite, C = K * d.
        b: (..., C).
        mu: (..., K) friction coefficients >= 0 (ignored when d == 1).
        d: contact-space dimension per contact: 1 (frictionless), 2 (2D), 3 (3D).
        lower: (..., K) lower bounds >= 0 on the normal impulses; None means 0.
        active: (..., K) bool; inactive contacts get f = 0 exactly and do not
            influence the others. None means all active.
        settings: :class:`SolverSettings`; defaults depend on the dtype.
        return_status: also return a :class:`SolverStatus`. Without it, a batch
            with unbounded or unconverged problems raises :class:`ConeQPError`.
        warm_start: (..., C) a guess of the solution (no gradient flows through it).
            Every problem is first polished from it (the natural-map Newton steps); a
            problem whose residual then reaches ``tol`` keeps that point and skips the
            interior point. Where the minimiser is not unique, the one found depends on
            the guess (it is still a function of the problem and its guess alone).

    Leading batch dims broadcast against each other; a parameter shared across
    the batch (e.g. ``mu.expand(N, K)``) receives the summed gradient.

    Returns:
        f: (..., C), same dtype and device as ``A`` (and the status if asked).

    Raises:
        ValueError: bad shapes, ``d``, dtypes, signs or non-finite inputs, or (with
            ``settings.check_inputs``) an ``A`` that is not symmetric or not positive
            semi-definite on the active contacts.
        ConeQPError: unbounded or unconverged problems (unless ``return_status``).
    """
    settings = settings_or_default(settings, "solve_cone_qp: settings")
    d = contact_dimension(d, "solve_cone_qp")
    _check("A", A, finite=False)
    resolved = settings.resolved(A.dtype, A.device)
    finite = resolved.backend != "warp"  # else checked in the kernel
    for name, x in (("A", A), ("b", b), ("mu", mu)):
        _check(name, x, finite)
    if not A.is_floating_point():
        raise ValueError(f"solve_cone_qp: A must be a floating-point tensor, got {A.dtype}")
    if A.dim() < 2 or A.shape[-1] != A.shape[-2]:
        raise ValueError(f"solve_cone_qp: A must have shape (..., C, C), got {tuple(A.shape)}")
    C = A.shape[-1]
    if C == 0 or C % d:
        raise ValueError(
            f"solve_cone_qp: C = {C} (A's size) must be a positive multiple of d = {d}"
        )
    K = C // d
    if b.dim() < 1 or b.shape[-1] != C:
        raise ValueError(f"solve_cone_qp: b must have shape (..., {C}), got {tuple(b.shape)}")
    if mu.dim() < 1 or mu.shape[-1] != K:
        raise ValueError(
            f"solve_cone_qp: mu must have shape (..., K) with K = {K} contacts, "
            f"got {tuple(mu.shape)}"
        )
    if lower is None:
        lower = _no_lower(K, A.dtype, A.device)
    else:
        _check("lower", lower, finite)
        if lower.dim() < 1 or lower.shape[-1] != K:
            raise ValueError(
                f"solve_cone_qp: lower must have shape (..., {K}), got {tuple(lower.shape)}"
            )
    if active is None:
        active = _all_active(K, A.device)
    elif not isinstance(active, Tensor) or active.dtype != torch.bool:
        raise ValueError("solve_cone_qp: active must be a bool tensor of shape (..., K)")
    else:
        check_dense("solve_cone_qp", "active", active)
        if active.dim() < 1 or active.shape[-1] != K:
            raise ValueError(
                f"solve_cone_qp: active must have shape (..., {K}), got {tuple(active.shape)}"
            )
    for name, x in (("b", b), ("mu", mu), ("lower", lower)):
        if x.dtype != A.dtype:
            raise ValueError(f"solve_cone_qp: {name} has dtype {x.dtype}, A has {A.dtype}")
    for name, x in (("b", b), ("mu", mu), ("lower", lower), ("active", active)):
        if x.device != A.device:
            raise ValueError(f"solve_cone_qp: {name} is on {x.device}, A is on {A.device}")
    try:
        batch = broadcast_shapes(
            A.shape[:-2], b.shape[:-1], mu.shape[:-1], lower.shape[:-1], active.shape[:-1]
        )
    except RuntimeError as err:
        raise ValueError(f"solve_cone_qp: batch dimensions do not broadcast: {err}") from None
    if settings.check_inputs and finite:  # (the Warp backend checks these in its kernel)
        if bool((mu < 0).any()):
            raise ValueError("solve_cone_qp: mu must be >= 0 (friction coefficients)")
        if bool((lower < 0).any()):
            raise ValueError("solve_cone_qp: lower must be >= 0")
        scale = A.diagonal(dim1=-2, dim2=-1).abs().amax(-1, keepdim=True).unsqueeze(-1)
        asym = (A - A.transpose(-1, -2)).abs()
        if bool((asym > 1e-6 * scale + 1e-12).any()):
            raise ValueError("solve_cone_qp: A must be symmetric")
        if not _semidefinite(A.to(resolved.compute_dtype), active, d):
            raise ValueError("solve_cone_qp: " + fused.FLAGS[9])

    if warm_start is not None:
        _check("warm_start", warm_start, finite)
        if warm_start.dtype != A.dtype:
            raise ValueError(
                f"solve_cone_qp: warm_start has dtype {warm_start.dtype}, A has {A.dtype}"
            )
        if warm_start.device != A.device:
            raise ValueError(
                f"solve_cone_qp: warm_start is on {warm_start.device}, A is on {A.device}"
            )
        if warm_start.dim() < 1 or warm_start.shape[-1] != C:
            raise ValueError(
                f"solve_cone_qp: warm_start must have shape (..., {C}), "
                f"got {tuple(warm_start.shape)}"
            )
        try:
            batch = broadcast_shapes(batch, warm_start.shape[:-1])
        except RuntimeError as err:
            raise ValueError(f"solve_cone_qp: warm_start does not broadcast: {err}") from None
    flat, warm_start = flatten_batch(batch, A, b, mu, lower, active, warm_start)
    n = flat[1].shape[0]
    if n == 0:  # an empty batch: nothing to solve (the solvers' loops and launches need one)
        empty = torch.zeros(0, dtype=torch.bool, device=A.device)
        return _finish(
            flat[1] * 0, ~empty, empty, empty.to(torch.int64), empty.to(A.dtype), batch, C, n,
            resolved, return_status,
        )  # fmt: skip
    if resolved.backend == "warp":
        # the whole call (scaling, fast paths, solve, certificate, status) in one kernel;
        # one host synchronisation reads its flags (non-finite inputs, failures)
        f, converged, unbounded, iterations, residual, flags = fused.FusedConeQP.apply(
            *flat, warm_start, d, resolved
        )
        deferred = getattr(_DEFERRED, "flags", None)
        if deferred is not None and deferred.device == flags.device:
            # with return_status the caller handles unconverged problems itself: only the
            # input errors are gathered then
            deferred.bitwise_or_(flags * _input_flags(flags.device) if return_status else flags)
            return _finish(
                f, converged, unbounded, iterations, residual, batch, C, n, resolved,
                return_status, all_converged=True,
            )  # fmt: skip
        flags = flags.tolist()
        error = fused.input_error(flags)
        if error is not None:
            raise ValueError(error)
        return _finish(
            f, converged, unbounded, iterations, residual, batch, C, n, resolved, return_status,
            all_converged=not flags[5],
        )  # fmt: skip
    s_c = _contact_scales(flat[0], flat[4], d)  # (n, C), detached
    A_f, b_f, mu_f, lower_f, act_f = flat
    A_f = A_f * (s_c[:, :, None] * s_c[:, None, :])
    b_f = b_f * s_c
    lower_f = lower_f / s_c[:, ::d]
    if warm_start is not None:
        warm_start = warm_start / s_c
    f, converged, unbounded, iterations, residual, _ = _ConeQPFunction.apply(
        A_f, b_f, mu_f, lower_f, act_f, d, resolved, warm_start
    )
    return _finish(
        f * s_c, converged, unbounded, iterations, residual, batch, C, n, resolved, return_status
    )


def _finish(
    f, converged, unbounded, iterations, residual, batch, C, n, resolved, return_status,
    all_converged: bool | None = None,
):  # fmt: skip
    """Shape the flat results to ``batch``; raise :class:`ConeQPError` on failures unless
    ``return_status`` (``all_converged``: known already, else read from the status)."""

    def shaped(x: Tensor, shape: tuple[int, ...]) -> Tensor:
        return x if x.shape == shape else x.reshape(shape)

    f = shaped(f, (*batch, C))
    status = SolverStatus(
        converged=shaped(converged, batch),
        unbounded=shaped(unbounded, batch),
        iterations=shaped(iterations, batch),
        residual=shaped(residual, batch),
    )
    if return_status:
        return f, status
    if all_converged is None:
        all_converged = status.all_converged
    if not all_converged:
        n_unb = int(status.unbounded.sum())
        n_bad = int((~status.converged).sum()) - n_unb
        parts = []
        if n_unb:
            parts.append(
                f"{n_unb} of {n} problems are unbounded below (A is singular and b has a "
                "descending direction inside the friction cones), or so nearly so that a "
                "minimiser would lie beyond 1/sqrt(eps) impulse scales"
            )
        if n_bad:
            worst = float(status.residual[~status.converged & ~status.unbounded].max())
            parts.append(
                f"{n_bad} of {n} problems did not converge (worst residual {worst:.3g}, "
                f"tol {resolved.tol:.3g})"
            )
        raise ConeQPError(
            "solve_cone_qp: " + "; ".join(parts) + ". Pass return_status=True to inspect them.",
            status,
        )
    return f
