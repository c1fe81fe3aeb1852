"""How well ``velocity_jumps`` finds impacts in positions-only data (docs/own-data.md).

Simulates trajectories of built-in tasks with diffcontact (whose impacts are known:
a contact is resolved at state t when some gap is negative there), keeps only the
positions, and reports per task: the impact states (1 <= t <= T-2), how many the
detector flags within one sample, the same for impacts changing some velocity by more
than 10 % of the RMS speed, the flagged samples with no contact within two samples,
and the error of the finite-difference velocities where they are marked reliable.

    python experiments/velocity_jumps.py [--n 16] [--seed 1]
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
import torch

import diffcontact as dc
from diffcontact.cli_args import non_negative_int, positive_int
from diffcontact.learning.data.convert import finite_difference_velocities, velocity_jumps

TASKS = ("BP5-e", "BP5", "BD5", "CP3", "CP3-e", "Gyro", "Rope")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=positive_int, default=16, help="trajectories per task")
    parser.add_argument("--seed", type=non_negative_int, default=1)
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore")
    print("| task | dt | impact states | flagged within 1 | impacts with dv > 0.1 v_rms | "
          "flagged within 1 | flags without contact within 2 (of states) | FD error where "
          "reliable: max / median (v_rms) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for task in TASKS:
        system = dc.load_system(task)
        z0 = system.sample_initial_conditions(args.n, seed=args.seed)
        traj = system.simulate(z0, system.default_steps, progress=False).numpy()
        x, v = traj[:, :, 0], traj[:, :, 1]
        jumps = velocity_jumps(x, system.dt)
        with torch.no_grad():
            contact = (system.gaps(torch.from_numpy(x)) < 0).any(-1).numpy()
        dv = np.zeros(contact.shape)
        dv[:, 2:] = np.linalg.norm(v[:, 2:] - 2 * v[:, 1:-1] + v[:, :-2], axis=-1).max(-1)
        v_rms = float(np.sqrt((np.linalg.norm(v, axis=-1) ** 2).mean()))
        near = np.zeros_like(contact)
        for k in (-1, 0, 1):
            near |= np.roll(jumps.jump, k, axis=1)
        impact = contact.copy()
        impact[:, :1] = impact[:, -1:] = False
        big = impact & (dv > 0.1 * v_rms)
        around = np.zeros_like(contact)
        for k in (-2, -1, 0, 1, 2):
            around |= np.roll(contact, k, axis=1)
        false = jumps.jump & ~around
        err = np.linalg.norm(finite_difference_velocities(x, system.dt) - v, axis=-1).max(-1)
        ok = ~jumps.unreliable
        ok[:, -1] = False  # an impact at the last sample is invisible in the positions
        print(
            f"| {task} | {system.dt:g} | {impact.sum()} | {(impact & near).sum()} | "
            f"{big.sum()} | {(big & near).sum()} | {false.sum()} ({contact.size}) | "
            f"{err[ok].max():.2g} / {np.median(err[ok]):.2g} ({v_rms:.2g}) |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
