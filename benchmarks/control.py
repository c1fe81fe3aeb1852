"""Benchmark: one planning iteration (forward + backward of a 100-step rollout) through simulate.

    python benchmarks/run.py control [--quick] [--device cpu|cuda] [--iterations 3]

Times ``diffcontact.optimize`` on the billiards problem (BP5-e, cue ball 0's velocity,
ball 2's final distance to a target) and the throwing problem (BD1-ground, a disk's
velocity and spin) with the true system as the planner, at 1 and 64 starts in one
batched call; then billiards at 64 starts with a learned CM-CD-CLNN model of BP5-e as
the planner (untrained weights: the same arithmetic as a trained model's), its potential
network in float64 and in float32 (``LearnedModel.potential_dtype``). An iteration is
one rollout of every start, the objective, its backward pass and an Adam step; the first
iteration (overlap check, warm-up) is left out of the mean.
"""

from __future__ import annotations

import argparse
import time

import torch

import diffcontact as dc
from common import check_device, machine_header, settings, sync
from diffcontact.cli_args import positive_int
from diffcontact.control import Spin, Velocity, as_planner
from diffcontact.control.tasks import billiards_scene, throw_scene


def _learned(potential_dtype: str) -> object:
    """An untrained CM-CD-CLNN model of BP5-e, its potential network in ``potential_dtype``."""
    from diffcontact.learning.models.physical import LearnedModel

    torch.manual_seed(0)
    model = LearnedModel("BP5-e", model="CM-CD-CLNN").double()
    model.potential_dtype = potential_dtype
    return model


def _problem(task: str, device: str, dtype: torch.dtype, learned: str | None = None):
    spec = "BP5-e" if task == "billiards" else "BD1-ground"
    planner = as_planner(spec if learned is None else _learned(learned).to(device))
    if task == "billiards":
        z0 = billiards_scene(planner, 1, seed=0)[0]
        z0[1, 0] = torch.tensor([1.0, 1.0], dtype=torch.float64)
        target = torch.tensor([0.5, 0.5], dtype=dtype, device=device)
        variables = [Velocity(0, bounds=(-4, 4))]

        def objective(traj):
            return (traj[..., -1, 0, 2, :] - target).norm(dim=-1)

    else:
        z0 = throw_scene(planner)
        z0[1] = 0
        variables = [Velocity(0, bounds=(-4, 4)), Spin(0, bounds=(-30, 30))]

        def objective(traj):
            return (traj[..., -1, 0, 0, 0] - 1.0).abs()

    return planner, z0.to(device=device, dtype=dtype), objective, variables


def time_case(
    task: str, starts: int, steps: int, iterations: int, device: str, dtype, learned=None
) -> dict:
    planner, z0, objective, variables = _problem(task, device, dtype, learned)
    stamps: list[float] = []

    def timed(traj):
        sync(device)
        stamps.append(time.perf_counter())
        return objective(traj)

    sync(device)
    t0 = time.perf_counter()
    res = dc.optimize(
        planner, z0, timed, variables=variables, steps=steps, starts=starts,
        iterations=iterations + 1, progress=False,
    )  # fmt: skip
    sync(device)
    wall = time.perf_counter() - t0
    per_it = (stamps[-1] - stamps[0]) / (len(stamps) - 1)
    return {"task": task, "starts": starts, "steps": steps, "s_per_it": per_it, "wall": wall,
            "its": res.iterations}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="20-step rollouts, 2 iterations")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument(
        "--iterations", type=positive_int, default=None,
        help="timed iterations per case (default 3, quick 2)",
    )  # fmt: skip
    ap.add_argument("--no-learned", action="store_true", help="only the true-system rows")
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    dtype = torch.float64
    steps = 20 if args.quick else 100
    iterations = settings(args, {"iterations": 3}, {"iterations": 2})["iterations"]
    print("planning: one optimize iteration (rollout of every start + backward + Adam step)")
    for line in machine_header(args.device, dtype):
        print(line)
    head = (
        f"{'task':>10} {'planner':>22} {'starts':>6} {'steps':>6} | {'s / iteration':>13} "
        f"{'ms / start':>11}"
    )
    print(head)
    print("-" * len(head))
    cases = [(task, None, starts) for task in ("billiards", "throw") for starts in (1, 64)]
    if not args.no_learned:
        cases += [("billiards", "float64", 64), ("billiards", "float32", 64)]
    for task, learned, starts in cases:
        r = time_case(task, starts, steps, iterations, args.device, dtype, learned)
        who = "true system" if learned is None else f"learned, {learned} MLP"
        print(
            f"{task:>10} {who:>22} {starts:>6} {steps:>6} | {r['s_per_it']:>13.2f} "
            f"{1e3 * r['s_per_it'] / starts:>11.1f}",
            flush=True,
        )
    print(
        "learned: an untrained CM-CD-CLNN model of BP5-e (256x3 potential MLP) as the "
        "planner, its potential network in float64 or float32 (LearnedModel.potential_dtype); "
        "the rollout and the contacts stay in float64."
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
