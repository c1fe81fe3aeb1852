"""Benchmark: CPU threads, with and without a competing process (the thread cliff).

    python benchmarks/run.py threads [--quick] [--task BP5] [--steps 48]

Times, on an idle CPU and then with one competing process (a busy loop started by
this script, standing for another user's job), side by side in one run:

- a training step of CM-CD-CLNN (as ``benchmarks/run.py train``) with 1 thread,
  with all available cores, and with ``threads="auto"`` (the
  :class:`diffcontact.threads.ThreadGovernor` that ``train()`` uses by default,
  including the steps it spends probing);
- one friction-cone QP solve, forward + backward, at batch 1024 with 5 contacts,
  on the fused (Warp, when installed) and the reference (torch) backends, with 1
  thread and with all available cores;
- a rollout ``System.simulate`` of 1024 scenes of ``--task`` over 100 steps with
  ``threads=1``, all cores, and its default ``threads="auto"`` (the governor timing
  the rollout's own steps, :func:`diffcontact.threads.thread_scope`).

Every cell is the mean seconds (or ms) per step over the timed steps after one
warm-up step; ``x best`` is the ratio to the fastest cell of its row and load.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

import torch

from common import check_tasks, machine_header, settings
from diffcontact.cli_args import positive_int

SPIN = "while True:\n    pass\n"


class Competitor:
    """One busy-loop process for the duration of a ``with`` block."""

    def __enter__(self) -> Competitor:
        self.proc = subprocess.Popen([sys.executable, "-c", SPIN])
        time.sleep(0.5)  # let it start spinning
        return self

    def __exit__(self, *exc: object) -> None:
        self.proc.kill()
        self.proc.wait()


def train_step_fn(task: str, batch: int):
    """A closure running one training step of CM-CD-CLNN on ``batch`` chunks of ``task``."""
    import diffcontact as dc
    from diffcontact.learning.models.physical import LearnedModel
    from diffcontact.learning.training.module import rollout_loss
    from train import make_chunks

    chunks = make_chunks(task, batch)
    model = LearnedModel(dc.load_system(task).config, model="CM-CD-CLNN").double()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)

    def step() -> None:
        opt.zero_grad()
        rollout_loss(model, chunks).backward()
        opt.step()

    return step


def solver_fn(backend: str, batch: int = 1024, contacts: int = 5):
    """A closure solving ``batch`` random problems of ``contacts`` contacts, forward + backward."""
    from diffcontact.contact import SolverSettings, solve_cone_qp
    from solver import make_problems

    p = make_problems(contacts, batch, seed=0)
    A, b, mu = p["A"], p["b"], p["mu"]
    W = torch.randn(b.shape, generator=torch.Generator().manual_seed(1), dtype=b.dtype)
    settings = SolverSettings(backend=backend, check_inputs=False)

    def step() -> None:
        Ar, br, mur = (x.clone().requires_grad_() for x in (A, b, mu))
        f = solve_cone_qp(Ar, br, mur, 2, settings=settings)
        (f * W).sum().backward()

    return step


class Rollout:
    """``System.simulate`` of ``batch`` scenes over ``steps`` steps; ``run(threads)`` is one
    call with that ``threads`` option. ``auto_cell`` times the default ``"auto"`` and reads
    the choice of the governor the call made."""

    def __init__(self, task: str, batch: int = 1024, steps: int = 100) -> None:
        import diffcontact as dc

        self.system = dc.load_system(task)
        self.z0 = self.system.sample_initial_conditions(batch, seed=0)
        self.steps = steps

    def run(self, threads) -> None:
        self.system.simulate(self.z0, self.steps, threads=threads)

    def __call__(self) -> None:  # fixed cells: the thread count time_fixed set
        self.run(None)

    def auto_cell(self, max_threads: int, reps: int) -> tuple[float, int, float]:
        import diffcontact.threads as threads_mod

        made = []
        original = threads_mod.ThreadGovernor

        class Recording(original):
            def __init__(self, *args, **kwargs) -> None:
                super().__init__(*args, **kwargs)
                made.append(self)

        torch.set_num_threads(max_threads)
        threads_mod.ThreadGovernor = Recording
        try:
            self.run("auto")  # warm-up
            times = []
            for _ in range(reps):
                t0 = time.perf_counter()
                self.run("auto")
                times.append(time.perf_counter() - t0)
        finally:
            threads_mod.ThreadGovernor = original
        last = made[-1]
        windows = [n for _, n, _ in last.history]
        share = windows.count(1) / len(windows) if windows else 0.0
        return statistics.mean(times), last.choice, share


def time_fixed(step, threads: int, reps: int) -> float:
    torch.set_num_threads(threads)
    step()  # warm-up
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    return statistics.mean(times)


def time_auto(step, max_threads: int, steps: int) -> tuple[float, int, float]:
    """Mean seconds per step under the governor (probes included), its final choice and the
    share of steps it ran with one thread."""
    from diffcontact.threads import ThreadGovernor

    torch.set_num_threads(max_threads)
    step()  # warm-up
    governor = ThreadGovernor(max_threads)
    times, ones = [], 0
    for _ in range(steps):
        ones += torch.get_num_threads() == 1
        t0 = time.perf_counter()
        with governor.step():
            step()
        times.append(time.perf_counter() - t0)
    governor.restore()
    return statistics.mean(times), governor.choice, ones / steps


def main(argv: list[str] | None = None) -> int:
    from diffcontact.threads import available_cores

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer steps (about two minutes)")
    ap.add_argument("--task", default="BP5", help="training and rollout task (default BP5)")
    ap.add_argument("--batch-size", type=positive_int, default=200, help="training chunks per step")
    ap.add_argument("--steps", type=positive_int, default=None, help="auto steps (48; quick 24)")
    ap.add_argument(
        "--reps", type=positive_int, default=None, help="timed steps per fixed cell (8; quick 3)"
    )
    args = ap.parse_args(argv)
    check_tasks(ap, "--task", [args.task])
    chosen = settings(args, {"steps": 48, "reps": 8}, {"steps": 24, "reps": 3})
    auto_steps, reps = chosen["steps"], chosen["reps"]
    cores = available_cores()
    if cores < 2:
        print(f"threads: this process may use {cores} core; nothing to compare")
        return 0
    initial = torch.get_num_threads()
    try:
        from diffcontact.contact import fused

        have_warp = fused.warp_installed()
    except Exception:
        have_warp = False

    print("CPU threads: idle vs one competing busy process, side by side in one run")
    for line in machine_header("cpu", torch.float64):
        print(line)
    print(f"available cores: {cores}; timed steps: {reps} per fixed cell, {auto_steps} for auto")
    head = f"{'what':>34} {'load':>5} | {'1 thread':>9} {f'{cores} threads':>10} {'auto':>9} | "
    head += f"{'x best':>17} | auto chose (1-thread share)"
    print(head)
    print("-" * len(head))
    rows = [(f"train step {args.task} (s)", train_step_fn(args.task, args.batch_size), 1.0, True)]
    backends = (["warp"] if have_warp else []) + ["torch"]
    rows += [(f"solve K=5 B=1024 f+b {b} (ms)", solver_fn(b), 1e3, False) for b in backends]
    rows.append((f"simulate {args.task} 1024x100 (s)", Rollout(args.task), 1.0, True))
    for load in ("idle", "busy"):
        for name, step, scale, auto in rows:
            if load == "busy":
                with Competitor():
                    cells = _row(step, cores, reps, auto_steps, auto)
            else:
                cells = _row(step, cores, reps, auto_steps, auto)
            one, many, auto_cell = cells
            values = [one, many] + ([auto_cell[0]] if auto_cell else [])
            best = min(values)
            ratios = " ".join(f"{v / best:>5.2f}" for v in values)
            auto_txt = f"{scale * auto_cell[0]:>9.3g}" if auto_cell else f"{'-':>9}"
            chose = f"{auto_cell[1]} ({auto_cell[2]:.0%})" if auto_cell else "-"
            print(
                f"{name:>34} {load:>5} | {scale * one:>9.3g} {scale * many:>10.3g} {auto_txt} | "
                f"{ratios:>17} | {chose}",
                flush=True,
            )
    torch.set_num_threads(initial)
    print(
        "x best: time / the fastest cell of the row (1 thread, all cores, auto). auto: the "
        "ThreadGovernor of train(threads='auto') (simulate: of simulate's default "
        "threads='auto', inside each call; the share counts its windows), its probes included."
    )
    return 0


def _row(step, cores: int, reps: int, auto_steps: int, auto: bool):
    if isinstance(step, Rollout):  # whole calls: a few repetitions, the governor inside
        reps = max(2, reps // 2)
    one = time_fixed(step, 1, reps)
    many = time_fixed(step, cores, reps)
    if not auto:
        return one, many, None
    if isinstance(step, Rollout):
        return one, many, step.auto_cell(cores, reps)
    return one, many, time_auto(step, cores, auto_steps)


if __name__ == "__main__":
    raise SystemExit(main())
