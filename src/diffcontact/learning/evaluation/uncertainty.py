"""How well the data determine the learned physical parameters (Gauss-Newton / Laplace).

After training, the learned mass ratios, ``mu`` and ``e_P`` are point values;
some are pinned down by the data and some are not (a friction coefficient of a
contact that only ever sticks is bounded below and free above; a parameter held
at the edge of its range by the model's clamp stops where the optimiser left
it). :func:`parameter_uncertainty` says which is which.

Method. Let ``r(theta)`` be the residuals of the training loss: the learned
model's rollouts of the training chunks from their first states minus the data
(every later state, every coordinate), and ``theta`` the physical parameters in
natural units:

- ``log(m_i / m_1)`` for every body but the first (mass ratios; the common scale
  is not identifiable and stays fixed, with the learned potential);
- ``log`` of the second moments of rigid bodies (nuisance parameters: their
  correlation with the others is accounted for, they are not reported);
- ``mu`` and ``e_P`` (one shared value, or one per contact).

The potential network is held fixed, so the errors are *conditional* on it.
The Jacobian ``J = dr/dtheta`` is taken by finite differences on both sides of
the learned value (one side only at the edge of a range: ``mu = 0``, ``e_P`` in
{0, 1}); the perturbed rollouts run as one batch with one parameter set per
trajectory.

The training loss is a mean absolute error, i.e. the likelihood of Laplace
noise of scale ``b``, estimated as ``b = mean |r|``. Its Fisher information is
``J^T J / b^2``, so the Laplace (Gauss-Newton) covariance is
``b^2 (J^T J)^-1``. Directions whose curvature is below ``rcond`` times the
largest (after scaling ``J``'s columns to unit norm) are flat, and a parameter
with a share of more than ``1e-6`` of its variance in them gets an infinite
standard error. Residuals within a chunk are correlated and the loss is not
smooth everywhere (contacts switch between sticking and sliding), so the errors
are a local, optimistic measure: use them to tell determined parameters from
undetermined ones, not as exact confidence intervals.

A parameter is **determined** unless

- the loss is flat along it (infinite standard error);
- it is a friction coefficient and no training impact slides (sticking impacts
  only bound ``mu`` from below; :func:`contact_regimes`);
- it is *one-sided*: the forward and backward difference quotients differ by
  more than a factor 2 (``one_sided_ratio``): the learned value sits at a kink
  of the loss, typically where an impact switches between sticking and sliding,
  so the data bound it from one side only;
- the half-width of its 95 % interval (1.96 standard errors) exceeds a
  tolerance (``mass_ratio_tol`` relative, ``mu_tol`` and ``cor_tol`` absolute:
  the criteria of docs/results.md);
- it is *not stable*: a Newton step of the absolute-error loss from the learned
  values (iteratively reweighted least squares, weights ``1 / |r|``; exact when
  the residuals are linear in the parameters) moves it by more than its
  tolerance. That is a value the data would move but training did not,
  typically one held at the edge of its range by the clamp, where the optimiser
  gets no gradient;
- it is a friction coefficient *not at its best* (only with
  ``UncertaintySettings(scan=...)``): a one-dimensional scan of the loss over
  multiples of its learned value finds a lower valley that the local analysis
  cannot see (the loss is not convex in ``mu``: training can stop on a plateau).

:func:`contact_regimes` counts, for every candidate contact, the training
states in which it is active under the learned model, split into sliding
(total impulse on the friction cone's boundary), sticking (strictly inside)
and separating (zero normal impulse): ``mu`` is only identified by sliding
impacts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "UncertaintySettings",
    "contact_regimes",
    "parameter_uncertainty",
    "supports_uncertainty",
]


@dataclass(frozen=True)
class UncertaintySettings:
    """Settings of :func:`parameter_uncertainty`.

    Attributes:
        step: finite-difference step in natural units (log mass ratios, log
            second moments, ``mu``, ``e_P``).
        rcond: curvature below ``rcond`` times the largest (of the column-scaled
            ``J^T J``) counts as flat.
        mass_ratio_tol: relative 95 % half-width of a determined mass ratio.
        mu_tol: absolute 95 % half-width of a determined ``mu``.
        cor_tol: absolute 95 % half-width of a determined ``e_P``.
        one_sided_ratio: a parameter whose forward and backward difference
            quotients (norms over the residuals) differ by more than this factor
            sits at a kink of the loss: the data bound it from one side only.
        max_states: states per batched rollout (perturbations x chunks).
        scan: factors of a one-dimensional scan of every ``mu`` (e.g.
            ``(0, 0.25, 0.5, 0.75, 1.5, 2)`` times its learned value), or
            ``None`` (off, the default). The local analysis cannot see a lower
            valley of the loss away from the learned value; the scan can, and a
            ``mu`` whose loss is lower somewhere on it (by more than 0.1 %) is
            flagged "not at its best". It costs one rollout of the chunks per
            factor and coefficient.
    """

    step: float = 1e-5
    rcond: float = 1e-9
    mass_ratio_tol: float = 0.005
    mu_tol: float = 0.01
    cor_tol: float = 0.02
    one_sided_ratio: float = 0.5
    max_states: int = 8192
    scan: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("step", "rcond", "mass_ratio_tol", "mu_tol", "cor_tol", "one_sided_ratio"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if self.scan is not None and not (
            len(self.scan) > 0 and all(math.isfinite(f) and f >= 0 for f in self.scan)
        ):
            raise ValueError(f"scan must be non-negative factors, got {self.scan!r}")
        if not isinstance(self.max_states, int) or self.max_states < 1:
            raise ValueError(f"max_states must be a positive integer, got {self.max_states!r}")


def supports_uncertainty(model: Any) -> bool:
    """Whether ``model`` is a physical model (a ``System`` with learned parameters)."""
    return all(
        hasattr(model, name)
        for name in ("system", "physical_params", "contact_model", "dynamics", "raw_mu")
    )


@dataclass
class _Layout:
    """Where each entry of ``theta`` lives."""

    n_mass: int  # log mass ratios of bodies 2..B
    n_moments: int  # log second moments (flattened)
    n_mu: int
    n_cor: int

    @property
    def p(self) -> int:
        return self.n_mass + self.n_moments + self.n_mu + self.n_cor

    def slices(self) -> tuple[slice, slice, slice, slice]:
        a = self.n_mass
        b = a + self.n_moments
        c = b + self.n_mu
        return slice(0, a), slice(a, b), slice(b, c), slice(c, c + self.n_cor)


def _base(model: Any) -> tuple[Any, _Layout, Tensor, Tensor]:
    """Base parameters, layout, base ``mu`` and ``e_P`` of the model (float64, detached)."""
    with torch.no_grad():
        base = model.physical_params()
        mu = torch.nn.functional.relu(model.raw_mu.detach()).double().cpu()
        cor = model.cor().detach().double().cpu()[: mu.numel()]
    B = int(base.mass.shape[-1])
    sm = base.second_moments
    layout = _Layout(B - 1, 0 if sm is None else sm.numel(), mu.numel(), cor.numel())
    return base, layout, mu, cor


def _batched_params(base: Any, layout: _Layout, mu0: Tensor, cor0: Tensor, delta: Tensor, n: int):
    """Parameters for ``G`` perturbations ``delta: (G, p)``, each repeated for ``n`` chunks."""
    G = delta.shape[0]
    sm_, sw_, smu, scor = layout.slices()
    dtype, device = delta.dtype, delta.device
    mass0 = base.mass.detach().to(dtype=dtype, device=device)
    log_ratio = torch.cat([delta.new_zeros(G, 1), delta[:, sm_]], dim=1)
    mass = mass0 * log_ratio.exp()  # (G, B)
    changes: dict[str, Tensor] = {"mass": mass}
    if base.second_moments is not None:
        sm0 = base.second_moments.detach().to(dtype=dtype, device=device)
        changes["second_moments"] = sm0 * delta[:, sw_].reshape(G, *sm0.shape).exp()
    changes["mu"] = (mu0.to(delta) + delta[:, smu]).clamp_min(0)
    changes["cor"] = (cor0.to(delta) + delta[:, scor]).clamp(0, 1)
    batched = {k: v.repeat_interleave(n, dim=0) for k, v in changes.items()}
    for name in ("gravity", "stiffness", "rest_length", "eps"):
        value = getattr(base, name)
        if isinstance(value, Tensor) and value.dim() > 0:
            raise ValueError(f"the model's {name} is per trajectory; expected one value")
    return base.replace(**batched)


def _residuals(
    model: Any, chunks: Tensor, base: Any, layout: _Layout, mu0: Tensor, cor0: Tensor,
    delta: Tensor, max_states: int,
) -> Tensor:  # fmt: skip
    """``(G, R)`` residuals (rollout minus data, later states) for each perturbation."""
    n, L = chunks.shape[:2]
    z0 = chunks[:, 0]
    per_call = max(1, max_states // n)
    out = []
    for start in range(0, delta.shape[0], per_call):
        d = delta[start : start + per_call]
        G = d.shape[0]
        params = _batched_params(base, layout, mu0, cor0, d, n)
        with torch.no_grad():
            traj = model.system.simulate(
                z0.repeat(G, 1, 1, 1),
                L - 1,
                params=params,
                contact_model=model.contact_model,
                dynamics=model.dynamics,
                check_overlap=False,
                on_tunnelling="ignore",
            )
        r = (traj[:, 1:] - chunks[:, 1:].repeat(G, 1, 1, 1, 1)).reshape(G, -1)
        out.append(r)
    return torch.cat(out)


def parameter_uncertainty(
    model: Any,
    chunks: Tensor,
    *,
    settings: UncertaintySettings | None = None,
    progress: bool = False,
) -> dict[str, Any]:
    """Standard errors and "determined" flags of a physical model's learned parameters.

    Args:
        model: a physical learned model (:func:`supports_uncertainty`), e.g.
            :class:`~diffcontact.learning.LearnedModel`.
        chunks: ``(n, L, 2, P, dim)`` training chunks (float64 recommended);
            chunks holding NaN are dropped.
        settings: :class:`UncertaintySettings`.
        progress: print one line saying how many rollouts it runs.

    Returns:
        A JSON-ready dict: ``method``, ``n_chunks``, ``n_residuals``,
        ``n_parameters``, ``residual_mean_abs`` (``b``), ``mass_ratios``
        (``m_i / m_1`` for bodies 2..B), ``mu``, ``cor`` (each a dict with lists
        ``value``, ``std_error`` (``None`` where the loss is flat), ``ci95``
        (pairs or ``None``), ``step`` (the Newton step), ``determined`` (bool)
        and ``reason`` ("" or why not)), ``tolerances`` and ``regimes``
        (:func:`contact_regimes`).

    Raises:
        ValueError: a model that is not a physical model, chunks of the wrong
            shape, or no finite chunk.
    """
    settings = settings or UncertaintySettings()
    if not supports_uncertainty(model):
        raise ValueError(
            f"{type(model).__name__} has no physical parameters to assess "
            "(parameter uncertainty is for the physical models, e.g. CM-CD-CLNN)"
        )
    shape = tuple(model.system.state_shape)
    if chunks.dim() != 5 or tuple(chunks.shape[2:]) != shape or chunks.shape[1] < 2:
        raise ValueError(f"chunks must have shape (n, L >= 2, *{shape}), got {tuple(chunks.shape)}")
    chunks = chunks.detach().to(torch.float64)
    ok = torch.isfinite(chunks.flatten(1)).all(1)
    chunks = chunks[ok]
    if chunks.shape[0] == 0:
        raise ValueError("no training chunk is finite")
    device = next((p.device for p in model.parameters()), torch.device("cpu"))
    chunks = chunks.to(device)

    base, layout, mu0, cor0 = _base(model)
    p = layout.p
    sm_, _, smu, scor = layout.slices()
    h = settings.step
    value = torch.zeros(p, dtype=torch.float64)
    mass0 = base.mass.detach().double().cpu()
    value[sm_] = (mass0[1:] / mass0[0]).log()
    lo = torch.full((p,), -math.inf, dtype=torch.float64)
    hi = torch.full((p,), math.inf, dtype=torch.float64)
    value[smu], lo[smu] = mu0, 0.0
    value[scor], lo[scor], hi[scor] = cor0, 0.0, 1.0
    # central differences; one-sided where a step would leave the range
    plus = torch.where(value + h <= hi, h, 0.0)
    minus = torch.where(value - h >= lo, -h, 0.0)
    eye = torch.eye(p, dtype=torch.float64)
    deltas = torch.cat([eye.new_zeros(1, p), eye * plus[:, None], eye * minus[:, None]])
    scan_values = None
    if settings.scan is not None and layout.n_mu:
        factors = torch.tensor(settings.scan, dtype=torch.float64)
        scan_values = mu0[:, None] * factors[None, :]  # (n_mu, F)
        rows = eye[smu].repeat_interleave(len(factors), dim=0)  # (n_mu * F, p)
        shift = (scan_values - mu0[:, None]).reshape(-1)
        deltas = torch.cat([deltas, rows * shift[:, None]])
    deltas = deltas.to(device)

    if progress:
        print(f"parameter uncertainty: {deltas.shape[0]} rollouts of {chunks.shape[0]} chunks")
    r_all = _residuals(model, chunks, base, layout, mu0, cor0, deltas, settings.max_states)
    r_all = r_all.double().cpu()
    if not torch.isfinite(r_all).all():
        raise ValueError("the learned model's rollouts of the training chunks are not finite")
    regimes = contact_regimes(model, chunks)
    sliding = torch.tensor(regimes["sliding"], dtype=torch.long)
    if layout.n_mu == 1:  # one shared mu: every contact's sliding impacts count
        sliding = sliding.sum().reshape(1)
    better = None
    if scan_values is not None:
        loss0 = float(r_all[0].abs().sum())
        losses = r_all[1 + 2 * p :].abs().sum(1).reshape(scan_values.shape)
        best = losses.argmin(1)
        better = [
            (float(scan_values[j, i]), float(losses[j, i]) / loss0 - 1)
            if float(losses[j, i]) < loss0 * (1 - 1e-3)
            else None
            for j, i in enumerate(best.tolist())
        ]
        r_all = r_all[: 1 + 2 * p]
    result = _assess(r_all, plus, minus, value, layout, settings, (sliding > 0).tolist(), better)
    return {"n_chunks": int(chunks.shape[0]), **result, "regimes": regimes}


def _assess(
    r_all: Tensor, plus: Tensor, minus: Tensor, value: Tensor, layout: _Layout,
    settings: UncertaintySettings, mu_slides: list[bool] | None = None,
    mu_better: list[tuple[float, float] | None] | None = None,
) -> dict[str, Any]:  # fmt: skip
    """The statistics of :func:`parameter_uncertainty` from the residuals.

    Args:
        r_all: ``(1 + 2p, R)`` residuals at the learned values, then with each
            parameter stepped by ``plus`` and by ``minus``.
        plus, minus: ``(p,)`` the steps (``0`` where a side would leave the range).
        value: ``(p,)`` the learned values (natural units).
        mu_slides: per friction coefficient, whether some training impact slides
            (``None``: do not use the regimes).
        mu_better: per friction coefficient, ``(value, relative change of the
            loss)`` of a scanned value that fits better, or ``None``.
    """
    p = layout.p
    r0, r_plus, r_minus = r_all[0], r_all[1 : p + 1], r_all[p + 1 :]
    n_res = r0.numel()
    # one-sided difference quotients; a missing side (range edge) copies the other
    J_plus = torch.where((plus > 0)[:, None], (r_plus - r0) / plus.clamp_min(1e-300)[:, None], 0)
    J_minus = torch.where(
        (minus < 0)[:, None], (r0 - r_minus) / (-minus).clamp_min(1e-300)[:, None], 0
    )
    J_plus = torch.where((plus > 0)[:, None], J_plus, J_minus)
    J_minus = torch.where((minus < 0)[:, None], J_minus, J_plus)
    J = (0.5 * (J_plus + J_minus)).T  # (R, p) central differences
    n_plus, n_minus = J_plus.norm(dim=1), J_minus.norm(dim=1)
    one_sided = torch.minimum(n_plus, n_minus) < settings.one_sided_ratio * torch.maximum(
        n_plus, n_minus
    )

    # Laplace noise (the training loss is a mean absolute error): scale b = mean |r|,
    # Fisher information J^T J / b^2, score J^T sign(r) / b
    b = float(r0.abs().mean())
    H = J.T @ J
    D = H.diagonal().sqrt()
    used = D > 0
    Dinv = torch.where(used, 1 / D.clamp_min(1e-300), 0.0)
    Hs = Dinv[:, None] * H * Dinv[None, :]
    lam, V = torch.linalg.eigh(Hs)
    cut = settings.rcond * float(lam.max().clamp_min(0)) if p else 0.0
    good = lam > cut
    inv_lam = torch.where(good, 1 / lam.clamp_min(1e-300), 0.0)
    var = b**2 * (V**2 @ inv_lam) * Dinv**2
    flat_share = V[:, ~good].pow(2).sum(1)
    flat = (~used) | (flat_share > 1e-6)
    se = torch.where(flat, math.inf, var.clamp_min(0).sqrt())
    # a Newton step of the absolute-error loss (iteratively reweighted least squares:
    # weights 1 / |r|), in the directions it determines: exact for a loss linear in the
    # parameters, so a value the data would move is told from one they hold
    w = 1 / r0.abs().clamp_min(1e-6 * b + 1e-300)
    Hw = J.T @ (w[:, None] * J)
    Dw = Hw.diagonal().sqrt()
    Dw_inv = torch.where(Dw > 0, 1 / Dw.clamp_min(1e-300), 0.0)
    lam_w, V_w = torch.linalg.eigh(Dw_inv[:, None] * Hw * Dw_inv[None, :])
    good_w = lam_w > settings.rcond * float(lam_w.max().clamp_min(0))
    inv_w = torch.where(good_w, 1 / lam_w.clamp_min(1e-300), 0.0)
    grad = Dw_inv * (J.T @ torch.sign(r0))
    step = -Dw_inv * (V_w @ (inv_w * (V_w.T @ grad)))

    def report(
        sl: slice, kind: str, slides: list[bool] | None = None, better: list[Any] | None = None
    ) -> dict[str, Any]:
        out: dict[str, list[Any]] = {
            key: [] for key in ("value", "std_error", "ci95", "step", "determined", "reason")
        }
        rows = zip(
            value[sl].tolist(), se[sl].tolist(), step[sl].tolist(), one_sided[sl].tolist(),
            strict=True,
        )  # fmt: skip
        for i, (v, s, st, lop) in enumerate(rows):
            half = 1.96 * s
            finite = math.isfinite(s)
            if kind == "mass_ratios":  # theta = log ratio
                ratio = math.exp(v)
                out["value"].append(ratio)
                out["std_error"].append(ratio * s if finite else None)
                out["ci95"].append(
                    [ratio * math.exp(-half), ratio * math.exp(half)] if finite else None
                )
                out["step"].append(ratio * math.expm1(st))
                tol = settings.mass_ratio_tol
            else:
                top = math.inf if kind == "mu" else 1.0
                out["value"].append(v)
                out["std_error"].append(s if finite else None)
                out["ci95"].append([max(v - half, 0.0), min(v + half, top)] if finite else None)
                out["step"].append(st)
                tol = settings.mu_tol if kind == "mu" else settings.cor_tol
            if not finite:
                reason = "not determined: the loss is flat along it"
            elif slides is not None and not slides[i]:
                reason = "not determined: no training impact slides (sticking bounds mu below)"
            elif lop:
                reason = "one-sided: the data bound it from one side only"
            elif half > tol:
                reason = "not determined: 95 % interval wider than the tolerance"
            elif abs(st) > tol:
                reason = "not stable: the data would move it beyond the tolerance"
            elif better is not None and better[i] is not None:
                where, change = better[i]
                reason = f"not at its best: the loss is {-100 * change:.1f} % lower at {where:.3g}"
            else:
                reason = ""
            out["determined"].append(reason == "")
            out["reason"].append(reason)
        return out

    sm_, _, smu, scor = layout.slices()
    return {
        "method": (
            "Laplace approximation of the absolute-error loss (Fisher information "
            "J^T J / b^2, b = mean |r|; J by finite differences; potential network held fixed)"
        ),
        "n_residuals": n_res,
        "n_parameters": p,
        "residual_mean_abs": b,
        "mass_ratios": report(sm_, "mass_ratios"),  # bodies 2..B
        "mu": report(smu, "mu", mu_slides, mu_better),
        "cor": report(scor, "cor"),
        "tolerances": {
            "mass_ratio_relative": settings.mass_ratio_tol,
            "mu": settings.mu_tol,
            "cor": settings.cor_tol,
        },
    }


def contact_regimes(model: Any, chunks: Tensor, *, rtol: float = 1e-6) -> dict[str, list[int]]:
    """How often each candidate contact is active in the training states, and how.

    Each state of each chunk but the last is stepped once with the learned
    model (the smooth step, then the contact model); every active contact is
    counted as ``sliding`` (the impulse of the compression or the restitution
    phase is on the cone's boundary: ``|f_t| >= mu f_n (1 - rtol)`` with
    ``f_n > 0``), ``sticking`` (a phase pushes, neither slides) or ``separating``
    (no normal impulse: ``f_n <= rtol`` times the largest one). Frictionless
    contacts (contact dimension 1) count as sliding.

    Args:
        model: a physical learned model (:func:`supports_uncertainty`).
        chunks: ``(n, L, 2, P, dim)``.
        rtol: relative tolerance of the classification.

    Returns:
        ``{"impacts": [...], "sliding": [...], "sticking": [...], "separating": [...]}``,
        one count per candidate contact.
    """
    if not supports_uncertainty(model):
        raise ValueError(f"{type(model).__name__} is not a physical model")
    system = model.system
    K = system.n_contacts
    chunks = chunks.detach().to(torch.float64)
    chunks = chunks[torch.isfinite(chunks.flatten(1)).all(1)]
    device = next((p.device for p in model.parameters()), torch.device("cpu"))
    z = chunks[:, :-1].reshape(-1, *chunks.shape[2:]).to(device)
    counts = {
        name: np.zeros(K, dtype=np.int64)
        for name in ("impacts", "sliding", "sticking", "separating")
    }
    if z.shape[0] == 0 or K == 0:
        return {k: v.tolist() for k, v in counts.items()}
    with torch.no_grad():
        params = model.physical_params()
        z1 = system.integrate(z, params=params, dynamics=model.dynamics)
        res = system.resolve_contacts(z1, params=params, contact_model=model.contact_model)
        idx, act = res.contact_index, res.active
        if idx.numel() == 0:
            return {k: v.tolist() for k, v in counts.items()}
        mu = params.mu.detach().double().expand(K)[idx]
        f_c, f_r = res.f_c.double(), res.f_r.double()  # (n, Ka, d) each
        scale = float(torch.maximum(f_c[..., 0].abs().max(), f_r[..., 0].abs().max()))
        scale = max(scale, 1e-300)

        def on_boundary(f: Tensor) -> Tensor:  # a phase's impulse pushes and slides
            f_n = f[..., 0]
            f_t = f[..., 1:].norm(dim=-1) if f.shape[-1] > 1 else torch.zeros_like(f_n)
            return (f_n > rtol * scale) & (f_t >= mu * f_n * (1 - rtol))

        pushes = (f_c[..., 0] > rtol * scale) | (f_r[..., 0] > rtol * scale)
        separating = act & ~pushes
        sliding = act & pushes & (on_boundary(f_c) | on_boundary(f_r))
        sticking = act & pushes & ~sliding
        for name, mask in (
            ("impacts", act), ("sliding", sliding), ("sticking", sticking),
            ("separating", separating),
        ):  # fmt: skip
            counts[name] = torch.bincount(idx[mask].cpu(), minlength=K).numpy()
    return {k: v.tolist() for k, v in counts.items()}
