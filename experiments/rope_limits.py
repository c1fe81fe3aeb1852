"""How well a long rope keeps its stretch limits, by time step and compensation fraction.

    python experiments/rope_limits.py [--task Rope-D200] [--horizon 5] [--n 2]
                                      [--dt 0.01 0.005 0.0025] [--fraction 0.125 1]

The rope's stretch limits (each segment within ``[min_ratio, max_ratio]`` of its rest
length; docs/config.md) are inelastic contacts resolved at the velocity level, with a
penetration-compensation target that removes ``fraction`` of a violation per step
(appendix G). A long rope whips, and many coupled limits are active at once; this
script simulates ``--n`` trajectories over ``--horizon`` seconds for every time step
and fraction and prints the largest and smallest segment-length ratio reached, next to
the limits, and the wall time.
"""

from __future__ import annotations

import argparse
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


def main(argv: Sequence[str] | None = None) -> int:
    import diffcontact as dc

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="Rope-D200")
    parser.add_argument("--horizon", type=float, default=5.0)
    parser.add_argument("--n", type=int, default=2, help="trajectories")
    parser.add_argument("--dt", type=float, nargs="+", default=[0.01, 0.005, 0.0025])
    parser.add_argument("--fraction", type=float, nargs="+", default=[0.125, 1.0])
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    base = dc.load_system(args.task)
    lo, hi = base.config.min_ratio, base.config.max_ratio
    print(f"{args.task}: {args.n} trajectories x {args.horizon:g} s; limits [{lo}, {hi}]")
    print(f"{'dt':>8} {'fraction':>9} {'steps':>6} {'max ratio':>10} {'min ratio':>10} {'s':>6}")
    for dt in args.dt:
        system = dc.load_system(args.task, dt=dt, horizon=args.horizon)
        z0 = system.sample_initial_conditions(args.n, seed=0)
        steps = round(args.horizon / dt)
        for fraction in args.fraction:
            start = time.perf_counter()
            traj = system.simulate(z0, steps, penetration_fraction=fraction, on_tunnelling="ignore")
            r = segment_ratios(system, traj)
            seconds = time.perf_counter() - start
            print(
                f"{dt:>8g} {fraction:>9g} {steps:>6} {float(r.max()):>10.3f} "
                f"{float(r.min()):>10.3f} {seconds:>6.0f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
