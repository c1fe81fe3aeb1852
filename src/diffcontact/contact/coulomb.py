"""Exact Coulomb friction: the two-phase Poisson impulse with Coulomb's law in each phase.

The paper's contact model (CM, :mod:`diffcontact.contact.impulse`) solves each phase
as a friction-cone QP, the *maximum-dissipation* relaxation of Coulomb friction. Its
optimality conditions put the contact velocity ``u = A f + b`` in the dual cone,
``u_n >= mu ||u_t||``: a sliding contact separates with a normal velocity of
``mu ||u_t||`` (the relaxation's lift-off). Coulomb's law asks ``u_n >= 0`` instead.
De Saxcé's bipotential form writes it as a cone complementarity problem on the
*modified* velocity ``û = u + mu ||u_t|| e_n`` (per contact ``k``, with the feasible
set ``C_k = {f_n >= l_k, ||f_t|| <= mu_k f_n}`` of the phase):

    f in C,   û in C*,   f ⊥ û    <=>    H(f) = f - Pi_C(f - rho û(f)) = 0   (any rho > 0)

Sliding contacts get ``f_t = -mu f_n u_t / ||u_t||`` and ``f_n u_n = 0``; sticking
ones ``u = 0``; separating ones ``f = 0`` (or ``f_n = l`` in the restitution phase
with ``u_n >= 0``). This is a nonlinear complementarity problem (NCP): ``û`` depends
on ``f`` through ``||u_t||``, so no convex program has it as its optimality condition.

**How it is solved** (:func:`solve_coulomb`; all problems of a batch at once, problems
leave the batch as they converge):

1. the cone QP with shift ``s = 0`` (CM's solution, :func:`~diffcontact.contact.solve_cone_qp`);
2. semismooth Newton steps on ``H`` (the generalised Jacobian below) from the
   current fixed-point iterate, with a backtracking line search on ``||H||`` (a step
   is taken only if it lowers it); the best point found so far is kept;
3. where Newton does not reach the tolerance, one *fixed-point step on the De Saxcé
   shift* from the fixed-point iterate (never from Newton's point):
   ``s = mu ||u_t(f_fp)||``, then ``f_fp = QP(A, b + s e_n)`` (warm-started). Its
   fixed points are exactly the Coulomb solutions (the shift only moves the normal
   components of ``b``, so ``u_t`` is the QP's own); for one contact with ``A = a I``
   the map contracts at the rate ``mu^2 / (1 + mu^2)``. Because Newton never feeds
   back into it, the method converges whenever the plain fixed point does (feeding
   Newton's point back stalled a BD5 problem with ``mu = 1.4`` at a residual of 0.15,
   which the plain fixed point solves in 62 steps);
4. repeat 2-3 up to ``max_iter`` times.

The fixed point is the globalisation (every iterate is an admissible impulse, the
solution of a convex problem with the existing solver's guarantees: padding,
singular ``A``, fast paths); Newton gives the last digits in one or two steps (in 2D,
``H`` is piecewise linear on the sliding branch, and the step from CM's solution is
often exact). Why not Newton alone: the NCP's Jacobian is not symmetric and can be
singular away from the solution, and a Newton iterate need not be an admissible
impulse; why not the fixed point alone: it converges linearly, slowly for large
``mu``.

**When it does not converge.** With a singular ``A`` (several contacts on one body,
equality constraints) Coulomb's NCP may have several solutions or none, and for large
``mu`` the fixed point need not contract. A problem whose scaled residual
``||H||_inf / max(c, ||f||_inf)`` is still above ``tol`` after ``max_iter`` outer
iterations is reported in the :class:`~diffcontact.contact.SolverStatus`
(``converged=False``); :func:`coulomb_two_phase_impulse` raises
:class:`~diffcontact.contact.ConeQPError` with that status (``System.simulate``
names the trajectories and the step), or, with ``on_failure="warn"``, warns naming
the contact-batch rows and keeps their last fixed-point iterate: the cone QP's
solution with the last shift, an admissible impulse (never silently).

**Gradients** (:class:`_CoulombFunction`): implicit differentiation of ``H(f; A, b,
mu, l) = 0`` at the returned point. With ``M = I + e_n g^T`` per contact
(``g = mu (0, u_t / ||u_t||)``, the derivative of the shift; ``0`` where
``u_t = 0``, a sticking contact: an element of the generalised Jacobian, so
gradients stay finite there) and ``P = dPi/dz``::

    dH/df = I - P + rho P M (A + delta I)

(``delta``: ``SolverSettings.kkt_reg`` relative to diag(A), as in the QP's backward).
One transposed solve ``(dH/df)^T v = grad_f`` per batch; then
``grad_b = -rho M^T P^T v``, ``grad_A = -rho sym((M^T P^T v) f^T)``,
``grad_mu = dPi/dmu . v - rho (P^T v)_n ||u_t||``, ``grad_l = dPi/dl . v``. At a
problem that did not converge the same formula is evaluated at the returned point
(finite, not a derivative of anything exact).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from diffcontact.contact.cone import project_contact_set
from diffcontact.contact.cone_qp import (
    ConeQPError,
    SolverSettings,
    SolverStatus,
    flatten_batch,
    settings_or_default,
    solve_cone_qp,
)
from diffcontact.contact.first_order import first_order_only
from diffcontact.contact.impulse import (
    ImpulseResult,
    check_impulse_inputs,
    empty_impulse,
    widened,
    wider_dtype,
)
from diffcontact.contact.interior_point import add_block_diag
from diffcontact.contact.operator import ContactOperator, as_operator
from diffcontact.fastops import lu_factor_ex
from diffcontact.shapes import broadcast_shapes, contact_dimension

__all__ = [
    "CoulombSettings",
    "ExactCoulomb",
    "coulomb_two_phase_impulse",
    "solve_coulomb",
]

ON_FAILURE = ("raise", "warn")


@dataclass(frozen=True)
class CoulombSettings:
    """Iteration caps and tolerance of :func:`solve_coulomb`.

    Attributes:
        max_iter: outer iterations (each: Newton steps, then one fixed-point step,
            i.e. one cone-QP solve, for the problems Newton did not finish; a problem
            leaves the batch once solved, so the cap costs only the hard ones). 30
            stopped one state of BP5's 64 generated trajectories at step 59
            (``tests/contact/test_coulomb.py``); the fixed point can need 62 steps
            (above).
        newton_steps: semismooth Newton steps per outer iteration.
        tol: accepted scaled residual ``||H||_inf / max(c, ||f||_inf)`` (``c`` the
            problem's impulse scale); ``None``: the cone QP's ``tol`` (float64 1e-7).
            Newton goes on to the QP's ``polish_tol`` (rounding level) while it helps.
        on_failure: ``"raise"`` (:class:`~diffcontact.contact.ConeQPError` with the
            per-problem status) or ``"warn"`` (a ``RuntimeWarning`` naming the rows;
            those problems keep their last fixed-point iterate). Used by
            :func:`coulomb_two_phase_impulse`; :func:`solve_coulomb` only reports.
    """

    max_iter: int = 100
    newton_steps: int = 8
    tol: float | None = None
    on_failure: str = "raise"

    def __post_init__(self) -> None:
        for name in ("max_iter", "newton_steps"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise ValueError(f"CoulombSettings.{name} must be an integer >= 0, got {value!r}")
        if self.tol is not None and not (isinstance(self.tol, (int, float)) and self.tol > 0):
            raise ValueError(f"CoulombSettings.tol must be a positive number, got {self.tol!r}")
        if self.on_failure not in ON_FAILURE:
            raise ValueError(
                f"CoulombSettings.on_failure must be one of {ON_FAILURE}, got {self.on_failure!r}"
            )


# ----------------------------------------------------------------- the De Saxcé map
def _decouple(A: Tensor, b: Tensor, mu: Tensor, lower: Tensor, active: Tensor, d: int):
    """Masked, decoupled copy of a flat batch (as in the cone QP): inactive contacts get
    an identity block and a separating velocity, so their ``f`` is 0 and ``H`` is 0 there.

    Returns ``A_m (B,C,C), b_m (B,C), mu_m, lower_m (B,K), rho (B,), reg_scale (B,),
    c (B,)`` (``rho = 1 / mean active diag(A)``, ``c`` the impulse scale)."""
    C = b.shape[-1]
    act_c = active.repeat_interleave(d, dim=-1)
    pair = act_c[:, :, None] & act_c[:, None, :]
    diag = A.diagonal(dim1=-2, dim2=-1)
    n_act = act_c.sum(-1).clamp_min(1)
    tiny = torch.finfo(A.dtype).tiny
    a_s = (torch.where(act_c, diag, 0).sum(-1) / n_act).clamp_min(tiny)
    a_s = torch.where(a_s > 1e3 * tiny, a_s, torch.ones_like(a_s))
    lower_m = torch.where(active, lower, 0)
    b_s = torch.where(act_c, b.abs(), 0).amax(-1)
    b_s = torch.maximum(b_s, a_s * lower_m.amax(-1))
    b_s = torch.where(b_s > 0, b_s, a_s)
    eye = torch.eye(C, dtype=A.dtype, device=A.device)
    is_normal = torch.zeros(C, dtype=torch.bool, device=A.device)
    is_normal[::d] = True
    A_m = torch.where(pair, A, 0) + torch.where(~act_c, a_s[:, None], 0)[:, :, None] * eye
    b_m = torch.where(act_c, b, torch.where(is_normal, b_s[:, None], 0))
    mu_m = torch.where(active, mu, 1)
    return A_m, b_m, mu_m, lower_m, 1 / a_s, a_s, b_s / a_s


def _desaxce_map(A: Tensor, b: Tensor, mu: Tensor, lower: Tensor, f: Tensor, rho: Tensor, d: int):
    """``H(f) = f - Pi_C(f - rho û)`` for a flat batch, with what its Jacobian needs.

    Shapes: A (B,C,C), b/f (B,C), mu/lower (B,K), rho (B,). Returns ``H (B,C)``,
    ``P (B,K,d,d)``, ``dmu, dl (B,K,d)``, ``u_hat_t (B,K,d-1)`` (unit slip directions,
    0 where there is no slip) and ``slip (B,K)`` (``||u_t||``)."""
    B, C = f.shape
    K = C // d
    u = (torch.einsum("bij,bj->bi", A, f) + b).reshape(B, K, d)
    if d > 1:
        ut = u[..., 1:]
        slip = torch.linalg.vector_norm(ut, dim=-1)
        pos = slip > 0
        t_hat = torch.where(pos[..., None], ut / torch.where(pos, slip, 1)[..., None], 0)
        w = torch.cat([(u[..., 0] + mu * slip)[..., None], ut], dim=-1)
    else:
        slip = torch.zeros_like(u[..., 0])
        t_hat = u[..., 1:]
        w = u
    z = f.reshape(B, K, d) - rho[:, None, None] * w
    proj, P, dmu, dl = project_contact_set(z, mu, lower)
    return f - proj.reshape(B, C), P, dmu, dl, t_hat, slip


def _shift_blocks(mu: Tensor, t_hat: Tensor, d: int) -> Tensor:
    """Per-contact blocks of ``M = I + e_n g^T``, ``g = mu (0, t_hat)``: (B, K, d, d)."""
    B, K = mu.shape
    M = torch.eye(d, dtype=mu.dtype, device=mu.device).expand(B, K, d, d).clone()
    if d > 1:
        M[..., 0, 1:] = mu[..., None] * t_hat
    return M


def _blockwise(P: Tensor, x: Tensor) -> Tensor:
    """Per-contact blocks applied to rows: P (B,K,d,d), x (B,K*d,...) -> (B,K*d,...)."""
    B, K, d, _ = P.shape
    xs = x.reshape(B, K, d, -1)
    return torch.einsum("bkij,bkjm->bkim", P, xs).reshape(x.shape)


def _jacobian(A: Tensor, P: Tensor, M: Tensor, rho: Tensor, reg: Tensor) -> Tensor:
    """``dH/df = I - P + rho P M (A + reg I)``: (B, C, C)."""
    C = A.shape[-1]
    eye = torch.eye(C, dtype=A.dtype, device=A.device)
    A_reg = A + reg[:, None, None] * eye
    PM = P @ M
    return add_block_diag(eye + rho[:, None, None] * _blockwise(PM, A_reg), -P)


def _residual(H: Tensor, f: Tensor, c: Tensor) -> Tensor:
    return H.abs().amax(-1) / torch.maximum(c, f.abs().amax(-1))


def _newton(f, data, d: int, steps: int, target: float):
    """Semismooth Newton on ``H`` from ``f`` (B, C), backtracking on the residual; a
    problem keeps its point where no step lowers it. Returns ``(f, residual)``."""
    A, b, mu, lower, rho, reg, c = data
    H, P, _, _, t_hat, _ = _desaxce_map(A, b, mu, lower, f, rho, d)
    res = _residual(H, f, c)
    for _ in range(steps):
        todo = res > target
        if not bool(todo.any()):
            break
        J = _jacobian(A, P, _shift_blocks(mu, t_hat, d), rho, reg)
        LU, piv, _ = lu_factor_ex(J)
        delta = -torch.linalg.lu_solve(LU, piv, H.unsqueeze(-1)).squeeze(-1)
        delta = torch.nan_to_num(delta, nan=0.0, posinf=0.0, neginf=0.0)
        improved = torch.zeros_like(todo)
        for alpha in (1.0, 0.5, 0.25, 0.125):
            f_new = f + alpha * delta
            H_new, P_new, _, _, t_new, _ = _desaxce_map(A, b, mu, lower, f_new, rho, d)
            res_new = _residual(H_new, f_new, c)
            better = todo & (res_new < res)
            f = torch.where(better[:, None], f_new, f)
            H = torch.where(better[:, None], H_new, H)
            P = torch.where(better[:, None, None, None], P_new, P)
            t_hat = torch.where(better[:, None, None], t_new, t_hat)
            res = torch.where(better, res_new, res)
            improved |= better
            todo = todo & ~better
            if not bool(todo.any()):
                break
        if not bool(improved.any()):
            break
    return f, res


def _forward(A, b, mu, lower, active, d: int, qp: SolverSettings, cs: CoulombSettings, warm):
    """The solve of a flat batch (no grad). Returns ``f, converged, unbounded,
    iterations, residual`` (``f`` in the input's dtype)."""
    B, C = b.shape
    tol = cs.tol if cs.tol is not None else qp.tol
    target = min(qp.polish_tol, tol)
    A_m, b_m, mu_m, lower_m, rho, a_s, c = _decouple(A, b, mu, lower, active, d)
    reg = qp.kkt_reg * a_s
    inner = replace(qp, check_inputs=False)
    f, st = solve_cone_qp(
        A, b, mu, d, lower, active, settings=inner, return_status=True, warm_start=warm
    )
    f = torch.where(active.repeat_interleave(d, -1), f, 0)
    ok = st.converged.clone()
    unbounded = st.unbounded.clone()
    iterations = torch.zeros(B, dtype=torch.int64, device=b.device)
    data = (A_m, b_m, mu_m, lower_m, rho, reg, c)
    H, *_ = _desaxce_map(A_m, b_m, mu_m, lower_m, f, rho, d)
    res = _residual(H, f, c)
    if d == 1:  # no friction: the QP is Coulomb's problem
        return f, ok & (res <= tol), unbounded, iterations, res
    # The fixed point on the De Saxcé shift runs on its own iterate ``f_fp`` (an
    # admissible impulse: the fallback); every outer iteration first tries Newton from
    # it, and ``f`` keeps the best point found (by residual). Newton never feeds back
    # into the fixed point, so the method converges whenever the plain fixed point does
    # (a Newton step that lowers the residual can still lead away from the solution).
    f_fp = f.clone()
    rows = ((res > target) & ok).nonzero().squeeze(-1)
    for it in range(cs.max_iter + 1):
        if rows.numel() == 0:
            break
        sub = tuple(x[rows] for x in data)
        f_r, res_r = _newton(f_fp[rows], sub, d, cs.newton_steps, target)
        better = res_r < res[rows]
        f[rows] = torch.where(better[:, None], f_r, f[rows])
        res[rows] = torch.where(better, res_r, res[rows])
        rows = rows[res[rows] > tol]
        if rows.numel() == 0 or it == cs.max_iter:
            break
        # fixed-point step on the De Saxcé shift, from the fixed-point iterate
        A_r, b_r, mu_r = A[rows], b[rows], mu[rows]
        fr = f_fp[rows]
        u = (torch.einsum("bij,bj->bi", A_r, fr) + b_r).reshape(rows.numel(), -1, d)
        shift = mu_r * torch.linalg.vector_norm(u[..., 1:], dim=-1)
        b_shift = (b_r.reshape(rows.numel(), -1, d) + torch.nn.functional.pad(
            shift[..., None], (0, d - 1))).reshape(rows.numel(), C)  # fmt: skip
        f_new, st_r = solve_cone_qp(
            A_r, b_shift, mu_r, d, lower[rows], active[rows], settings=inner,
            return_status=True, warm_start=fr,
        )  # fmt: skip
        f_new = torch.where(active[rows].repeat_interleave(d, -1), f_new, 0)
        good = st_r.converged
        f_fp[rows] = torch.where(good[:, None], f_new, fr)
        iterations[rows] += 1
        H_r, *_ = _desaxce_map(*(x[rows] for x in data[:4]), f_fp[rows], rho[rows], d)
        res_fp = _residual(H_r, f_fp[rows], c[rows])
        take = good & (res_fp < res[rows])
        f[rows] = torch.where(take[:, None], f_fp[rows], f[rows])
        res[rows] = torch.where(take, res_fp, res[rows])
        ok[rows] = good
        unbounded[rows] |= st_r.unbounded
        rows = rows[good & (res[rows] > target)]
    converged = ok & (res <= tol)
    f = torch.where(converged[:, None], f, f_fp)
    return f, converged, unbounded, iterations, res


class _CoulombFunction(torch.autograd.Function):
    """Forward: :func:`_forward`; backward: implicit differentiation of ``H = 0``."""

    @staticmethod
    def forward(A, b, mu, lower, active, d, qp, cs, warm):
        work = qp.compute_dtype
        A = 0.5 * (A + A.transpose(-1, -2))
        A_w, b_w, mu_w, l_w = A.to(work), b.to(work), mu.to(work), lower.to(work)
        with torch.no_grad():
            w = None if warm is None else warm.detach().to(work)
            f, conv, unb, its, res = _forward(A_w, b_w, mu_w, l_w, active, d, qp, cs, w)
        return f.to(A.dtype), conv, unb, its, res, (A_w, b_w, mu_w, l_w, f, active)

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.d = inputs[5]
        ctx.kkt_reg = inputs[6].kkt_reg
        ctx.save_for_backward(*output[5])
        ctx.mark_non_differentiable(*output[1:5])

    @staticmethod
    @first_order_only
    def backward(ctx, grad_f, *_):
        A, b, mu, lower, f, active = ctx.saved_tensors
        d = ctx.d
        B, C = f.shape
        K = C // d
        out = grad_f.dtype
        act_c = active.repeat_interleave(d, -1)
        A_m, b_m, mu_m, lower_m, rho, a_s, _ = _decouple(A, b, mu, lower, active, d)
        _, P, dmu, dl, t_hat, slip = _desaxce_map(A_m, b_m, mu_m, lower_m, f, rho, d)
        M = _shift_blocks(mu_m, t_hat, d)
        J = _jacobian(A_m, P, M, rho, ctx.kkt_reg * a_s)
        g = torch.where(act_c, grad_f.to(f.dtype), 0)
        LU, piv, _ = lu_factor_ex(J)
        v = torch.linalg.lu_solve(LU, piv, g.unsqueeze(-1), adjoint=True).squeeze(-1)
        v = torch.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0)
        q = _blockwise(P.transpose(-1, -2), v.unsqueeze(-1)).squeeze(-1)  # P^T v
        Mq = _blockwise(M.transpose(-1, -2), q.unsqueeze(-1)).squeeze(-1)  # M^T P^T v
        grad_A = grad_b = grad_mu = grad_l = None
        if ctx.needs_input_grad[1]:
            grad_b = torch.where(act_c, -rho[:, None] * Mq, 0)
        if ctx.needs_input_grad[0]:
            G = -rho[:, None, None] * Mq.unsqueeze(-1) * f.unsqueeze(-2)
            G = torch.where(act_c[:, :, None] & act_c[:, None, :], G, 0)
            grad_A = 0.5 * (G + G.transpose(-1, -2))
        vk, qk = v.reshape(B, K, d), q.reshape(B, K, d)
        if ctx.needs_input_grad[2]:
            if d == 1:
                grad_mu = torch.zeros_like(mu)
            else:
                grad_mu = (dmu * vk).sum(-1) - rho[:, None] * qk[..., 0] * slip
                grad_mu = torch.where(active, grad_mu, 0)
        if ctx.needs_input_grad[3]:
            grad_l = torch.where(active, (dl * vk).sum(-1), 0)
        grads = [None if x is None else x.to(out) for x in (grad_A, grad_b, grad_mu, grad_l)]
        return *grads, None, None, None, None, None


def solve_coulomb(
    A: Tensor,
    b: Tensor,
    mu: Tensor,
    d: int,
    lower: Tensor | None = None,
    active: Tensor | None = None,
    *,
    settings: SolverSettings | None = None,
    coulomb: CoulombSettings | None = None,
    warm_start: Tensor | None = None,
) -> tuple[Tensor, SolverStatus]:
    """Solve a batch of Coulomb-friction contact problems (De Saxcé's NCP), differentiably.

    Find ``f`` with, per contact ``k``, ``f_k in C_k = {f_n >= l_k, ||f_t|| <= mu_k
    f_n}``, ``û_k = u_k + mu_k ||u_t,k|| e_n in C_k*`` and the complementarity of
    the variational inequality, ``u = A f + b`` (module docstring).

    Args:
        A: (..., C, C) symmetric positive semi-definite, C = K * d.
        b: (..., C).
        mu: (..., K) friction coefficients >= 0.
        d: contact-space dimension: 1, 2 or 3 (with 1 this is the cone QP).
        lower: (..., K) lower bounds >= 0 on the normal impulses; None means 0.
        active: (..., K) bool (None: all); inactive contacts get ``f = 0`` exactly.
        settings: the cone QP's :class:`~diffcontact.contact.SolverSettings` (its
            tolerances, ``kkt_reg`` and ``compute_dtype`` are used here too).
        coulomb: :class:`CoulombSettings`.
        warm_start: (..., C) a guess for the first cone-QP solve (no gradient).

    Returns:
        ``f: (..., C)`` (A's dtype and device; differentiable with respect to ``A``,
        ``b``, ``mu``, ``lower``) and a :class:`~diffcontact.contact.SolverStatus`
        shaped like the batch (``iterations`` counts fixed-point steps, ``residual``
        the scaled De Saxcé residual). Problems that did not converge keep their last
        fixed-point iterate; nothing is raised here.

    Raises:
        ValueError: bad shapes, dtypes, devices, ``d`` or non-finite inputs.
    """
    settings = settings_or_default(settings, "solve_coulomb: settings")
    coulomb = coulomb or CoulombSettings()
    d = contact_dimension(d, "solve_coulomb")
    for name, x in (("A", A), ("b", b), ("mu", mu)):
        if not isinstance(x, Tensor) or not x.is_floating_point():
            raise ValueError(f"solve_coulomb: {name} must be a floating-point torch.Tensor")
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"solve_coulomb: {name} contains NaN or infinite values")
    if A.dim() < 2 or A.shape[-1] != A.shape[-2] or A.shape[-1] % d or A.shape[-1] == 0:
        raise ValueError(
            f"solve_coulomb: A must have shape (..., C, C) with C a positive multiple of "
            f"d = {d}, got {tuple(A.shape)}"
        )
    C = A.shape[-1]
    K = C // d
    if lower is None:
        lower = torch.zeros(K, dtype=A.dtype, device=A.device)
    if active is None:
        active = torch.ones(K, dtype=torch.bool, device=A.device)
    if not isinstance(active, Tensor) or active.dtype != torch.bool:
        raise ValueError("solve_coulomb: active must be a bool tensor of shape (..., K)")
    shapes = {"b": (b, C), "mu": (mu, K), "lower": (lower, K), "active": (active, K)}
    for name, (x, n) in shapes.items():
        if x.dim() < 1 or x.shape[-1] != n:
            raise ValueError(
                f"solve_coulomb: {name} must have shape (..., {n}), got {tuple(x.shape)}"
            )
        if x.device != A.device:
            raise ValueError(f"solve_coulomb: {name} is on {x.device}, A is on {A.device}")
        if name != "active" and x.dtype != A.dtype:
            raise ValueError(f"solve_coulomb: {name} has dtype {x.dtype}, A has {A.dtype}")
    if settings.check_inputs and (bool((mu < 0).any()) or bool((lower < 0).any())):
        raise ValueError("solve_coulomb: mu and lower must be >= 0")
    try:
        batch = broadcast_shapes(
            A.shape[:-2], b.shape[:-1], mu.shape[:-1], lower.shape[:-1], active.shape[:-1]
        )
        if warm_start is not None:
            batch = broadcast_shapes(batch, warm_start.shape[:-1])
    except RuntimeError as err:
        raise ValueError(f"solve_coulomb: batch dimensions do not broadcast: {err}") from None
    flat, warm_start = flatten_batch(batch, A, b, mu, lower, active, warm_start)
    resolved = settings.resolved(A.dtype, A.device)
    f, conv, unb, its, res, _ = _CoulombFunction.apply(*flat, d, resolved, coulomb, warm_start)
    status = SolverStatus(
        converged=conv.reshape(batch),
        unbounded=unb.reshape(batch),
        iterations=its.reshape(batch),
        residual=res.to(A.dtype).reshape(batch),
    )
    return f.reshape(*batch, C), status


def _merge(a: SolverStatus, b: SolverStatus) -> SolverStatus:
    return SolverStatus(
        converged=a.converged & b.converged,
        unbounded=a.unbounded | b.unbounded,
        iterations=a.iterations + b.iterations,
        residual=torch.maximum(a.residual, b.residual),
    )


def coulomb_two_phase_impulse(
    J_C: Tensor | ContactOperator,
    Mhat_inv: Tensor | None,
    v: Tensor,
    mu: Tensor,
    cor: Tensor,
    active: Tensor,
    d: int,
    *,
    v_C_star: Tensor | None = None,
    settings: SolverSettings | None = None,
    coulomb: CoulombSettings | None = None,
) -> ImpulseResult:
    """The two-phase Poisson impulse with exact Coulomb friction in each phase.

    Same phases as :func:`~diffcontact.contact.two_phase_impulse` (CM): compression
    with ``b = v_C``; restitution with ``f_r,n >= e_P f_c,n`` and
    ``b = v_C + A f_c - v_C^*`` (the slip speed of the shift is that of ``A f + b``,
    i.e. relative to the penetration target, which has no tangential part for one
    contact); each phase solved by :func:`solve_coulomb` instead of the cone QP.

    Args:
        J_C: (..., K*d, D), or a :class:`~diffcontact.contact.ContactOperator` of ``J_C``
        and ``Mhat^-1`` (then ``Mhat_inv=None``); Mhat_inv: (..., D, D); v: (..., D);
        mu, cor: (..., K);
        active: (..., K) bool; d: contact-space dimension;
        v_C_star: (..., K*d) or None; settings: the cone QP's settings;
        coulomb: :class:`CoulombSettings`.

    Returns:
        An :class:`~diffcontact.contact.ImpulseResult`.

    Raises:
        ConeQPError: some problems did not converge and ``coulomb.on_failure`` is
            ``"raise"``; its ``status`` (shaped like the batch) says which.

    States narrower than ``settings.compute_dtype`` (float32 states, the default float64
    solve) are resolved in the compute dtype from the rows on, as CM's
    (:func:`~diffcontact.contact.impulse.widened`).
    """
    coulomb = coulomb or CoulombSettings()
    d = contact_dimension(d, "coulomb_two_phase_impulse")
    if (settings or SolverSettings()).check_inputs:
        check_impulse_inputs(
            cor, v, "coulomb_two_phase_impulse", J_C=J_C, Mhat_inv=Mhat_inv, mu=mu,
            active=active, d=d, v_C_star=v_C_star,
        )  # fmt: skip
    if v.numel() == 0:  # batch 0
        return empty_impulse(v, active, d)
    work = wider_dtype(v.dtype, (settings or SolverSettings()).compute_dtype)
    if work is not None:
        op, v_w, mu_w, cor_w, star_w = widened(work, J_C, Mhat_inv, v, mu, cor, v_C_star)
        return coulomb_two_phase_impulse(
            op, None, v_w, mu_w, cor_w, active, d,
            v_C_star=star_w, settings=settings, coulomb=coulomb,
        ).to(v.dtype)  # fmt: skip
    op = as_operator(J_C, Mhat_inv)
    A = op.delassus()  # symmetric
    v_C = op.contact_velocity(v)
    f_c, st_c = solve_coulomb(A, v_C, mu, d, None, active, settings=settings, coulomb=coulomb)
    v_C_c = v_C + (A @ f_c.unsqueeze(-1)).squeeze(-1)
    lower = (cor * f_c[..., ::d]).clamp_min(0)
    target = v_C_c if v_C_star is None else v_C_c - v_C_star
    f_c_k = f_c.detach().reshape(*f_c.shape[:-1], -1, d)
    guess = (cor.detach().unsqueeze(-1) * f_c_k).flatten(-2)
    f_r, st_r = solve_coulomb(
        A, target, mu, d, lower, active, settings=settings, coulomb=coulomb, warm_start=guess
    )
    status = _merge(st_c, st_r)
    if not status.all_converged:
        bad = (~status.converged).nonzero().tolist()
        worst = float(status.residual[~status.converged].max())
        rows = ", ".join(str(r[0] if len(r) == 1 else tuple(r)) for r in bad[:8])
        more = "" if len(bad) <= 8 else f" and {len(bad) - 8} more"
        why = "unbounded cone QP" if bool(status.unbounded.any()) else "no Coulomb solution found"
        message = (
            f"Coulomb contact model: {len(bad)} of {status.converged.numel()} contact problems "
            f"did not converge (rows {rows}{more}; worst De Saxcé residual {worst:.3g}; "
            f"{why} in {coulomb.max_iter} fixed-point iterations: with a singular A the Coulomb "
            "problem may have several solutions or none)"
        )
        if coulomb.on_failure == "raise":
            raise ConeQPError(message + "; CoulombSettings(on_failure='warn') keeps the last "
                              "fixed-point iterate instead", status)  # fmt: skip
        warnings.warn(message + "; kept their last fixed-point iterate", RuntimeWarning, 2)
    v_plus = v + op.velocity_change(f_c + f_r)
    return ImpulseResult(v_plus, f_c, f_r)


class ExactCoulomb:
    """Contact model ``"Coulomb"``: two Poisson phases, exact Coulomb friction (NCP).

    Args:
        max_iter, newton_steps, tol, on_failure: :class:`CoulombSettings`.

    It accepts a :class:`~diffcontact.contact.ContactOperator` in place of the dense
    ``J_C`` (``accepts_contact_operator``).
    """

    accepts_contact_operator = True

    def __init__(
        self,
        max_iter: int = 100,
        newton_steps: int = 8,
        tol: float | None = None,
        on_failure: str = "raise",
    ) -> None:
        self.settings = CoulombSettings(max_iter, newton_steps, tol, on_failure)

    def __repr__(self) -> str:
        return f"ExactCoulomb({self.settings})"

    def resolve(
        self,
        J_C: Tensor | ContactOperator,
        Mhat_inv: Tensor | None,
        v: Tensor,
        params,
        active: Tensor,
        d: int,
        *,
        v_C_star: Tensor | None = None,
        settings: SolverSettings | None = None,
    ) -> ImpulseResult:
        """The :class:`~diffcontact.contact.ContactModel` method (shapes there)."""
        return coulomb_two_phase_impulse(
            J_C,
            Mhat_inv,
            v,
            params.mu,
            params.cor,
            active,
            d,
            v_C_star=v_C_star,
            settings=settings,
            coulomb=self.settings,
        )


def Coulomb(**options) -> ExactCoulomb:
    """Registry factory of ``"Coulomb"``: :class:`ExactCoulomb` (options: its arguments)."""
    return ExactCoulomb(**options)
