"""How well a long rope keeps its limits, with and without the position projection.

    python experiments/rope_limits.py [--task Rope-D200] [--horizon 5] [--n 2]
                                      [--dt 0.01 0.005 0.0025] [--fraction 0.125]
                                      [--projection 10] [--positions-only]
                                      [--tip-mass 100] [--undamped] [--cor 0.5]

The rope's limits (each segment within ``[min_ratio, max_ratio]`` of its rest length,
each joint's bend within ``+-max_angle``; docs/config.md) are inelastic contacts
resolved at the velocity level. Without a position-level correction
(``position_projection: 0``) only the penetration-compensation target removes
``fraction`` of a violation per step (appendix G); with it (the rope tasks' default,
``position_projection: 10``) the positions are projected back onto the limits after
every step (systems/projection.py), and the velocities onto the limits closed there
(``velocity_projection``; ``--positions-only`` adds runs without it, the behaviour
before that key, whose energy can rise). ``--tip-mass`` sets the last point's mass (a rope
with a heavy end; the other points keep the config's), and ``--undamped`` adds runs whose
projection takes plain Gauss-Newton steps (``projection.DAMPING = 0``, the behaviour
before the damping; systems/projection.py, "Damping"); ``--cor`` gives the limits
restitution (default the config's 0, inelastic). This script simulates ``--n``
trajectories over ``--horizon`` seconds for every time step, once per setting, and
prints the largest and smallest segment-length ratio, the largest bend beyond
``max_angle`` (radians), the most negative gap of any limit (radians for bends, metres
for lengths: how far a limit was left violated), the energy change (mean over
trajectories of ``E(T) - E(0)``, and the largest rise ``max_t E(t) - E(0)``), and the wall
time.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence

import torch


def segment_ratios(system, traj: torch.Tensor) -> torch.Tensor:
    """``(N, T, P)`` segment lengths over the rest length (segment 0 from the anchor)."""
    x = traj[:, :, 0]  # (N, T, P, 2)
    anchor = torch.as_tensor(system.config.anchor, dtype=x.dtype)
    first = x[:, :, :1] - anchor
    seg = torch.cat([first, x[:, :, 1:] - x[:, :, :-1]], dim=2).norm(dim=-1)
    return seg / float(system.config.rest_length)


def bending_excess(system, traj: torch.Tensor) -> torch.Tensor:
    """``(N, T, P - 1)`` ``|theta| - max_angle`` per joint (> 0: the bending limit is exceeded)."""
    x = traj[:, :, 0]
    anchor = torch.as_tensor(system.config.anchor, dtype=x.dtype)
    seg = torch.cat([x[:, :, :1] - anchor, x[:, :, 1:] - x[:, :, :-1]], dim=2)
    a, b = seg[:, :, :-1], seg[:, :, 1:]
    theta = torch.atan2(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0], (a * b).sum(-1))
    return theta.abs() - float(system.config.max_angle)


def main(argv: Sequence[str] | None = None) -> int:
    import diffcontact as dc

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="Rope-D200")
    parser.add_argument("--horizon", type=float, default=5.0)
    parser.add_argument("--n", type=int, default=2, help="trajectories")
    parser.add_argument("--dt", type=float, nargs="+", default=[0.01, 0.005, 0.0025])
    parser.add_argument(
        "--fraction", type=float, nargs="+", default=[0.125],
        help="compensation fractions of the runs without projection",
    )  # fmt: skip
    parser.add_argument(
        "--projection", type=int, nargs="+", default=[10],
        help="position_projection (iterations) of the runs with it",
    )  # fmt: skip
    parser.add_argument(
        "--positions-only", action="store_true",
        help="also run each projection setting without the velocities' projection",
    )  # fmt: skip
    parser.add_argument(
        "--tip-mass", type=float, default=None,
        help="the last point's mass (default: the config's)",
    )  # fmt: skip
    parser.add_argument("--cor", type=float, default=None, help="the limits' cor")
    parser.add_argument(
        "--undamped", action="store_true",
        help="also run each projection setting with plain Gauss-Newton steps",
    )  # fmt: skip
    args = parser.parse_args(argv)
    if not all(math.isfinite(v) and v > 0 for v in args.dt):
        parser.error(f"--dt must be positive numbers, got {args.dt}")
    if not all(0 <= v <= 1 for v in args.fraction):
        parser.error(f"--fraction must lie in [0, 1], got {args.fraction}")
    if args.n < 1 or not math.isfinite(args.horizon) or args.horizon <= 0:
        parser.error("--n must be at least 1 and --horizon a positive number")
    if any(k < 1 for k in args.projection):
        parser.error(f"--projection must be at least 1 iteration, got {args.projection}")
    if args.tip_mass is not None and not (math.isfinite(args.tip_mass) and args.tip_mass > 0):
        parser.error(f"--tip-mass must be a positive number, got {args.tip_mass:g}")
    if args.cor is not None and not 0 <= args.cor <= 1:
        parser.error(f"--cor must lie in [0, 1], got {args.cor:g}")
    from diffcontact.cli_args import one_line
    from diffcontact.systems import load_config, projection

    try:
        cfg = load_config(args.task)
    except ValueError as err:
        parser.error(f"--task {args.task}: {one_line(err)}")
    if not hasattr(cfg, "min_ratio"):
        parser.error(f"--task {args.task}: not a rope (a task with segment limits)")
    rope_keys = {}  # the config keys of --tip-mass and --cor
    if args.tip_mass is not None:
        mass = cfg.mass if isinstance(cfg.mass, list) else [cfg.mass] * cfg.n_points
        rope_keys["mass"] = [*mass[:-1], args.tip_mass]
    if args.cor is not None:
        rope_keys["cor"] = args.cor
    for dt in args.dt:  # every time step, before the first is simulated
        try:
            load_config(args.task, dt=dt, horizon=args.horizon)
        except ValueError as err:
            parser.error(f"--dt {dt:g} with --horizon {args.horizon:g}: {one_line(err)}")
    torch.set_num_threads(1)
    base = dc.load_system(args.task, **rope_keys)
    cfg = base.config
    extra = ""
    if args.tip_mass is not None:
        extra = f"; tip mass {args.tip_mass:g} (the others' {cfg.mass[0]:g})"
    if args.cor is not None:
        extra += f"; cor {args.cor:g}"
    print(
        f"{args.task}: {args.n} trajectories x {args.horizon:g} s; limits: ratio "
        f"[{cfg.min_ratio}, {cfg.max_ratio}], bend {cfg.max_angle} rad{extra}"
    )
    print(
        f"{'dt':>7} {'setting':>16} {'steps':>5} {'max ratio':>10} {'min ratio':>9} "
        f"{'max bend-lim':>12} {'min gap':>9} {'mean dE':>9} {'max rise':>9} {'s':>5}"
    )
    # (label, config keys, simulate options[, projection.DAMPING])
    settings = [(f"projection {k}", {}, {"position_projection": k}) for k in args.projection]
    if args.undamped:
        settings += [
            (f"undamped {k}", {}, {"position_projection": k}, 0.0) for k in args.projection
        ]
    if args.positions_only:
        settings += [
            (f"positions only {k}", {"velocity_projection": False}, {"position_projection": k})
            for k in args.projection
        ]
    settings += [
        (f"fraction {f:g}", {}, {"position_projection": 0, "penetration_fraction": f})
        for f in args.fraction
    ]
    for dt in args.dt:
        for label, keys, options, *damping in settings:
            system = dc.load_system(args.task, dt=dt, horizon=args.horizon, **rope_keys, **keys)
            z0 = system.sample_initial_conditions(args.n, seed=0)
            steps = round(args.horizon / dt)
            default = projection.DAMPING
            projection.DAMPING = damping[0] if damping else default
            try:
                start = time.perf_counter()
                traj = system.simulate(z0, steps, on_tunnelling="ignore", **options)
                seconds = time.perf_counter() - start
            finally:
                projection.DAMPING = default
            r = segment_ratios(system, traj)
            bend = bending_excess(system, traj)
            E = system.energy(traj)
            change = float((E[:, -1] - E[:, 0]).mean())
            rise = float((E - E[:, :1]).amax())
            # the most negative gap of any limit and state (bends in rad, lengths in m)
            gap = float(system.gaps(traj[:, :, 0]).min())
            print(
                f"{dt:>7g} {label:>16} {steps:>5} {float(r.max()):>10.4g} {float(r.min()):>9.4g} "
                f"{float(bend.max()):>12.3g} {gap:>9.3g} {change:>9.3g} {rise:>9.3g} "
                f"{seconds:>5.0f}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
