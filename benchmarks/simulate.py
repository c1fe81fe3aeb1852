"""Benchmark: ground-truth simulation, wall time of System.simulate.

    python benchmarks/run.py simulate [--quick] [--device cpu|cuda] [--dtype float64|float32]

Simulates N trajectories of each task from its own initial-condition distribution and
prints the wall time, the time per step and the number of state-steps per second. The
default rows are the ones the simulator issue asks for: 1024 BP5 trajectories of 100 steps
and 1024 ropes of 200 points (Rope-D400) over their horizon (19 steps).
"""

from __future__ import annotations

import argparse
import time

import torch

import diffcontact as dc
from common import machine_header, sync

DEFAULT_CASES = [("BP5", 1024, 100), ("Rope-D400", 1024, 19)]
QUICK_CASES = [("BP5", 256, 20), ("Rope-D400", 128, 5)]
EXTRA_CASES = [("BD5", 1024, 100), ("CP3", 1024, 100), ("Gyro", 1024, 100), ("Rope", 1024, 19)]


def time_case(task: str, n: int, steps: int, device: str, dtype: torch.dtype) -> dict:
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=0).to(device=device, dtype=dtype)
    system.simulate(z0[: min(n, 8)], steps=2)  # warm-up (device caches, allocator)
    sync(device)
    t0 = time.perf_counter()
    traj = system.simulate(z0, steps=steps)
    sync(device)
    wall = time.perf_counter() - t0
    contacts = (system.gaps(traj[:, 1:, 0].reshape(-1, *traj.shape[-2:])) < 0).any(-1)
    return {
        "task": task,
        "n": n,
        "steps": steps,
        "wall_s": wall,
        "ms_per_step": 1e3 * wall / steps,
        "state_steps_per_s": n * steps / wall,
        "contact_share": float(contacts.double().mean()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small batches (about a minute)")
    ap.add_argument("--all-tasks", action="store_true", help="also BD5, CP3, Gyro and Rope")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    args = ap.parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        ap.error("--device cuda: no CUDA device available")
    dtype = getattr(torch, args.dtype)
    cases = QUICK_CASES if args.quick else DEFAULT_CASES + (EXTRA_CASES if args.all_tasks else [])

    print("ground-truth simulation: System.simulate (RK4 + detection + two-phase impulse)")
    for line in machine_header(args.device, dtype):
        print(line)
    head = (
        f"{'task':>10} {'N':>6} {'steps':>6} | {'wall s':>8} {'ms/step':>9} "
        f"{'state-steps/s':>14} | {'states in contact':>17}"
    )
    print(head)
    print("-" * len(head))
    for task, n, steps in cases:
        r = time_case(task, n, steps, args.device, dtype)
        print(
            f"{r['task']:>10} {r['n']:>6} {r['steps']:>6} | {r['wall_s']:>8.2f} "
            f"{r['ms_per_step']:>9.1f} {r['state_steps_per_s']:>14.0f} | "
            f"{r['contact_share']:>16.1%}",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
