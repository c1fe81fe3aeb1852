"""The two-phase (compression / restitution) contact impulse with Poisson's hypothesis.

Paper eqs. (5) and (7), S.11-S.16 and appendix G. Given the contact Jacobian
of the (padded) candidate contacts, the constrained inverse inertia and the
pre-impact velocity:

1. compression (5): ``f_c = argmin 0.5 f'A f + f' v_C`` over the friction cones;
2. Poisson: the restitution normal impulse is at least ``e_P * f_c,n``;
3. restitution (7): ``f_r = argmin 0.5 f'A f + f'(v_C + A f_c - v_C^*)`` over the
   cones with ``f_n >= e_P f_c,n``, where ``v_C^*`` is the penetration-compensation
   target (appendix G);
4. ``v+ = v + Mhat^-1 J_C^T (f_c + f_r)`` (S.11).

CM solves with ``A = J_C Mhat^-1 J_C^T`` (PSD, singular with equality
constraints); CMr with ``A + eps I`` (pass ``eps``). The contact-model objects
of :mod:`diffcontact.contact.models` wrap this function.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import torch
from torch import Tensor

from diffcontact.contact.cone_qp import (
    SolverSettings,
    check_dense,
    settings_or_default,
    solve_cone_qp,
)
from diffcontact.contact.operator import ContactOperator, DenseContact, as_operator
from diffcontact.fastops import cholesky_solve, spd_solve
from diffcontact.shapes import broadcast_shapes, contact_dimension


@dataclass
class ImpulseResult:
    """Impulses of one contact resolution.

    Attributes:
        v_plus: (..., D) post-impact velocities.
        f_c: (..., K*d) compression impulses (contact space).
        f_r: (..., K*d) restitution impulses.
    """

    v_plus: Tensor
    f_c: Tensor
    f_r: Tensor

    def to(self, dtype: torch.dtype) -> ImpulseResult:
        """The three impulses in ``dtype`` (differentiable casts)."""
        return ImpulseResult(self.v_plus.to(dtype), self.f_c.to(dtype), self.f_r.to(dtype))


def penetration_target(
    J_C: Tensor | ContactOperator,
    depth: Tensor,
    active: Tensor,
    dt: float,
    d: int,
    fraction: float = 1 / 8,
    J_E: Tensor | None = None,
    Mhat_inv: Tensor | None = None,
) -> Tensor:
    """Penetration-compensation target ``v_C^*`` (appendix G, S.22-S.24).

    The desired contact velocity has normal components ``fraction * depth / dt``
    and zero tangential ones; it is lifted to Cartesian space with a pseudo-inverse of
    ``J_C``, made to respect the equality constraints, and mapped back with ``J_C``.

    With ``Mhat_inv`` (the constrained inverse inertia, S.12) the pseudo-inverse is the
    mass metric's, ``Mhat^-1 J_C^T A^+`` with ``A = J_C Mhat^-1 J_C^T``: the velocity
    change of the impulse that makes the contact velocities the desired ones, which
    respects the equality constraints by construction. The target is then ``A A^+ v``,
    the projection of the desired velocity onto the range of ``A``: the desired velocity
    itself where ``A`` is non-singular, so tangential targets stay zero. Appendix G as
    written (``Mhat_inv=None``: the Euclidean ``pinv(J_C)`` of S.24, then the Euclidean
    projection onto the null space of ``J_E``, S.22-S.23) gives extended bodies a
    tangential target that depends on how their points are laid out: a uniform disk
    resting on a ground with friction drifted sideways by millimetres per second at body
    angle 0, by nothing at 45 degrees (config key ``penetration_metric``, docs/config.md).
    Without equality constraints the two agree (the ranges of ``A`` and ``J_C`` are
    the same) and ``Mhat_inv`` is not used.

    No gradient flows through it.

    ``pinv(J_C) v`` is ``J_C^T (J_C J_C^T)^-1 v`` where ``J_C`` has full row rank (padded
    zero rows aside): Cholesky solves instead of an SVD. Where its rows are (nearly)
    dependent, several contacts on one body with more rows than degrees of freedom, the
    damped pseudo-inverse ``J_C^T (J_C J_C^T + lambda I)^-1``
    (``lambda = sqrt(eps)`` times the largest diagonal entry of ``J_C J_C^T``) stands in:
    it agrees with ``pinv`` to ``sqrt(eps)`` relative on the range of ``J_C`` and ignores
    the dependent part as ``pinv`` does.

    Without equality constraints the target is ``J_C pinv(J_C) v``, the projection of ``v``
    onto the range of ``J_C``: ``v`` itself where ``J_C`` has full row rank, which most
    states have. Those states get ``v`` exactly; states with dependent rows get
    ``G (G + lambda I)^-1 v`` with ``G = J_C J_C^T``, without a product with ``J_C``.
    No host synchronisation; a state's target does not depend on the other states of
    its batch.

    Args:
        J_C: (..., K*d, D) contact Jacobian (padded rows may be zero), or a
            :class:`~diffcontact.contact.operator.ContactOperator` of it.
        depth: (..., K) penetration depths (>= 0 where active).
        active: (..., K) bool.
        dt: time step.
        d: contact-space dimension.
        fraction: share of the depth removed per step (the released code used 1/8).
        J_E: (..., E, D) equality-constraint Jacobian, or None.
        Mhat_inv: (..., D, D) constrained inverse inertia for the mass metric, or None
            (the Euclidean one of S.24).

    Returns:
        v_C_star: (..., K*d).

    Raises:
        ValueError: ``dt`` not a finite number > 0, ``fraction`` outside [0, 1], ``depth``
            not floating or NaN/infinite at an active contact, ``active`` not bool, shapes
            (``J_C`` rows not ``K*d`` for ``depth``'s ``K``, ``J_E``, ``Mhat_inv``), dtypes
            or devices that do not fit, or batch dimensions that do not broadcast.
    """
    d = contact_dimension(d, "penetration_target")
    dt, fraction = _check_target_inputs(J_C, depth, active, dt, d, fraction, J_E, Mhat_inv)
    return _penetration_target(J_C, depth, active, dt, d, fraction, J_E, Mhat_inv)


def _target_number(name: str, value: Any, ok: Callable[[float], bool], want: str) -> float:
    """``value`` (a real number, or a one-element real tensor) as a float for which ``ok``
    holds, else a ``ValueError`` naming ``name`` (NaN fails every ``ok``)."""
    real = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if isinstance(value, Tensor):
        real = value.numel() == 1 and value.dtype != torch.bool and not value.is_complex()
    if not real or not ok(float(value)):
        raise ValueError(f"penetration_target: {name} must be {want}, got {value!r}")
    return float(value)


def _check_target_inputs(
    J_C: Any, depth: Any, active: Any, dt: Any, d: int, fraction: Any, J_E: Any, Mhat_inv: Any
) -> tuple[float, float]:
    """The checks of :func:`penetration_target`'s public entry (the simulator's step calls
    :func:`_penetration_target`, whose inputs hold by construction): ``(dt, fraction)`` as
    floats, or a ``ValueError`` naming the argument."""
    caller = "penetration_target"
    dt = _target_number("dt", dt, lambda x: 0 < x < math.inf, "a finite number > 0 (time step)")
    fraction = _target_number(
        "fraction", fraction, lambda x: 0 <= x <= 1, "a number in [0, 1] (share of the depth)"
    )
    if not isinstance(J_C, (Tensor, ContactOperator)):
        raise ValueError(
            f"{caller}: J_C must be a torch.Tensor (..., K*d, D) or a ContactOperator, "
            f"got {type(J_C).__name__}"
        )
    named = {"depth": depth, "active": active, "J_E": J_E, "Mhat_inv": Mhat_inv}
    for name, x in named.items():
        if x is None and name in ("J_E", "Mhat_inv"):
            continue
        if not isinstance(x, Tensor):
            raise ValueError(f"{caller}: {name} must be a torch.Tensor, got {type(x).__name__}")
        check_dense(caller, name, x)
    if not depth.is_floating_point() or depth.dim() < 1:
        raise ValueError(
            f"{caller}: depth must be a floating-point tensor of shape (..., K), got "
            f"{depth.dtype} {tuple(depth.shape)}"
        )
    K = depth.shape[-1]
    if active.dtype != torch.bool or active.dim() < 1 or active.shape[-1] != K:
        raise ValueError(
            f"{caller}: active must be a bool tensor of shape (..., {K}) (K = {K} contacts, "
            f"depth's last dimension), got {active.dtype} {tuple(active.shape)}"
        )
    batches = {"depth": depth.shape[:-1], "active": active.shape[:-1]}
    D = None
    if isinstance(J_C, Tensor):
        check_dense(caller, "J_C", J_C)
        if J_C.dim() < 2 or not J_C.is_floating_point() or J_C.shape[-2] != K * d:
            raise ValueError(
                f"{caller}: J_C must be a floating tensor of shape (..., K*d, D) with K = {K} "
                f"contacts (depth's last dimension) and d = {d}, got {J_C.dtype} "
                f"{tuple(J_C.shape)}"
            )
        D = J_C.shape[-1]
        batches["J_C"] = J_C.shape[:-2]
    for name, x in (("J_E", J_E), ("Mhat_inv", Mhat_inv)):
        if x is None:
            continue
        rows = "E" if name == "J_E" else "D"
        fits = x.dim() >= 2 and x.is_floating_point()
        if fits and D is not None:  # J_E: (..., E, D); Mhat_inv: (..., D, D)
            fits = x.shape[-1] == D and (name == "J_E" or x.shape[-2] == D)
        if not fits:
            cols = "D" if D is None else D
            raise ValueError(
                f"{caller}: {name} must be a floating tensor of shape (..., {rows}, {cols})"
                f"{'' if D is None else f' for J_C of shape {tuple(J_C.shape)}'}, got "
                f"{x.dtype} {tuple(x.shape)}"
            )
        batches[name] = x.shape[:-2]
    ref = J_C if isinstance(J_C, Tensor) else depth
    for name, x in (("depth", depth), ("active", active), ("J_E", J_E), ("Mhat_inv", Mhat_inv)):
        if x is None or x is ref:
            continue
        if name != "active" and x.dtype != ref.dtype:
            what = "J_C" if ref is J_C else "depth"
            raise ValueError(f"{caller}: {name} has dtype {x.dtype}, {what} has {ref.dtype}")
        if x.device != ref.device:
            what = "J_C" if ref is J_C else "depth"
            raise ValueError(f"{caller}: {name} is on {x.device}, {what} is on {ref.device}")
    check_batches(caller, batches)
    if bool((active & ~torch.isfinite(depth.detach())).any()):
        raise ValueError(f"{caller}: depth contains NaN or infinite values at active contacts")
    return dt, fraction


def _penetration_target(
    J_C: Tensor | ContactOperator,
    depth: Tensor,
    active: Tensor,
    dt: float,
    d: int,
    fraction: float,
    J_E: Tensor | None = None,
    Mhat_inv: Tensor | None = None,
) -> Tensor:
    """:func:`penetration_target` without its checks: what a simulation step calls, whose
    inputs hold by construction (``d`` an int, ``dt > 0``, ``depth`` from the gaps)."""
    op = as_operator(J_C, None)
    depth = torch.where(active, depth.clamp_min(0), 0)
    v_d = torch.stack([fraction * depth / dt, *[torch.zeros_like(depth)] * (d - 1)], -1)
    v_d = v_d.flatten(-2)
    if J_E is None or J_E.shape[-2] == 0:
        return _range_projection(op, v_d)
    if Mhat_inv is not None:
        if not isinstance(op, DenseContact):
            raise ValueError("penetration_target: the mass metric needs the dense J_C")
        return _range_projection(op, v_d, DenseContact(op.J_C, Mhat_inv).delassus())
    v_star = _pinv_apply(op, v_d)
    JJt = J_E @ J_E.transpose(-1, -2)
    corr = spd_solve(JJt, J_E @ v_star.unsqueeze(-1))
    v_star = v_star - (J_E.transpose(-1, -2) @ corr).squeeze(-1)
    return op.contact_velocity(v_star)


def _gram_cholesky(G: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Of ``G = J J^T: (..., m, m)``: the Cholesky factor ``L`` of ``G`` (a unit pivot
    for each zero row of ``J``), whether ``J``'s rows are (nearly) dependent ``(...)``,
    the damping ``lambda: (..., 1)`` of :func:`penetration_target`, and which rows of
    ``J`` are zero ``(..., m)``."""
    diag = G.diagonal(dim1=-2, dim2=-1)
    finfo = torch.finfo(G.dtype)
    scale = diag.amax(-1, keepdim=True).clamp_min(finfo.tiny)  # (..., 1)
    padded = diag <= 0  # zero rows (padded contacts): a unit pivot keeps them out
    exact = G + torch.diag_embed(torch.where(padded, scale, 0))
    L, info = torch.linalg.cholesky_ex(exact)
    pivots = L.diagonal(dim1=-2, dim2=-1).square()
    damping = finfo.eps**0.5 * scale
    dependent = (info != 0) | (pivots < damping).any(-1)
    return L, dependent, damping, padded


def _damped_cholesky(G: Tensor, damping: Tensor) -> Tensor:
    """The Cholesky factor of ``G + lambda I`` (positive definite; NaN in: NaN out)."""
    eye = torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)
    return torch.linalg.cholesky_ex(G + damping.unsqueeze(-1) * eye)[0]


def _pinv_apply(J: Tensor | ContactOperator, v: Tensor) -> Tensor:
    """``pinv(J) v`` for ``J: (..., m, D)`` (or an operator of it), ``v: (..., m)`` (see
    :func:`penetration_target`)."""
    op = as_operator(J, None)
    G = op.gram()
    L, dependent, damping, _ = _gram_cholesky(G)
    L = torch.where(dependent[..., None, None], _damped_cholesky(G, damping), L)
    y = cholesky_solve(v.unsqueeze(-1), L)
    return op.generalized_impulse(y.squeeze(-1))


def _range_projection(op: ContactOperator, v: Tensor, G: Tensor | None = None) -> Tensor:
    """``J pinv(J) v`` for ``v: (..., m)``: ``v`` where ``J``'s rows are independent (zero
    on its zero rows, which its range does not reach), the damped pseudo-inverse's ``J
    J^T (J J^T + lambda I)^-1 v`` where they are dependent (see
    :func:`penetration_target`), from ``G = J J^T`` alone. Every state is solved and the
    dependent ones selected: no read of the device (a step reads it once, to select the
    states in contact). With ``G`` given (``(..., m, m)``, e.g. ``A = J Mhat^-1 J^T``),
    the projection onto its range instead."""
    G = op.gram() if G is None else G
    _, dependent, damping, zero_rows = _gram_cholesky(G)
    y = cholesky_solve(v.unsqueeze(-1), _damped_cholesky(G, damping))
    independent = torch.where(zero_rows, 0.0, v)
    return torch.where(dependent.unsqueeze(-1), (G @ y).squeeze(-1), independent)


def check_impulse_inputs(
    cor: Tensor,
    v: Tensor,
    caller: str,
    *,
    J_C: Tensor | ContactOperator | None = None,
    Mhat_inv: Tensor | None = None,
    mu: Tensor | None = None,
    active: Tensor | None = None,
    d: int | None = None,
    v_C_star: Tensor | None = None,
    eps: float | Tensor | None = None,
) -> None:
    """The public impulse functions' checks (with ``SolverSettings.check_inputs``, off
    inside a simulation step, whose boundary checks once): ``cor`` a tensor in [0, 1] (a
    ``cor`` of 1.5 had sent a body away faster than it came), ``v`` a floating tensor,
    ``mu >= 0``, and where ``J_C`` is a tensor the shapes and dtypes of the problem
    (``J_C`` (..., K*d, D), ``Mhat_inv`` (..., D, D), ``v`` (..., D), ``mu``, ``cor``,
    ``active`` (..., K), ``v_C_star`` (..., K*d)), each named where it does not fit, and
    that the batch dimensions of all of them (and of a tensor ``eps``, ``(...)``) broadcast."""
    if not isinstance(v, Tensor) or not v.is_floating_point():
        what = v.dtype if isinstance(v, Tensor) else type(v).__name__
        raise ValueError(f"{caller}: v must be a floating-point torch.Tensor, got {what}")
    named = {"v": v, "cor": cor, "mu": mu, "J_C": J_C, "Mhat_inv": Mhat_inv}
    for name, x in (named | {"active": active, "v_C_star": v_C_star}).items():
        if isinstance(x, Tensor):
            check_dense(caller, name, x)
    if not isinstance(cor, Tensor):
        raise ValueError(f"{caller}: cor must be a torch.Tensor, got {type(cor).__name__}")
    c = cor.detach()
    if c.numel() and not bool(((c >= 0) & (c <= 1)).all()):
        raise ValueError(
            f"{caller}: cor (e_P) must lie in [0, 1], got values in "
            f"[{float(c.min()):g}, {float(c.max()):g}]"
        )
    if mu is not None:
        if not isinstance(mu, Tensor):
            raise ValueError(f"{caller}: mu must be a torch.Tensor, got {type(mu).__name__}")
        if mu.numel() and bool((mu.detach() < 0).any()):
            raise ValueError(f"{caller}: mu must be >= 0 (friction coefficients)")
    if not isinstance(J_C, Tensor) or d is None:
        _check_batch(caller, v, mu, cor, active, v_C_star, eps)
        return  # (an operator's maps are the library's own)
    if J_C.dim() < 2 or not J_C.is_floating_point() or J_C.shape[-2] % d:
        raise ValueError(
            f"{caller}: J_C must be a floating tensor of shape (..., K*d, D) with d = {d}, got "
            f"{J_C.dtype} {tuple(J_C.shape)}"
        )
    m, D = J_C.shape[-2:]
    K = m // d
    if not isinstance(Mhat_inv, Tensor) or Mhat_inv.shape[-2:] != (D, D):
        got = tuple(Mhat_inv.shape) if isinstance(Mhat_inv, Tensor) else type(Mhat_inv).__name__
        raise ValueError(f"{caller}: Mhat_inv must have shape (..., {D}, {D}), got {got}")
    expected = {"Mhat_inv": (Mhat_inv, D), "v": (v, D), "mu": (mu, K), "cor": (cor, K)}
    expected |= {"active": (active, K), "v_C_star": (v_C_star, m)}
    for name, (x, size) in expected.items():
        if isinstance(x, Tensor) and (x.dim() < 1 or x.shape[-1] != size):
            raise ValueError(
                f"{caller}: {name} must have shape (..., {size}) for J_C of shape "
                f"{tuple(J_C.shape)} (K = {K} contacts, D = {D}), got {tuple(x.shape)}"
            )
        if isinstance(x, Tensor) and name != "active" and x.dtype != J_C.dtype:
            raise ValueError(f"{caller}: {name} has dtype {x.dtype}, J_C has {J_C.dtype}")
    _check_batch(caller, v, mu, cor, active, v_C_star, eps, J_C=J_C, Mhat_inv=Mhat_inv)


def _check_batch(
    caller: str,
    v: Tensor,
    mu: Any,
    cor: Any,
    active: Any,
    v_C_star: Any,
    eps: Any,
    *,
    J_C: Tensor | None = None,
    Mhat_inv: Tensor | None = None,
) -> None:
    """``ValueError`` naming ``caller`` unless the batch dimensions of the impulse's
    tensors broadcast (a ``v`` or ``eps`` of another batch size than ``J_C``'s had failed
    in a product, with torch's message naming neither)."""
    vectors = {"v": v, "mu": mu, "cor": cor, "active": active, "v_C_star": v_C_star}
    batches = {n: x.shape[:-1] for n, x in vectors.items() if isinstance(x, Tensor) and x.dim()}
    for name, x in (("J_C", J_C), ("Mhat_inv", Mhat_inv)):
        if isinstance(x, Tensor) and x.dim() > 1:
            batches[name] = x.shape[:-2]
    if isinstance(eps, Tensor):  # (...): one per state
        batches["eps"] = eps.shape
    check_batches(caller, batches)


def check_batches(caller: str, batches: dict[str, tuple[int, ...]]) -> None:
    """``ValueError`` naming ``caller`` and each tensor's batch shape unless the batch
    shapes ``batches`` (by argument name) broadcast."""
    try:
        broadcast_shapes(*batches.values())
    except RuntimeError as err:
        named = ", ".join(f"{name} {tuple(shape)}" for name, shape in batches.items())
        why = str(err).split("cannot be broadcast: ")[-1]  # (the shapes: named here)
        raise ValueError(f"{caller}: batch dimensions do not broadcast ({named}): {why}") from None


def empty_impulse(v: Tensor, active: Tensor, d: int) -> ImpulseResult:
    """The impulses of an empty batch: ``v`` unchanged, no impulse."""
    f = v.new_zeros(*v.shape[:-1], active.shape[-1] * d)
    return ImpulseResult(v.clone(), f, f.clone())


def wider_dtype(dtype: torch.dtype, work: torch.dtype | None) -> torch.dtype | None:
    """``work`` where it is a floating dtype wider than ``dtype``, else ``None``: the
    dtype a contact model resolves states of ``dtype`` in (``work``: its solver's
    ``compute_dtype``)."""
    if work is None or not dtype.is_floating_point or not work.is_floating_point:
        return None
    return work if torch.finfo(work).bits > torch.finfo(dtype).bits else None


def widened(
    work: torch.dtype,
    J_C: Tensor | ContactOperator,
    Mhat_inv: Tensor | None,
    *tensors: Tensor | None,
) -> tuple[ContactOperator, ...]:
    """A contact problem's operator and tensors cast to ``work`` (differentiable casts;
    ``None`` and non-tensors kept): ``(op, *tensors)``.

    Contact models resolve states narrower than their solver's compute dtype in that dtype
    *from the rows on*, not only inside the solver: ``A = J_C Mhat^-1 J_C^T`` is singular
    wherever a body has more contacts than freedoms; formed in float32 it is not, by
    rounding, and the solver then picks the solution of the perturbed problem instead of
    the canonical one (which impulse a body's contacts share feeds Poisson's bound, and
    the LCP's pivoting), so a float32 rollout took another post-impact velocity and parted
    from the float64 one (``tests/systems/test_simulate.py``)."""
    op = as_operator(J_C, Mhat_inv)
    op = op.to(work) if hasattr(op, "to") else op
    cast = tuple(t.to(work) if isinstance(t, Tensor) else t for t in tensors)
    return (op, *cast)


def two_phase_impulse(
    J_C: Tensor | ContactOperator,
    Mhat_inv: Tensor | None,
    v: Tensor,
    mu: Tensor,
    cor: Tensor,
    active: Tensor,
    d: int,
    *,
    v_C_star: Tensor | None = None,
    eps: float | Tensor | None = None,
    settings: SolverSettings | None = None,
) -> ImpulseResult:
    """Resolve all active contacts of a batch of states at once.

    Args:
        J_C: (..., K*d, D) contact Jacobian of the (padded) contacts, or a
            :class:`~diffcontact.contact.operator.ContactOperator` of ``J_C`` and
            ``Mhat^-1`` (e.g. the sparse rows of a long rope).
        Mhat_inv: (..., D, D) constrained inverse inertia (S.12); ``None`` with an
            operator.
        v: (..., D) pre-impact velocities.
        mu: (..., K) friction coefficients.
        cor: (..., K) Poisson coefficients of restitution in [0, 1].
        active: (..., K) bool; inactive (padding) contacts receive no impulse.
        d: contact-space dimension.
        v_C_star: (..., K*d) penetration-compensation target, or None for zero.
        eps: CMr's regulariser ``()`` or ``(...)`` (number or tensor, learnable
            if you like); ``None`` solves CM's unregularised problem.
        settings: solver settings.

    Returns:
        An :class:`ImpulseResult`, in ``v``'s dtype.

    States in a narrower dtype than the solver's ``compute_dtype`` (float32 states, the
    default float64 solve) are resolved in the compute dtype from the rows on (``A``, the
    contact velocity, both phases), not only inside the solver (:func:`widened` says
    why; the canonical minimiser: :mod:`~diffcontact.contact.cone_qp`).
    """
    d = contact_dimension(d, "two_phase_impulse")
    settings = settings_or_default(settings, "two_phase_impulse: settings")
    if settings.check_inputs:
        check_impulse_inputs(
            cor, v, "two_phase_impulse", J_C=J_C, Mhat_inv=Mhat_inv, mu=mu, active=active,
            d=d, v_C_star=v_C_star, eps=eps,
        )  # fmt: skip
        if eps is not None and bool((torch.as_tensor(eps).detach() < 0).any()):
            raise ValueError(f"two_phase_impulse: eps (CMr's regulariser) must be >= 0, got {eps}")
        # the QPs' A = J_C Mhat^-1 J_C^T is semi-definite by construction, up to rounding
        # that the QP's own check cannot tell from an indefinite A where a contact's row
        # is constrained away (A_kk ~ -1e-16): its checks stay off
        settings = replace(settings, check_inputs=False)
    if v.numel() == 0:  # batch 0 (it failed in a reshape)
        return empty_impulse(v, active, d)
    work = wider_dtype(v.dtype, settings.compute_dtype)
    if work is not None:
        op, v_w, mu_w, cor_w, star_w, eps_w = widened(
            work, J_C, Mhat_inv, v, mu, cor, v_C_star, eps
        )
        return two_phase_impulse(
            op, None, v_w, mu_w, cor_w, active, d, v_C_star=star_w, eps=eps_w, settings=settings
        ).to(v.dtype)
    op = as_operator(J_C, Mhat_inv)
    A = op.delassus()  # symmetric
    A_qp = A
    if eps is not None:
        eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
        A_qp = A + torch.as_tensor(eps, dtype=A.dtype, device=A.device)[..., None, None] * eye
    v_C = op.contact_velocity(v)
    f_c = solve_cone_qp(A_qp, v_C, mu, d, None, active, settings=settings)
    v_C_c = v_C + (A @ f_c.unsqueeze(-1)).squeeze(-1)
    lower = (cor * f_c[..., ::d]).clamp_min(0)
    target = v_C_c if v_C_star is None else v_C_c - v_C_star
    # warm start: e_P times the compression impulse is feasible (f_n = e_P f_c,n meets
    # the bound; the cone is scale invariant) and usually close; the polish from it
    # finishes most restitution problems without an interior point
    f_c_k = f_c.detach().reshape(*f_c.shape[:-1], -1, d)
    guess = (cor.detach().unsqueeze(-1) * f_c_k).flatten(-2)
    f_r = solve_cone_qp(A_qp, target, mu, d, lower, active, settings=settings, warm_start=guess)
    v_plus = v + op.velocity_change(f_c + f_r)
    return ImpulseResult(v_plus, f_c, f_r)
