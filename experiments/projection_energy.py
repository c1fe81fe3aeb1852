"""The energy of bouncing systems with the position projection switched on.

    python experiments/projection_energy.py [--tasks BP5 BD5] [--cor 1] [--mu 0]
                                            [--n 32] [--projection 10]

The position projection (config key ``position_projection``, default 0 outside the rope
tasks) moves the positions back onto the contacts' admissible set after every step, and
the velocities' projection (``velocity_projection``, default true) then corrects the
velocities at the contacts closed there: inelastically on the limits without restitution,
with Poisson's restitution on the others (systems/projection.py, "Restitution"). This
script simulates ``--n`` trajectories of each task over its config's horizon with the
given ``cor`` and ``mu``, without the projection, with both projections, and with the
positions projected alone, and prints the smallest and largest relative energy change
``(E(t) - E(0)) / |E(0)|`` over all states, the mean at the end, the deepest
penetration (the most negative gap) and, for systems with equality constraints (rigid
bodies, the chain pendulum), their largest drift ``|Phi(x(t)) - Phi(x(0))|`` (``-``
without). With ``cor`` 1 and ``mu`` 0 the true motion keeps its energy.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence

import torch


def _drift(system, traj: torch.Tensor) -> str:
    """The equality constraints' largest drift ``|Phi(x(t)) - Phi(x(0))|`` over the
    trajectories ``traj: (N, T, 2, P, dim)``, formatted; ``-`` for a system without."""
    constraints = system.constraints
    if constraints is None or constraints.num_equations == 0:
        return "-"
    n, T = traj.shape[:2]
    phi = constraints.phi(traj[:, :, 0].flatten(0, 1)).view(n, T, -1)
    return f"{float((phi - phi[:, :1]).abs().max()):.3g}"


def main(argv: Sequence[str] | None = None) -> int:
    import diffcontact as dc
    from diffcontact.cli_args import non_negative_int, one_line, positive_int

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["BP5", "BD5"])
    parser.add_argument("--cor", type=float, default=1.0, help="every contact's cor")
    parser.add_argument("--mu", type=float, default=0.0, help="every contact's mu")
    parser.add_argument("--n", type=positive_int, default=32, help="trajectories per task")
    parser.add_argument("--projection", type=positive_int, default=10, help="iterations")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    args = parser.parse_args(argv)
    if not 0 <= args.cor <= 1:
        parser.error(f"--cor must lie in [0, 1], got {args.cor:g}")
    if not (math.isfinite(args.mu) and args.mu >= 0):
        parser.error(f"--mu must be a number >= 0, got {args.mu:g}")
    from diffcontact.systems import load_config

    for task in args.tasks:  # every task, before the first is simulated
        try:
            load_config(task, cor=args.cor, mu=args.mu)
        except ValueError as err:
            parser.error(f"--tasks {task}: {one_line(err)}")
    torch.set_num_threads(1)
    print(f"cor {args.cor:g}, mu {args.mu:g}; {args.n} trajectories per task")
    print(
        f"{'task':>8} {'setting':>24} {'min dE/E':>10} {'max dE/E':>10} {'mean final':>10} "
        f"{'deepest':>10} {'drift':>10}"
    )
    settings = [
        ("no projection", {"position_projection": 0}),
        (f"projection {args.projection}", {"position_projection": args.projection}),
        (
            f"positions only {args.projection}",
            {"position_projection": args.projection, "velocity_projection": False},
        ),
    ]
    for task in args.tasks:
        for label, keys in settings:
            system = dc.load_system(task, cor=args.cor, mu=args.mu, **keys)
            z0 = system.sample_initial_conditions(args.n, seed=args.seed)
            traj = system.simulate(z0, on_tunnelling="ignore")
            energy = system.energy(traj)
            change = (energy - energy[:, :1]) / energy[:, :1].abs()
            deepest = float(system.gaps(traj[:, :, 0]).min())
            print(
                f"{task:>8} {label:>24} {float(change.min()):>10.3g} {float(change.max()):>10.3g} "
                f"{float(change[:, -1].mean()):>10.3g} {deepest:>10.3g} {_drift(system, traj):>10}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
