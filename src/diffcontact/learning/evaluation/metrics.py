"""Evaluation metrics (``docs/evaluation.md`` has the definitions).

Pure functions, numpy in and numpy out (torch tensors are accepted):

- :func:`relative_error`: ``||z_pred - z_true|| / ||z_true||`` per trajectory
  and step, the norm over the whole state ``(2, P, dim)``;
- :func:`mean_ci95`: mean and the half-width of a Student-t 95% confidence
  interval over independent samples (the per-trajectory mean errors);
- :func:`energy_rel_drift`: the *true* energy along predicted and true
  trajectories, relative to the true initial energy (both over the same trajectories);
- :func:`true_parameters`: mass ratios ``m_i / m_1`` (i >= 2), ``mu`` and ``e_P``
  per contact (contact numbering of ``docs/conventions.md``);
- :func:`rollout_steps`: the length of an evaluation rollout.

torch is imported only by the functions that evaluate a system's energy.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = [
    "MIN_EVAL_STATES",
    "as_numpy",
    "energy_drifts",
    "energy_rel_drift",
    "energy_scale",
    "finite_mean",
    "finite_rows",
    "mean_ci95",
    "relative_drift",
    "relative_error",
    "rollout_steps",
    "t_quantile_975",
    "true_energy",
    "true_parameters",
]

MIN_EVAL_STATES = 100  # paper-facts.md: roll out for max(horizon, 100 dt)


def as_numpy(x: Any) -> np.ndarray:
    """``x`` (numpy, torch or nested lists) as a float64 numpy array."""
    if hasattr(x, "detach"):  # torch tensor, without importing torch
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def relative_error(pred: Any, true: Any) -> np.ndarray:
    """Relative error of predicted states: ``||z_pred - z_true|| / ||z_true||``.

    The norm is the Euclidean norm over the whole state (positions and
    velocities of all points, ``2 * P * dim`` numbers).

    Args:
        pred: ``(N, T, 2, P, dim)`` predicted trajectories (numpy or torch;
            any leading dims work, the last three are the state).
        true: same shape, the ground truth.

    Returns:
        ``(N, T)`` float64. NaN/inf where the prediction is not finite or the
        true state is zero.
    """
    p, t = as_numpy(pred), as_numpy(true)
    if p.shape != t.shape:
        raise ValueError(f"pred and true must have the same shape, got {p.shape} and {t.shape}")
    if p.ndim < 3:
        raise ValueError(f"expected states (..., 2, P, dim), got shape {p.shape}")
    lead = p.shape[:-3]
    num = np.linalg.norm((p - t).reshape(*lead, -1), axis=-1)
    den = np.linalg.norm(t.reshape(*lead, -1), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return num / den


# two-sided 95% Student-t quantiles t_{0.975, df} for df = 1..30
_T975 = (
    12.706205, 4.302653, 3.182446, 2.776445, 2.570582, 2.446912, 2.364624, 2.306004,
    2.262157, 2.228139, 2.200985, 2.178813, 2.160369, 2.144787, 2.131450, 2.119905,
    2.109816, 2.100922, 2.093024, 2.085963, 2.079614, 2.073873, 2.068658, 2.063899,
    2.059539, 2.055529, 2.051831, 2.048407, 2.045230, 2.042272,
)  # fmt: skip
_Z975 = 1.959963984540054


def t_quantile_975(df: int) -> float:
    """The 0.975 quantile of Student's t with ``df`` degrees of freedom.

    Tabulated for ``df <= 30``; above, the Cornish-Fisher expansion (error
    below 1e-7). ``nan`` for ``df < 1``.
    """
    if df < 1:
        return math.nan
    if df <= len(_T975):
        return _T975[df - 1]
    z, n = _Z975, float(df)
    return (
        z
        + (z**3 + z) / (4 * n)
        + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * n**2)
        + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * n**3)
        + (79 * z**9 + 776 * z**7 + 1482 * z**5 - 1920 * z**3 - 945 * z) / (92160 * n**4)
    )


def mean_ci95(x: Any, axis: int = 0) -> tuple[Any, Any]:
    """Sample mean and the half-width of its 95% confidence interval.

    The interval is Student-t: ``t_{0.975, n-1} * s / sqrt(n)`` with ``s`` the
    sample standard deviation (``ddof=1``) of the ``n`` samples along ``axis``.
    For the headline number pass one value per test trajectory (its mean error
    over time), so the samples are independent; passing ``(N, T)`` errors with
    ``axis=0`` gives the mean and band per time step.

    Args:
        x: samples, e.g. ``(N,)`` or ``(N, T)``.
        axis: the axis of the samples.

    Returns:
        ``(mean, halfwidth)``: floats for 1-d input, else arrays of the other
        dims. The half-width is ``nan`` for a single sample. Non-finite
        samples propagate (filter them first).
    """
    a = np.moveaxis(as_numpy(x), axis, 0)
    n = a.shape[0]
    if n == 0:
        raise ValueError("mean_ci95 needs at least one sample")
    mean = a.mean(0)
    if n == 1:
        half = np.full_like(mean, np.nan)
    else:
        half = t_quantile_975(n - 1) * a.std(0, ddof=1) / math.sqrt(n)
    if np.ndim(mean) == 0:
        return float(mean), float(half)
    return mean, half


def rollout_steps(system: Any) -> int:
    """Steps of an evaluation rollout: ``max(horizon / dt, 100) - 1``.

    The rollout then holds ``max(horizon, 100 dt) / dt`` states, the first
    being the test initial state (paper-facts.md, "Training set-up").
    """
    return max(round(system.horizon / system.dt), MIN_EVAL_STATES) - 1


def true_energy(system: Any, traj: Any) -> np.ndarray:
    """Energy of the true system along trajectories (no gradient, float64).

    Args:
        system: the ground-truth ``System`` (its ``energy``).
        traj: ``(..., 2, P, dim)`` states, e.g. ``(N, T, 2, P, dim)``.

    Returns:
        ``(...)`` float64 numpy, e.g. ``(N, T)``.
    """
    import torch

    z = torch.as_tensor(as_numpy(traj), dtype=torch.float64)
    with torch.no_grad():
        return system.energy(z).detach().cpu().numpy().astype(np.float64)


def energy_scale(system: Any, true: Any) -> float:
    """The energy unit of the drift metrics: the mean kinetic energy of the true motion.

    ``mean over n and t of T(true[n, t])``. Unlike ``E(0)`` it does not depend
    on the potential's arbitrary zero (the pendulum's pivot height), it is
    positive whenever anything moves, and unlike the *initial* kinetic energy
    it includes what a fall converts from potential energy (a pendulum
    released nearly at rest).

    Args:
        system: the ground-truth ``System`` (its ``kinetic_energy``).
        true: ``(N, T, 2, P, dim)`` true trajectories.
    """
    import torch

    z = torch.as_tensor(as_numpy(true), dtype=torch.float64)
    with torch.no_grad():
        T = system.kinetic_energy(z).detach().cpu().numpy().astype(np.float64)
    return float(np.mean(T)) if T.size else math.nan


def relative_drift(E: np.ndarray, E0: np.ndarray, scale: float) -> np.ndarray:
    """``|E[n, t] - E0[n]| / scale``; all NaN when ``scale`` is not positive."""
    if not (scale > 0 and math.isfinite(scale)):
        return np.full(E.shape, np.nan)
    return np.abs(E - E0[:, None]) / scale


def finite_mean(curves: np.ndarray) -> float:
    """Mean over the rows that are finite at every step of their per-row means."""
    ok = np.isfinite(curves).all(-1)
    return float(curves[ok].mean()) if ok.any() else math.nan


def finite_rows(*curves: np.ndarray) -> np.ndarray:
    """``(N,)``: the rows finite at every step in every one of ``curves`` (each ``(N, T)``).

    The model's and the truth's energy metrics are means over these same rows: a
    diverged rollout leaves its trajectory out of both, not only of the model's.
    """
    ok = np.ones(len(curves[0]), dtype=bool)
    for c in curves:
        ok &= np.isfinite(c).all(-1)
    return ok


def energy_drifts(
    E_pred: np.ndarray, E_true: np.ndarray, scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(drift_pred, drift_true, rows)``: the relative drifts ``(N, T)`` of the true energy
    along predicted and true trajectories (:func:`relative_drift` from ``E_true[:, 0]``),
    and the ``(N,)`` trajectories where both are finite (:func:`finite_rows`), over which
    both are averaged."""
    E0 = E_true[:, 0]
    drift_pred = relative_drift(E_pred, E0, scale)
    drift_true = relative_drift(E_true, E0, scale)
    return drift_pred, drift_true, finite_rows(drift_pred, drift_true)


def energy_rel_drift(system: Any, pred: Any, true: Any) -> dict[str, Any]:
    """Relative drift of the true energy along predicted and true trajectories.

    With ``E`` the true system's energy, ``E0[n] = E(true[n, 0])`` and
    ``scale`` the mean kinetic energy along the true trajectories (:func:`energy_scale`)::

        drift_X[n, t] = |E(X[n, t]) - E0[n]| / scale,   X in {pred, true}
        result[X]     = mean over n of (mean over t = 0..T-1 of drift_X[n, t])

    Both means are over the same trajectories: those where both drifts are finite (a
    diverged prediction leaves its trajectory out of both), ``n`` of them. For an
    energy-conserving task both numbers should be ~0 (``true`` measures the
    simulator's own drift); for a dissipative task ``true`` is the real energy
    loss and ``pred`` should match it.

    Args:
        system: the ground-truth ``System``.
        pred, true: ``(N, T, 2, P, dim)``.

    Returns:
        ``{"pred": float, "true": float, "n": int}`` (NaN means when ``n`` is 0).
    """
    p, t = as_numpy(pred), as_numpy(true)
    if p.shape != t.shape or p.ndim != 5:
        raise ValueError(f"pred and true must both be (N, T, 2, P, dim), got {p.shape}, {t.shape}")
    E_pred, E_true = true_energy(system, p), true_energy(system, t)
    drift_pred, drift_true, rows = energy_drifts(E_pred, E_true, energy_scale(system, t))
    return {
        "pred": finite_mean(drift_pred[rows]),
        "true": finite_mean(drift_true[rows]),
        "n": int(rows.sum()),
    }


def true_parameters(system: Any) -> dict[str, list[float]]:
    """The physical parameters a model should learn, as plain numbers.

    Args:
        system: a ``System`` (or anything ``load_system`` accepts).

    Returns:
        ``mass_ratios``: ``m_i / m_1`` for bodies 2..B (Tables S.1-S.3; empty
        for one body); ``mu`` and ``cor``: one value per candidate contact in
        the contact numbering of ``docs/conventions.md``.
    """
    if not hasattr(system, "mass"):
        from diffcontact.systems import load_system

        system = load_system(system)
    m = as_numpy(system.mass).reshape(-1)
    K = int(system.n_contacts)
    return {
        "mass_ratios": (m[1:] / m[0]).tolist(),
        "mu": np.broadcast_to(as_numpy(system.mu), (K,)).tolist(),
        "cor": np.broadcast_to(as_numpy(system.cor), (K,)).tolist(),
    }
