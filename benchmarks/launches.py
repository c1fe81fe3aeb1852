"""Benchmark: how much work a step launches, not how long it takes.

    python benchmarks/run.py launches [--device cpu|cuda] [--tasks BP5 CP3 Rope] [--quick]
        [--potential-dtype float32|float64]

For one simulation step (``System.simulate`` of ``--scenes`` BP5 scenes, averaged over 10
steps) and one training step of CM-CD-CLNN per task (batch 200 chunks of 5 states, as
``benchmarks/train.py`` times it), prints the wall time and the number of torch operations
(dispatches, forward and backward) and the host reads among them (``.item()``,
``bool(tensor)``, ``nonzero``, ``.tolist()``, a copy to the CPU: each a synchronisation on
CUDA, so on the CPU a count of the reads a GPU run synchronises on).
With ``--device cuda`` it adds, from the torch
profiler, the CUDA kernel launches, the host synchronisations (``cudaStreamSynchronize``,
``cudaDeviceSynchronize``, ...), the ``cudaMemcpyAsync`` calls (on the step's path these
are device-to-host reads, such as ``.item()`` or ``nonzero``, each also a
synchronisation) and the share of the wall time the GPU was busy. A step whose GPU is busy
for a small share of its wall time is bound by launches and synchronisations, not by the
GPU's arithmetic.
"""

from __future__ import annotations

import argparse
import contextlib
import time

import torch

import diffcontact as dc
from backends import count_dispatches
from common import (
    READ_FREE_HELP,
    check_device,
    check_tasks,
    choose_read_free_projection,
    machine_header,
    settings,
    sync,
)
from diffcontact.cli_args import positive_int
from train import make_chunks

SIM_TASK = "BP5"
SIM_STEPS = 10
LAUNCH_NAMES = ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx")


def cuda_counts(fn) -> dict:
    """Kernel launches, synchronisations, memcpy calls and GPU-busy seconds of ``fn()``."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    launches = syncs = copies = 0
    for event in prof.events():
        name = event.name
        if name in LAUNCH_NAMES:
            launches += 1
        elif name.startswith(("cuda", "cu")) and "Synchronize" in name:
            syncs += 1
        elif name == "cudaMemcpyAsync":
            copies += 1
    # the kernels' own events (an operator's device time repeats that of its kernels)
    cuda = torch.autograd.DeviceType.CUDA
    busy = sum(e.device_time_total for e in prof.events() if e.device_type == cuda) * 1e-6
    return {"launches": launches, "syncs": syncs, "copies": copies, "gpu_busy_s": busy}


def count_ops(fn, device: str) -> tuple[int, int]:
    """Torch operations dispatched by ``fn()``, and its host reads of tensors on ``device``
    (:func:`diffcontact.testing.count_host_reads`; ``fn`` runs once for each count)."""
    from diffcontact.testing import count_host_reads

    return count_dispatches(fn), count_host_reads(fn, device)


def measure(fn, device: str, per: int, reads_fn=None) -> dict:
    """Wall time (median of 3), torch operations, host reads (of ``reads_fn``, default
    ``fn``) and, on CUDA, launches per ``per`` units."""
    fn()  # warm-up
    times = []
    for _ in range(3):
        sync(device)
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    wall = sorted(times)[1]
    ops, reads = count_ops(fn, device)
    if reads_fn is not None:
        _, reads = count_ops(reads_fn, device)
    out = {"wall_ms": 1e3 * wall / per, "ops": ops / per, "reads": reads / per}
    if device == "cpu":
        from diffcontact.testing import count_host_reads

        with cuda_path():
            out["reads_cuda_path"] = count_host_reads(reads_fn or fn, device) / per
            out["ops_cuda_path"] = count_dispatches(fn) / per
    if device == "cuda":
        counts = cuda_counts(fn)
        out.update({k: v / per for k, v in counts.items() if k != "gpu_busy_s"})
        out["gpu_busy"] = counts["gpu_busy_s"] / wall
    return out


@contextlib.contextmanager
def cuda_path():
    """Inside, step-by-step rollouts on the CPU take the path they take on CUDA: every state
    padded through the contact solve instead of a selection of the states in contact (a
    read of the device per step; ``diffcontact.systems.rollout._pads_contacts``)."""
    from diffcontact.systems import rollout

    original = rollout._pads_contacts
    rollout._pads_contacts = lambda device: True
    try:
        yield
    finally:
        rollout._pads_contacts = original


def simulate_row(scenes: int, device: str) -> dict:
    system = dc.load_system(SIM_TASK)
    z0 = system.sample_initial_conditions(scenes, seed=0).to(device)
    return measure(lambda: system.simulate(z0, steps=SIM_STEPS), device, SIM_STEPS)


def train_row(task: str, device: str, batch: int, potential_dtype: str | None = None) -> dict:
    from diffcontact.learning.models.physical import LearnedModel
    from diffcontact.learning.training.module import rollout_loss

    chunks = make_chunks(task, batch).to(device)
    # float64 parameters, as ``diffcontact train`` keeps them (its default dtype)
    model = LearnedModel(
        dc.load_system(task).config, model="CM-CD-CLNN", potential_dtype=potential_dtype
    ).to(device, torch.float64)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)

    def forward_backward() -> None:
        opt.zero_grad()
        rollout_loss(model, chunks).backward()

    def step() -> None:
        forward_backward()
        opt.step()

    # host reads without the optimiser's (AdamW reads its step counts, which live on the
    # CPU whatever the device)
    return measure(step, device, 1, reads_fn=forward_backward)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="64 scenes, batch 32, BP5 only")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument(
        "--scenes", type=positive_int, default=None,
        help="BP5 scenes of the simulate row (default 1024, quick 64)",
    )  # fmt: skip
    ap.add_argument("--tasks", nargs="+", default=None, help="training rows (default BP5 CP3 Rope)")
    ap.add_argument("--read-free-projection", action="store_true", help=READ_FREE_HELP)
    ap.add_argument(
        "--potential-dtype",
        choices=("float32", "float64"),
        default=None,
        help="the potential MLP's dtype in the training rows (LearnedModel's potential_dtype)",
    )
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    if args.tasks is not None:
        check_tasks(ap, "--tasks", args.tasks)
    choose_read_free_projection(args.read_free_projection)
    chosen = settings(
        args, {"tasks": ["BP5", "CP3", "Rope"], "scenes": 1024}, {"tasks": ["BP5"], "scenes": 64}
    )
    tasks, scenes = chosen["tasks"], chosen["scenes"]
    batch = 32 if args.quick else 200

    print("work per step: torch operations (and CUDA launches and synchronisations)")
    for line in machine_header(args.device, torch.float64):
        print(line)
    cuda = args.device == "cuda"
    head = f"{'row':>24} | {'ms':>8} {'torch ops':>10} {'host reads':>11}"
    if not cuda:
        head += f" {'CUDA path':>10} {'CUDA ops':>9}"
    if cuda:
        head += f" {'launches':>9} {'syncs':>6} {'memcpy':>7} {'GPU busy':>9}"
    print(head)
    print("-" * len(head))
    rows = [(f"simulate {SIM_TASK} x{scenes} /step", lambda: simulate_row(scenes, args.device))]
    rows += [
        (
            f"train {task} b{batch} /step",
            lambda t=task: train_row(t, args.device, batch, args.potential_dtype),
        )
        for task in tasks
    ]
    for name, fn in rows:
        r = fn()
        line = f"{name:>24} | {r['wall_ms']:>8.1f} {r['ops']:>10.0f} {r['reads']:>11.1f}"
        if not cuda:
            line += f" {r['reads_cuda_path']:>10.1f} {r['ops_cuda_path']:>9.0f}"
        if cuda:
            line += (
                f" {r['launches']:>9.0f} {r['syncs']:>6.1f} {r['copies']:>7.1f} "
                f"{r['gpu_busy']:>8.0%}"
            )
        print(line, flush=True)
    print(
        "ms: wall time per step (median of 3 calls after a warm-up). torch ops: dispatched "
        "operations, forward and backward. host reads: operations that copy a value of the "
        "device to the host (.item(), bool(tensor), nonzero, .tolist(); without the "
        "optimiser's), each a synchronisation on CUDA."
        + (
            " CUDA path, CUDA ops: the host reads and torch operations where the rollout "
            "takes its CUDA path (every state padded through the contact solve, no "
            "selection; with --read-free-projection, the position projection read-free: "
            "every iteration, padded rows)."
            if not cuda
            else ""
        )
        + (
            " launches: CUDA kernel launches; syncs: host synchronisations; memcpy: "
            "cudaMemcpyAsync calls (device-to-host reads on this path); GPU busy: the "
            "kernels' time over the wall time."
            if cuda
            else ""
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
