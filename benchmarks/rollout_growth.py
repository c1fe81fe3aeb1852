"""Benchmark: how a step-by-step rollout's time grows along its steps, and with the
states in contact selected (reads of the device) or every state padded.

    python benchmarks/run.py rollout_growth [--device cpu|cuda] [--task Rope-D400]
        [--scenes N] [--first K] [--steps N] [--rows N] [--quick]

Times ``System.simulate(cuda_graph=False)`` of ``--scenes`` states over the first
``--first`` steps and over all ``--steps``, each with the contact resolution selecting the
states in contact (``rollout._pads_contacts`` False: a read of the device per step) and
padding every state (True: the CUDA default), twice in turn after a warm-up; then counts,
for the position projection's solves of one rollout (the ropes'), the rows and the fused
solver's interior-point iterations per problem, with the projection asking for any
minimiser (its setting) and for the canonical one (``SolverSettings.canonical``, the
solver's default); then profiles one padded rollout of ``--first`` steps and lists the
operations and kernels that take the most device time. Written after the H200 run of
2026-11-27, where 4096 Rope-D400 ropes took far longer per step over 19 steps than over
their first 3 (benchmarks/README.md).
"""

from __future__ import annotations

import argparse
import time

import torch
from torch.profiler import ProfilerActivity, profile

import diffcontact as dc
from common import check_device, check_tasks, machine_header, settings
from diffcontact.cli_args import positive_int
from diffcontact.systems import projection
from diffcontact.systems import rollout as rollout_module


def _timed(system: dc.System, z0: torch.Tensor, steps: int, pads: bool) -> float:
    rollout_module._pads_contacts = lambda device: pads
    if z0.is_cuda:
        torch.cuda.synchronize()
    start = time.perf_counter()
    system.simulate(z0, steps, cuda_graph=False, on_tunnelling="ignore")
    if z0.is_cuda:
        torch.cuda.synchronize()
    return time.perf_counter() - start


def _projection_solves(system: dc.System, z0: torch.Tensor, steps: int, canonical: bool) -> str:
    """The position projection's solves over one rollout: calls, most rows, and the
    interior-point iterations per problem (mean, max)."""
    solve, replace = projection.solve_cone_qp, projection.replace
    calls = []

    def counted(A, *args, **kwargs):
        out = solve(A, *args, **kwargs)
        calls.append((A.shape[-1], out[1].iterations.double()))
        return out

    projection.solve_cone_qp = counted
    if canonical:  # (undo the projection's replace(settings, canonical=False))
        projection.replace = lambda settings, **changes: settings
    try:
        system.simulate(z0, steps, cuda_graph=False, on_tunnelling="ignore")
    finally:
        projection.solve_cone_qp, projection.replace = solve, replace
    if not calls:
        return "no projection solves"
    iterations = torch.cat([it.flatten() for _, it in calls])
    return (
        f"{len(calls)} solves, up to {max(r for r, _ in calls)} rows; interior-point "
        f"iterations per problem: mean {float(iterations.mean()):.2f}, max {int(iterations.max())}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="Rope, 64 states, 2 and 5 steps")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--task", default=None, help="default Rope-D400 (quick Rope)")
    ap.add_argument("--scenes", type=positive_int, default=None, help="default 4096 (quick 64)")
    ap.add_argument("--first", type=positive_int, default=None, help="default 3 (quick 2)")
    ap.add_argument(
        "--steps", type=positive_int, default=None,
        help="default: the task's horizon (quick 5)",
    )  # fmt: skip
    ap.add_argument("--rows", type=positive_int, default=12, help="operations listed")
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    if args.task is not None:
        check_tasks(ap, "--task", [args.task])
    chosen = settings(
        args,
        {"task": "Rope-D400", "scenes": 4096, "first": 3, "steps": None},
        {"task": "Rope", "scenes": 64, "first": 2, "steps": 5},
    )
    task, scenes, first, steps = chosen["task"], chosen["scenes"], chosen["first"], chosen["steps"]
    if steps is not None and first > steps:
        ap.error(f"--first ({first}) must be at most --steps ({steps}, the steps timed)")
    system = dc.load_system(task)
    steps = system.default_steps if steps is None else steps
    if first > steps:
        ap.error(f"--first ({first}) must be at most the task's {steps} steps (--steps)")
    print("a step-by-step rollout's time along its steps, states selected or padded")
    for line in machine_header(args.device, torch.float64):
        print(line)
    z0 = system.sample_initial_conditions(scenes, seed=0, device=args.device)
    original = rollout_module._pads_contacts
    try:
        _timed(system, z0, 1, True)  # warm-up (kernels, caches, the padding it needs)
        print(f"{task}, {scenes} states")
        print(f"{'contacts':>9} | {f'{first} steps s':>12} {f'{steps} steps s':>12} | per step")
        for pads in (False, True, False, True):
            t_first = _timed(system, z0, first, pads)
            t_all = _timed(system, z0, steps, pads)
            name = "padded" if pads else "selected"
            print(
                f"{name:>9} | {t_first:12.3f} {t_all:12.3f} | first {t_first / first:.4f} s, "
                f"the rest {(t_all - t_first) / max(steps - first, 1):.4f} s"
            )
        for canonical in (False, True):
            which = "the canonical minimiser" if canonical else "any minimiser (default)"
            print(f"projection, {which}: {_projection_solves(system, z0, steps, canonical)}")
        rollout_module._pads_contacts = lambda device: True
        activities = [ProfilerActivity.CPU]
        if args.device == "cuda":
            activities.append(ProfilerActivity.CUDA)
        with profile(activities=activities) as prof:
            system.simulate(z0, first, cuda_graph=False, on_tunnelling="ignore")
            if args.device == "cuda":
                torch.cuda.synchronize()
        key = "self_device_time_total" if args.device == "cuda" else "self_cpu_time_total"
        print(f"padded rollout of {first} steps, by {key}:")
        print(prof.key_averages().table(sort_by=key, row_limit=args.rows))
    finally:
        rollout_module._pads_contacts = original
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
