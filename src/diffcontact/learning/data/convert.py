"""Converters: recorded data in other forms to diffcontact's layout (``docs/own-data.md``).

``diffcontact generate --from-arrays`` takes trajectories ``z: (N, T, 2, P, d)``:
positions then velocities of the config's P points (extended bodies: centre of
mass and axis points, ``docs/conventions.md``). Recorded data rarely comes like
that. This module builds ``z`` from

- **positions only** (:func:`trajectories_from_positions`): velocities by
  finite differences (:func:`finite_difference_velocities`), with the samples
  where an impact between samples makes them unreliable found by
  :func:`velocity_jumps`;
- **generalised coordinates** of the built-in system types
  (:func:`trajectories_from_coordinates`): disk centres and angles, chain
  angles, gyroscope orientations (quaternion or rotation matrix) and angular
  velocities, through :mod:`diffcontact.mechanics.bodies`
  (:func:`~diffcontact.mechanics.bodies.disk_points_2d`,
  :func:`~diffcontact.mechanics.bodies.chain_points_2d`,
  :func:`~diffcontact.mechanics.bodies.rigid_body_points_3d`,
  :func:`~diffcontact.mechanics.bodies.quaternion_to_matrix`);
- **MuJoCo** ``qpos``/``qvel``: :mod:`diffcontact.learning.data.mujoco`.

:func:`trajectory_checks` measures what to check after converting (constraint
residuals, overlaps). Arrays go in as numpy arrays or torch tensors and come
out as the same kind (numpy: float64; torch: the input's dtype and device).

Finite differences (``dt`` the sampling step, ``x_t`` the samples)::

    v_0     = (-3 x_0 + 4 x_1 - x_2) / (2 dt)          one-sided, second order
    v_t     = (x_{t+1} - x_{t-1}) / (2 dt)              central, second order
    v_{T-1} = (3 x_{T-1} - 4 x_{T-2} + x_{T-3}) / (2 dt)

all with error ``O(dt^2)`` on smooth motion (``dt^2 |x'''| / 6`` inside,
``dt^2 |x'''| / 3`` at the ends). Across an impact the velocity jumps and no
difference of positions can see where: the velocities of the states whose
stencil straddles the impact are a blend of the pre- and post-impact ones.
"""

from __future__ import annotations

import math
import warnings
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from diffcontact.learning.data.checks import DT_RTOL
from diffcontact.mechanics.bodies import (
    chain_points_2d,
    disk_points_2d,
    quaternion_to_matrix,
    rigid_body_points_3d,
)

__all__ = [
    "JUMP_FACTOR",
    "JUMP_RELATIVE",
    "MIN_JUMP_SAMPLES",
    "VelocityJumps",
    "finite_difference_velocities",
    "trajectories_from_coordinates",
    "trajectories_from_positions",
    "trajectory_checks",
    "velocity_jumps",
    "velocity_mismatch",
]

JUMP_FACTOR = 10.0
"""Automatic jump threshold: this many times the median jump statistic of the data..."""
JUMP_RELATIVE = 0.05
"""... and at least this share of the RMS speed per time step (``0.01 * v_rms / dt``)."""
ON_JUMP = ("warn", "raise", "ignore")
VELOCITY_MISMATCH_WARN = 0.25
"""Given rates whose :func:`velocity_mismatch` is above this get a warning."""
# predictions of a second difference D2_t from D2_{t+k}: {k: weight}; polynomial
# interpolation / extrapolation in time (error O(dt^4) for the first three, O(dt^5) and
# O(dt^6) for the others where the motion is smooth)
_PREDICTORS: tuple[dict[int, float], ...] = (
    {-2: 0.5, 2: 0.5},
    {-2: 2.0, -4: -1.0},
    {2: 2.0, 4: -1.0},
    {-4: -1 / 6, -2: 2 / 3, 2: 2 / 3, 4: -1 / 6},
    {-2: 3.0, -4: -3.0, -6: 1.0},
    {2: 3.0, 4: -3.0, 6: 1.0},
)
MIN_JUMP_SAMPLES = 8
"""Fewest samples per trajectory :func:`velocity_jumps` needs (6 second differences)."""


# --------------------------------------------------------------------------- inputs
def _tensor(a: Any, name: str) -> tuple[Tensor, bool]:
    """``a`` as a float tensor, and whether it came as a numpy array (or a list)."""
    if isinstance(a, Tensor):
        t = a.detach() if not a.requires_grad else a
        return (t if t.is_floating_point() else t.to(torch.float64)), False
    try:
        arr = np.asarray(a)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be a numeric array: {err}") from None
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name} must be a numeric array, got dtype {arr.dtype}")
    return torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float64)), True


def _output(t: Tensor, numpy_out: bool) -> Any:
    return t.detach().cpu().numpy() if numpy_out else t


def _check_finite(t: Tensor, name: str) -> None:
    bad = ~torch.isfinite(t.detach()).flatten(2).all(-1)
    if bool(bad.any()):
        rows, cols = bad.nonzero(as_tuple=True)
        where = ", ".join(
            f"trajectory {r} sample {c}"
            for r, c in zip(rows[:5].tolist(), cols[:5].tolist(), strict=True)
        )
        raise ValueError(f"{name} contains NaN or infinite values at {where}")


def _check_shape(t: Tensor, name: str, tail: tuple[int, ...], meaning: str) -> None:
    want = "(N, T" + "".join(f", {n}" for n in tail) + ")"
    if t.dim() != 2 + len(tail) or tuple(t.shape[2:]) != tail:
        hint = ""
        if t.dim() == 1 + len(tail) and tuple(t.shape[1:]) == tail:
            hint = " (a single trajectory? add a leading axis: a[None])"
        raise ValueError(f"{name} must have shape {want} ({meaning}); got {tuple(t.shape)}{hint}")
    if t.shape[0] == 0:
        raise ValueError(f"{name} holds no trajectory (shape {tuple(t.shape)})")


def _check_samples(t: Tensor, name: str, least: int) -> None:
    """``t (N, T, ...)`` holds a trajectory and at least ``least`` samples in each (``T = 0``
    gave torch's "max(): Expected reduction dim" in the checks after the conversion)."""
    if t.shape[0] == 0:
        raise ValueError(f"{name} holds no trajectory (shape {tuple(t.shape)})")
    if t.shape[1] < least:
        samples = "sample" if least == 1 else "samples"
        raise ValueError(
            f"{name} needs T >= {least} {samples} per trajectory; got {t.shape[1]} (shape "
            f"{tuple(t.shape)})"
        )


def _check_dt(dt: float | None, system: Any) -> float:
    if dt is None:
        if system is None:
            raise ValueError("give dt (the sampling step) or a config whose dt is the step")
        return float(system.dt)
    try:
        dt_f = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a positive number, got {dt!r}") from None
    if not (dt_f > 0 and math.isfinite(dt_f)):
        raise ValueError(f"dt must be a positive number, got {dt!r}")
    if system is not None and not math.isclose(dt_f, system.dt, rel_tol=DT_RTOL, abs_tol=1e-12):
        raise ValueError(
            f"dt={dt_f!r} of the data differs from the config's dt={system.dt!r}; models step "
            "with the config's dt: set dt in the config to the recording's step (or resample)"
        )
    return dt_f


def _system(config: Any) -> Any:
    from diffcontact.systems import System, load_system

    return config if isinstance(config, System) else load_system(config)


# ----------------------------------------------------------------- finite differences
def finite_difference_velocities(x: Any, dt: float) -> Any:
    """Velocities of sampled positions by second-order finite differences.

    Central differences ``(x_{t+1} - x_{t-1}) / (2 dt)`` inside, the one-sided
    second-order differences ``(-3 x_0 + 4 x_1 - x_2) / (2 dt)`` and
    ``(3 x_{T-1} - 4 x_{T-2} + x_{T-3}) / (2 dt)`` at the ends: error ``O(dt^2)``
    where the motion is smooth. Wrong across impacts (see :func:`velocity_jumps`).

    Args:
        x: ``(N, T, ...)`` positions (any trailing shape, e.g. ``(N, T, P, d)``), time
            along axis 1, ``T >= 3``; numpy array or torch tensor (differentiable).
        dt: the sampling step.

    Returns:
        ``(N, T, ...)`` velocities, same kind (numpy/torch), dtype and device as ``x``.
    """
    t, numpy_out = _tensor(x, "positions")
    dt = _check_dt(dt, None)
    if t.dim() < 2 or t.shape[1] < 3:
        raise ValueError(
            f"positions must have shape (N, T, ...) with T >= 3 samples for second-order "
            f"differences; got {tuple(t.shape)}"
        )
    inner = (t[:, 2:] - t[:, :-2]) / (2 * dt)
    first = (-3 * t[:, 0] + 4 * t[:, 1] - t[:, 2]) / (2 * dt)
    last = (3 * t[:, -1] - 4 * t[:, -2] + t[:, -3]) / (2 * dt)
    v = torch.cat([first[:, None], inner, last[:, None]], dim=1)
    return _output(v, numpy_out)


class VelocityJumps(NamedTuple):
    """Where the positions show a velocity jump (an impact) between samples.

    Attributes:
        jump: ``(N, T)`` bool, True at sample t when the second difference of some
            point at t departs from those at t - 2 and t + 2 by more than
            ``threshold``: an impact happened in ``(t - 1, t + 1)``.
        unreliable: ``(N, T)`` bool, True where the finite-difference velocity's
            stencil may straddle such an impact (``jump`` widened by one sample
            each side): those velocities blend pre- and post-impact ones.
        threshold: the threshold used (units of acceleration).
    """

    jump: Any
    unreliable: Any
    threshold: float


def velocity_jumps(x: Any, dt: float, *, threshold: float | None = None) -> VelocityJumps:
    """Find the samples where positions show a velocity jump (an impact between samples).

    With ``D2_t = x_{t+1} - 2 x_t + x_{t-1}`` the second difference of each point, the
    statistic at sample t is ``min |D2_t - pred| / dt^2`` over the predictions
    ``(D2_{t-2} + D2_{t+2}) / 2``, ``2 D2_{t-2} - D2_{t-4}`` and ``2 D2_{t+2} - D2_{t+4}``
    (those that exist), maximised over the points: an impact spoils no prediction of
    the clean samples next to it. On smooth motion it is about ``2 dt^2 |x''''|``; an
    impact that changes a point's velocity by ``dv`` anywhere in ``(t_k, t_{k+1})``
    gives at least ``|dv| / (2 dt)`` at ``k`` or ``k + 1`` (``|dv| / dt`` when it falls
    on a sample, as in diffcontact's own data, where ``x_t`` is the position at the
    impact and ``v_t`` the velocity after it). The positions cannot show an impact at
    the last sample.

    Args:
        x: ``(N, T, P, d)`` positions (or ``(N, T, ..., d)``), ``T >= 8``.
        dt: the sampling step.
        threshold: flag where the statistic exceeds this (an acceleration); default
            ``max(JUMP_FACTOR * median, JUMP_RELATIVE * v_rms / dt)`` over the data
            (``v_rms`` the RMS finite-difference speed): velocity jumps above ~2 % of
            the typical speed are found, smooth curvature is not.

    Returns:
        :class:`VelocityJumps` (masks of the same kind as ``x``: numpy or torch).
    """
    t, numpy_out = _tensor(x, "positions")
    dt = _check_dt(dt, None)
    if t.dim() < 3 or t.shape[1] < MIN_JUMP_SAMPLES:
        raise ValueError(
            f"positions must have shape (N, T, ..., d) with T >= {MIN_JUMP_SAMPLES} samples "
            f"to find velocity jumps; got {tuple(t.shape)}"
        )
    t = t.detach()
    N, T, d = t.shape[0], t.shape[1], t.shape[-1]
    pts = t.reshape(N, T, -1, d)
    d2 = pts[:, 2:] - 2 * pts[:, 1:-1] + pts[:, :-2]  # (N, M, P, d), M = T-2, centred at 1..T-2
    M = d2.shape[1]
    # each second difference predicted from those 2, 4 and 6 samples away by polynomial
    # inter- and extrapolation (_PREDICTORS); the closest prediction counts, so that an
    # impact spoils no prediction of the clean samples next to it
    preds = []
    for weights in _PREDICTORS:
        lo, hi = min(weights), max(weights)
        lo_i, hi_i = max(0, -lo), M - max(0, hi)
        if hi_i <= lo_i:
            continue
        pred = torch.full_like(d2, math.inf)
        pred[:, lo_i:hi_i] = sum(w * d2[:, lo_i + k : hi_i + k] for k, w in weights.items())
        preds.append(d2 - pred)
    miss = torch.stack(preds).nan_to_num(math.inf, math.inf)
    stat = torch.linalg.vector_norm(miss, dim=-1).amin(0).amax(-1) / dt**2  # (N, M)
    if threshold is None:
        v = finite_difference_velocities(pts, dt)
        v_rms = float(torch.linalg.vector_norm(v, dim=-1).square().mean().sqrt())
        median = float(stat.median())
        threshold = max(JUMP_FACTOR * median, JUMP_RELATIVE * v_rms / dt)
    else:
        threshold = float(threshold)
        if not threshold >= 0:
            raise ValueError(f"threshold must be a non-negative number, got {threshold!r}")
    jump = torch.zeros((N, T), dtype=torch.bool, device=t.device)
    jump[:, 1:-1] = stat > threshold
    unreliable = jump.clone()
    unreliable[:, 1:] |= jump[:, :-1]
    unreliable[:, :-1] |= jump[:, 1:]
    return VelocityJumps(_output(jump, numpy_out), _output(unreliable, numpy_out), threshold)


def _report_jumps(x: Tensor, dt: float, threshold: float | None, on_jump: str) -> None:
    if on_jump not in ON_JUMP:
        raise ValueError(f"on_jump must be one of {', '.join(ON_JUMP)}; got {on_jump!r}")
    if on_jump == "ignore":
        return
    if x.shape[1] < MIN_JUMP_SAMPLES:
        warnings.warn(
            f"velocities by finite differences: trajectories of {x.shape[1]} samples are too "
            f"short (< {MIN_JUMP_SAMPLES}) to look for impacts between samples",
            RuntimeWarning,
            stacklevel=3,
        )
        return
    jumps = velocity_jumps(x, dt, threshold=threshold)
    n = int(jumps.jump.sum())
    if n == 0:
        return
    rows, cols = jumps.jump.nonzero(as_tuple=True)
    where = ", ".join(
        f"trajectory {r} sample {c}"
        for r, c in zip(rows[:5].tolist(), cols[:5].tolist(), strict=True)
    )
    more = f" and {n - 5} more" if n > 5 else ""
    message = (
        f"velocities by finite differences: the positions show {n} velocity jumps "
        f"(impacts between samples) at {where}{more}; the velocities of "
        f"{int(jumps.unreliable.sum())} states next to them blend pre- and post-impact "
        f"velocities (threshold {jumps.threshold:.3g}; velocity_jumps(x, dt).unreliable marks "
        "them). Record velocities if you can, or sample faster (docs/own-data.md)"
    )
    if on_jump == "raise":
        raise ValueError(message)
    warnings.warn(message, RuntimeWarning, stacklevel=3)


def trajectories_from_positions(
    x: Any,
    dt: float | None = None,
    config: Any = None,
    *,
    threshold: float | None = None,
    on_jump: str = "warn",
) -> Any:
    """Trajectories ``(N, T, 2, P, d)`` from positions alone (velocities by differences).

    Args:
        x: ``(N, T, P, d)`` positions of the config's points in diffcontact's layout
            (``docs/conventions.md``); ``T >= 3``.
        dt: the sampling step; default the config's, and checked against it.
        config: the system (task name, ``.yaml``/``.json`` path, dict or ``System``):
            checks ``P``, ``d`` and ``dt``. Optional when ``dt`` is given.
        threshold: for :func:`velocity_jumps`.
        on_jump: ``"warn"`` (default: a ``RuntimeWarning`` naming the samples where
            the positions show an impact between samples), ``"raise"`` (``ValueError``)
            or ``"ignore"``.

    Returns:
        ``z (N, T, 2, P, d)``: ``z[:, :, 0] = x``, ``z[:, :, 1]`` from
        :func:`finite_difference_velocities`; numpy or torch as ``x``.
    """
    t, numpy_out = _tensor(x, "positions")
    system = _system(config) if config is not None else None
    dt = _check_dt(dt, system)
    if system is not None:
        _check_shape(
            t, "positions", (system.n_points, system.dim), f"positions of the {system.n_points} "
            f"points of {system.name} in {system.dim}D",
        )  # fmt: skip
    elif t.dim() != 4:
        raise ValueError(f"positions must have shape (N, T, P, d); got {tuple(t.shape)}")
    _check_finite(t, "positions")
    if t.shape[1] < 3:
        raise ValueError(f"positions need T >= 3 samples per trajectory; got {t.shape[1]}")
    _report_jumps(t, dt, threshold, on_jump)
    v = finite_difference_velocities(t, dt)
    return _output(torch.stack([t, v], dim=2), numpy_out)


# ---------------------------------------------------------- generalised coordinates
def _unwrap(angle: Tensor) -> Tensor:
    """Angles along axis 1 made continuous (steps of more than pi are wrapped)."""
    step = torch.diff(angle, dim=1)
    wrapped = torch.remainder(step + math.pi, 2 * math.pi) - math.pi
    return torch.cat([angle[:, :1], angle[:, :1] + torch.cumsum(wrapped, dim=1)], dim=1)


def _vee(W: Tensor) -> Tensor:
    """The vector of the skew part of ``W (..., 3, 3)``: ``W x = omega x x``."""
    S = 0.5 * (W - W.transpose(-1, -2))
    return torch.stack([S[..., 2, 1], S[..., 0, 2], S[..., 1, 0]], dim=-1)


def _rotations(q: Tensor) -> Tensor:
    """``(N, T, 3, 3)`` rotations from quaternions ``(N, T, 4)`` or matrices, checked."""
    if q.dim() == 3 and q.shape[-1] == 4:
        norm = torch.linalg.vector_norm(q.detach(), dim=-1)
        worst = float((norm - 1).abs().max())
        if worst > 1e-3:
            raise ValueError(
                f"quaternions must have unit norm (w, x, y, z); the worst is off by {worst:.3g}"
            )
        return quaternion_to_matrix(q)
    if q.dim() == 4 and q.shape[-2:] == (3, 3):
        eye = torch.eye(3, dtype=q.dtype, device=q.device)
        ortho = float((q.detach().transpose(-1, -2) @ q.detach() - eye).abs().max())
        det = torch.linalg.det(q.detach())
        if ortho > 1e-4 or bool((det < 0).any()):
            raise ValueError(
                "orientations must be rotation matrices (orthonormal, det +1; columns are "
                f"the body axes in the world): max |R^T R - I| = {ortho:.3g}, min det = "
                f"{float(det.min()):.3g}"
            )
        return q
    raise ValueError(
        "gyroscope orientations must have shape (N, T, 4) (unit quaternions w, x, y, z) or "
        f"(N, T, 3, 3) (rotation matrices); got {tuple(q.shape)}"
    )


_COORDINATES = {
    "bouncing_masses": "q (N, T, B, 2) centres, qdot (N, T, B, 2) their velocities",
    "rope": "q (N, T, P, 2) point positions, qdot (N, T, P, 2) their velocities",
    "bouncing_disks": "q (N, T, B, 3) (x, y, angle) per disk, qdot (N, T, B, 3) "
    "(vx, vy, angular velocity)",
    "chain_pendulum": "q (N, T, L) absolute link angles from straight down, qdot (N, T, L)",
    "gyroscope": "q (N, T, 4) unit quaternions (w, x, y, z) or (N, T, 3, 3) rotation "
    "matrices, qdot (N, T, 3) angular velocity",
}


def trajectories_from_coordinates(
    config: Any,
    q: Any,
    qdot: Any = None,
    *,
    omega_frame: str = "world",
    threshold: float | None = None,
    on_jump: str = "warn",
) -> Any:
    """Trajectories ``(N, T, 2, P, d)`` from the generalised coordinates of a built-in type.

    Per system type (the config's ``type``):

    - ``bouncing_masses``, ``rope``: ``q (N, T, P, 2)`` the points themselves,
      ``qdot`` their velocities;
    - ``bouncing_disks``: ``q (N, T, B, 3)`` = centre x, y and angle a of each disk
      (body x axis ``(cos a, sin a)``), ``qdot (N, T, B, 3)`` = centre velocity and
      counter-clockwise angular velocity
      (:func:`~diffcontact.mechanics.bodies.disk_points_2d`);
    - ``chain_pendulum``: ``q (N, T, L)`` absolute link angles from straight down
      (``x_i = x_{i-1} + l_i (sin q_i, -cos q_i)``, link lengths and pivot from the
      config), ``qdot`` their rates (:func:`~diffcontact.mechanics.bodies.chain_points_2d`);
    - ``gyroscope``: ``q (N, T, 4)`` unit quaternions ``(w, x, y, z)`` or
      ``(N, T, 3, 3)`` rotation matrices (columns: body axes in the world; body axis 3
      is the symmetry axis, the pivot at the origin and the centre of mass at
      ``R (0, 0, com_distance)``), ``qdot (N, T, 3)`` the angular velocity
      (:func:`~diffcontact.mechanics.bodies.rigid_body_points_3d`).

    Args:
        config: task name, ``.yaml``/``.json`` path, dict or ``System``.
        q: generalised coordinates as above (numpy or torch).
        qdot: their rates; ``None``: finite differences of ``q`` (angles unwrapped
            first; the gyroscope's angular velocity from ``dR/dt R^T``), with impacts
            between samples reported as in :func:`trajectories_from_positions`.
        omega_frame: the gyroscope's angular velocity in ``"world"`` coordinates
            (default) or ``"body"`` coordinates (``omega_world = R omega_body``).
        threshold, on_jump: as in :func:`trajectories_from_positions` (used only when
            ``qdot`` is ``None``).

    Returns:
        ``z (N, T, 2, P, d)`` in the config's point layout, numpy or torch as ``q``.
    """
    system = _system(config)
    kind = system.type
    if kind not in _COORDINATES:
        raise ValueError(f"no generalised coordinates for system type {kind!r}")
    if omega_frame not in ("world", "body"):
        raise ValueError(f"omega_frame must be 'world' or 'body'; got {omega_frame!r}")
    if omega_frame == "body" and kind != "gyroscope":  # (was ignored)
        raise ValueError(
            f"omega_frame='body' applies to a gyroscope's angular velocity; a {kind} system "
            "has none"
        )
    qt, numpy_out = _tensor(q, "q")
    cfg, dt = system.config, float(system.dt)
    meaning = _COORDINATES[kind]
    B = system.n_bodies
    if kind in ("bouncing_masses", "rope"):
        _check_shape(qt, "q", (system.n_points, 2), meaning)
    elif kind == "bouncing_disks":
        _check_shape(qt, "q", (B, 3), meaning)
    elif kind == "chain_pendulum":
        _check_shape(qt, "q", (B,), meaning)
    if qt.dim() >= 2:  # (the gyroscope's q is checked by _rotations, once it holds samples)
        _check_samples(qt, "q", 1)
        if qdot is None and qt.shape[1] < 3:
            raise ValueError(
                "finite differences (qdot=None) need T >= 3 samples per trajectory; got "
                f"{qt.shape[1]}"
            )
    if kind == "gyroscope":
        R = _rotations(qt)
    _check_finite(qt if qt.dim() > 2 else qt[..., None], "q")

    def rates(shape: tuple[int, ...], angles: Tensor | None = None) -> Tensor:
        """qdot checked against ``shape``, or finite differences of ``angles``/``q``."""
        if qdot is None:
            return finite_difference_velocities(qt if angles is None else angles, dt)
        qd, _ = _tensor(qdot, "qdot")
        qd = qd.to(dtype=qt.dtype, device=qt.device)
        _check_shape(qd, "qdot", shape, meaning)
        if tuple(qd.shape[:2]) != tuple(qt.shape[:2]):
            raise ValueError(
                f"q and qdot must hold the same trajectories and samples: (N, T) = "
                f"{tuple(qt.shape[:2])} and {tuple(qd.shape[:2])}"
            )
        _check_finite(qd if qd.dim() > 2 else qd[..., None], "qdot")
        return qd

    if kind in ("bouncing_masses", "rope"):
        z = torch.stack([qt, rates((system.n_points, 2))], dim=2)
    elif kind == "bouncing_disks":
        angles = qt.clone()
        angles[..., 2] = _unwrap(qt[..., 2])
        qd = rates((B, 3), angles)
        pts = disk_points_2d(qt[..., :2], qt[..., 2], qd[..., :2], qd[..., 2])  # (N,T,B,2,3,2)
        z = pts.movedim(3, 2).reshape(*qt.shape[:2], 2, 3 * B, 2)
    elif kind == "chain_pendulum":
        qd = rates((B,), _unwrap(qt))
        lengths = torch.tensor(cfg.link_lengths, dtype=qt.dtype, device=qt.device)
        pivot = torch.tensor(cfg.pivot, dtype=qt.dtype, device=qt.device)
        z = chain_points_2d(qt, qd, lengths, pivot)
    else:
        if qdot is None:
            omega = _vee(finite_difference_velocities(R, dt) @ R.transpose(-1, -2))
        else:
            omega = rates((3,))
            if omega_frame == "body":
                omega = (R @ omega[..., None])[..., 0]
        axis = torch.tensor([0.0, 0.0, cfg.com_distance], dtype=R.dtype, device=R.device)
        centre = R @ axis
        z = rigid_body_points_3d(centre, R, torch.linalg.cross(omega, centre, dim=-1), omega)
    if qdot is None:
        _report_jumps(z[:, :, 0], dt, threshold, on_jump)
    elif z.shape[1] >= 3:
        mismatch = velocity_mismatch(z[:, :, 0], z[:, :, 1], dt)
        if mismatch > VELOCITY_MISMATCH_WARN:
            frame = " (omega_frame: world or body?)" if kind == "gyroscope" else ""
            warnings.warn(
                f"the given rates qdot do not match the motion of q: the point velocities "
                f"differ from the positions' finite differences by {mismatch:.2f} of the "
                f"median speed{frame}; check their frame, units and order",
                RuntimeWarning,
                stacklevel=2,
            )
    return _output(z, numpy_out)


# -------------------------------------------------------------------------- checks
def trajectory_checks(config: Any, z: Any) -> dict[str, float]:
    """What to look at after converting: how well ``z`` fits the config's structure.

    Args:
        config: task name, path, dict or ``System``.
        z: ``(N, T, 2, P, d)`` trajectories.

    Returns:
        A dict of plain numbers:

        - ``constraint_residual``: max ``|Phi(x)|`` of the equality constraints (rigid
          bodies' unit orthogonal axes, chain links, pivots; 0 when none): lengths
          off by this much (e.g. the wrong link lengths or axis points of wrong length);
        - ``velocity_constraint_residual``: max ``|J_E(x) v|``: velocities
          inconsistent with the constraints (finite differences across impacts, noise);
        - ``share_of_states_in_contact``: states with some gap < 0;
        - ``min_gap``: the smallest signed gap (a large negative one means the config's
          radii or walls do not match the data);
        - ``max_speed``: the largest point speed;
        - ``velocity_mismatch`` (``T >= 3``): :func:`velocity_mismatch` of the velocities
          against the positions' central differences (0.01 or less for smooth motion
          sampled finely; around 1 when velocities of another frame, unit or order of
          points were given).
    """
    system = _system(config)
    t, _ = _tensor(z, "trajectories")
    P, d = system.n_points, system.dim
    _check_shape(t, "trajectories", (2, P, d), f"positions then velocities of {P} points")
    if t.shape[1] == 0:  # (torch's "max(): Expected reduction dim" below)
        raise ValueError(f"trajectories hold no state (shape {tuple(t.shape)})")
    t = t.detach().to(torch.float64)
    x, v = t[:, :, 0], t[:, :, 1]
    out: dict[str, float] = {"constraint_residual": 0.0, "velocity_constraint_residual": 0.0}
    if system.constraints is not None and system.constraints.num_equations > 0:
        cons = system.constraints.to(device=t.device)
        out["constraint_residual"] = float(cons.phi(x).abs().max())
        out["velocity_constraint_residual"] = float(cons.phi_dot(x, v).abs().max())
    gaps = system.gaps(x)
    out["share_of_states_in_contact"] = float((gaps < 0).any(-1).double().mean())
    out["min_gap"] = float(gaps.min())
    out["max_speed"] = float(torch.linalg.vector_norm(v, dim=-1).max())
    if x.shape[1] >= 3:
        out["velocity_mismatch"] = velocity_mismatch(x, v, float(system.dt))
    return out


def velocity_mismatch(x: Tensor, v: Tensor, dt: float) -> float:
    """How far velocities ``v`` are from the positions' motion: the median over the inner
    samples of ``|v_t - (x_{t+1} - x_{t-1}) / (2 dt)|`` over the median speed.

    Robust to the few samples an impact spoils (a median); near the finite differences'
    error ``O(dt^2)`` (relative) for velocities that belong to the positions.

    Args:
        x, v: ``(N, T, P, d)`` positions and velocities, ``T >= 3``.
        dt: the sampling step.
    """
    central = (x[:, 2:] - x[:, :-2]) / (2 * dt)
    inner = v[:, 1:-1]
    error = torch.linalg.vector_norm((inner - central).flatten(2), dim=-1).median()
    speed = torch.linalg.vector_norm(inner.flatten(2), dim=-1).median()
    if float(speed) == 0.0:
        return 0.0 if float(error) == 0.0 else float("inf")
    return float(error / speed)


def _unreliable(x: Any, dt: float, threshold: float | None) -> Any:
    """``velocity_jumps(x, dt).unreliable``, or ``None`` for trajectories too short."""
    if np.shape(x)[1] < MIN_JUMP_SAMPLES:
        return None
    return velocity_jumps(x, dt, threshold=threshold).unreliable
