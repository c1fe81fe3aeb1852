"""Benchmark: where the time of the read-free (CUDA-graph) simulation step goes.

    python benchmarks/run.py profile_step [--device cpu|cuda] [--tasks BP5 BD5]
        [--scenes N] [--steps N] [--quick]

Runs ``--steps`` steps of the static step that ``System.simulate(cuda_graph=...)``
captures (every state padded to ``GRAPH_CONTACTS`` contacts, the solver's flags deferred,
the ropes' position projection read-free; here run eagerly,
``Rollout.graphed(capture=False)``, so that the profiler sees each kernel) under
``torch.profiler`` and prints, per task, the device time per step and the operations and
kernels that take the most of it (CUDA time on CUDA, CPU time on the CPU).
"""

from __future__ import annotations

import argparse

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

import diffcontact as dc
from common import check_device, check_tasks, machine_header, settings
from diffcontact.cli_args import positive_int
from diffcontact.systems.rollout import Rollout, RolloutOptions


def profile_task(task: str, scenes: int, steps: int, device: str, rows: int) -> None:
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(scenes, seed=0).to(device)
    model, dynamics, fraction, params = system._options("CM", None, None)
    ctx = system._context(z0, params, scenes)
    iterations = system._projection_iterations(None)  # the ropes' projection, as simulate
    options = RolloutOptions(model, dynamics, 0.0 if iterations else fraction, iterations, None)

    def run(k: int) -> None:
        Rollout(system, ctx, z0, k, options).graphed(capture=False)
        if device == "cuda":
            torch.cuda.synchronize()

    run(2)  # warm-up
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    with profile(activities=activities) as prof:
        run(steps)
    cuda = device == "cuda"
    if cuda:  # the kernels (an operation's device time is also its kernels')
        events = [e for e in prof.key_averages() if e.device_type == DeviceType.CUDA]
    else:  # the operations' own CPU time (without their children's)
        events = list(prof.key_averages())

    def own(e) -> float:  # microseconds
        return e.self_device_time_total if cuda else e.self_cpu_time_total

    total = sum(own(e) for e in events)
    per = steps + 1  # (the rollout runs one warm-up step of its own before the timed ones)
    where = "GPU" if cuda else "CPU"
    print(
        f"== {task}: {scenes} states, {steps} steps (+1 warm-up step inside the rollout): "
        f"{total / 1e3 / per:.2f} ms of {where} time per step"
    )
    for e in sorted(events, key=own, reverse=True)[:rows]:
        if own(e) <= 0:
            break
        print(
            f"  {100 * own(e) / total:5.1f} %  {own(e) / 1e3 / per:8.3f} ms/step  "
            f"{e.count / per:6.1f}/step  {e.key[:70]}"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="BP5, 256 states, 3 steps")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--tasks", nargs="+", default=None, help="default BP5 BD5 (quick BP5)")
    ap.add_argument("--scenes", type=positive_int, default=None, help="default 4096 (quick 256)")
    ap.add_argument("--steps", type=positive_int, default=None, help="default 10 (quick 3)")
    ap.add_argument("--rows", type=positive_int, default=12, help="operations listed per task")
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    if args.tasks is not None:
        check_tasks(ap, "--tasks", args.tasks)
    chosen = settings(
        args,
        {"tasks": ["BP5", "BD5"], "scenes": 4096, "steps": 10},
        {"tasks": ["BP5"], "scenes": 256, "steps": 3},
    )
    tasks, scenes, steps = chosen["tasks"], chosen["scenes"], chosen["steps"]
    print("the read-free simulation step (what a CUDA graph replays), profiled")
    for line in machine_header(args.device, torch.float64):
        print(line)
    for task in tasks:
        profile_task(task, scenes, steps, args.device, args.rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
