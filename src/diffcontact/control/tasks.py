"""The paper's downstream tasks: billiards and throwing, planned through a simulator.

- **Billiards** (a BP/BD-type system: circles in a box, no gravity): all balls
  at rest in a seeded layout; choose the cue ball's initial velocity so that
  the target ball is at ``target`` at time ``time``. Starts: aims at "ghost
  ball" points (where the cue must touch the ball to push it towards the
  target) and around the direct line, at speeds spread over ``(0, max_speed]``.
- **Throwing** (a bouncing-disk system with gravity and a ground line, e.g.
  ``BD1-ground``): the disk starts at rest at ``start``; choose its initial
  velocity and spin so that its centre is at horizontal position ``target``
  at time ``time`` (it has bounced and rolls or slides by then: "passes the
  target at that time"). Starts: uniform in the velocity/spin box.

Both plan ``N`` targets in one batched :func:`~diffcontact.control.optimize`
call and judge the plans with the ground-truth system (``planner.truth``):
``distance_model`` is the final distance under the planning model,
``distance_true`` under the truth.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from diffcontact.control.optimize import ControlError, OptimizeResult, optimize
from diffcontact.control.planner import Planner, as_planner
from diffcontact.control.variables import Spin, Velocity
from diffcontact.geometry.base import unit_normal_planes
from diffcontact.systems.config import ALLOW_LARGE_ENV, MAX_STATES, large_allowed

__all__ = [
    "FAR",
    "ShotPlan",
    "billiards_scene",
    "plan_billiards",
    "plan_throw",
    "random_targets",
    "throw_scene",
]


@dataclass
class ShotPlan:
    """Plans for ``N`` targets (see the module docstring).

    Attributes:
        task: ``"billiards"`` or ``"throw"``.
        target: ``(N, 2)`` (billiards) or ``(N,)`` (throw).
        variables: the chosen values by variable name, ``(N, size)``.
        distance_model, distance_true: ``(N,)`` final distances to the target
            (``distance_true`` NaN where the truth is unknown: ``planner.truth_known``).
        traj_model, traj_true: ``(N, steps + 1, 2, P, dim)`` the planned motion
            under the planner and under the truth (its contact model,
            ``planner.truth_contact_model``; NaN where unknown).
        result: the :class:`OptimizeResult`.
    """

    task: str
    target: Tensor
    variables: dict[str, Tensor]
    distance_model: Tensor
    distance_true: Tensor
    traj_model: Tensor
    traj_true: Tensor
    result: OptimizeResult
    info: dict[str, Any] = field(default_factory=dict)

    def as_json(self, i: int = 0) -> dict[str, Any]:
        """``{"variables", "distance_model", "distance_true", ...}`` of target ``i``."""
        return {
            "task": self.task,
            "target": self.target[i].tolist(),
            "variables": {k: v[i].tolist() for k, v in self.variables.items()},
            "distance_model": float(self.distance_model[i]),
            "distance_true": float(self.distance_true[i]),
            **{k: v[i] if isinstance(v, list) else v for k, v in self.info.items()},
        }


def _steps(time: float, dt: float) -> int:
    if not (isinstance(time, (int, float)) and math.isfinite(time) and time > 0):
        raise ControlError(f"time must be a positive number of seconds, got {time!r}")
    steps = round(time / dt)
    if steps < 1 or abs(steps * dt - time) > 1e-9 * max(1.0, time):
        raise ControlError(f"time {time:g} s is not a positive multiple of the step dt = {dt:g} s")
    if steps > MAX_STATES and not large_allowed():  # (a typo would fill the memory)
        raise ControlError(
            f"time {time:g} s is {steps} steps of dt = {dt:g} s; at most {MAX_STATES} "
            f"(set {ALLOW_LARGE_ENV}=1 to lift the limit)"
        )
    return steps


def _circle_system(planner: Planner, task: str) -> Any:
    cfg = planner.truth.config
    if cfg.type not in ("bouncing_masses", "bouncing_disks"):
        raise ControlError(
            f"{task} needs a system of circles (bouncing_masses or bouncing_disks), "
            f"got {cfg.name or cfg.type} ({cfg.type})"
        )
    return cfg


def _walls(cfg: Any) -> Tensor:
    """``(W, 3)`` unit-normal walls ``n . x + c >= 0``."""
    return unit_normal_planes(torch.tensor(cfg.walls, dtype=torch.float64).reshape(-1, 3), 2)


def _check_ball(planner: Planner, name: str, index: int) -> None:
    n = len(planner.bodies)
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < n:
        raise ControlError(f"{name} must be a body index 0..{n - 1}, got {index!r}")


# --------------------------------------------------------------------- billiards


def billiards_scene(planner: Planner, n: int, seed: int = 0) -> Tensor:
    """``(n, 2, P, 2)`` layouts: the task's initial positions (seeded), all at rest."""
    z0 = planner.truth.sample_initial_conditions(n, seed=seed)
    return torch.stack([z0[:, 0], torch.zeros_like(z0[:, 1])], dim=1)


FAR = 1000
"""Targets farther than ``FAR`` times the reach of a shot (its top speed times ``time``)
where no wall bounds the table, and throws' targets that far from the start, are refused
(:class:`ControlError`): nothing near them is planned, and their distances swamp the
position of the ball in float64 (``1e300`` was planned as a shot at rest)."""


def _table_box(walls: Tensor, radius: float) -> tuple[tuple[float, float], ...] | None:
    """The x and y ranges of the points where a ball of ``radius`` fits inside ``walls``
    (``(W, 3)``, unit normals), or ``None`` where the walls do not bound them (or nothing
    fits)."""
    normal, offset = walls[:, :2], walls[:, 2] - radius
    angles = torch.atan2(normal[:, 1], normal[:, 0]).sort().values
    turns = torch.diff(torch.cat([angles, angles[:1] + 2 * math.pi]))
    if len(angles) < 3 or float(turns.max()) >= math.pi - 1e-12:  # open in some direction
        return None
    corners = []
    for i in range(len(walls)):
        for j in range(i + 1, len(walls)):
            pair = normal[[i, j]]
            if abs(float(torch.linalg.det(pair))) < 1e-12:  # parallel walls
                continue
            point = torch.linalg.solve(pair, -offset[[i, j]])
            if bool((normal @ point + offset >= -1e-9).all()):
                corners.append(point)
    if not corners:
        return None
    pts = torch.stack(corners)
    low, high = pts.min(0).values.tolist(), pts.max(0).values.tolist()
    return (low[0], high[0]), (low[1], high[1])


def _ranges(box: Sequence[tuple[float, float]]) -> str:
    """``x in [lo, hi], y in [lo, hi]`` of ``box``: ``((x_lo, x_hi), (y_lo, y_hi))``."""
    return ", ".join(
        f"{name} in [{lo:.4g}, {hi:.4g}]" for name, (lo, hi) in zip("xy", box, strict=True)
    )


def _check_table_targets(
    cfg: Any, target: Tensor, ball: int, radius: float, start: Tensor, reach: float, time: float
) -> None:
    """Refuse targets ``(N, 2)`` that are not finite, where ball ``ball`` (of ``radius``,
    at ``start``: ``(N, 2)``) does not fit inside the walls or, where no wall bounds the
    table, farther from its start than :data:`FAR` times ``reach`` (the distance the cue's
    top speed covers in ``time``); the error names the target and the allowed range."""
    finite = torch.isfinite(target).all(-1)
    box = None
    outside = torch.zeros_like(finite)
    if cfg.walls:
        walls = _walls(cfg)
        box = _table_box(walls, radius)
        gap = torch.where(finite[:, None], target, 0.0) @ walls[:, :2].T + walls[:, 2]  # (N, W)
        outside = (gap < radius).any(-1)
    far = torch.zeros_like(finite)
    if box is None and 0 < reach < math.inf:  # (a bad max_speed: optimize's error)
        far = ((target - start).abs() > FAR * reach).any(-1)
    bad = ~finite | outside | far
    if not bool(bad.any()):
        return
    i = int(bad.nonzero()[0])
    what = "is not finite" if not finite[i] else "is outside the table" if outside[i] else ""
    fits = f", where ball {ball}, of radius {radius:g}, fits inside the walls"
    if box is not None:
        allowed = f"allowed: {_ranges(box)}{fits}"
    else:
        x0, y0 = start[i].tolist()
        span = FAR * reach
        box = ((x0 - span, x0 + span), (y0 - span, y0 + span))
        allowed = (
            f"allowed: {_ranges(box)}{fits if cfg.walls else ''}: within {FAR} times the "
            f"{reach:.4g} m the cue's top speed covers in {time:g} s of ball {ball} at "
            f"({x0:.4g}, {y0:.4g})"
        )
        what = what or "is far out of reach"
    raise ControlError(f"target {target[i].tolist()} {what} ({allowed})")


def _billiards_starts(
    z0: Tensor, cue: int, ball: int, target: Tensor, radii: Tensor, S: int, max_speed: float
) -> Tensor:
    """``(N, S, 2)`` cue velocities: ghost-ball aims and angles around the line to the ball."""
    N = z0.shape[0]
    gen = torch.Generator().manual_seed(0)
    pc, pb = z0[:, 0, cue], z0[:, 0, ball]
    push = target - pb
    push = push / push.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    ghost = pb - (radii[cue] + radii[ball]) * push  # where the cue's centre must be at impact
    aim_ghost = ghost - pc
    aim_line = pb - pc
    angle = lambda v: torch.atan2(v[:, 1], v[:, 0])  # noqa: E731
    half = S // 2
    a_ghost = angle(aim_ghost).unsqueeze(1) + 0.05 * torch.randn(N, half, generator=gen).to(z0)
    a_line = angle(aim_line).unsqueeze(1) + 0.6 * (
        torch.rand(N, S - half, generator=gen).to(z0) - 0.5
    )
    a = torch.cat([a_ghost, a_line], dim=1)
    speed = max_speed * (0.15 + 0.85 * torch.rand(N, S, generator=gen).to(z0))
    return torch.stack([speed * torch.cos(a), speed * torch.sin(a)], dim=-1)


def plan_billiards(
    simulator: Any,
    target: Any,
    *,
    cue: int = 0,
    ball: int = 2,
    time: float = 1.0,
    seed: int = 0,
    z0: Tensor | None = None,
    starts: int = 32,
    iterations: int = 60,
    lr: float = 0.05,
    tolerance: float | None = 0.005,
    max_speed: float = 4.0,
    progress: bool = True,
) -> ShotPlan:
    """Choose the cue ball's velocity so that ``ball`` ends at ``target`` after ``time`` s.

    Args:
        simulator: what to plan with (:func:`~diffcontact.control.as_planner`).
        target: ``(2,)`` or ``(N, 2)`` points on the table.
        cue, ball: body indices (distinct).
        time: seconds (a multiple of ``dt``).
        seed: the layout of the balls (:func:`billiards_scene`); each of ``N``
            targets gets layout ``seed`` unless ``z0`` is given.
        z0: ``(N, 2, P, 2)`` layouts instead (velocities are ignored: at rest).
        starts: candidate shots per target, optimised together.
        iterations, lr, tolerance: of :func:`optimize` (``tolerance`` in
            distance units: stop when every target is reached that closely).
        max_speed: bound on each component of the cue velocity.
        progress: progress bar.

    Raises:
        ControlError: not a system of circles, bad indices, a target that is not
            finite or outside the table (or, where no wall bounds the table, farther
            from the ball than :data:`FAR` times the cue's top speed times ``time``),
            a time that is not a multiple of ``dt``.
    """
    planner = as_planner(simulator)
    cfg = _circle_system(planner, "billiards")
    _check_ball(planner, "cue", cue)
    _check_ball(planner, "ball", ball)
    if cue == ball:
        raise ControlError(f"cue and ball must be different bodies, both are {cue}")
    steps = _steps(time, planner.dt)
    tgt = torch.as_tensor(target, dtype=torch.float64)
    if tgt.dim() == 1:
        tgt = tgt.unsqueeze(0)
    if tgt.dim() != 2 or tgt.shape[-1] != 2:
        raise ControlError(
            f"target must be (x, y) points, shape (2,) or (N, 2), got shape {tuple(tgt.shape)}"
        )
    radii = torch.tensor(cfg.radii, dtype=torch.float64)
    N = tgt.shape[0]
    if z0 is None:
        z0 = billiards_scene(planner, 1, seed).expand(N, -1, -1, -1).clone()
    else:
        z0 = torch.as_tensor(z0, dtype=torch.float64)
        if tuple(z0.shape) != (N, *planner.state_shape):
            raise ControlError(
                f"z0 must have shape {(N, *planner.state_shape)} (a layout per target), got "
                f"{tuple(z0.shape)}"
            )
        z0 = torch.stack([z0[:, 0], torch.zeros_like(z0[:, 1])], dim=1)
    point = planner.bodies[ball].points[0]
    reach = time * max_speed * math.sqrt(2)  # the cue's top speed (each component bounded)
    _check_table_targets(cfg, tgt, ball, float(radii[ball]), z0[:, 0, point], reach, time)
    tgt_b = tgt.unsqueeze(1)  # (N, 1, 2)

    def objective(traj: Tensor) -> Tensor:
        return (traj[:, :, -1, 0, point] - tgt_b).norm(dim=-1)

    var = Velocity(cue, bounds=(-max_speed, max_speed), name="velocity")
    init = _billiards_starts(z0, cue, ball, tgt, radii, starts, max_speed).clamp(
        -max_speed, max_speed
    )
    result = optimize(
        planner, z0, objective, variables=[var], steps=steps, starts={"velocity": init},
        iterations=iterations, lr=lr, tolerance=tolerance, progress=progress,
    )  # fmt: skip
    return _judge(
        "billiards", planner, result, steps, tgt, lambda tr: objective(tr.unsqueeze(1))[:, 0]
    )


# ------------------------------------------------------------------------- throw


def throw_scene(planner: Planner, start: tuple[float, float] = (0.0, 0.5)) -> Tensor:
    """``(2, P, 2)``: the disk (body 0) at rest at ``start``, axes aligned, others unchanged."""
    truth = planner.truth
    z = truth.sample_initial_conditions(1, seed=0)[0].clone()
    pts = list(planner.bodies[0].points)
    centre = torch.tensor(start, dtype=torch.float64)
    z[0, pts] = z[0, pts] - z[0, pts[0]] + centre
    if len(pts) == 3:  # re-orient the axes to the world axes
        r = (z[0, pts[1]] - centre).norm()
        z[0, pts[1]] = centre + torch.tensor([r, 0.0], dtype=torch.float64)
        z[0, pts[2]] = centre + torch.tensor([0.0, r], dtype=torch.float64)
    z[1] = 0
    return z


def plan_throw(
    simulator: Any,
    target: Any,
    *,
    time: float = 1.0,
    start: tuple[float, float] = (0.0, 0.5),
    starts: int = 16,
    iterations: int = 60,
    lr: float = 0.1,
    tolerance: float | None = 0.005,
    max_speed: float = 4.0,
    max_spin: float = 30.0,
    progress: bool = True,
) -> ShotPlan:
    """Choose the disk's initial velocity and spin so that its centre passes ``x = target``.

    Args:
        simulator: a bouncing-disk system with gravity and walls (``BD1-ground``)
            or a model trained on its data.
        target: a number or ``(N,)`` horizontal positions.
        time: seconds (a multiple of ``dt``).
        start: the disk's centre at rest before the throw (above the ground).
        starts, iterations, lr, tolerance: of :func:`optimize`.
        max_speed, max_spin: bounds of each velocity component (m/s) and of
            the spin (rad/s).

    Raises:
        ControlError: not a disk system with gravity, a start inside the
            ground, a target that is not finite or farther from the start than
            :data:`FAR` times the reach (nearer targets beyond reach are planned
            as close as they can be, with a warning), a start coordinate beyond
            ``FAR**2`` times the reach, a bad time.
    """
    planner = as_planner(simulator)
    cfg = _circle_system(planner, "throw")
    if cfg.type != "bouncing_disks" or cfg.gravity <= 0 or not cfg.walls:
        raise ControlError(
            f"throw needs rigid disks (bouncing_disks) with gravity and a ground wall, e.g. "
            f"BD1-ground; {cfg.name or cfg.type} has type {cfg.type}, gravity {cfg.gravity:g}, "
            f"{len(cfg.walls)} wall(s)"
        )
    steps = _steps(time, planner.dt)
    tgt = torch.as_tensor(target, dtype=torch.float64).reshape(-1)
    if tgt.numel() < 1:
        raise ControlError(f"target must be one or more numbers, got {target!r}")
    st = torch.as_tensor(start, dtype=torch.float64)
    if st.shape != (2,) or not torch.isfinite(st).all():
        raise ControlError(f"start must be a finite point (x, y), got {start!r}")
    # the centre moves horizontally at most at the larger of the thrown speed and the
    # rolling speed the spin can give (friction only trades one for the other)
    reach = time * max(max_speed, max_spin * float(cfg.radii[0]))
    # (x = 1e300 had been planned as a throw at rest, y = 1e300 failed to simulate)
    if 0 < reach < math.inf and bool((st.abs() > FAR**2 * reach).any()):
        raise ControlError(
            f"start {tuple(st.tolist())} is too far from the origin: each coordinate must be "
            f"within {FAR**2:g} times the {reach:g} m a throw covers in {time:g} s (farther "
            "out, float64 rounds the throw's motion away)"
        )
    z = throw_scene(planner, tuple(st.tolist()))
    if (planner.truth.gaps(z[0].unsqueeze(0)) <= 0).any():
        raise ControlError(f"start {tuple(st.tolist())}: the disk overlaps a wall or another body")
    N = tgt.shape[0]
    absurd = ~torch.isfinite(tgt)
    if 0 < reach < math.inf:  # (a bad max_speed or max_spin: optimize's error)
        absurd |= (tgt - st[0]).abs() > FAR * reach
    if bool(absurd.any()):
        bad = float(tgt[absurd][0])
        x0, span = float(st[0]), FAR * reach
        what = "is not finite" if not math.isfinite(bad) else "is far out of reach"
        raise ControlError(
            f"target x = {bad:g} {what} (allowed: x in [{x0 - span:g}, {x0 + span:g}], within "
            f"{FAR} times the {reach:g} m a throw from x = {x0:g} covers in {time:g} s at "
            f"max_speed {max_speed:g} m/s and max_spin {max_spin:g} rad/s)"
        )
    far = (tgt - st[0]).abs() > reach
    if bool(far.any()):
        warnings.warn(
            f"throw: target(s) {tgt[far].tolist()[:5]} are beyond reach from x = {float(st[0]):g}"
            f" in {time:g} s (at most {reach:g} m at max_speed {max_speed:g} m/s and max_spin "
            f"{max_spin:g} rad/s): the plan gets as close as it can",
            stacklevel=2,
        )
    z0 = z.unsqueeze(0).expand(N, -1, -1, -1).clone()
    point = planner.bodies[0].points[0]
    tgt_b = tgt.reshape(N, 1)

    def objective(traj: Tensor) -> Tensor:
        return (traj[:, :, -1, 0, point, 0] - tgt_b).abs()

    variables = [
        Velocity(0, bounds=(-max_speed, max_speed), name="velocity"),
        Spin(0, bounds=(-max_spin, max_spin), name="spin"),
    ]
    result = optimize(
        planner, z0, objective, variables=variables, steps=steps, starts=starts,
        iterations=iterations, lr=lr, tolerance=tolerance, progress=progress, seed=1,
    )  # fmt: skip
    plan = _judge("throw", planner, result, steps, tgt, lambda tr: objective(tr.unsqueeze(1))[:, 0])
    return plan


# -------------------------------------------------------------------------- common


def _judge(
    task: str, planner: Planner, result: OptimizeResult, steps: int, target: Tensor, distance
) -> ShotPlan:
    """Roll out the best plans under the planner and the truth; distances to the target."""
    z0 = result.z0
    with planner.frozen():  # no torch.no_grad: a learned potential's force needs autograd
        traj_model = planner.simulate(z0, steps, result.params).detach()
    if planner.truth_known:
        traj_true = planner.simulate_truth(z0, steps).detach()
    else:  # recorded data without true parameters: nothing to judge by (NaN distances)
        traj_true = torch.full_like(traj_model, math.nan)
    return ShotPlan(
        task=task,
        target=target,
        variables=dict(result.variables),
        distance_model=distance(traj_model),
        distance_true=distance(traj_true),
        traj_model=traj_model,
        traj_true=traj_true,
        result=result,
    )


def random_targets(planner: Planner, task: str, n: int, seed: int = 0) -> Tensor:
    """``n`` random targets: points on the table that fit the target ball (billiards, inside
    the walls with a margin of its radius), or horizontal positions in ``[0.3, 2.0]`` m (throw)."""
    gen = torch.Generator().manual_seed(int(seed))
    if task == "throw":
        return 0.3 + 1.7 * torch.rand(n, generator=gen, dtype=torch.float64)
    cfg = planner.truth.config
    r = max(cfg.radii)
    low = torch.tensor(cfg.initial_conditions.position_low, dtype=torch.float64) + r
    high = torch.tensor(cfg.initial_conditions.position_high, dtype=torch.float64) - r
    return low + (high - low) * torch.rand(n, 2, generator=gen, dtype=torch.float64)
