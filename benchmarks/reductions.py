"""Benchmark: sums over a short last dimension, ``torch.sum`` vs ``reductions.sum_last``.

    python benchmarks/run.py reductions [--quick] [--device cpu|cuda] [--threads N]

The per-step hot paths reduce many short vectors (squared lengths of 2D and 3D contact
vectors, dot products). The table prints microseconds per call of ``(v * v).sum(-1)`` and
of ``diffcontact.reductions.dot_last(v, v)`` (a product with a vector of ones), forward
and forward + backward, for float64 and float32 inputs of the shapes that BP5 and a 3D
task produce, and the ratio. Medians over repetitions after a warm-up call.
"""

from __future__ import annotations

import argparse

import torch

from common import machine_header, median_time
from diffcontact.reductions import dot_last

SHAPES = ((1024, 10, 2), (1024, 30, 3), (64, 10, 2))


def _time(fn, device: str, reps: int) -> float:
    """Median microseconds per call after a warm-up call."""
    fn()
    return 1e6 * median_time(fn, device, reps)


def _row(shape: tuple, dtype: torch.dtype, device: str, reps: int) -> str:
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
    name = str(dtype).removeprefix("torch.")
    return (
        f"{shape!s:>14} {name:>8} | {fw[0]:8.1f} {fw[1]:11.1f} {fw[0] / fw[1]:6.1f} | "
        f"{bw[0]:8.1f} {bw[1]:12.1f} {bw[0] / bw[1]:6.1f}"
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="run.py reductions", description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    reps = 20 if args.quick else 200
    print("sums over the last dimension: torch.sum vs diffcontact.reductions.dot_last")
    for line in machine_header(args.device, torch.float64):
        print(line)
    head = (
        f"{'shape':>14} {'dtype':>8} | {'sum us':>8} {'dot_last us':>11} {'ratio':>6} | "
        f"{'+bw sum':>8} {'+bw dot_last':>12} {'ratio':>6}"
    )
    print(head)
    print("-" * len(head))
    for shape in SHAPES:
        for dtype in (torch.float64, torch.float32):
            print(_row(shape, dtype, args.device, reps))
    print("ratio: torch.sum time over dot_last's (> 1: dot_last faster)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
