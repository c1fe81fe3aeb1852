"""Benchmark: seconds per training step of a learned model, for each task.

    python benchmarks/run.py train [--quick] [--device cpu|cuda] [--dtype float64|float32]
                                   [--model CM-CD-CLNN] [--batch-size 200]
    python benchmarks/run.py train --compare-dtypes   # float32 vs float64 loss and gradient
    python benchmarks/run.py train --against none     # without the previous release
    python benchmarks/run.py train --mixed            # also with the potential MLP in float32
    python benchmarks/run.py train --potential-dtype float32 --against REF  # A/B at one dtype
    python benchmarks/run.py train --network          # also the potential network's share
    python benchmarks/run.py train --position-projection 0 --tasks Rope  # without the rope's
                                                      # projection onto its limits
    python benchmarks/run.py train --rounds 5         # each row 5 times, alternating: medians

By default every task is also timed, side by side in the same run, with the previous
release: the package and this benchmark at git ref ``--against`` (default
:data:`PREVIOUS_RELEASE`, the last commit before issue 11's speed work), extracted with
``git archive`` into a temporary folder and run in a subprocess on the same chunks, the
same dtype and the same number of threads (and the same ``--potential-dtype`` when one is
given: then the release must have that option, as every commit since 2026-11-24 has).
The ratio column is previous / now. With ``--rounds N`` each task's timings (this version,
the float32 column, the previous release) are taken N times in turn and the table shows
their medians, and the ratios are the medians of the N rounds' ratios: on a shared machine
whose speed drifts by tens of percent within a minute, a ratio of two timings taken
seconds apart, repeated, is what can be compared.

One training step is what ``diffcontact train`` does per batch: roll the learned model
(contact model + true collision detection + CLNN/CHNN with the MLP potential) out over a
chunk of 5 states from its first state, the MAE loss against the chunk, the backward pass
through the rollout (RK4, the two-phase impulse, the implicit gradients of the cone QP)
and an AdamW step. The chunks are ground-truth states of the task: half of them start
right before a contact (as in the training sets, about half the chunks contain one).
"""

from __future__ import annotations

import argparse
import functools
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

import diffcontact as dc
from common import (
    CONTACT_ROWS_HELP,
    READ_FREE_HELP,
    SPARSE_GRAM_CUDA_HELP,
    WARP_BLOCK_DIM_HELP,
    WARP_SCRATCH_HELP,
    check_device,
    check_tasks,
    choose_contact_rows,
    choose_read_free_projection,
    choose_sparse_gram_cuda,
    choose_warp_block_dim,
    choose_warp_scratch,
    machine_header,
    sync,
)
from diffcontact.cli_args import non_negative_int, positive_int

# 2026-11-23, the last commit before issue 11's solver and training-step work (the fused
# solver, fast paths, batch-invariant polish): the "previous release" of the ratio column
PREVIOUS_RELEASE = "42af21d"
REPO = Path(__file__).resolve().parent.parent
TASKS = ("BP5-e", "BP5", "BD5", "CP3-e", "CP3", "Gyro-e", "Gyro", "Rope")
CHUNK = 5


@functools.lru_cache(maxsize=4)
def make_chunks(task: str, n: int, seed: int = 0) -> torch.Tensor:
    """(n, 5, 2, P, d) ground-truth chunks chosen as the datasets choose them (about half
    contain a contact; diffcontact.learning.data.select_chunks)."""
    from diffcontact.learning.data.chunks import contact_states, select_chunks

    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=seed)
    traj = system.simulate(z0, steps=system.default_steps)  # (n, T, 2, P, d)
    start, _ = select_chunks(contact_states(system, traj), CHUNK, 0.5, seed)
    idx = torch.as_tensor(start)[:, None] + torch.arange(CHUNK)
    return traj[torch.arange(n)[:, None], idx]


def time_task(task: str, args: argparse.Namespace, dtype: torch.dtype) -> dict:
    from diffcontact.learning.models.physical import LearnedModel
    from diffcontact.learning.training.module import rollout_loss

    chunks = make_chunks(task, args.batch_size).to(args.device, dtype)
    overrides = {}
    if args.position_projection is not None:  # the learned model's, not the data's
        overrides["position_projection"] = args.position_projection
    model = LearnedModel(
        dc.load_system(task, **overrides).config,
        model=args.model,
        potential_dtype=args.potential_dtype,
    ).to(args.device, dtype)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)

    def step() -> float:
        sync(args.device)
        t0 = time.perf_counter()
        opt.zero_grad()
        loss = rollout_loss(model, chunks)
        loss.backward()
        opt.step()
        sync(args.device)
        return time.perf_counter() - t0

    step()  # warm-up
    times = [step() for _ in range(args.reps)]
    contact = (dc.load_system(task).gaps(chunks[:, 1:, 0].double().cpu()) < 0).any(-1).any(-1)
    return {
        "task": task,
        "s_per_step": statistics.median(times),
        "chunks_with_contact": float(contact.double().mean()),
    }


def time_network(task: str, args: argparse.Namespace, dtype: torch.dtype) -> float:
    """Seconds of the potential network's share of a step: ``grad V`` at the ``4 (CHUNK - 1)``
    RK4 stages of a chunk's rollout, on the whole batch, each stage's positions depending
    on the last (as in the rollout), and the backward pass to the input and the weights.
    The arithmetic a step cannot avoid while the network has this size (the median of
    ``args.reps`` runs after a warm-up)."""
    from diffcontact.learning.models.physical import LearnedModel

    chunks = make_chunks(task, args.batch_size).to(args.device, dtype)
    net = (
        LearnedModel(
            dc.load_system(task).config, model=args.model, potential_dtype=args.potential_dtype
        )
        .to(args.device, dtype)
        .potential
    )
    if not callable(getattr(net, "gradient", None)):  # a model without the MLP potential
        return float("nan")
    x0 = chunks[:, 0, 0]

    def run() -> float:
        sync(args.device)
        t0 = time.perf_counter()
        x = x0.clone().requires_grad_(True)
        h = x
        for _ in range(4 * (CHUNK - 1)):
            h = h + 1e-4 * net.gradient(h)
        h.sum().backward()
        sync(args.device)
        return time.perf_counter() - t0

    run()
    return statistics.median(run() for _ in range(args.reps))


def extract_release(ref: str, into: Path) -> Path:
    """``src/`` and ``benchmarks/`` of git ref ``ref`` under ``into`` (raises RuntimeError)."""
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", ref, "src", "benchmarks"],
        capture_output=True, check=False,
    )  # fmt: skip
    if archive.returncode != 0:
        raise RuntimeError(f"git archive {ref}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return into


def time_release(root: Path, task: str, args: argparse.Namespace) -> float:
    """Seconds per step of the release extracted at ``root``, in a subprocess."""
    env = dict(os.environ, PYTHONPATH=str(root / "src"), OMP_NUM_THREADS=str(args.threads))
    env.pop("DIFFCONTACT_SOLVER", None)
    cmd = [
        sys.executable, str(root / "benchmarks" / "run.py"), "train", "--tasks", task,
        "--reps", str(args.reps), "--batch-size", str(args.batch_size), "--dtype", args.dtype,
        "--model", args.model, "--device", args.device, "--against", "none",
    ]  # fmt: skip
    source = (root / "benchmarks" / "train.py").read_text()
    if "--against" not in source:
        cmd = cmd[:-2]
    if args.potential_dtype is not None:  # the same network dtype, where the release has it
        if "--potential-dtype" not in source:
            raise RuntimeError(f"the release at {root} has no --potential-dtype option")
        cmd += ["--potential-dtype", args.potential_dtype]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    match = re.search(rf"^\s*{re.escape(task)} \|\s+([0-9.]+)", out.stdout, re.MULTILINE)
    if out.returncode != 0 or match is None:
        raise RuntimeError(f"previous release failed on {task}: {out.stderr.strip()[-400:]}")
    return float(match.group(1))


def compare_dtypes(task: str, args: argparse.Namespace) -> dict:
    """Loss and gradient of one training batch in float32 against float64 (same weights)."""
    import copy

    from diffcontact.learning.models.physical import LearnedModel
    from diffcontact.learning.training.module import rollout_loss

    chunks = make_chunks(task, args.batch_size)
    m64 = LearnedModel(dc.load_system(task).config, model=args.model).double()
    m32 = copy.deepcopy(m64).float()
    mixed = copy.deepcopy(m64)
    mixed.potential.compute_dtype = torch.float32  # = LearnedModel(potential_dtype="float32")
    out = {}
    cases = (("float64", m64, chunks), ("float32", m32, chunks.float()), ("mixed", mixed, chunks))
    for name, model, data in cases:
        loss = rollout_loss(model, data)
        grads = torch.autograd.grad(loss, [p for p in model.parameters() if p.requires_grad])
        out[name] = (loss.detach().double(), torch.cat([g.double().flatten() for g in grads]))
    l64, g64 = out["float64"]
    result = {"task": task}
    for name in ("float32", "mixed"):
        loss, grad = out[name]
        result[f"{name}_loss_rel"] = float((loss - l64).abs() / l64.abs())
        result[f"{name}_grad_rel"] = float((grad - g64).norm() / g64.norm())
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 tasks, 2 timed steps")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument("--model", default="CM-CD-CLNN")
    ap.add_argument(
        "--potential-dtype", choices=("float32", "float64"), default=None,
        help="the potential MLP's dtype inside the rollout (LearnedModel's potential_dtype)",
    )  # fmt: skip
    ap.add_argument("--batch-size", type=positive_int, default=200)
    ap.add_argument(
        "--reps", type=positive_int, default=None, help="timed steps (default 5, quick 2)"
    )
    ap.add_argument("--tasks", nargs="+", default=None, help=f"default: {' '.join(TASKS)}")
    ap.add_argument(
        "--against", default=PREVIOUS_RELEASE, metavar="REF",
        help=f"git ref of the previous release timed side by side (default {PREVIOUS_RELEASE}; "
        "'none': only this version)",
    )  # fmt: skip
    ap.add_argument(
        "--mixed", action="store_true",
        help="also time each task with the potential MLP in float32 (a column, same run)",
    )  # fmt: skip
    ap.add_argument(
        "--network", action="store_true",
        help="also time the potential network alone (its gradient at every RK4 stage and "
        "the backward pass) and print its share of the step",
    )  # fmt: skip
    ap.add_argument(
        "--threads", type=positive_int, default=None,
        help="torch threads for both versions (default: torch's default)",
    )  # fmt: skip
    ap.add_argument(
        "--position-projection", type=non_negative_int, default=None, metavar="N",
        help="the learned model's position_projection iterations (default: the task's; "
        "0: without the projection onto the limits, the work the rope's step adds); this "
        "version only, the data keep the task's",
    )  # fmt: skip
    ap.add_argument("--read-free-projection", action="store_true", help=READ_FREE_HELP)
    ap.add_argument("--sparse-gram-cuda", action="store_true", help=SPARSE_GRAM_CUDA_HELP)
    ap.add_argument(
        "--warp-block-dim", type=positive_int, default=None, metavar="N", help=WARP_BLOCK_DIM_HELP
    )
    ap.add_argument(
        "--warp-scratch", choices=("strided", "contiguous", "matrices"), default=None,
        help=WARP_SCRATCH_HELP,
    )  # fmt: skip
    ap.add_argument(
        "--contact-rows", choices=("auto", "dense", "sparse"), default="auto",
        help=CONTACT_ROWS_HELP + " (this version)",
    )  # fmt: skip
    ap.add_argument(
        "--rounds", type=positive_int, default=1, metavar="N",
        help="time each row N times, the versions in turn, and print medians (of the times, "
        "and of each round's ratios)",
    )  # fmt: skip
    ap.add_argument(
        "--compare-dtypes",
        action="store_true",
        help="instead of timing: relative difference of the loss and the gradient of one "
        "batch in float32 against float64 (same weights, CPU)",
    )
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    from diffcontact.learning.models.registry import BUILTIN_MODELS, is_physical_model

    if not is_physical_model(args.model):
        ap.error(f"--model: {args.model!r} is not a physical model; choose from "
                 f"{', '.join(BUILTIN_MODELS)}")  # fmt: skip
    if args.tasks is not None:
        check_tasks(ap, "--tasks", args.tasks)
    if args.compare_dtypes:  # options of the timing, which --compare-dtypes does not do
        timing = {
            "--reps": args.reps is not None, "--rounds": args.rounds != 1,
            "--mixed": args.mixed, "--network": args.network,
            "--position-projection": args.position_projection is not None,
            "--potential-dtype": args.potential_dtype is not None,
        }  # fmt: skip
        if given := [k for k, v in timing.items() if v]:
            ap.error(f"{', '.join(given)}: options of the timing, not of --compare-dtypes")
    args.reps = args.reps or (2 if args.quick else 5)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    args.threads = torch.get_num_threads()
    choose_read_free_projection(args.read_free_projection)
    choose_sparse_gram_cuda(args.sparse_gram_cuda)
    choose_warp_block_dim(args.warp_block_dim)
    choose_warp_scratch(args.warp_scratch)
    choose_contact_rows(args.contact_rows)
    tasks = args.tasks or (("BP5", "CP3", "Gyro") if args.quick else TASKS)
    dtype = getattr(torch, args.dtype)
    if args.compare_dtypes:
        print(f"against float64, one batch of {args.batch_size} chunks, {args.model}, same weights")
        print("float32: everything in float32 (the QP in float64 inside, kkt_reg 1e-7)")
        print("mixed: float64, the potential MLP in float32 (--potential-dtype float32)")
        print(f"{'':>8} | {'float32':^29} | {'mixed':^29}")
        print(f"{'task':>8} |" + f" {'loss rel. diff':>14} {'grad rel. diff':>14} |" * 2)
        for task in tasks:
            r = compare_dtypes(task, args)
            print(
                f"{task:>8} | {r['float32_loss_rel']:>14.1e} {r['float32_grad_rel']:>14.1e} | "
                f"{r['mixed_loss_rel']:>14.1e} {r['mixed_grad_rel']:>14.1e}",
                flush=True,
            )
        return 0

    with tempfile.TemporaryDirectory(prefix="diffcontact-previous-") as tmp:
        previous = None
        if args.against.lower() != "none":
            try:
                previous = extract_release(args.against, Path(tmp))
            except (RuntimeError, OSError, subprocess.CalledProcessError) as err:
                print(f"previous release not timed: {err}", file=sys.stderr)
        _table(tasks, args, dtype, previous)
    return 0


def _table(tasks, args: argparse.Namespace, dtype: torch.dtype, previous: Path | None) -> None:
    mlp = "" if args.potential_dtype is None else f", potential MLP in {args.potential_dtype}"
    if args.position_projection is not None:
        mlp += f", position_projection {args.position_projection} (this version)"
    if args.read_free_projection:
        mlp += ", read-free projection (this version)"
    if args.sparse_gram_cuda:
        mlp += ", sparse J J^T on CUDA (this version)"
    if args.contact_rows != "auto":
        mlp += f", the contact impulse from the {args.contact_rows} rows (this version)"
    print(f"training step: {args.model}, batch {args.batch_size} chunks of {CHUNK} states{mlp}")
    for line in machine_header(args.device, dtype):
        print(line)
    if previous is not None:
        print(f"previous release: git {args.against}, timed in a subprocess right after each row")
    if args.rounds > 1:
        print(
            f"{args.rounds} rounds per row, the versions in turn: medians of the times and of "
            "the rounds' ratios"
        )
    head = f"{'task':>8} | {'s/step':>8} {'chunks/s':>9} | {'chunks with a contact':>21}"
    if args.network:
        head += f" | {'network s':>9} {'share':>5}"
    if args.mixed:
        head += f" | {'MLP f32 s/step':>14} {'now/f32':>7}"
    if previous is not None:
        head += f" | {'previous s/step':>15} {'previous/now':>12}"
        head += f" {'previous/f32':>12}" if args.mixed else ""
    print(head)
    print("-" * len(head))
    med = statistics.median

    def ratio(a: list[float], b: list[float]) -> float:  # the median of the rounds' ratios
        return med([x / y for x, y in zip(a, b, strict=True)])

    for task in tasks:
        now, mixed, old, failed = [], [], [], False
        for _ in range(args.rounds):
            r = time_task(task, args, dtype)
            now.append(r["s_per_step"])
            if args.mixed:
                f32 = argparse.Namespace(**{**vars(args), "potential_dtype": "float32"})
                mixed.append(time_task(task, f32, dtype)["s_per_step"])
            if previous is not None and not failed:
                try:
                    old.append(time_release(previous, task, args))
                except RuntimeError as err:
                    failed = True
                    print(err, file=sys.stderr)
        line = (
            f"{task:>8} | {med(now):>8.3f} {args.batch_size / med(now):>9.0f} | "
            f"{r['chunks_with_contact']:>20.0%}"
        )
        if args.network:
            net = time_network(task, args, dtype)
            line += f" | {net:>9.3f} {net / med(now):>5.0%}"
        if args.mixed:
            line += f" | {med(mixed):>14.3f} {ratio(now, mixed):>7.2f}"
        if previous is not None and failed:
            line += f" | {'failed':>15} {'-':>12}"
        elif previous is not None:
            line += f" | {med(old):>15.3f} {ratio(old, now):>12.2f}"
            if args.mixed:
                line += f" {ratio(old, mixed):>12.2f}"
        print(line, flush=True)


if __name__ == "__main__":
    raise SystemExit(main())
