"""Benchmark: what sets the time of one launch of the fused solver's forward kernel.

    python benchmarks/run.py chain [--device cpu|cuda] [--task BP5] [--scenes 4096]
        [--steps 30] [--reps 5] [--scratch strided contiguous matrices] [--quick]

Records every call of the fused forward pass (``FusedConeQP``: its flat inputs) in
``--steps`` steps of the static step that ``System.simulate`` captures in a CUDA graph
(every state padded to ``GRAPH_CONTACTS`` contacts; run here without a graph,
``Rollout.graphed(capture=False)``), then launches the kernel on each recorded call again,
``--reps`` times, on three batches:

- ``all``: the whole call;
- ``no IPM``: without the problems that went to the interior point (iterations > 0);
- ``IPM only``: those problems alone.

A kernel launch lasts as long as its slowest thread (on a GPU, each thread solves one
problem, and a few thousand threads run at once). If the few problems that need the
interior point set a launch's time, ``no IPM`` is much shorter than ``all`` and ``IPM
only`` about as long. Each column is the median over the calls that hold such problems of
each call's median launch time, in milliseconds: on the CPU wall time, device-
synchronised; on CUDA the kernel's own time (``torch.profiler``), so that the host's
share of a call does not blur it. ``calls w/o IPM`` is the median ``all`` of the other
calls. ``--scratch`` repeats the table for each layout of the kernel's scratch memory on
CUDA (``diffcontact.contact.fused.CUDA_SCRATCH``, default all three; on the CPU there is
one layout); ``same f`` says whether its impulses are bitwise those of the first
layout's.
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time

import torch
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile

import diffcontact as dc
from common import check_device, check_tasks, machine_header, settings, sync
from diffcontact.cli_args import positive_int
from diffcontact.contact import fused
from diffcontact.systems.rollout import Rollout, RolloutOptions

DEFAULT = {"task": "BP5", "scenes": 4096, "steps": 30, "reps": 5}
QUICK = {"task": "BP5", "scenes": 256, "steps": 10, "reps": 3}


def record_calls(task: str, scenes: int, steps: int, device: str) -> list[tuple]:
    """The fused forward's inputs ``(A, b, mu, lower, active, warm_start, d, settings)`` of
    every solve in ``steps`` static steps of ``scenes`` states of ``task``."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(scenes, seed=0).to(device)
    model, dynamics, fraction, params = system._options("CM", None, None)
    ctx = system._context(z0, params, scenes)
    iterations = system._projection_iterations(None)
    options = RolloutOptions(model, dynamics, 0.0 if iterations else fraction, iterations, None)
    calls: list[tuple] = []
    forward = fused.FusedConeQP.forward

    def recording(ctx_, A, b, mu, lower, active, warm_start, d, solver_settings):
        warm = None if warm_start is None else warm_start.detach().clone()
        kept = (A.detach().clone(), b.detach().clone(), mu.detach().clone())
        calls.append((*kept, lower.detach().clone(), active.clone(), warm, d, solver_settings))
        return forward(ctx_, A, b, mu, lower, active, warm_start, d, solver_settings)

    fused.FusedConeQP.forward = staticmethod(recording)
    try:
        with torch.no_grad():
            Rollout(system, ctx, z0, steps, options).graphed(capture=False)
    finally:
        fused.FusedConeQP.forward = staticmethod(forward)
    sync(device)
    return calls


def _subset(call: tuple, rows: torch.Tensor) -> tuple:
    A, b, mu, lower, active, warm, d, solver_settings = call
    picked = [x.index_select(0, rows) for x in (A, b, mu, lower, active)]
    return (*picked, None if warm is None else warm.index_select(0, rows), d, solver_settings)


class _Launches:
    """Launches of the fused forward, timed: wall milliseconds around each (the device
    synchronised), and on CUDA, where the host's share of a call would blur the kernel's,
    the kernel's own duration from ``torch.profiler`` (one session for all launches, the
    kernels matched to the launches in order)."""

    def __init__(self, device: str) -> None:
        self.device = device
        self.labels: list[tuple[int, str] | None] = []  # per launch, None: not timed
        self.ms: dict[tuple[int, str], list[float]] = {}
        self.note = ""

    def __call__(self, call: tuple, label: tuple[int, str] | None) -> tuple:
        with torch.no_grad():
            sync(self.device)
            t0 = time.perf_counter()
            out = fused.FusedConeQP.apply(*call)
            sync(self.device)
        self.labels.append(label)
        if label is not None:
            self.ms.setdefault(label, []).append(1e3 * (time.perf_counter() - t0))
        return out

    def profiled(self):
        if self.device != "cuda":
            return contextlib.nullcontext(None)
        return profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA])

    def use_kernel_times(self, prof) -> None:
        """Replace the wall times by the kernels' durations (CUDA)."""
        if prof is None:
            return
        kernels = [
            e for e in prof.events()
            if e.device_type == DeviceType.CUDA and e.name.startswith("fused_forward")
        ]  # fmt: skip
        kernels.sort(key=lambda e: e.time_range.start)
        if len(kernels) != len(self.labels):
            self.note = (f"(wall times: {len(kernels)} kernels profiled for "
                         f"{len(self.labels)} launches)")  # fmt: skip
            return
        self.ms = {}
        for label, e in zip(self.labels, kernels, strict=True):
            if label is not None:
                self.ms.setdefault(label, []).append(e.time_range.elapsed_us() / 1e3)
        self.note = "(kernel times from torch.profiler)"

    def median(self, label: tuple[int, str]) -> float:
        return statistics.median(self.ms[label])


def time_calls(calls: list[tuple], device: str, reps: int) -> dict:
    """The table's row for the current scratch layout, and each call's impulses."""
    launch = _Launches(device)
    impulses, ipm_rows = [], []
    with launch.profiled() as prof:
        for i, call in enumerate(calls):
            f, _, _, iterations, *_ = launch(call, None)  # (untimed: caches, recordings)
            impulses.append(f)
            ipm = torch.nonzero(iterations > 0).flatten()
            rest = torch.nonzero(iterations == 0).flatten()
            ipm_rows.append((ipm, rest, iterations))
            batches = [("all", call)]
            if ipm.numel():
                batches.append(("ipm", _subset(call, ipm)))
                if rest.numel():
                    batches.append(("rest", _subset(call, rest)))
            for kind, batch in batches:
                if kind != "all":
                    launch(batch, None)
                for _ in range(reps):
                    launch(batch, (i, kind))
    launch.use_kernel_times(prof)
    with_ipm, without_ipm = [], []
    worst = None
    for i, (call, (ipm, rest, iterations)) in enumerate(zip(calls, ipm_rows, strict=True)):
        all_ms = launch.median((i, "all"))
        if ipm.numel() == 0:
            without_ipm.append(all_ms)
            continue
        rest_ms = launch.median((i, "rest")) if rest.numel() else 0.0
        active = call[4].index_select(0, ipm).sum(-1)
        entry = (all_ms, rest_ms, launch.median((i, "ipm")), ipm.numel(), int(active.max()))
        entry += (int(iterations.max()),)
        with_ipm.append(entry)
        if worst is None or all_ms > worst[0]:
            worst = entry

    def median(column: int) -> float:
        return statistics.median(e[column] for e in with_ipm) if with_ipm else float("nan")

    return {
        "calls": len(calls),
        "problems": statistics.median(c[1].shape[0] for c in calls),
        "ipm_calls": len(with_ipm),
        "ipm_per_call": statistics.mean(e[3] for e in with_ipm) if with_ipm else 0.0,
        "all": median(0),
        "no_ipm": median(1),
        "ipm_only": median(2),
        "calls_without": statistics.median(without_ipm) if without_ipm else float("nan"),
        "worst": worst,
        "impulses": impulses,
        "note": launch.note,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="benchmarks/run.py chain", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--task", default=None, help="a built-in task (default BP5)")
    ap.add_argument("--scenes", type=positive_int, default=None)
    ap.add_argument("--steps", type=positive_int, default=None)
    ap.add_argument("--reps", type=positive_int, default=None)
    ap.add_argument(
        "--scratch", nargs="+", choices=fused.SCRATCH_LAYOUTS, default=None,
        help="layouts of the scratch memory to time on CUDA (default: all)",
    )  # fmt: skip
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    if args.task is not None:
        check_tasks(ap, "--task", [args.task])
    s = settings(args, DEFAULT, QUICK)
    if not fused.warp_installed():
        ap.error("the fused solver needs Warp (pip install warp-lang)")
    layouts = args.scratch or (list(fused.SCRATCH_LAYOUTS) if args.device == "cuda" else [None])
    if args.device == "cpu" and args.scratch:
        ap.error("--scratch: the layouts differ on CUDA only")
    for line in machine_header(args.device, torch.float64):
        print(line)
    print(f"{s['task']}: {s['scenes']} states, {s['steps']} static steps, {s['reps']} launches "
          "per batch; ms per launch")  # fmt: skip
    calls = record_calls(s["task"], s["scenes"], s["steps"], args.device)
    header = (f"{'scratch':>10} {'calls':>5} {'problems':>8} {'with IPM':>8} {'IPM/call':>8} "
              f"{'all':>8} {'no IPM':>8} {'IPM only':>8} {'calls w/o IPM':>13} "
              f"{'same f':>6}")  # fmt: skip
    print(header)
    print("-" * len(header))
    previous = fused.CUDA_SCRATCH
    first = None
    try:
        for layout in layouts:
            if layout is not None:
                fused.CUDA_SCRATCH = layout
            r = time_calls(calls, args.device, s["reps"])
            name = layout or "(cpu)"
            first = first or r["impulses"]
            same = all(torch.equal(x, y) for x, y in zip(first, r["impulses"], strict=True))
            print(f"{name:>10} {r['calls']:>5} {r['problems']:>8.0f} {r['ipm_calls']:>8} "
                  f"{r['ipm_per_call']:>8.1f} {r['all']:>8.3f} {r['no_ipm']:>8.3f} "
                  f"{r['ipm_only']:>8.3f} {r['calls_without']:>13.3f} "
                  f"{'yes' if same else 'NO':>6}")  # fmt: skip
            if r["note"]:
                print(f"{'':>10} {r['note']}")
            if r["worst"] is not None:
                all_ms, rest_ms, ipm_ms, count, active, its = r["worst"]
                print(f"{'':>10} slowest call: {all_ms:.3f} ms, without its {count} IPM "
                      f"problem(s) {rest_ms:.3f} ms, they alone {ipm_ms:.3f} ms (at most "
                      f"{active} active contacts, {its} iterations)")  # fmt: skip
    finally:
        fused.CUDA_SCRATCH = previous
    return 0
