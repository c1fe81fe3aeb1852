"""Benchmark: ``diffcontact.fastops`` against the plain torch expressions they replace.

    python benchmarks/run.py fastops [--quick] [--device cpu|cuda] [--threads N]

Two tables of microseconds per call, forward and forward + backward (to every input that
the hot paths differentiate), for float64 and float32, with the ratio plain / fastops:

- ``(v * v).sum(-1)`` vs ``dot_last(v, v)`` on the contact vectors of BP5 (1024 x 10 x 2),
  of a 3D task (1024 x 30 x 3) and of a training batch (64 x 10 x 2);
- ``G @ X`` (an unbatched matrix broadcast over the batch) vs ``left_matmul(G, X)`` on the
  shapes of BD5's constrained dynamics in a training step of 200 chunks: the inverse
  mass matrix (15 x 15) times the constraint Jacobian's rows (200 x 15 x 15 x 2), and a
  constraint selector (15 x 15, a constant) times positions (200 x 15 x 2), where
  ``left_matmul`` keeps ``@`` (fewer than 16384 numbers); backward to the operands that
  carry a gradient there (both, resp. the positions);
- LAPACK's Cholesky factorisation and solve (``cholesky_ex`` + ``cholesky_solve``, what
  ``spd_solve`` runs for large systems or few) vs the written-out factorisation that
  ``spd_solve`` runs on the CPU for many small ones (``fastops._unrolled_spd_solve``), by
  the number of 3 x 3 systems: 256 to 2000 (where ``_UNROLL_BATCH`` sets the switch:
  BD5's training batch is 200 states x 5 bodies) and 20480 (4096 simulated BD5 scenes x 5
  bodies), and 2 x 2; backward to both operands;
- the Gram matrix ``J J^T`` of rope-limit rows (three adjacent points each) from the dense
  rows (``geometry.sparse_gram.dense_gram``) vs the Warp kernel from their entries
  (``sparse_gram``), for states x rows x points from a 10-point rope's training batch to
  Rope-D400's simulation: the sizes behind ``sparse_gram.MIN_DENSE_SIZE``; backward to
  the entries' values (CPU, with Warp installed; float64);
- the penetration target without equality constraints, ``J pinv(J) v``: through the
  pseudo-inverse (``J @ contact.impulse._pinv_apply(J, v)``, what ``penetration_target``
  ran until 2026-11-27) vs the projection onto ``J``'s range from ``J J^T`` alone
  (``_range_projection``: ``v`` where the rows are independent), for states x rows x
  columns of BP5's contact batches (one state in eight with dependent rows); forward
  only (no gradient flows through the target).

Medians over repetitions after a warm-up call.
"""

from __future__ import annotations

import argparse
import importlib.util

import torch

from common import check_device, machine_header, median_time
from diffcontact.cli_args import positive_int
from diffcontact.fastops import _unrolled_spd_solve, dot_last, left_matmul

SUM_SHAPES = ((1024, 10, 2), (1024, 30, 3), (64, 10, 2))
MATMUL_SHAPES = (((15, 15), (200, 15, 15, 2), True), ((15, 15), (200, 15, 2), False))
# (states, rows, points) of the Gram rows
GRAM_SHAPES = ((120, 8, 10), (1024, 5, 10), (1024, 8, 20), (128, 20, 50), (128, 78, 200))
# (states, rows, columns) of penetration-target problems
RANGE_SHAPES = ((256, 2, 10), (256, 6, 10), (1024, 10, 10))
SOLVE_SHAPES = ((256, 3, 3), (512, 3, 3), (1000, 3, 3), (2000, 3, 3), (20480, 3, 3), (1000, 2, 2))
HEAD = (
    f"{'shape':>26} {'dtype':>8} | {'plain us':>9} {'fastops us':>10} {'ratio':>6} | "
    f"{'+bw plain':>9} {'+bw fastops':>11} {'ratio':>6}"
)


def _time(fn, device: str, reps: int) -> float:
    """Median microseconds per call after a warm-up call."""
    fn()
    return 1e6 * median_time(fn, device, reps)


def _line(name: str, dtype: torch.dtype, fw: list[float], bw: list[float]) -> str:
    dt = str(dtype).removeprefix("torch.")
    return (
        f"{name:>26} {dt:>8} | {fw[0]:9.1f} {fw[1]:10.1f} {fw[0] / fw[1]:6.1f} | "
        f"{bw[0]:9.1f} {bw[1]:11.1f} {bw[0] / bw[1]:6.1f}"
    )


def _sum_row(shape: tuple, dtype: torch.dtype, device: str, reps: int) -> str:
    v = torch.randn(*shape, dtype=dtype, device=device)
    g = v.clone().requires_grad_()
    fw = [
        _time(lambda: (v * v).sum(-1), device, reps),
        _time(lambda: dot_last(v, v), device, reps),
    ]
    bw = [
        _time(lambda: (g * g).sum(-1).sum().backward(), device, reps),
        _time(lambda: dot_last(g, g).sum().backward(), device, reps),
    ]
    return _line(str(shape), dtype, fw, bw)


def _matmul_row(shapes: tuple, dtype: torch.dtype, device: str, reps: int, grad_G: bool) -> str:
    G = torch.randn(*shapes[0], dtype=dtype, device=device)
    X = torch.randn(*shapes[1], dtype=dtype, device=device)
    W = torch.randn(*shapes[1][:-2], shapes[0][0], shapes[1][-1], dtype=dtype, device=device)
    Gg, Xg = G.clone().requires_grad_(grad_G), X.clone().requires_grad_()
    fw = [
        _time(lambda: G @ X, device, reps),
        _time(lambda: left_matmul(G, X), device, reps),
    ]
    bw = [
        _time(lambda: (Gg @ Xg).backward(W), device, reps),
        _time(lambda: left_matmul(Gg, Xg).backward(W), device, reps),
    ]
    return _line(f"{shapes[0]} @ {shapes[1]}", dtype, fw, bw)


def _lapack_solve(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    L, _ = torch.linalg.cholesky_ex(A)
    return torch.cholesky_solve(B, L)


def _solve_row(shape: tuple, dtype: torch.dtype, device: str, reps: int) -> str:
    g = torch.Generator().manual_seed(0)
    R = torch.randn(*shape, generator=g, dtype=dtype)
    A = (R @ R.mT + torch.eye(shape[-1], dtype=dtype)).to(device)
    B = torch.randn(*shape[:-1], 1, generator=g, dtype=dtype).to(device)
    Ag, Bg = A.clone().requires_grad_(), B.clone().requires_grad_()
    fw = [
        _time(lambda: _lapack_solve(A, B), device, reps),
        _time(lambda: _unrolled_spd_solve(A, B), device, reps),
    ]
    bw = [
        _time(lambda: _lapack_solve(Ag, Bg).sum().backward(), device, reps),
        _time(lambda: _unrolled_spd_solve(Ag, Bg).sum().backward(), device, reps),
    ]
    return _line(f"solve {shape}", dtype, fw, bw)


def _gram_row(shape: tuple, device: str, reps: int) -> str:
    from diffcontact.geometry.sparse_gram import dense_gram, sparse_gram

    n, R, P = shape
    g = torch.Generator().manual_seed(0)
    first = torch.randint(0, P - 2, (n, R, 1), generator=g)
    points = (first + torch.arange(3)).to(device)
    values = torch.randn(n, R, 3, 2, generator=g, dtype=torch.float64).to(device)
    W = torch.randn(n, R, R, generator=g, dtype=torch.float64).to(device)
    v = values.clone().requires_grad_()
    fw = [
        _time(lambda: dense_gram(points, values, P), device, reps),
        _time(lambda: sparse_gram(points, values), device, reps),
    ]
    bw = [
        _time(lambda: (dense_gram(points, v, P) * W).sum().backward(), device, reps),
        _time(lambda: (sparse_gram(points, v) * W).sum().backward(), device, reps),
    ]
    size = n * R * P * 2
    return _line(f"gram {shape} {size}", torch.float64, fw, bw)


def _range_row(shape: tuple, dtype: torch.dtype, device: str, reps: int) -> str:
    from diffcontact.contact.impulse import _pinv_apply, _range_projection
    from diffcontact.contact.operator import DenseContact

    n, m, D = shape
    g = torch.Generator().manual_seed(0)
    J = torch.randn(n, m, D, generator=g, dtype=dtype)
    if m > 2:  # one state in eight: more rows than its two coordinates (a body in a corner)
        J[::8] = (
            torch.randn(n, m, 2, generator=g, dtype=dtype)[::8]
            @ torch.randn(n, 2, D, generator=g, dtype=dtype)[::8]
        )
    J, v = J.to(device), torch.randn(n, m, generator=g, dtype=dtype).to(device)
    op = DenseContact(J, None)
    fw = [
        _time(lambda: (J @ _pinv_apply(J, v).unsqueeze(-1)).squeeze(-1), device, reps),
        _time(lambda: _range_projection(op, v), device, reps),
    ]
    nan = float("nan")
    return _line(f"J pinv(J) v {shape}", dtype, fw, [nan, nan])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="run.py fastops", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--threads", type=positive_int, default=None, help="torch threads")
    args = parser.parse_args(argv)
    check_device(parser, args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    reps = 20 if args.quick else 200
    print("diffcontact.fastops against plain torch")
    for line in machine_header(args.device, torch.float64):
        print(line)
    print(HEAD)
    print("-" * len(HEAD))
    dtypes = (torch.float64, torch.float32)
    for shape in SUM_SHAPES:
        for dtype in dtypes:
            print(_sum_row(shape, dtype, args.device, reps))
    for *shapes, grad_G in MATMUL_SHAPES:
        for dtype in dtypes:
            print(_matmul_row(tuple(shapes), dtype, args.device, reps, grad_G))
    for shape in SOLVE_SHAPES:
        for dtype in dtypes:
            print(_solve_row(shape, dtype, args.device, max(3, reps // 10)))
    for shape in RANGE_SHAPES:
        for dtype in dtypes:
            print(_range_row(shape, dtype, args.device, max(3, reps // 10)))
    if args.device == "cpu" and importlib.util.find_spec("warp") is not None:
        for shape in GRAM_SHAPES:
            print(_gram_row(shape, args.device, max(3, reps // 10)))
    print(
        "plain: (v * v).sum(-1), resp. G @ X, resp. cholesky_ex + cholesky_solve, resp. "
        "J @ _pinv_apply(J, v), resp. dense_gram; fastops: dot_last(v, v), resp. "
        "left_matmul(G, X), resp. the written-out solve, resp. _range_projection, resp. "
        "sparse_gram. gram (states, rows, points) n R P dim. ratio: plain time / fastops "
        "time (> 1: fastops faster)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
