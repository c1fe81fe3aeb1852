"""Position-level projection onto the admissible set of the contacts (post-stabilisation).

The contact impulse acts on velocities only: it stops a violated limit (or an
overlap) from growing but leaves the positions where the step put them, and the
penetration target of appendix G removes only a fraction of a violation per
step. A long rope, whose stretch limits carry its weight, then drifts far past
its limits (docs/config.md, ``rope``). After a step, :func:`project_positions`
moves the positions of the states that violate a candidate back onto

    gap_k(x) >= 0 for every candidate k,   Phi(x) = Phi(x_pred)

(``Phi`` the equality constraints, kept at their values before the projection),
by a fixed maximum number of Gauss-Newton iterations, each the smallest step in
the mass metric that satisfies the constraints linearised at the iterate ``x_i``
(``J`` the normal rows of ``J_C``, ``J_E`` the equality-constraint Jacobian,
``r = Phi(x_i) - Phi(x_pred)``):

    dx = dx_E + Mhat^-1 J^T lambda,   dx_E = -M^-1 J_E^T (J_E M^-1 J_E^T)^-1 r,
    lambda = argmin_{lambda >= 0} 0.5 lambda^T A lambda + lambda^T (gap + J dx_E),
    A = J Mhat^-1 J^T,

the frictionless (``d = 1``) case of the contact impulse's cone QP, solved by the
same :func:`~diffcontact.contact.solve_cone_qp`. ``Mhat^-1`` (S.12) keeps the
step tangent to the equality constraints and ``dx_E`` removes their second-order
drift, so ``Phi`` is unchanged to the tolerance. Near the solution the
iteration converges quadratically; it is a sequence of projections of the
iterate, not the exact nearest point to ``x_pred`` (the two differ at second
order in the violation: the exact nearest point's Gauss-Newton iteration, which
ignores the constraints' curvature, diverged on whipping ropes).

Making it robust on a whipping rope (violations of 0.1-0.4 rad per step at
``dt = 0.01``) took three things, all measured on Rope and Rope-D200:

- both sides of a two-sided limit (the rope's ``gap = min(side_1, side_2)``, with
  ``side_2 = width - side_1``, :meth:`~diffcontact.geometry.base.GeometryBase.gap_widths`)
  are linear constraints, so a step cannot throw a joint across its band;
- the limits in an iteration's problem are those violated, those within
  :data:`MARGIN` of the largest violation (distances in the mass metric,
  ``gap_k / ||J_k||_{M^-1}``, so bends and lengths compare), and those a trial
  step crossed, kept once chosen; ``lambda >= 0`` releases the ones not needed;
- a backtracking line search over :data:`STEPS` keeps the step with the least
  violation (``0`` if none improves).

Damping. Where the masses differ a lot (a rope with a heavy tip), the Gauss-Newton step
stalls: a taut chain can only shorten by moving its heavy end, but the linearised limits
offer a cheap way through the light points, sideways, which the limits' curvature does
not allow (moving a joint onto the chord of its neighbours shortens both segments to
first order only). The full step then throws the light points far, and no step of the
line search reduces the violation (a tip 1000 times the other points stretched Rope's
segments to 5 times their rest length at dt = 0.01). A state whose line search
backtracks therefore iterates in the damped metric ``M + rho mbar I`` (``mbar`` its mean
point mass): ``rho`` starts at :data:`DAMPING`, and each backtracked step multiplies it
by :data:`DAMPING_FACTOR`, each full step divides it, as in Levenberg-Marquardt. The
isotropic term charges the light points' sideways motion as the curvature of a taut
segment does (in proportion to its tension, whatever the points' masses). With equal
point masses the damped metric is the masses' times a number (the same steps), and
point masses within a factor :data:`UNEVEN` of each other are not damped (a learned
rope's masses, a few per cent apart: the steps barely change, and damping costs each
iteration some operations). A damped state's projected positions are admissible like the
others', but not those of the iterations in the mass metric.

With the positions projected alone, the per-step violations of a long whipping rope
(Rope-D200 at ``dt = 0.01``) grew beyond what the iterations resolve; with the velocities
projected too (below) the limits hold there (docs/config.md, ``rope``).

Each state stops iterating once its gaps are above ``-tol`` and its ``Phi`` is within
``tol`` (its positions are then kept, whatever the other states of its batch still do:
a state's projection does not depend on its batch), and the iterations end when every
state has stopped. Everything but the discrete choices (rows, step length, early stop) is
differentiable; with the projection on, ``System`` drops the penetration target
(it would add a velocity for a violation the projection already removed, which
pumped energy into a hanging rope).

Velocities (:func:`project_state`, the config's ``velocity_projection``). The step's
impulse made the velocities admissible for the limits violated before the projection,
at those positions; the projection closes further limits, active only at the projected
positions, and left the velocities pointing into them: the next step turned potential
energy into that speed and the projection put it back, so an inelastic rope gained
energy. After the positions, the velocities of the projected states get the smallest
change in the mass metric that stops them approaching the limits closed at the projected
positions ``x_p`` (gap below :data:`CLOSED`; ``J`` their rows at ``x_p``):

    v+ = v + Mhat^-1 J^T lambda,
    lambda = argmin_{lambda >= 0} 0.5 lambda^T A lambda + lambda^T J v,   A = J Mhat^-1 J^T,

an inelastic, frictionless impulse (the same QP as an iteration above, with ``J v`` for
the gaps): ``J v+ >= 0`` on every closed limit, and the kinetic energy never rises.

Given the step ``dt`` (``System`` passes it), the open limits that the velocities would
cross within the next step join too, with ``J v+ >= -gap / dt``: they may close within the
step, not be crossed. A limit that the projection released (a neighbour's correction moved
it to a small positive gap) was otherwise left approaching, the next step crossed it and
the projection's correction raised the energy (Rope at ``dt = 0.02``: up to 0.887 J within
1 s). The correction can make the velocities cross further open limits (rows share
points): those join and the problem is solved again from ``v``, at most
:data:`VELOCITY_ROUNDS` times. The kinetic energy still cannot rise (``lambda^T gap >= 0``).
Only inelastic limits are foreseen (``System``: ``cor == 0``, the ropes'): a bouncing one
would lose the approach its bounce needs.

Constraint rates. The projection keeps the equality constraints' values, ``Phi(x) =
Phi(x_pred)``, but moving the positions turns their Jacobian: velocities tangent to the
constraints at ``x_pred`` are not at ``x``, and the next steps' integration moved the
bodies off them (``python experiments/projection_energy.py --tasks Gyro CP3``, ``cor`` 1,
``mu`` 0, before this: the gyroscope's constraints drifted by 1.44, against 1.5e-3
without the projection, and it lost up to 57 % of its energy; the chain pendulum's drifted
by 0.31, and its energy changed by up to 11 times its initial value). With equality constraints,
:func:`project_state` (and ``System`` with the velocities' projection off) first changes
the projected states' velocities the least in the mass metric so that the constraints'
rates at ``x`` are those at ``x_pred`` (:func:`keep_constraint_rates`); the limits'
correction above, in ``Mhat^-1``, keeps them.

Restitution. Given the candidates' coefficients (``System`` passes ``cor`` where one is
positive), a closed limit with restitution joins the problem only where it approaches
at the projected positions, and after the correction above (the compression phase, its
impulse ``lambda_c`` the canonical minimiser) a restitution phase, the frictionless
second QP of the contact model (CM), gives each closed row an impulse of at least ``e_k
lambda_c,k`` with the same targets. A contact that only the position projection closed
thus bounces instead of stopping: elastic billiards (BP5 with ``cor`` 1 and the
projection on) lost up to 68 % of a trajectory's energy in one event, and now keep it
to rounding (``python experiments/projection_energy.py``). A closed limit with
restitution that does not approach is left to the next step's impulse: held by the
compression, it took its share of a neighbour's correction inelastically, which in the
billiards lost energy again. A bounce can make such a neighbour approach (a ball in a
corner, hit by another); the next step's impulse resolves it. Where a projection with
restitution lifts a system (raises its potential energy), ``System`` slows the motion
along the lift so that the kinetic energy pays for it (``system._lift_within_energy``):
without that, a bounce kept its speed and an elastic ball on the ground, or a rope given
restitution, gained energy (docs/config.md, "rope", "Restitution").

With point masses (the ropes) each iteration needs only ``J_s = J M^-1/2``: ``A = J_s
J_s^T`` and the step ``M^-1/2 J_s^T lambda``. On the CPU with Warp, where the dense
``(n, R, P dim)`` rows would be large (:data:`~diffcontact.geometry.sparse_gram.
MIN_DENSE_SIZE`: long ropes, whose dense rows' fill and product were the projection's
largest costs), both come from the rows' few entries
(:func:`~diffcontact.geometry.sparse_gram.sparse_gram`, and a scatter for ``J_s^T
lambda``); elsewhere (small problems, CUDA, or the torch backend) from the dense rows.
The same positions and gradients to rounding.

Choosing the states to project, each iteration's rows and the early stop reads the
device (a synchronisation on CUDA, which a CUDA graph cannot capture). With
:class:`ReadFree` nothing is read: every state and every iteration take part, the
correction of an iteration the early stop would have skipped is not applied, and each
problem is padded to a fixed number of rows (a state that selects more sets a flag on
the device, and the caller computes again). Same positions to rounding, more
arithmetic.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from diffcontact.contact.cone_qp import SolverSettings, solve_cone_qp
from diffcontact.fastops import spd_solve
from diffcontact.geometry.base import (
    GeometryBase,
    SparseJacobian,
    assemble_jacobian,
    at_points,
    jacobian_matvec,
    jacobian_rmatvec,
    take_rows,
)
from diffcontact.geometry.sparse_gram import MIN_DENSE_SIZE, sparse_gram, sparse_gram_available
from diffcontact.mechanics import EqualityConstraints, Mhat_inv

__all__ = [
    "ReadFree",
    "keep_constraint_rates",
    "project_positions",
    "project_state",
    "warn_unconverged",
]

STEPS = (1.0, 0.5, 0.25, 0.125, 0.0)
"""Step lengths tried along each Gauss-Newton direction (the one with the least violation wins)."""
DAMPING = 1.0
"""The damping ``rho`` a state's metric gets at its first backtracked step (module
docstring, "Damping"), in units of its mean point mass."""
DAMPING_FACTOR = 10.0
"""A backtracked step multiplies a state's damping by this, a full step divides it."""
UNEVEN = 2.0
"""Point masses are damped only where the largest is more than this times the smallest."""
MARGIN = 0.25
"""A limit enters an iteration's problem once its distance (mass metric) is below
``MARGIN`` times the state's largest violation: the limits a correction can reach
(0 converged too slowly on whipping ropes, 0.5 and more doubled the problem size)."""
VELOCITY_ROUNDS = 4
"""With a step ``dt``, the velocities' problems solved at most: each adds the open limits
that the previous one's velocities cross within ``dt``."""
CLOSED = 1e-6
"""A limit whose gap is below ``CLOSED`` is closed (:func:`closed_below`):
:func:`project_state` projects the velocities onto it at the projected positions, and
with the velocity projection on, a step's impulse treats it as active (``System``). A
limit the projection corrected ends within its tolerance of gap 0; one it released (a
neighbour's correction moved it away) ends farther out."""


def closed_below(dtype: torch.dtype) -> float:
    """The gap below which a limit is closed: :data:`CLOSED`, the same in float32 and
    float64 (a step in either then treats the same limits), or eight rounding units of a
    coarser ``dtype``."""
    return max(CLOSED, 8 * torch.finfo(dtype).eps)


@dataclass
class ReadFree:
    """How :func:`project_positions` runs without reading the device: the step of a
    CUDA graph, or of a step-by-step rollout on CUDA, where each read stalls the queue.

    Every state takes part (those without a violated limit get no rows and keep their
    positions), every iteration runs (a state's correction is applied until the state
    has converged, as the early stop would have it, and is zero after), and each
    state's problem is padded to ``rows`` rows, so that no shape depends on the data.

    Attributes:
        rows: the rows of each state's problem. A state that selects more in an
            iteration the early stop would have run sets :attr:`overflowed`; its
            result is then not the projection's, and the caller must compute it again.
        needed: ``()`` int64 on the device, updated in place: the most rows any state
            not yet converged selected (read once by the caller, after the rollout).
        diagonal: whether ``M^-1`` is diagonal (point masses), known from the system's
            structure instead of read from the matrix.
        two_sided: whether the geometry has two-sided limits (finite ``gap_widths``).
    """

    rows: int
    needed: Tensor
    diagonal: bool
    two_sided: bool

    @property
    def overflowed(self) -> Tensor:
        """``()`` bool on the device: a state needed more than :attr:`rows` rows."""
        return self.needed > self.rows


@functools.lru_cache(maxsize=16)
def _step_lengths(dtype: torch.dtype, device: torch.device) -> Tensor:
    """:data:`STEPS` as a tensor, made once per dtype and device: a copy from the host in
    every call would be a transfer inside a captured CUDA step, which a graph cannot
    replay (the warm-up step before the capture fills this cache)."""
    with torch.inference_mode(False):
        return torch.tensor(STEPS, dtype=dtype, device=device)


def _gather_rows(mask_rows: Tensor, R: int | None = None) -> tuple[Tensor, Tensor]:
    """Selected rows first, in row order: ``idx, mask: (n, R)`` (``R``: at least the
    largest number of selected rows of a state, if read already)."""
    if R is None:
        R = int(mask_rows.sum(-1).max())
    R = max(R, 1)
    order = torch.argsort((~mask_rows).to(torch.uint8), dim=-1, stable=True)
    idx = order[:, :R]
    return idx, mask_rows.gather(-1, idx)


def _gaps_and_rows(geometry: Any, x: Tensor) -> tuple[Tensor, SparseJacobian]:
    """Every candidate's gap ``(n, K)`` and sparse rows at ``x: (n, P, dim)``, points
    expanded to ``(n, K, m)``: from one evaluation where the geometry has
    ``gaps_and_rows_all`` (:meth:`GeometryBase.gaps_and_rows_all`)."""
    if hasattr(geometry, "gaps_and_rows_all"):
        gaps, jac = geometry.gaps_and_rows_all(x)
    elif hasattr(geometry, "jacobian_sparse_all"):
        gaps, jac = geometry.gaps(x), geometry.jacobian_sparse_all(x)
    else:  # a user geometry with the Geometry protocol only: jacobian_sparse on arange(K)
        gaps, jac = geometry.gaps(x), GeometryBase.jacobian_sparse_all(geometry, x)
    points = jac.points.expand(*jac.values.shape[:-4], *jac.points.shape[-2:])
    return gaps, SparseJacobian(points, jac.values)


def _metric_norms(
    geometry: Any,
    x: Tensor,
    M_inv: Tensor,
    rows: SparseJacobian | None = None,
    diagonal: bool = False,
) -> Tensor:
    """``(n, K)``: ``||J_k||_{M^-1}`` of every candidate's normal row at ``x: (n, P, dim)``
    (``rows``: those of :func:`_gaps_and_rows` at ``x`` if the caller has them; their
    values are detached here; ``diagonal``: ``M_inv`` is diagonal, point masses).

    From the sparse rows (``m`` entries of point ``p_a`` and value ``v_a``):
    ``J_k M^-1 J_k^T = sum_a sum_b M^-1[p_a, p_b] (v_a . v_b)`` (``M^-1 = kron(M_inv,
    I_dim)``; repeated points add up correctly). A dense ``(n, K, P * dim)`` Jacobian of
    all candidates would take 245 MB for 128 ropes of 200 points.
    """
    n = x.shape[0]
    jac = _gaps_and_rows(geometry, x)[1] if rows is None else rows
    v = jac.values[..., 0, :, :].detach()  # (n, K, m, dim)
    gram = v @ v.transpose(-1, -2)  # (n, K, m, m): v_a . v_b
    pa, pb = jac.points.unsqueeze(-1), jac.points.unsqueeze(-2)  # (n, K, m, 1), (n, K, 1, m)
    if diagonal:  # M^-1[p_a, p_b] = w[p_a] where p_a == p_b, else 0: no (P, P) lookups
        w = M_inv.diagonal(dim1=-2, dim2=-1).to(v)  # (P,) or (n, P)
        w_a = at_points(w, jac.points.expand(n, *jac.points.shape[-2:]))
        w = torch.where(pa == pb, w_a.unsqueeze(-1), 0.0)
    elif M_inv.dim() == 2:
        w = M_inv.to(v)[pa, pb]
    else:
        w = M_inv.to(v)[torch.arange(n, device=x.device).view(n, 1, 1, 1), pa, pb]
    return (gram * w).sum((-1, -2)).clamp_min(0).sqrt()


def _damped(masses: Tensor, damping: Tensor, diagonal: bool) -> Tensor:
    """The metric of a damped iteration, ``(M + rho mbar I)^-1`` per state (``mbar`` the mean
    of ``M``'s diagonal, ``rho = damping: (n,)``), from the masses' metric ``masses``:
    ``M_inv``, ``(P, P)`` or ``(n, P, P)``, or with ``diagonal`` its diagonal, ``(P,)`` or
    ``(n, P)``. Returns ``(n, P, P)``, or ``(n, P)`` with ``diagonal``; where ``rho = 0``,
    ``masses`` itself."""
    n = damping.shape[0]
    rho = damping.to(masses)
    if diagonal:
        w = masses.expand(n, masses.shape[-1])  # (n, P)
        mbar = w.reciprocal().mean(-1, keepdim=True)
        return w / (1 + rho[:, None] * mbar * w)  # the same w where rho = 0
    Mi = masses.expand(n, *masses.shape[-2:])
    # inv_ex: no error check, which would read the device (a CUDA graph captures this);
    # M^-1 is positive definite
    M = torch.linalg.inv_ex(Mi)[0]
    mbar = M.diagonal(dim1=-2, dim2=-1).mean(-1)
    eye = torch.eye(M.shape[-1], dtype=M.dtype, device=M.device)
    damped = torch.linalg.inv_ex(M + (rho * mbar)[:, None, None] * eye)[0]
    return torch.where(rho[:, None, None] > 0, damped, Mi)


def _minv_rows(rows: Tensor, metric: Tensor, P: int, dim: int, diagonal: bool) -> Tensor:
    """``rows M^-1`` for ``rows: (n, R, P * dim)``, ``M^-1 = kron(M_inv, I_dim)`` (symmetric;
    ``metric``: ``M_inv``, ``(P, P)`` or ``(n, P, P)``, or with ``diagonal`` (point masses,
    no dense product) its diagonal, ``(P,)`` or ``(n, P)``)."""
    r = rows.reshape(*rows.shape[:-1], P, dim)
    if diagonal:
        w = metric
        out = r * (w[:, None, :, None] if w.dim() == 2 else w[:, None])
    else:
        Mi = metric if metric.dim() == 3 else metric.unsqueeze(0)
        out = torch.einsum("nrpd,nqp->nrqd", r, Mi.expand(rows.shape[0], P, P))
    return out.reshape(rows.shape)


def keep_constraint_rates(
    x_pred: Tensor,
    x: Tensor,
    v: Tensor,
    constraints: EqualityConstraints,
    M_inv: Tensor,
    *,
    diagonal: bool = False,
) -> Tensor:
    """The velocities ``v`` changed the least in the mass metric so that the equality
    constraints' rates at the projected positions ``x`` are those at ``x_pred``:
    ``J_E(x) v+ = J_E(x_pred) v`` (module docstring, "Constraint rates").

    ``v+ = v - M^-1 J_E^T (J_E M^-1 J_E^T)^-1 (J_E(x) - J_E(x_pred)) v`` with ``J_E =
    J_E(x)``: a projection in the mass metric, so the kinetic energy does not rise; a
    state with ``x`` equal to ``x_pred`` keeps ``v`` exactly.

    Args:
        x_pred: ``(n, P, dim)`` positions before the projection.
        x: ``(n, P, dim)`` the projected positions.
        v: ``(n, P, dim)`` velocities.
        constraints: the equality constraints ``Phi`` (at least one equation).
        M_inv: ``(P, P)`` or ``(n, P, P)`` inverse mass matrix over points, or with
            ``diagonal`` its diagonal, ``(P,)`` or ``(n, P)``.
        diagonal: ``M_inv`` is the diagonal (point masses).

    Returns:
        ``(n, P, dim)``.
    """
    n, P, dim = v.shape
    flat = v.reshape(n, P * dim, 1)
    J_E = constraints.jacobian(x)  # (n, E, D)
    r = J_E @ flat - constraints.jacobian(x_pred) @ flat  # (n, E, 1)
    B = _minv_rows(J_E, M_inv, P, dim, diagonal).transpose(-1, -2)  # (n, D, E): M^-1 J_E^T
    return v - (B @ spd_solve(J_E @ B, r)).reshape(n, P, dim)


def _smallest_correction(
    rows: SparseJacobian,
    mask: Tensor,
    rhs: Tensor,
    metric: Tensor,
    *,
    diagonal: bool,
    sparse: bool,
    settings: SolverSettings,
    Mh: Tensor | None = None,
    base: Tensor | None = None,
    lower: Tensor | None = None,
    impulse: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """The smallest correction in a metric (the masses', or a damped iteration's) that
    meets ``R`` linear rows: ``W J^T lambda (+ base)``, ``lambda = argmin_{lambda >= lower}
    0.5 lambda^T A lambda + lambda^T (rhs + J base)``, ``A = J W J^T``, ``W`` = ``Mh``
    (``Mhat^-1``, with equality constraints) or ``kron(metric, I_dim)``: the frictionless
    cone QP of one projection iteration (``rhs`` the gaps) or of the velocity projection
    (``rhs = J v``).

    Args:
        rows: the rows' sparse entries, ``points (n, R, m)`` and ``values (n, R, 1, m,
            dim)``, signed and zero on padded rows.
        mask: ``(n, R)`` bool, the real rows.
        rhs: ``(n, R)``.
        metric: ``W``'s inverse mass matrix over points, ``(P, P)`` or ``(n, P, P)``, or
            with ``diagonal`` its diagonal, ``(P,)`` or ``(n, P)``.
        diagonal: point masses (``metric`` is the diagonal).
        sparse: ``A`` from the rows' entries where large (point masses, Warp on the CPU).
        settings: the cone QP's settings.
        Mh: ``(n, D, D)`` ``Mhat^-1`` with equality constraints, else ``None``.
        base: ``(n, D)`` a fixed part of the correction (the equality constraints' drift).
        lower: ``(n, R)`` lower bounds of ``lambda`` (Poisson's, in a restitution phase),
            else zero.
        impulse: also return ``lambda``.

    Returns:
        ``(n, P, dim)``, and with ``impulse`` ``lambda: (n, R)``.
    """
    n, R = mask.shape
    P, dim = metric.shape[-1], rows.values.shape[-1]
    D = P * dim
    values, root = rows.values, None
    if diagonal and Mh is None:
        # point masses: the rows scaled by sqrt(M^-1), J_s = J M^-1/2, so that A = J_s J_s^T
        # and the correction M^-1 J^T lambda = M^-1/2 J_s^T lambda need only J_s, not J and
        # J M^-1 (scaled on the few sparse entries, not on dense rows)
        root = metric.sqrt()  # (P,) or (n, P)
        values = values * at_points(root, rows.points)[:, :, None, :, None]
    if root is not None and sparse and n * R * D >= MIN_DENSE_SIZE:
        # A = J_s J_s^T from the rows' few entries (sparse_gram): no dense rows
        J = JM = None
        A = sparse_gram(rows.points, values[:, :, 0])
    else:
        J = assemble_jacobian(SparseJacobian(rows.points, values), P).reshape(n, R, D)
        if root is not None:
            JM = J  # (J_s)
        elif Mh is not None:
            JM = J @ Mh  # (n, R, D)
        else:
            JM = _minv_rows(J, metric, P, dim, diagonal)
        A = JM @ J.transpose(-1, -2)
        A = 0.5 * (A + A.transpose(-1, -2))
    if base is not None:
        rhs = rhs + (J @ base.unsqueeze(-1)).squeeze(-1)
    rhs = torch.where(mask, rhs, torch.zeros_like(rhs))
    lam, status = solve_cone_qp(
        A, rhs, torch.zeros_like(rhs), 1, lower, mask, settings=settings, return_status=True
    )
    # a problem the solver did not finish still gives a direction (the projection's line
    # search keeps only steps that reduce the violation); an unbounded one does not
    usable = ~status.unbounded & torch.isfinite(lam).all(-1)
    lam = torch.where(usable.unsqueeze(-1), lam, torch.zeros_like(lam))
    if JM is None:  # J_s^T lambda from the entries
        dx = jacobian_rmatvec(SparseJacobian(rows.points, values), lam.unsqueeze(-1), P)
    else:
        dx = (JM.transpose(-1, -2) @ lam.unsqueeze(-1)).squeeze(-1)
        dx = (dx if base is None else dx + base).reshape(n, P, dim)
    dx = dx if root is None else dx * root.unsqueeze(-1)
    return (dx, lam) if impulse else dx


def _check_inputs(
    x: Tensor,
    v: Tensor | None,
    geometry: Any,
    M_inv: Tensor,
    iterations: int,
    gaps: Tensor | None,
    tol: float | None,
    read_free: ReadFree | None,
) -> None:
    """The public functions' arguments, checked before any work: a ``ValueError`` naming
    the argument (``System`` calls :func:`_project` with its own, already checked). The
    values (finite positions and velocities, positive masses) are read from the device
    once; with ``read_free`` only shapes and dtypes are checked."""

    def shape(t: Tensor) -> tuple[int, ...]:
        return tuple(t.shape)

    if not isinstance(x, Tensor) or x.dim() != 3 or not x.is_floating_point():
        got = shape(x) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"x must be a floating-point tensor of shape (N, P, dim), got {got}")
    N, P, _ = x.shape
    if v is not None and (not isinstance(v, Tensor) or shape(v) != shape(x)):
        got = shape(v) if isinstance(v, Tensor) else type(v).__name__
        raise ValueError(f"v must have the shape of x, {shape(x)}, got {got}")
    if not isinstance(M_inv, Tensor) or shape(M_inv) not in ((P, P), (N, P, P)):
        got = shape(M_inv) if isinstance(M_inv, Tensor) else type(M_inv).__name__
        raise ValueError(f"M_inv must have shape ({P}, {P}) or ({N}, {P}, {P}), got {got}")
    for name, t in (("v", v), ("M_inv", M_inv)):
        if t is not None and t.dtype != x.dtype:
            raise ValueError(f"{name} has dtype {t.dtype} but x has {x.dtype}: give them one dtype")
    K = getattr(geometry, "n_candidates", None)
    if gaps is not None and (not isinstance(gaps, Tensor) or shape(gaps) != (N, K)):
        got = shape(gaps) if isinstance(gaps, Tensor) else type(gaps).__name__
        raise ValueError(f"gaps must have shape ({N}, {K}), one per state and candidate, got {got}")
    if isinstance(iterations, bool) or not isinstance(iterations, int) or iterations < 0:
        raise ValueError(f"iterations must be an integer >= 0, got {iterations!r}")
    if tol is not None and not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol >= 0):
        raise ValueError(f"tol must be a number >= 0 or None, got {tol!r}")
    if read_free is not None or x.shape[0] == 0:
        return
    checks = [torch.isfinite(x).all(), M_inv.diagonal(dim1=-2, dim2=-1).gt(0).all()]
    checks.append(torch.isfinite(v).all() if v is not None else checks[0])
    finite_x, positive, finite_v = torch.stack(checks).tolist()  # one read
    if not finite_x:
        raise ValueError("x contains NaN or infinite values")
    if not finite_v:
        raise ValueError("v contains NaN or infinite values")
    if not positive:
        raise ValueError("M_inv must be an inverse mass matrix: its diagonal must be positive")


def warn_unconverged(geometry: Any, x: Tensor, iterations: int, tol: float | None = None) -> None:
    """Warn (once per call) where projected positions ``x: (N, P, dim)`` still violate a
    candidate by more than ``tol`` (the projection's default per dtype): the iterations
    ran out before the state reached the admissible set (a state far from it, such as a
    rope stretched to twice its limits). One read of the device."""
    if x.shape[0] == 0:
        return
    if tol is None:
        tol = 1e-10 if x.dtype == torch.float64 else 1e-5
    with torch.no_grad():
        worst = geometry.gaps(x.detach()).amin(-1)  # (N,)
        bad = worst < -tol
        count, first, gap = torch.stack(
            [bad.sum().to(worst), bad.to(torch.uint8).argmax().to(worst), worst.min()]
        ).tolist()
    if count:
        warnings.warn(
            f"the position projection did not converge within {iterations} iterations for "
            f"{int(count)} of {x.shape[0]} states (the first: state {int(first)}; the worst "
            f"gap left: {gap:.3g}): more iterations, or states nearer the admissible set "
            "(the projection corrects the small violations of a step)",
            RuntimeWarning,
            stacklevel=3,
        )


def project_positions(
    x: Tensor,
    geometry: Any,
    M_inv: Tensor,
    iterations: int,
    *,
    constraints: EqualityConstraints | None = None,
    gaps: Tensor | None = None,
    settings: SolverSettings | None = None,
    tol: float | None = None,
    read_free: ReadFree | None = None,
) -> Tensor:
    """Project positions onto the admissible set of their violated contacts (module docstring).

    Args:
        x: ``(N, P, dim)`` positions after a step (``x_pred``).
        geometry: the contact geometry (``gaps``, ``jacobian``; row 0 of each
            candidate's ``J_C`` block is the gap's gradient).
        M_inv: ``(P, P)`` or ``(N, P, P)`` inverse mass matrix over points (the metric).
        iterations: the most Gauss-Newton iterations (0 returns ``x``).
        constraints: the equality constraints ``Phi``, or ``None``.
        gaps: ``(N, K)`` the gaps at ``x`` if already computed (saves one evaluation).
        settings: settings of the cone QP.
        tol: the iterations stop early once no gap is below ``-tol`` (default
            ``1e-10`` in float64, ``1e-5`` in lower precision).
        read_free: run without reading the device (:class:`ReadFree`: every state,
            every iteration, padded rows); ``None`` (default): the states to project,
            the rows and the early stop are read from the device (a few reads per
            iteration, the least work).

    Returns:
        ``(N, P, dim)``: ``x`` with the states that violated a candidate projected;
        the others are returned unchanged (the same values, no extra graph).

    Raises:
        ValueError: an argument of the wrong shape or dtype, NaN positions, or an
            ``M_inv`` without a positive diagonal (read-free: shapes and dtypes only).

    Warns:
        RuntimeWarning: a state still violates a candidate after ``iterations``
            (:func:`warn_unconverged`; not read-free).
    """
    _check_inputs(x, None, geometry, M_inv, iterations, gaps, tol, read_free)
    args = (constraints, gaps, settings, tol, read_free)
    out = _project(x, None, geometry, M_inv, iterations, *args)[0]
    if read_free is None and iterations > 0:
        warn_unconverged(geometry, out, iterations, tol)
    return out


def project_state(
    x: Tensor,
    v: Tensor,
    geometry: Any,
    M_inv: Tensor,
    iterations: int,
    *,
    constraints: EqualityConstraints | None = None,
    gaps: Tensor | None = None,
    settings: SolverSettings | None = None,
    tol: float | None = None,
    read_free: ReadFree | None = None,
    dt: float | None = None,
    foresee: Tensor | None = None,
    restitution: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """:func:`project_positions`, then the velocities of the projected states onto the
    limits closed at their new positions (module docstring, "Velocities").

    Args:
        x: ``(N, P, dim)`` positions after a step.
        v: ``(N, P, dim)`` velocities after the step's impulse.
        geometry, M_inv, iterations, constraints, gaps, settings, tol, read_free: as
            :func:`project_positions` (``read_free`` pads the velocities' problem to the
            same rows, and records the rows it needed in ``read_free.needed`` too).
        dt: the step (a positive float): also project onto the limits open at the new
            positions that the velocities would cross within ``dt``, to close at most
            (``J v+ >= -gap / dt``; module docstring, "Velocities"). ``None``: only the
            limits closed there (``J v+ >= 0``).
        foresee: ``(K,)`` or ``(N, K)`` bool, the candidates whose crossing within ``dt``
            is foreseen (``System``: the inelastic ones, ``cor == 0``); default all.
        restitution: ``(K,)`` or ``(N, K)`` Poisson's coefficients of restitution in [0, 1],
            or one number for every candidate (``System``: ``cor``, where one is
            positive): a closed limit that the correction stopped then gets a
            restitution impulse of at least its coefficient times that one (module
            docstring, "Restitution"). ``None`` (default): inelastic.

    Returns:
        ``x, v``: ``(N, P, dim)`` each; the states without a violated candidate unchanged.

    Raises:
        ValueError: as :func:`project_positions` (and NaN velocities), and a ``dt``,
            ``restitution`` or ``foresee`` of the wrong kind.

    Warns:
        RuntimeWarning: as :func:`project_positions`.
    """
    if dt is not None and not (math.isfinite(dt) and dt > 0):
        raise ValueError(f"dt must be a positive number or None, got {dt!r}")
    _check_inputs(x, v, geometry, M_inv, iterations, gaps, tol, read_free)
    if restitution is not None and not isinstance(restitution, Tensor):
        if not isinstance(restitution, (int, float)):
            kind = type(restitution).__name__
            raise ValueError(f"restitution must be a number or a tensor, got {kind}")
        restitution = torch.full((geometry.n_candidates,), float(restitution), dtype=x.dtype)
        restitution = restitution.to(x.device)
    if foresee is not None and (not isinstance(foresee, Tensor) or foresee.dtype != torch.bool):
        what = foresee.dtype if isinstance(foresee, Tensor) else type(foresee).__name__
        raise ValueError(f"foresee must be a bool tensor, got {what}")
    x, v1 = _project(
        x, v, geometry, M_inv, iterations, constraints, gaps, settings, tol, read_free, dt,
        foresee, restitution,
    )  # fmt: skip
    if read_free is None and iterations > 0:
        warn_unconverged(geometry, x, iterations, tol)
    return x, v if v1 is None else v1


def _project(
    x: Tensor,
    v: Tensor | None,
    geometry: Any,
    M_inv: Tensor,
    iterations: int,
    constraints: EqualityConstraints | None,
    gaps: Tensor | None,
    settings: SolverSettings | None,
    tol: float | None,
    read_free: ReadFree | None,
    dt: float | None = None,
    foresee: Tensor | None = None,
    restitution: Tensor | None = None,
) -> tuple[Tensor, Tensor | None]:
    """:func:`project_state` (``v``: ``None`` projects the positions only, and returns
    ``None`` for the velocities)."""
    if iterations <= 0:
        return x, v
    P, dim = x.shape[-2:]
    if tol is None:
        tol = 1e-10 if x.dtype == torch.float64 else 1e-5
    widths = geometry.gap_widths() if hasattr(geometry, "gap_widths") else None
    with torch.no_grad():
        g0 = geometry.gaps(x.detach()) if gaps is None else gaps.detach()
        violated = g0 < 0
        has = violated.any(-1)  # (N,)
        N, K = g0.shape
        for name, t in (("foresee", foresee), ("restitution", restitution)):
            if t is not None and tuple(t.shape) not in ((K,), (N, K)):
                shape = tuple(t.shape)
                raise ValueError(f"{name} must have shape ({K},) or ({N}, {K}), got {shape}")
        if read_free is None:
            # one read of the device (a synchronisation on CUDA) for the states to project
            # and two properties of the problem: point masses (a diagonal M^-1: no dense
            # products; all states' checked, a superset of the projected ones) and
            # two-sided limits (the rope's)
            diag = torch.diag_embed(M_inv.diagonal(dim1=-2, dim2=-1))
            flags = [has.sum(), (M_inv == diag).all()]
            flags.append(torch.isfinite(widths).any() if widths is not None else has.new_zeros(()))
            if restitution is not None:  # (read-free: the caller's, System's checked cor)
                flags.append(((restitution >= 0) & (restitution <= 1)).all())
            flags = torch.stack([f.to(has.device, torch.int64) for f in flags])
            n, diagonal, two_sided, *valid = flags.tolist()
            if valid and not valid[0]:
                raise ValueError("restitution must lie in [0, 1] (a number per candidate)")
        else:
            n, diagonal, two_sided = x.shape[0], read_free.diagonal, read_free.two_sided
    if n == 0:
        return x, v
    if read_free is None:
        b = torch.argsort((~has).to(torch.uint8), stable=True)[:n]  # (n,) states to project
        x_pred = x[b]  # (n, P, dim)
        Minv_b = M_inv if M_inv.dim() == 2 else M_inv[b]
    else:  # every state (those without a violation select no rows: no correction)
        x_pred, Minv_b = x, M_inv

    if constraints is not None and constraints.num_equations == 0:
        constraints = None
    phi0 = None if constraints is None else constraints.phi(x_pred)
    width = widths.to(dtype=x.dtype, device=x.device) if two_sided else None  # (K,)
    # every candidate's gap and rows at x_pred: the metric below and the first iteration's
    gaps_raw, rows_i = _gaps_and_rows(geometry, x_pred)
    with torch.no_grad():
        # distances are compared in the mass metric: gap_k / ||J_k||_{M^-1} is the distance
        # (in sqrt(mass) * length) from the linearised limit, whatever the gap's unit
        scale = _metric_norms(geometry, x_pred, Minv_b, rows_i, bool(diagonal)).clamp_min(1e-300)
        scale_rows = torch.cat([scale, scale], -1) if two_sided else scale
        steps = _step_lengths(x.dtype, x.device)
        mask_rows = torch.zeros_like(scale_rows, dtype=torch.bool)

    def row_gaps(g: Tensor, total: Tensor | float | None = None) -> Tensor:
        """``(..., K) -> (..., R_all)``: each side of each limit, the second ``total - g``
        (default ``width``; 0 for the gaps' rates)."""
        if width is None:
            return g
        return torch.cat([g, (width if total is None else total) - g], -1)

    def signed_rows(
        rows: SparseJacobian, selected: Tensor, R: int
    ) -> tuple[SparseJacobian, Tensor, Tensor]:
        """The ``selected: (n, R_all)`` rows of ``rows`` (every candidate's), at most ``R``
        a state: their entries signed (the other side of a two-sided limit) and zero where
        padded, and the ``(n, R)`` row indices and mask (applied to the few sparse entries,
        before any dense ``(n, R, P * dim)`` rows are assembled)."""
        idx, mask = _gather_rows(selected, R)
        taken = take_rows(rows, idx % K)
        values = taken.values[:, :, :1]  # (n, R, 1, m, dim): the normal rows
        sign = torch.where(idx < K, 1.0, -1.0).to(values)[:, :, None, None, None]
        keep = mask[:, :, None, None, None]
        values = torch.where(keep, sign * values, torch.zeros_like(values))
        return SparseJacobian(taken.points, values), idx, mask

    # the step M^-1 J^T lambda is the same for every minimiser lambda (two differ by a null
    # vector g of A = J M^-1 J^T, and g^T A g = 0 makes M^-1 J^T g = 0): any will do, which
    # spares the fused solver's interior point at the many kinks of these problems (rows
    # just corrected sit at gap 0 with lambda 0)
    any_minimiser = replace(settings or SolverSettings(), canonical=False)
    # point masses on the CPU with Warp: A = J_s J_s^T and J_s^T lambda from the rows' entries
    sparse = bool(diagonal) and phi0 is None and sparse_gram_available(settings, x.dtype, x.device)

    # the masses' metric: M_inv, or its diagonal for point masses
    masses = Minv_b.diagonal(dim1=-2, dim2=-1) if diagonal else Minv_b
    with torch.no_grad():  # (n,) the states damping can help: not equal point masses (their
        # damped metric is the masses' times a number, the same steps), nor nearly equal
        # ones (a learned rope's: the steps barely change, and each damped iteration costs)
        if diagonal:
            uneven = masses.amax(-1) > UNEVEN * masses.amin(-1)
        else:
            uneven = x.new_ones((), dtype=torch.bool)
        uneven = uneven.expand(x_pred.shape[0])

    def correction(
        rows: SparseJacobian,
        mask: Tensor,
        rhs: Tensor,
        x_at: Tensor,
        base: bool,
        metric: Tensor = masses,
        **options: Any,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """:func:`_smallest_correction` at positions ``x_at`` in ``metric`` (``base``: with
        the equality constraints' drift back to ``phi0``; ``options``: its ``settings``
        (default: any minimiser), ``lower`` and ``impulse``)."""
        Mh = drift = None
        if phi0 is not None:
            # Mhat^-1 keeps the correction tangent to Phi; dx_E = -M^-1 J_E^T (J_E M^-1
            # J_E^T)^-1 r takes Phi back to its value at x_pred
            J_E = constraints.jacobian(x_at)  # (n, E, D)
            Mh = Mhat_inv(torch.diag_embed(metric) if diagonal else metric, J_E)
            if base:
                r = (constraints.phi(x_at) - phi0).unsqueeze(-1)  # (n, E, 1)
                B = _minv_rows(J_E, metric, P, dim, bool(diagonal)).transpose(-1, -2)
                drift = -(B @ spd_solve(J_E @ B, r)).squeeze(-1)  # (n, D); SPD: no read
        options = {"settings": any_minimiser, **options}
        return _smallest_correction(
            rows, mask, rhs, metric, diagonal=bool(diagonal), sparse=sparse, Mh=Mh,
            base=drift, **options,
        )  # fmt: skip

    x_i = x_pred
    # (n,) each state's damping rho of the metric (module docstring, "Damping"): zero until
    # its line search first backtracks; whether an iteration computes the damped metric
    # (reading: once a state has damping; read-free: always, the same steps)
    damping = x.new_zeros(x_pred.shape[0])
    damp = read_free is not None
    dist = None  # after the first iteration: the line search's distances at x_i
    going = None  # after the first iteration: (n,) bool, the states not converged yet
    for it in range(iterations):
        with torch.no_grad():
            if dist is None:
                dist = row_gaps(gaps_raw.detach()) / scale_rows
            # the violated rows, and those a step of about the largest violation can reach
            worst = (-dist).amax(-1, keepdim=True).clamp_min(0)
            rows = mask_rows | (dist < 0) | (dist < MARGIN * worst)
            R = rows.sum(-1).max()
            if it > 0:  # the states with a limit left, and the rows' count
                left = (dist * scale_rows < -tol).any(-1)  # (n,)
                if phi0 is not None:  # or the equality constraints not back where they were
                    drift = (constraints.phi(x_i.detach()) - phi0.detach()).abs() > tol
                    left = left | drift.any(-1)
                # a state stops at its own convergence, whatever the others in its batch
                going = left if going is None else going & left
                R = torch.where(going, rows.sum(-1), 0).max()
                if read_free is None:  # one read
                    damped = (damping > 0).any().to(R)
                    left, R, damp = torch.stack([going.any().to(R), R, damped]).tolist()
                    if not left:
                        break  # converged (the line search's gaps said so: no evaluation more)
            if read_free is not None:  # the padded rows; the count they had to hold
                read_free.needed.copy_(torch.maximum(read_free.needed, R))
                R = min(read_free.rows, rows.shape[-1])
            mask_rows = rows
        if it > 0:
            gaps_raw, rows_i = _gaps_and_rows(geometry, x_i)  # with the graph
        taken, idx, mask = signed_rows(rows_i, mask_rows, int(R))
        gap = row_gaps(gaps_raw).gather(-1, idx)  # (n, R)
        metric = _damped(masses, damping, bool(diagonal)) if damp else masses
        dx = correction(taken, mask, gap, x_i, base=True, metric=metric)
        with torch.no_grad():  # backtracking: the step length with the least violation
            trial = x_i.detach() + steps[:, None, None, None] * dx.detach()  # (S, n, P, dim)
            trial_dist = row_gaps(geometry.gaps(trial)) / scale_rows  # (S, n, R_all)
            # the largest violation, max(0, -min dist): one pass over the rows, not three
            merit = trial_dist.amin(-1).neg().clamp_min(0)  # (S, n)
            choice = merit.argmin(0)  # (n,)
            best = steps[choice]
            # a state whose line search backtracked raises its damping, one that took the
            # full step lowers it
            backtracked = (choice > 0) & uneven
            raised = torch.clamp_min(damping * DAMPING_FACTOR, DAMPING)
            damping = torch.where(backtracked, raised, damping / DAMPING_FACTOR)
            # limits that a trial step crossed join the next iteration's problem
            mask_rows = mask_rows | (trial_dist.amin(0) < 0)
            # the distances at the chosen step: the next iteration's convergence test
            dist = trial_dist.gather(0, choice.view(1, n, 1).expand(1, *trial_dist.shape[1:]))[0]
        x_next = x_i + best[:, None, None] * dx
        x_i = x_next if going is None else torch.where(going[:, None, None], x_next, x_i)

    v_i = None
    if v is not None:  # the velocities onto the limits closed at the projected positions
        # (and, given dt, the open ones they would cross within it)
        v_b = v if read_free is not None else v[b]
        if phi0 is not None:  # the equality constraints' rates at x_i back to theirs at x_pred
            v_b = keep_constraint_rates(
                x_pred, x_i, v_b, constraints, masses, diagonal=bool(diagonal)
            )
        gaps_raw, rows_i = _gaps_and_rows(geometry, x_i)

        def rates(vel: Tensor) -> Tensor:
            """``(n, R_all)``: the rows' gap rates ``J vel`` at the projected positions."""
            return row_gaps(jacobian_matvec(rows_i, vel.detach())[..., 0], 0.0)

        with torch.no_grad():
            gap_rows = row_gaps(gaps_raw.detach())  # (n, R_all)
            closed = gap_rows < closed_below(x.dtype)

            def per_row(t: Tensor) -> Tensor:
                """A candidate's ``(K,)`` or ``(N, K)`` -> ``(1 or n, R_all)``, its rows'."""
                t = t.to(closed.device)
                if t.dim() == 1:
                    t = t.unsqueeze(0)
                elif read_free is None:
                    t = t[b]
                return torch.cat([t, t], -1) if width is not None else t

            if foresee is not None:
                foresee = per_row(foresee)
            # the closed limits whose approach a correction stops: all inelastic ones, the
            # others where they approach at the projected positions
            stops = closed
            if restitution is not None:
                approaching = rates(v_b) < -tol
                stops = closed & ((per_row(restitution.detach()) == 0) | approaching)

        def selected_by(vel: Tensor) -> Tensor:
            """``(n, R_all)``: the closed rows (with restitution: those that approach), and
            the open ones that ``vel`` crosses within ``dt``."""
            rows = stops
            if dt is not None:
                crossed = gap_rows + dt * rates(vel) < -tol
                rows = rows | (crossed if foresee is None else crossed & foresee)
            return rows & has[:, None] if read_free is not None else rows

        v_i = v_b
        # Poisson's restitution needs the compression impulse itself (the canonical one)
        qp = {} if restitution is None else {"settings": settings or SolverSettings()}
        last = None  # the last problem solved: its rows, targets and impulse
        with torch.no_grad():
            selected = selected_by(v_b)
        # the corrected velocities can cross further open limits (the rows share points):
        # those join the problem, solved again from v, until none is added (at most
        # VELOCITY_ROUNDS solves; read-free: all of them)
        for round_ in range(VELOCITY_ROUNDS if dt is not None else 1):
            with torch.no_grad():
                more = None
                if round_ > 0:
                    new = selected_by(v_i) & ~selected
                    more = new.any()
                    selected = selected | new
                R = selected.sum(-1).max()
                if read_free is None:  # one read
                    if more is None:
                        R = int(R)
                    else:
                        more, R = torch.stack([more.to(R), R]).tolist()
                        if not more:
                            break
                else:
                    read_free.needed.copy_(torch.maximum(read_free.needed, R))
                    R = min(read_free.rows, selected.shape[-1])
            if R == 0:
                break
            taken, idx, mask = signed_rows(rows_i, selected, R)
            approach = jacobian_matvec(taken, v_b)[..., 0]  # (n, R): J v
            allowed = torch.zeros_like(approach)  # (n, R): the approach a row may keep
            if dt is not None:  # an open limit may close within the step, not be crossed
                gap = row_gaps(gaps_raw).gather(-1, idx)  # (n, R)
                open_ = gap.detach() >= closed_below(x.dtype)
                allowed = torch.where(open_, gap / dt, allowed)
            # the masses' metric
            dv, lam = correction(taken, mask, approach + allowed, x_i, False, impulse=True, **qp)
            v_i = v_b + dv
            last = (taken, idx, mask, allowed, lam)
        if restitution is not None and last is not None:
            e_rows = per_row(restitution).expand(closed.shape)  # (n, R_all)

            # the restitution phase: at least e times the compression impulse on the closed
            # rows (the open ones, foreseen, are inelastic), the compression's targets
            taken, idx, mask, allowed, lam = last
            e = e_rows.gather(-1, idx)  # (n, R)
            e = torch.where(mask & closed.gather(-1, idx), e, torch.zeros_like(e))
            approach = jacobian_matvec(taken, v_i)[..., 0] + allowed  # (n, R)
            v_i = v_i + correction(taken, mask, approach, x_i, False, lower=e * lam, **qp)
    if read_free is not None:
        keep = has[:, None, None]
        return torch.where(keep, x_i, x), None if v_i is None else torch.where(keep, v_i, v)
    return x.index_put((b,), x_i), None if v_i is None else v.index_put((b,), v_i)
