"""How small a rollout error can a learned model reach? The error of the *true* system
with one parameter slightly off, on a dataset's test trajectories.

    python experiments/chaos_floor.py runs/repro/data/BP5-e              # masses 1e-6..1e-3
    python experiments/chaos_floor.py runs/repro/data/CP3 --rel 1e-5 1e-4 --body 2

Billiard balls and chain pendulums are chaotic: a tiny error of a learned mass ratio
grows at every collision, and a grazing collision decided the other way sends a
trajectory elsewhere. This script rolls the dataset's test initial states out with the
ground-truth config except one body's mass scaled by ``1 + rel`` (``--body``, default
1, the second body: the first fixes the unobservable scale), and reports the relative
error exactly as ``diffcontact evaluate`` does (rollouts of max(horizon, 100 dt), the
mean over trajectories of each one's mean error over the steps after the first, with
its 95 % interval), plus the median trajectory and the largest ones. A learned model
whose mass ratios are off by ``rel`` cannot be expected to do better than this row.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch


def floor(data_dir: Path, rels: list[float], body: int) -> list[dict]:
    import diffcontact as dc
    from diffcontact.learning.data.format import load_dataset
    from diffcontact.learning.evaluation.metrics import mean_ci95, relative_error, rollout_steps

    ds = load_dataset(data_dir)
    system = ds.system
    steps = rollout_steps(system)
    traj = ds.split("test", dtype=torch.float64).traj  # (N, T, 2, P, d)
    z0 = traj[:, 0]
    cfg = system.config.model_dump(mode="json")
    masses = cfg.get("masses")
    if not isinstance(masses, list) or not 0 <= body < len(masses):
        raise SystemExit(f"--body {body}: the config has masses {masses!r}")
    with torch.no_grad():
        true = system.simulate(z0, steps).numpy()
    rows = []
    for rel in rels:
        perturbed = dict(
            cfg, masses=[m * (1 + rel) if i == body else m for i, m in enumerate(masses)]
        )
        with torch.no_grad():
            pred = dc.System(perturbed).simulate(z0, steps).numpy()
        per_traj = relative_error(pred, true)[:, 1:].mean(1)
        mean, ci = mean_ci95(per_traj)
        rows.append(
            {
                "rel": rel,
                "mean": mean,
                "ci95": ci,
                "median": float(np.median(per_traj)),
                "largest": np.sort(per_traj)[::-1][:3].tolist(),
            }
        )
    return rows


def learned_physics(data_dir: Path, learned: dict) -> dict | None:
    """The rollout error of the *true* system with the learned physical parameters.

    The config's masses (whole scale included), ``mu`` and ``e_P`` are replaced by
    ``learned`` (``learned.json``'s ``learned`` dict); its potential (gravity, springs)
    stays the true one and follows the learned masses, so only the
    learned potential network is left out. The gap between a model's error and this
    one is the potential network's share. ``None`` where the config's parameters
    cannot be replaced one for one: per-contact ``mu`` or ``e_P`` where the config holds
    one number, and rigid bodies (learned second moments). For a body pinned at a pivot
    (the gyroscope) the data fix its inertia about the pivot only up to a factor shared
    with the learned potential, so the learned mass does not give the true potential's
    scale (its learned mass and second moments split that inertia differently).
    """
    import diffcontact as dc
    from diffcontact.learning.data.format import load_dataset
    from diffcontact.learning.evaluation.metrics import mean_ci95, relative_error, rollout_steps

    ds = load_dataset(data_dir)
    system = ds.system
    traj = ds.split("test", dtype=torch.float64).traj
    cfg = system.config.model_dump(mode="json")
    new = dict(cfg)
    mass = [float(m) for m in learned["mass"]]
    if isinstance(cfg.get("masses"), list) and len(cfg["masses"]) == len(mass):
        new["masses"] = mass
    elif "mass" in cfg and len(mass) == 1:
        new["mass"] = mass[0]
    else:
        return None
    if learned.get("second_moments") is not None:
        return None
    for key in ("mu", "cor"):
        values = [float(v) for v in learned[key]]
        if len(set(values)) > 1 or not isinstance(cfg.get(key), (int, float)):
            return None  # per-contact values: not a one-for-one replacement here
        new[key] = values[0]
    with torch.no_grad():
        pred = dc.System(new).simulate(traj[:, 0], rollout_steps(system)).numpy()
    per_traj = relative_error(pred, traj.numpy())[:, 1:].mean(1)
    mean, ci = mean_ci95(per_traj)
    return {"mean": mean, "ci95": ci, "median": float(np.median(per_traj))}


def main(argv: list[str] | None = None) -> int:
    from diffcontact.cli_args import float_above, non_negative_int

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data_dir", type=Path, help="a dataset (diffcontact generate)")
    ap.add_argument(
        "--rel", type=float_above(-1), nargs="+", default=[1e-6, 1e-5, 1e-4, 1e-3],
        help="relative mass errors (finite, > -1)",
    )  # fmt: skip
    ap.add_argument(
        "--body", type=non_negative_int, default=1, help="the body whose mass is scaled"
    )
    args = ap.parse_args(argv)
    if not (args.data_dir / "metadata.json").is_file():
        print(f"{args.data_dir}: not a dataset folder (no metadata.json)", file=sys.stderr)
        return 2
    try:
        masses = json.loads((args.data_dir / "metadata.json").read_text())["config"].get("masses")
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
        ap.error(f"{args.data_dir}: unreadable metadata.json ({type(err).__name__}: {err})")
    if not isinstance(masses, list) or args.body >= len(masses):
        ap.error(f"--body {args.body}: the config has masses {masses!r}")
    rows = floor(args.data_dir, args.rel, args.body)
    print(f"{args.data_dir}: true system, mass of body {args.body} x (1 + rel), test set")
    print("| mass error rel | rel. error (95 % CI) | median trajectory | largest three |")
    print("|---|---|---|---|")
    for r in rows:
        big = ", ".join(f"{x:.2g}" for x in r["largest"])
        print(f"| {r['rel']:.0e} | {r['mean']:.2e} ({r['ci95']:.2e}) | {r['median']:.2e} | {big} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
