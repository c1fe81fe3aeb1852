"""Exact Coulomb vs CM: which learned model recovers the true e_P and mu?

    python experiments/coulomb.py --out runs/coulomb [--n 200 --epochs 30 --mu 0.3 --cor 0.7]

Data: one point mass (radius 0.1, mass 0.3) in the unit box, no gravity, known
``mu`` and ``e_P`` (``--mu``, ``--cor``; 0.3 and 0.7 by default), rolled out by the
exact event-driven simulator (:func:`diffcontact.systems.event_driven.simulate_event_driven`:
straight flights, impacts at their exact times with the textbook Coulomb rule),
sampled every dt = 0.01 and written as a dataset with ``dataset_from_arrays``. Then
``Coulomb-CD-CLNN`` and ``CM-CD-CLNN`` are trained on it with the same options, and
their learned ``e_P`` and ``mu`` (one shared value each) are printed next to the
truth, with the wall time. docs/results.md ("Exact Coulomb friction") quotes the
output; ``tests/systems/test_event_driven.py`` runs a small version (slow marker).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

import diffcontact as dc
from diffcontact.cli_args import (
    float_in,
    int_at_least,
    non_negative_int,
    positive_int,
    run_stoppable,
)
from diffcontact.io import check_writable_folder
from diffcontact.learning.data.arrays import dataset_from_arrays
from diffcontact.learning.training.run import train
from diffcontact.systems.event_driven import simulate_event_driven


def box_config(mu: float, cor: float) -> dict:
    """The geometry of the data: one point mass in the unit box, no gravity."""
    return {
        "name": "ball-in-box",
        "type": "bouncing_masses",
        "masses": [0.3],
        "radii": [0.1],
        "walls": [[1, 0, 0], [0, 1, 0], [-1, 0, 1], [0, -1, 1]],
        "gravity": 0.0,
        "mu": mu,
        "cor": cor,
        "dt": 0.01,
        "horizon": 1.0,
        "initial_conditions": {
            "position_low": [0.1, 0.1],
            "position_high": [0.9, 0.9],
            "velocity_std": 1.0,
        },
    }


def impact_windows(traj: torch.Tensor, length: int, impact_share: float, seed: int):
    """Windows of ``length`` states cut from exact trajectories ``(N, T, 2, 1, 2)``.

    The dataset tools mark contact by a negative gap, which exact data never has
    (impacts happen between samples), so the windows are chosen here: every window
    whose states are sampled across an impact (a change of velocity; there is no
    gravity) at most once per trajectory and impact, plus contact-free windows
    so that ``impact_share`` of all hold an impact. Returns ``(M, length, 2, 1, 2)``.
    """
    gen = torch.Generator().manual_seed(seed)
    N, T = traj.shape[:2]
    v = traj[:, :, 1].flatten(2)
    impact = (v[:, 1:] - v[:, :-1]).abs().amax(-1) > 1e-12  # (N, T-1): in interval k
    starts = T - length + 1
    # window s covers intervals s .. s + length - 2
    covered = impact.unfold(1, length - 1, 1)[:, :starts]  # (N, S, length-1)
    with_impact = covered.any(-1)
    # one window per impact: the impact at a uniformly drawn position inside it
    first = covered.to(torch.int8).argmax(-1)
    pick = with_impact & (torch.rand(N, starts, generator=gen) < 1.0 / (length - 1))
    pick &= first >= 0
    free = ~with_impact & (torch.rand(N, starts, generator=gen) < 0.02)
    rows_i, cols_i = pick.nonzero(as_tuple=True)
    rows_f, cols_f = free.nonzero(as_tuple=True)
    n_free = int(len(rows_i) * (1 - impact_share) / impact_share)
    keep = torch.randperm(len(rows_f), generator=gen)[:n_free]
    rows = torch.cat([rows_i, rows_f[keep]])
    cols = torch.cat([cols_i, cols_f[keep]])
    idx = cols[:, None] + torch.arange(length)
    return traj[rows[:, None], idx]


def run(
    out: Path,
    *,
    n: int = 200,
    epochs: int = 30,
    mu: float = 0.3,
    cor: float = 0.7,
    batch_size: int = 32,
    hidden: tuple[int, ...] = (32, 32),
    seed: int = 0,
    chunk_length: int = 5,
    impact_share: float = 0.8,
    models: tuple[str, ...] = ("Coulomb-CD-CLNN", "CM-CD-CLNN"),
) -> dict:
    """Make the data, train every model; returns ``{model: {"cor", "mu", "seconds"}}``."""
    config = box_config(mu, cor)
    system = dc.load_system(config)
    z0 = system.sample_initial_conditions(n, seed=seed)
    traj = simulate_event_driven(system, z0)
    windows = impact_windows(traj, chunk_length, impact_share, seed)
    data = dataset_from_arrays(
        windows, config, out / "data", seed=seed, chunk_length=chunk_length, progress=False
    )
    results = {}
    for name in models:
        t0 = time.perf_counter()
        model = train(
            data,
            out / name,
            model=name,
            epochs=epochs,
            batch_size=batch_size,
            hidden=hidden,
            seed=seed,
            progress=False,
        )
        learned = model.learned_parameters()
        results[name] = {
            "cor": float(learned["cor"][0]),
            "mu": float(learned["mu"][0]),
            "seconds": time.perf_counter() - t0,
        }
    return results


def main(argv: list[str] | None = None) -> int:
    """The command line; a stop by Ctrl-C or SIGTERM is one line (this script does not
    resume: the next run needs a new --out)."""
    hint = "this script does not resume: run it again with a new --out"
    return run_stoppable(_main, argv, "coulomb.py", hint)


def _main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="folder for the data and runs")
    p.add_argument(
        "--n", type=int_at_least(10), default=200, help="trajectories (default 200, >= 10)"
    )
    p.add_argument("--epochs", type=positive_int, default=30)
    p.add_argument("--mu", type=float_in(0), default=0.3, help="friction coefficient (>= 0)")
    p.add_argument("--cor", type=float_in(0, 1), default=0.7, help="restitution in [0, 1]")
    p.add_argument("--seed", type=non_negative_int, default=0)
    args = p.parse_args(argv)
    try:
        check_writable_folder(args.out)
    except OSError as err:
        p.error(f"--out: {err}")
    if args.out.exists() and any(args.out.iterdir()):  # (a TrainingInputError traceback)
        p.error(f"--out {args.out} is not empty: this script does not resume; give a new folder")
    torch.set_num_threads(max(1, torch.get_num_threads()))
    t0 = time.perf_counter()
    res = run(args.out, n=args.n, epochs=args.epochs, mu=args.mu, cor=args.cor, seed=args.seed)
    print(f"truth: e_P = {args.cor:.4f}, mu = {args.mu:.4f}  ({args.n} trajectories, "
          f"{args.epochs} epochs)")  # fmt: skip
    print(f"{'model':<18}{'e_P':>8}{'|err|':>8}{'mu':>8}{'|err|':>8}{'within 0.02':>13}{'s':>8}")
    for name, r in res.items():
        ok = abs(r["cor"] - args.cor) <= 0.02 and abs(r["mu"] - args.mu) <= 0.02
        print(
            f"{name:<18}{r['cor']:8.4f}{abs(r['cor'] - args.cor):8.4f}{r['mu']:8.4f}"
            f"{abs(r['mu'] - args.mu):8.4f}{'yes' if ok else 'no':>13}{r['seconds']:8.1f}"
        )
    print(f"total {time.perf_counter() - t0:.1f} s")
    from diffcontact.io import atomic_write_json

    atomic_write_json(args.out / "results.json", res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
