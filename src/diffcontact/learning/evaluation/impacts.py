"""Impacts in the test data and what the model predicts for them (``impacts.png``).

Does the contact model reproduce the data's impacts? For every test trajectory,
:func:`first_impacts` finds the first step ``t -> t + 1`` across which a
contact closes and its normal velocity jumps (an impact in the data, whether
simulated or recorded), and :func:`impact_ratios` compares, for that contact,
the observed normal velocity ratio

    r_obs  = u_n(t + 1) / -u_n(t)

with the model's one step from the same observed state ``z_t``:

    r_pred = u_n^model(t + 1) / -u_n(t)

where ``u_n`` is the contact's normal velocity (the rate of its gap,
``System.contact_velocities``). For a point mass hitting a wall with the
textbook impact law, ``r_obs`` is the Newton coefficient of restitution;
CM's maximum-dissipation cone QP adds a separation velocity of about
``mu |u_t|`` in sliding impacts (docs/training.md, "What the learned e_P and mu
mean"), so ``r_pred`` grows with the slip ratio ``|u_t| / |u_n|``, which the
second panel of the plot shows.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["ImpactSteps", "first_impacts", "impact_ratios", "impact_summary", "plot_impacts"]

CLOSING_STEPS = 1.5
"""A contact can close within a step when ``gap(t) <= CLOSING_STEPS * |u_n(t)| dt``."""
MIN_JUMP = 0.5
"""An impact raises the normal velocity by at least ``MIN_JUMP * |u_n(t)|`` in one step."""
MIN_SPEED = 0.05
"""...and approaches at ``|u_n(t)| >= MIN_SPEED`` times the data's RMS point speed."""


@dataclass
class ImpactSteps:
    """The first impact of each trajectory that has one.

    Attributes:
        trajectory: ``(M,)`` indices into the trajectories.
        step: ``(M,)`` the pre-impact state ``t`` (the impact lies in ``t -> t + 1``).
        contact: ``(M,)`` the candidate contact.
    """

    trajectory: np.ndarray
    step: np.ndarray
    contact: np.ndarray


def first_impacts(system: Any, traj: np.ndarray) -> ImpactSteps:
    """The first impact step and contact of every trajectory (those without one are left out).

    A step ``t -> t + 1`` holds an impact at contact ``k`` when ``k`` approaches
    (``u_n(t) <= -MIN_SPEED v_rms``), can close within the step (``gap(t) <=
    CLOSING_STEPS |u_n(t)| dt``) and its normal velocity jumps (``u_n(t + 1) -
    u_n(t) >= MIN_JUMP |u_n(t)|``). Of several contacts in the same step the
    fastest-approaching one is taken.

    Args:
        system: the :class:`~diffcontact.systems.System` (geometry and ``dt``).
        traj: ``(N, T, 2, P, dim)`` observed trajectories.
    """
    z = torch.as_tensor(np.asarray(traj), dtype=torch.float64)
    N, T = z.shape[:2]
    empty = np.zeros(0, dtype=np.int64)
    if N == 0 or T < 2:
        return ImpactSteps(empty, empty, empty)
    with torch.no_grad():
        gaps = system.gaps(z[:, :, 0]).numpy()  # (N, T, K)
        u_n = system.contact_velocities(z)[..., 0].numpy()  # (N, T, K)
    v = z[:, :, 1].numpy()
    v_rms = float(np.sqrt(np.mean(np.sum(v * v, axis=-1))))
    pre, post = u_n[:, :-1], u_n[:, 1:]
    speed = -pre
    hit = (
        (speed >= MIN_SPEED * v_rms)
        & (speed > 0)
        & (gaps[:, :-1] <= CLOSING_STEPS * speed * system.dt)
        & (post - pre >= MIN_JUMP * speed)
    )  # (N, T-1, K)
    any_step = hit.any(-1)  # (N, T-1)
    has = any_step.any(-1)
    rows = np.flatnonzero(has)
    steps = any_step[rows].argmax(-1)
    score = np.where(hit[rows, steps], speed[rows, steps], -np.inf)  # (M, K)
    contacts = score.argmax(-1)
    return ImpactSteps(rows.astype(np.int64), steps.astype(np.int64), contacts.astype(np.int64))


def impact_ratios(
    system: Any, model: Any, traj: np.ndarray, device: Any = "cpu", simulate: Any = None
) -> dict[str, np.ndarray]:
    """Observed and predicted normal velocity ratios of each test trajectory's first impact.

    Args:
        system: the dataset's :class:`~diffcontact.systems.System`.
        model: has ``simulate(z0, steps)`` (``(M, 2, P, dim)`` -> ``(M, steps + 1, ...)``).
        traj: ``(N, T, 2, P, dim)`` observed test trajectories.
        device: where the model runs.
        simulate: ``simulate(z0, steps) -> (M, steps + 1, 2, P, dim)`` used instead of
            ``model.simulate`` (evaluation passes one that returns NaN for states whose
            contact solve fails).

    Returns:
        Arrays of shape ``(M,)``, one entry per impact: ``trajectory``, ``step``,
        ``contact``, ``u_n_pre`` (negative), ``u_n_post`` (observed),
        ``u_n_pred`` (the model's step from the observed pre-impact state),
        ``u_t_pre`` (tangential speed before, 0 for one-row contacts),
        ``ratio_observed`` and ``ratio_predicted`` (``u_n_post / -u_n_pre``).
    """
    found = first_impacts(system, traj)
    M = found.trajectory.size
    z = torch.as_tensor(np.asarray(traj), dtype=torch.float64)
    out: dict[str, np.ndarray] = {
        "trajectory": found.trajectory,
        "step": found.step,
        "contact": found.contact,
    }
    if M == 0:
        for key in ("u_n_pre", "u_n_post", "u_n_pred", "u_t_pre"):
            out[key] = np.zeros(0)
        out["ratio_observed"] = out["ratio_predicted"] = np.zeros(0)
        return out
    rows, steps, k = (torch.from_numpy(a) for a in (found.trajectory, found.step, found.contact))
    z_pre, z_post = z[rows, steps], z[rows, steps + 1]  # (M, 2, P, dim)
    with torch.no_grad():
        if simulate is None:  # the data's states, which a recording may hold penetrating
            from diffcontact.learning.evaluation.evaluate import simulate_data_states

            def simulate(z: torch.Tensor, n: int) -> Any:
                return simulate_data_states(model, z, n)

        run = simulate
        pred = torch.as_tensor(run(z_pre.to(device), 1))[:, 1].detach().to("cpu", torch.float64)
        take = k[:, None]
        u_pre = system.contact_velocities(z_pre)[torch.arange(M), k]  # (M, d)
        u_post = system.contact_velocities(z_post).gather(
            1, take[..., None].expand(M, 1, system.d)
        )[:, 0, 0]
        u_pred = system.contact_velocities(pred).gather(1, take[..., None].expand(M, 1, system.d))[
            :, 0, 0
        ]
    speed = -u_pre[:, 0]
    out.update(
        u_n_pre=u_pre[:, 0].numpy(),
        u_n_post=u_post.numpy(),
        u_n_pred=u_pred.numpy(),
        u_t_pre=u_pre[:, 1:].norm(dim=-1).numpy(),
        ratio_observed=(u_post / speed).numpy(),
        ratio_predicted=(u_pred / speed).numpy(),
    )
    return out


def impact_summary(ratios: dict[str, np.ndarray]) -> dict[str, Any]:
    """``metrics.json``'s ``impacts``: counts, means and the mean predicted - observed gap.

    ``n_found``: the impacts found in the data (first impacts of the test trajectories);
    ``n_predicted``: those where the model's step from the pre-impact state is finite.
    ``ratio_observed_mean`` is over every impact found, whatever the model; the predicted
    mean and the errors (each prediction against its own observation) are over the
    ``n_predicted`` impacts. Means without an impact to average are ``None``.
    """
    obs, pred = ratios["ratio_observed"], ratios["ratio_predicted"]
    seen = np.isfinite(obs)
    ok = seen & np.isfinite(pred)
    diff = pred[ok] - obs[ok]

    def mean(x: np.ndarray) -> float | None:
        return float(x.mean()) if x.size else None

    return {
        "n_found": int(obs.size),
        "n_predicted": int(ok.sum()),
        "ratio_observed_mean": mean(obs[seen]),
        "ratio_predicted_mean": mean(pred[ok]),
        "ratio_error_mean": mean(diff),
        "ratio_error_abs_mean": mean(np.abs(diff)),
    }


def plot_impacts(ratios: dict[str, np.ndarray], path: Path, title: str) -> Path:
    """Left: predicted against observed normal velocity ratio, one point per impact with a
    finite prediction. Right: both against the slip ratio ``|u_t| / |u_n|`` before the
    impact (every observed impact; the model's where finite). The titles count the impacts
    found and those the model predicted (a diverged step is left out and said so)."""
    from diffcontact.learning.evaluation.plots import _figure, _save

    obs, pred = ratios["ratio_observed"], ratios["ratio_predicted"]
    slip = ratios["u_t_pre"] / -ratios["u_n_pre"]
    seen = np.isfinite(obs)
    ok = seen & np.isfinite(pred)
    n_found, n_ok = int(obs.size), int(ok.sum())
    fig = _figure(10.0, 4.0)
    ax1, ax2 = fig.subplots(1, 2)
    ax1.scatter(obs[ok], pred[ok], s=14, color="#1f77b4", alpha=0.8, lw=0)
    if n_ok:
        lo = min(0.0, float(obs[ok].min()), float(pred[ok].min()))
        hi = max(1.0, float(obs[ok].max()), float(pred[ok].max()))
        ax1.plot([lo, hi], [lo, hi], color="#555555", lw=1.0, ls="--", label="predicted = observed")
        ax1.legend(fontsize=8, loc="upper left")
    ax1.set_xlabel(r"observed $u_n^+ / |u_n^-|$")
    ax1.set_ylabel(r"predicted $u_n^+ / |u_n^-|$")
    found = f"{n_found} first {'impact' if n_found == 1 else 'impacts'} of the test trajectories"
    if n_ok < n_found:
        found += f", {n_ok} with a finite prediction"
    ax1.set_title(f"{found}; model: one step", fontsize=10)
    ax2.scatter(slip[seen], obs[seen], s=16, color="#444444", label="observed", lw=0)
    ax2.scatter(slip[ok], pred[ok], s=22, facecolors="none", edgecolors="#d62728", label="model")
    ax2.set_xlabel(r"slip ratio $|u_t^-| / |u_n^-|$ before the impact")
    ax2.set_ylabel(r"normal velocity ratio $u_n^+ / |u_n^-|$")
    ax2.set_title("restitution against sliding", fontsize=10)
    ax2.legend(fontsize=8)
    for ax in (ax1, ax2):
        ax.grid(True, lw=0.3, alpha=0.6)
    if not n_found:
        ax1.text(0.5, 0.5, "no impact found in the test trajectories", ha="center",
                 va="center", transform=ax1.transAxes)  # fmt: skip
    elif not n_ok:
        ax1.text(
            0.5, 0.5, f"{n_found} {'impact' if n_found == 1 else 'impacts'} found; the model's "
            "step diverged\n(non-finite) for every one", ha="center", va="center",
            transform=ax1.transAxes, color="#b00000",
        )  # fmt: skip
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)
