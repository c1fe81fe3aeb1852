"""Benchmark: forward + backward time per problem of the friction-cone QP.

    python benchmarks/run.py solver [--quick] [--device cpu|cuda] [--dtype float64|float32]

For each contact count K (d = 2) and batch size B the same random problems are solved by

  ours       diffcontact.contact.solve_cone_qp on the whole batch at once;
  ref-style  cvxpylayers as in the paper's code: a new cvxpy problem and CvxpyLayer built
             for every state, one state at a time (see baselines.py);
  prebuilt   one CvxpyLayer built per K (build time reported separately), called on the
             whole batch.

Each run is the forward solve plus the backward pass of loss = sum(f * W) (W random) to A,
b and mu. Times are per problem (total / B). Baselines that would take longer than the time
budget are run on the first n < B problems and their per-problem time is extrapolated to B;
such cells are marked with '*' and n is printed. See benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from common import check_device, machine_header, sync
from diffcontact.cli_args import non_negative_int, positive_float, positive_int

D = 2


# --------------------------------------------------------------------------------------------
# problems


def make_problems(K: int, n: int, seed: int) -> dict[str, torch.Tensor]:
    """n random compression-phase problems with K contacts of dimension 2, float64 on CPU.

    A = B B^T with B = Q diag(s) (Q random orthogonal, s log-uniform in [0.3, 3]), so A is
    positive definite with condition number <= 100 (the paper's CMr Cholesky needs that);
    b ~ N(0, I) (about half the contacts approach); mu ~ U(0.1, 1); W ~ N(0, I) weights of
    the loss. Shapes A (n, C, C), b (n, C), mu (n, K), W (n, C), C = 2 K.
    """
    rng = np.random.default_rng(seed)
    C = K * D
    Q, R = np.linalg.qr(rng.standard_normal((n, C, C)))
    Q = Q * np.sign(np.diagonal(R, axis1=-2, axis2=-1))[:, None, :]
    s = np.exp(rng.uniform(np.log(0.3), np.log(3.0), (n, 1, C)))
    B = Q * s
    A = B @ B.transpose(0, 2, 1)
    A = 0.5 * (A + A.transpose(0, 2, 1))
    return {
        "A": torch.from_numpy(A),
        "b": torch.from_numpy(rng.standard_normal((n, C))),
        "mu": torch.from_numpy(rng.uniform(0.1, 1.0, (n, K))),
        "W": torch.from_numpy(rng.standard_normal((n, C))),
    }


def leaves(P: dict, B: int, device, dtype) -> tuple[torch.Tensor, ...]:
    """Fresh leaf tensors A, b, mu (requiring grad) and W for the first B problems."""
    out = []
    for name in ("A", "b", "mu"):
        out.append(P[name][:B].to(device=device, dtype=dtype).requires_grad_(True))
    out.append(P["W"][:B].to(device=device, dtype=dtype))
    return tuple(out)


# --------------------------------------------------------------------------------------------
# timing


def time_ours(
    P: dict, B: int, device: str, dtype, reps: int, backend: str = "auto"
) -> tuple[float, torch.Tensor]:
    """Median seconds for one batched forward + backward on B problems (after a warm-up),
    and the solution f (B, C) on CPU float64. At least ``reps`` calls, and more (up to
    500) until they have taken a second: a sub-millisecond call's median of a handful
    would mostly measure the machine's noise."""
    from diffcontact.contact import SolverSettings, solve_cone_qp

    def once():
        A, b, mu, W = leaves(P, B, device, dtype)
        sync(device)
        t0 = time.perf_counter()
        f = solve_cone_qp(A, b, mu, D, settings=SolverSettings(backend=backend))
        (f * W).sum().backward()
        sync(device)
        return time.perf_counter() - t0, f.detach()

    _, f = once()  # warm-up (allocations, first-call overheads)
    times = [once()[0] for _ in range(reps)]
    while sum(times) < 1.0 and len(times) < 500:
        times.append(once()[0])
    return statistics.median(times), f.to("cpu", torch.float64)


def time_reference_style(P: dict, n_max: int, budget: float, solver_args: dict):
    """Per-problem seconds of the paper-style loop (build + solve + backward, one state at a
    time) over the first n <= n_max problems, stopping once ``budget`` seconds are spent.
    Returns (list of per-problem seconds, list of solutions f (C,))."""
    from baselines import reference_style

    times, sols = [], []
    start = time.perf_counter()
    for i in range(n_max):
        A, b, mu, W = leaves({k: v[i : i + 1] for k, v in P.items()}, 1, "cpu", torch.float64)
        t0 = time.perf_counter()
        f = reference_style(A[0], b[0], mu[0], D, solver_args)
        (f * W[0]).sum().backward()
        times.append(time.perf_counter() - t0)
        sols.append(f.detach())
        if time.perf_counter() - start > budget:
            break
    return times, sols


def time_prebuilt(layer, P: dict, B: int, budget: float, per_problem_guess: float | None):
    """Seconds per problem of the prebuilt layer on a batch of B problems, or on the first n
    problems when B problems would exceed ``budget`` (estimated from ``per_problem_guess``).
    Returns (seconds per problem, n, f (n, C))."""
    from baselines import prebuilt_batched

    n = B
    if per_problem_guess is not None and per_problem_guess * B > budget:
        n = max(1, min(B, int(budget / per_problem_guess)))
    A, b, mu, W = leaves(P, n, "cpu", torch.float64)
    t0 = time.perf_counter()
    f = prebuilt_batched(layer, A, b, mu)
    (f * W).sum().backward()
    return (time.perf_counter() - t0) / n, n, f.detach()


# --------------------------------------------------------------------------------------------
# report


@dataclass
class Row:
    K: int
    B: int
    ours_ms: float | None
    ref_ms: float | None
    ref_n: int
    pre_ms: float | None
    pre_n: int
    build_s: float | None
    max_rel_diff: float | None


def fmt_ms(x: float | None, n: int, B: int) -> str:
    if x is None:
        return "-"
    s = f"{x:.3g}" if x < 1000 else f"{x:.0f}"
    return s + ("*" if n < B else "")


HEADER = (
    f"{'K':>3} {'batch':>6} | {'ours':>9} | {'ref-style':>10} {'(n)':>6} | "
    f"{'prebuilt':>9} {'(n)':>6} | {'ref/ours':>9} {'pre/ours':>9} | {'max rel diff':>12}"
)


def format_row(r: Row) -> str:
    ratio_ref = f"{r.ref_ms / r.ours_ms:.3g}" if r.ref_ms and r.ours_ms else "-"
    ratio_pre = f"{r.pre_ms / r.ours_ms:.3g}" if r.pre_ms and r.ours_ms else "-"
    diff = f"{r.max_rel_diff:.1e}" if r.max_rel_diff is not None else "-"
    return (
        f"{r.K:>3} {r.B:>6} | {fmt_ms(r.ours_ms, r.B, r.B):>9} | "
        f"{fmt_ms(r.ref_ms, r.ref_n, r.B):>10} {r.ref_n:>6} | "
        f"{fmt_ms(r.pre_ms, r.pre_n, r.B):>9} {r.pre_n:>6} | "
        f"{ratio_ref:>9} {ratio_pre:>9} | {diff:>12}"
    )


def write_json(path: Path, payload: dict) -> None:
    """Atomic write: temporary file in the same folder, then rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    with os.fdopen(fd, "w") as fh:
        json.dump(payload, fh, indent=2)
    os.replace(tmp, path)


# --------------------------------------------------------------------------------------------
# main


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small time budgets (about a minute)")
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="device of ours")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    ap.add_argument("--contacts", type=positive_int, nargs="+", default=[1, 5, 10, 30])
    ap.add_argument("--batches", type=positive_int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--seed", type=non_negative_int, default=0)
    ap.add_argument(
        "--budget",
        type=positive_float,
        default=None,
        help="seconds per cell for each cvxpylayers baseline (default 2 with --quick, else 20)",
    )
    ap.add_argument(
        "--cvx-solver",
        default="Clarabel",
        choices=("Clarabel", "SCS", "ECOS"),
        help="cone solver inside cvxpylayers/diffcp (default Clarabel)",
    )
    ap.add_argument(
        "--cvx-tol",
        type=positive_float,
        default=None,
        help="Clarabel's tol_gap_abs/tol_gap_rel/tol_feas inside cvxpylayers (default: its 1e-8)",
    )
    ap.add_argument("--no-baselines", action="store_true", help="time only ours")
    ap.add_argument(
        "--backend",
        choices=("auto", "torch", "warp"),
        default="auto",
        help="solver backend of ours (auto: Warp when installed; see the backends suite)",
    )
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args(argv)

    check_device(ap, args.device)
    if args.json is not None:
        from diffcontact.io import check_writable_folder

        try:
            if args.json.is_dir():
                raise IsADirectoryError(f"{args.json} is a directory; give a file")
            check_writable_folder(args.json.parent)
        except OSError as err:
            ap.error(f"--json: {err}")
    dtype = getattr(torch, args.dtype)
    budget = args.budget if args.budget is not None else (2.0 if args.quick else 20.0)
    reps = 1 if args.quick else 5
    solver_args = {"solve_method": args.cvx_solver}
    if args.cvx_tol is not None:
        if args.cvx_solver != "Clarabel":
            ap.error("--cvx-tol applies to --cvx-solver Clarabel only")
        solver_args |= dict.fromkeys(("tol_gap_abs", "tol_gap_rel", "tol_feas"), args.cvx_tol)
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    baselines = not args.no_baselines
    if baselines:
        try:
            import baselines as _  # noqa: F401
        except ImportError as e:
            print(f"cvxpylayers baselines unavailable ({e}); timing ours only\n")
            baselines = False

    print("friction-cone QP, forward + backward (loss = sum(f * W) -> A, b, mu), d = 2")
    header = machine_header(args.device, dtype)
    from diffcontact.contact import SolverSettings

    backend = SolverSettings(backend=args.backend).resolved(dtype, torch.device(args.device))
    header.append(f"ours: solver backend {backend.backend}")
    header.append(
        f"cvxpylayers baselines on CPU in float64 (diffcp, {json.dumps(solver_args)})"
        if baselines
        else "cvxpylayers baselines not run"
    )
    for line in header:
        print(line)
    print(
        "time per problem in ms; '*' = measured on the first n problems of the batch and "
        f"extrapolated to the batch (budget {budget:g} s per cell)\n"
    )

    print(HEADER)
    print("-" * len(HEADER))
    rows: list[Row] = []
    for K in args.contacts:
        P = make_problems(K, max(args.batches), seed=args.seed + K)
        # ours first, for every batch size: the baselines' solvers can leave threads
        # spinning for a while after they return, which a sub-millisecond call would feel
        ours = {}
        for B in args.batches:
            try:
                ours[B] = time_ours(P, B, args.device, dtype, reps, args.backend)
            except RuntimeError as e:  # e.g. ConeQPError: report it and go on
                print(f"    ours failed at K={K}, batch={B}: {e}")
                ours[B] = (None, None)
        ref_times, ref_sols = [], []
        layer, build_s, pre_guess = None, None, None
        if baselines:
            from baselines import build_layer

            ref_times, ref_sols = time_reference_style(P, max(args.batches), budget, solver_args)
            t0 = time.perf_counter()
            layer = build_layer(K, D, solver_args)
            build_s = time.perf_counter() - t0
        for B in args.batches:
            ours_s, f_ours = ours[B]
            ours_ms = None if ours_s is None else 1e3 * ours_s / B
            row = Row(K, B, ours_ms, None, 0, None, 0, build_s, None)
            if baselines:
                n_ref = min(B, len(ref_times))
                row.ref_ms, row.ref_n = 1e3 * statistics.fmean(ref_times[:n_ref]), n_ref
                pre_s, n_pre, f_pre = time_prebuilt(layer, P, B, budget, pre_guess)
                pre_guess = pre_s
                row.pre_ms, row.pre_n = 1e3 * pre_s, n_pre
                if f_ours is not None:
                    diffs = [rel_diff(f_ours[i], ref_sols[i]) for i in range(n_ref)]
                    diffs += [rel_diff(f_ours[i], f_pre[i]) for i in range(n_pre)]
                    row.max_rel_diff = max(diffs)
            rows.append(row)
            print(format_row(row), flush=True)
        if baselines:
            print(f"    (K={K}: building the prebuilt layer took {build_s:.2f} s, not included)")
    print()
    print(
        "ref/ours, pre/ours: how many times longer per problem than ours. "
        "max rel diff: largest ||f_ours - f_cvxpylayers|| / max(||f_cvxpylayers||, 1) over "
        "the problems both solved (limited by cvxpylayers' default tolerances)."
    )
    if args.json:
        write_json(args.json, {"header": header, "rows": [asdict(r) for r in rows]})
    return 0


def rel_diff(f: torch.Tensor, g: torch.Tensor) -> float:
    """||f - g|| / max(||g||, 1): impulses here are of order one, and cvxpylayers returns
    a separating contact's zero impulse only to about 1e-6."""
    g = g.to(torch.float64)
    return float((f - g).norm() / max(float(g.norm()), 1.0))


if __name__ == "__main__":
    raise SystemExit(main())
