"""Benchmark: ground-truth simulation, wall time of System.simulate.

    python benchmarks/run.py simulate [--quick] [--device cpu|cuda] [--dtype float64|float32]
        [--cuda-graph auto|on|off|both] [--again] [--grad]
    python benchmarks/run.py simulate --compare mujoco [--quick] [--threads N]

Simulates N trajectories of each task from its own initial-condition distribution and
prints the wall time, the time per step and the number of state-steps per second. The
default rows are the ones the simulator issue asks for: 1024 BP5 trajectories of 100 steps
and 1024 ropes of 200 points (Rope-D400) over their horizon (19 steps).

``--compare mujoco`` instead times 1024 BP5 scenes x 100 steps (``--quick``: 64 x 20) in
diffcontact (``System.simulate``, then again with the backward pass of the final
positions) and in MuJoCo (``mujoco.rollout`` on the matched scene of
``benchmarks/mujoco_scene.py``, one and two threads) side by side, with the ratio to
MuJoCo on one thread and how far the two simulators' positions are apart. Each row is
the median of 3 timed calls (``--quick``: 1), the simulators taking turns, after one
full-size warm-up call of each. It needs the optional ``mujoco`` package.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings

import numpy as np
import torch

import diffcontact as dc
from common import (
    CONTACT_ROWS_HELP,
    SPARSE_GRAM_CUDA_HELP,
    WARP_BLOCK_DIM_HELP,
    WARP_SCRATCH_HELP,
    check_device,
    choose_contact_rows,
    choose_sparse_gram_cuda,
    choose_warp_block_dim,
    choose_warp_scratch,
    machine_header,
    sync,
)
from diffcontact.cli_args import positive_int

DEFAULT_CASES = [("BP5", 1024, 100), ("Rope-D400", 1024, 19)]
QUICK_CASES = [("BP5", 256, 20), ("Rope-D400", 128, 5)]
EXTRA_CASES = [
    ("BD5", 1024, 100),
    ("CP3", 1024, 100),
    ("Gyro", 1024, 100),
    ("Rope", 1024, 19),
    ("Rope-D200", 1024, 19),
]


def time_case(
    task: str,
    n: int,
    steps: int,
    device: str,
    dtype: torch.dtype,
    cuda_graph="auto",
    again: bool = False,
    grad: bool = False,
) -> dict:
    """Time one call of ``System.simulate`` on a fresh system (after a small warm-up), with
    ``again`` a second, identical call on the same system (which then knows the contact
    padding and projection rows its rollouts need on CUDA), and with ``grad`` one more
    call from ``z0`` with ``requires_grad`` and the backward pass of the sum of the final
    positions (the cost of a gradient through the rollout)."""
    system = dc.load_system(task)
    z0 = system.sample_initial_conditions(n, seed=0).to(device=device, dtype=dtype)
    system.simulate(z0[: min(n, 8)], steps=2)  # warm-up (device caches, allocator)
    sync(device)
    walls, graphed = [], []
    for _ in range(2 if again else 1):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            t0 = time.perf_counter()
            traj = system.simulate(z0, steps=steps, cuda_graph=cuda_graph)
            sync(device)
            walls.append(time.perf_counter() - t0)
        graphed.append(graph_used(system, caught))
    grad_s = None
    if grad:
        z = z0.clone().requires_grad_(True)
        t0 = time.perf_counter()
        system.simulate(z, steps=steps, cuda_graph=cuda_graph)[:, -1, 0].sum().backward()
        sync(device)
        grad_s = time.perf_counter() - t0
        if not bool(torch.isfinite(z.grad).all()):
            raise RuntimeError(f"{task}: the gradient of the final positions is not finite")
    wall = walls[0]
    active = system.gaps(traj[:, 1:, 0].reshape(-1, *traj.shape[-2:])) < 0
    contacts = active.any(-1)
    return {
        "task": task,
        "n": n,
        "steps": steps,
        "wall_s": wall,
        "ms_per_step": 1e3 * wall / steps,
        "state_steps_per_s": n * steps / wall,
        "contact_share": float(contacts.double().mean()),
        "max_contacts": int(active.sum(-1).max()) if active.numel() else 0,
        "graph": graphed[0],
        "again_s": walls[1] if again else None,
        "again_graph": graphed[1] if again else None,
        "grad_s": grad_s,
    }


def graph_used(system, caught) -> bool:
    """Whether the last ``simulate`` call of ``system`` replayed a CUDA graph (its
    warnings are printed)."""
    for w in caught:
        print(f"  ({w.category.__name__}: {w.message})", file=sys.stderr)
    return system._last_rollout_graphed


COMPARE_TASK = "BP5"
COMPARE_SIZE = (1024, 100)  # scenes, steps
COMPARE_QUICK_SIZE = (64, 20)
MUJOCO_THREADS = (1, 2)


def _timed(fn, device: str) -> tuple[float, object]:
    sync(device)
    t0 = time.perf_counter()
    out = fn()
    sync(device)
    return time.perf_counter() - t0, out


def compare_mujoco(
    n: int, steps: int, device: str, dtype: torch.dtype, task: str = COMPARE_TASK, repeats: int = 3
) -> dict:
    """Time diffcontact and MuJoCo on the same ``n`` scenes of ``task`` for ``steps`` steps.

    Returns ``{"rows": [...], "sanity": {...}, "mujoco_version": str, "timeconst": float}``;
    each row has ``name``, ``wall_s``, ``ms_per_step``, ``state_steps_per_s`` and
    ``ratio`` (its wall time over MuJoCo's on one thread). ``sanity`` holds the position
    differences (mean over bodies of the Euclidean distance, float64) between diffcontact
    and MuJoCo: ``free_max`` over every state up to each scene's first contact (the first
    state where a gap is negative in either trajectory; it is still reached by free
    flight), ``free_states`` how many such states, ``final_mean`` the mean at the last step,
    ``contact_free_scenes`` how many scenes never touch anything.
    """
    from mujoco_scene import Roller, build_scene, import_mujoco, initial_states, positions

    mujoco = import_mujoco()
    system = dc.load_system(task)
    scene = build_scene(system.config)
    z0 = system.sample_initial_conditions(n, seed=0)
    init = initial_states(scene, z0)
    z0 = z0.to(device=device, dtype=dtype)

    def ours() -> torch.Tensor:
        return system.simulate(z0, steps=steps)

    def ours_grad() -> torch.Tensor:
        z = z0.clone().requires_grad_(True)
        traj = system.simulate(z, steps=steps)
        traj[:, -1, 0].sum().backward()
        return z.grad

    # warm-up: one full-size call of each (device caches, the allocator's first touch of
    # the memory, recorded kernel launches, MuJoCo's first call), then the median of
    # `repeats` timed calls, the simulators taking turns
    rollers = {k: Roller(scene, k) for k in MUJOCO_THREADS}
    calls = {"diffcontact simulate": ours, "diffcontact + gradient": ours_grad}
    for k, roll in rollers.items():
        calls[f"MuJoCo rollout {k} thr"] = lambda roll=roll: roll(init, steps)
    for fn in calls.values():
        fn()
    walls: dict[str, list[float]] = {name: [] for name in calls}
    outputs: dict[str, object] = {}
    for _ in range(repeats):
        for name, fn in calls.items():
            wall, outputs[name] = _timed(fn, "cpu" if name.startswith("MuJoCo") else device)
            walls[name].append(wall)
    for roll in rollers.values():
        roll.close()
    traj, grad = outputs["diffcontact simulate"], outputs["diffcontact + gradient"]
    if not bool(torch.isfinite(grad).all()):
        raise RuntimeError("the gradient of the final positions is not finite")
    rows = [(name, statistics.median(w)) for name, w in walls.items()]
    mj_states = {k: outputs[f"MuJoCo rollout {k} thr"] for k in MUJOCO_THREADS}
    base = rows[2][1]

    x_ours = traj[:, :, 0].detach().to(device="cpu", dtype=torch.float64)
    x_mj = positions(scene, init, mj_states[MUJOCO_THREADS[0]])
    dist = (x_ours - x_mj).norm(dim=-1).mean(-1)  # (n, steps + 1)
    touching = (system.gaps(x_ours) < 0).any(-1) | (system.gaps(x_mj) < 0).any(-1)
    T = steps + 1
    first = torch.where(touching.any(1), touching.long().argmax(1), torch.full((n,), T - 1))
    free = torch.arange(T)[None] <= first[:, None]
    sanity = {
        "free_max": float(dist[free].max()),
        "free_states": int(free.sum()),
        "final_mean": float(dist[:, -1].mean()),
        "contact_free_scenes": int((~touching.any(1)).sum()),
        "threads_agree": all(
            np.array_equal(mj_states[k], mj_states[MUJOCO_THREADS[0]]) for k in MUJOCO_THREADS
        ),
    }
    return {
        "rows": [
            {
                "name": name,
                "wall_s": wall,
                "ms_per_step": 1e3 * wall / steps,
                "state_steps_per_s": n * steps / wall,
                "ratio": wall / base,
            }
            for name, wall in rows
        ],
        "sanity": sanity,
        "mujoco_version": mujoco.__version__,
        "timeconst": scene.timeconst,
    }


def main_compare(args: argparse.Namespace, dtype: torch.dtype) -> int:
    from mujoco_scene import MISSING_MUJOCO

    try:
        import mujoco  # noqa: F401
    except ImportError:
        print(MISSING_MUJOCO, file=sys.stderr)
        return 2
    n, steps = COMPARE_QUICK_SIZE if args.quick else COMPARE_SIZE
    n, steps = args.n or n, args.steps or steps
    repeats = 1 if args.quick else 3
    r = compare_mujoco(n, steps, args.device, dtype, repeats=repeats)
    print(f"simulation: diffcontact vs MuJoCo on a matched {COMPARE_TASK} scene")
    for line in machine_header(args.device, dtype):
        print(line)
    print(
        f"MuJoCo {r['mujoco_version']}: mujoco.rollout on the CPU in float64, Euler, elliptic "
        f"cones, soft contacts (timeconst {r['timeconst']:g} s; benchmarks/mujoco_scene.py)"
    )
    print(
        f"{n} scenes x {steps} steps, dt {dc.load_system(COMPARE_TASK).config.dt:g} s; median of "
        f"{repeats} timed call(s) each after a full-size warm-up, the simulators taking turns"
    )
    head = (
        f"{'simulator':>24} | {'wall s':>8} {'ms/step':>9} {'state-steps/s':>14} | "
        f"{'/ MuJoCo 1 thr':>14}"
    )
    print(head)
    print("-" * len(head))
    for row in r["rows"]:
        print(
            f"{row['name']:>24} | {row['wall_s']:>8.3f} {row['ms_per_step']:>9.2f} "
            f"{row['state_steps_per_s']:>14.0f} | {row['ratio']:>14.2f}",
            flush=True,
        )
    s = r["sanity"]
    print(
        "matched scene: |x_diffcontact - x_MuJoCo| (mean over bodies, box side 1): "
        f"up to the first contact max {s['free_max']:.1e} ({s['free_states']} states), "
        f"at step {steps} mean {s['final_mean']:.3f} "
        f"({s['contact_free_scenes']} of {n} scenes never touch)"
    )
    if not s["threads_agree"]:
        print("note: MuJoCo's 1- and 2-thread rollouts differ")
    print(
        "'/ MuJoCo 1 thr': wall time over MuJoCo's on one thread (> 1: slower than MuJoCo). "
        "After the first contact the trajectories differ by design: MuJoCo's contacts are "
        "soft and last several steps, ours are the two-phase impulse (benchmarks/README.md)."
    )
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small batches (about a minute)")
    ap.add_argument("--all-tasks", action="store_true", help="also BD5, CP3, Gyro and Rope")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument("--threads", type=positive_int, default=None, help="torch intra-op threads")
    ap.add_argument(
        "--scenes",
        type=positive_int,
        default=None,
        help="scenes per row instead of each row's default (e.g. 4096 on a GPU)",
    )
    ap.add_argument("--tasks", nargs="+", default=None, help="only the rows of these tasks")
    ap.add_argument(
        "--cuda-graph",
        choices=("auto", "on", "off", "both"),
        default="auto",
        help="System.simulate's cuda_graph (both: a row with and one without; CUDA only)",
    )
    ap.add_argument(
        "--again",
        action="store_true",
        help="also time a second, identical call on the same system (column 'again s')",
    )
    ap.add_argument(
        "--grad",
        action="store_true",
        help="also time a call with the backward pass of the final positions (column "
        "'+grad s': simulate and backward)",
    )
    ap.add_argument("--sparse-gram-cuda", action="store_true", help=SPARSE_GRAM_CUDA_HELP)
    ap.add_argument(
        "--warp-block-dim", type=positive_int, default=None, metavar="N", help=WARP_BLOCK_DIM_HELP
    )
    ap.add_argument(
        "--warp-scratch", choices=("strided", "contiguous", "matrices"), default=None,
        help=WARP_SCRATCH_HELP,
    )  # fmt: skip
    ap.add_argument(
        "--contact-rows",
        choices=("auto", "dense", "sparse"),
        default="auto",
        help=CONTACT_ROWS_HELP,
    )
    ap.add_argument(
        "--compare",
        choices=("mujoco",),
        default=None,
        help=f"time {COMPARE_TASK} against mujoco.rollout on a matched scene",
    )
    # sizes of the --compare run (tests use tiny ones)
    ap.add_argument("--n", type=positive_int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--steps", type=positive_int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    check_device(ap, args.device)
    # options of one mode only (they were ignored in the other)
    table_only = {
        "--scenes": args.scenes is not None, "--tasks": args.tasks is not None,
        "--all-tasks": args.all_tasks, "--again": args.again, "--grad": args.grad,
        "--cuda-graph": args.cuda_graph != "auto",
    }  # fmt: skip
    if args.compare is not None and (given := [k for k, v in table_only.items() if v]):
        ap.error(f"{', '.join(given)}: not with --compare {args.compare} (its sizes: --quick)")
    if args.compare is None and (args.n is not None or args.steps is not None):
        ap.error("--n and --steps are the sizes of --compare mujoco; the table takes --scenes")
    if args.quick and args.all_tasks:
        ap.error("--all-tasks adds rows to the full run, not to --quick's two rows")
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    choose_sparse_gram_cuda(args.sparse_gram_cuda)
    choose_warp_block_dim(args.warp_block_dim)
    choose_warp_scratch(args.warp_scratch)
    choose_contact_rows(args.contact_rows)
    if args.compare == "mujoco":
        return main_compare(args, dtype)
    cases = QUICK_CASES if args.quick else DEFAULT_CASES + (EXTRA_CASES if args.all_tasks else [])
    if args.scenes is not None:
        cases = [(task, args.scenes, steps) for task, _, steps in cases]
    if args.tasks is not None:
        unknown = set(args.tasks) - {task for task, _, _ in cases}
        if unknown:
            ap.error(f"--tasks: no row for {sorted(unknown)} (--all-tasks adds more rows)")
        cases = [case for case in cases if case[0] in args.tasks]

    print("ground-truth simulation: System.simulate (RK4 + detection + two-phase impulse)")
    if args.sparse_gram_cuda:
        print("the projection's J J^T from the rows' entries on CUDA too (--sparse-gram-cuda)")
    if args.contact_rows != "auto":
        print(f"the contact impulse of point masses from the {args.contact_rows} rows")
    for line in machine_header(args.device, dtype):
        print(line)
    head = (
        f"{'task':>10} {'N':>6} {'steps':>6} {'graph':>5} | {'wall s':>8} {'ms/step':>9} "
        f"{'state-steps/s':>14} | {'states in contact':>17} {'max contacts':>12}"
    )
    if args.again:
        head += f" | {'again s':>8} {'graph':>5}"
    if args.grad:
        head += f" | {'+grad s':>8}"
    print(head)
    print("-" * len(head))
    modes = {"auto": ["auto"], "on": [True], "off": [False], "both": [False, True]}
    for task, n, steps in cases:
        for mode in modes[args.cuda_graph]:
            try:
                r = time_case(task, n, steps, args.device, dtype, mode, args.again, args.grad)
            except ValueError as err:  # cuda_graph=True where it cannot be used
                print(f"{task:>10} {n:>6} {steps:>6} {'on':>5} | {err}", flush=True)
                continue
            row = (
                f"{r['task']:>10} {r['n']:>6} {r['steps']:>6} "
                f"{'yes' if r['graph'] else 'no':>5} | {r['wall_s']:>8.2f} "
                f"{r['ms_per_step']:>9.1f} {r['state_steps_per_s']:>14.0f} | "
                f"{r['contact_share']:>16.1%} {r['max_contacts']:>12}"
            )
            if args.again:
                row += f" | {r['again_s']:>8.2f} {'yes' if r['again_graph'] else 'no':>5}"
            if args.grad:
                row += f" | {r['grad_s']:>8.2f}"
            print(row, flush=True)
    print(
        "graph: the rollout replayed one step captured in a CUDA graph "
        "(System.simulate's cuda_graph; --cuda-graph). max contacts: the most active "
        "contacts of one state at one step"
        + (
            ". again s: a second, identical call on the same system (its contact padding "
            "and projection rows then known)"
            if args.again
            else ""
        )
        + (
            ". +grad s: a call from z0 with requires_grad, and the backward pass of the sum of "
            "the final positions (a CUDA graph is not used with gradients)"
            if args.grad
            else ""
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
